//! Tile chunks: the points one strip contributes to one tile, struct-of-arrays, in acquisition
//! order, with everything estimation needs and nothing else.
//!
//! Encoded little-endian behind a versioned header (`PMCHUNK` + version byte), so chunks can live
//! in files or an object store (`tiles/{tx}_{ty}/{strip}.chunk`).
//! Version 2 added the segment id, version 3 the point's index in its strip file (so that what
//! estimation does with a point can be traced back to it: QC per point, the assignment audit);
//! both are 64 bytes per point. Version 4 (the one written) holds the same values bit for
//! bit in about 60 % of the bytes: each column stores the zigzagged difference from the point
//! before (for `f32`s, of their bit patterns, which for nearby values of one sign differ in the
//! low bits only), and scan-image neighbours as their offset from the point, in blocks of 64
//! values of the fewest whole bytes that hold the block's largest. In acquisition order most of
//! those differences are small: the scan head moves micrometres between points, anchors and
//! strip indices step by 0 or 1, a neighbour along the profile is the next point. Every tile's
//! chunks are read again in every iteration (from an object store, by executors elsewhere), so
//! their size is traffic. Version 6 is version 4 with the body attitude at every anchor of the
//! chunk's range (its rotation vector, three more such columns of one value per anchor),
//! written only for campaigns that estimate the scanners' mounting calibration. Versions 3–6
//! are read; version 5's attitudes (one per point) are skipped, so its chunks serve campaigns
//! that do not estimate the calibration. Older chunks are rejected (re-run the preparation).

use precimap_core::TileKey;

/// Marks a missing scan-image neighbour.
pub const NO_NEIGHBOUR: u32 = u32::MAX;

const MAGIC: &[u8; 7] = b"PMCHUNK";
/// The version written.
const VERSION: u8 = 4;
/// The version written when the chunk carries the body attitudes at its anchors.
const VERSION_ATTITUDE: u8 = 6;
/// The version that carried one body attitude per point (read, its attitudes skipped).
const VERSION_POINT_ATTITUDE: u8 = 5;
/// The fixed-width version still read.
const VERSION_FIXED: u8 = 3;
const HEADER_BYTES: usize = 8 + 4 * 4 + 3 * 8 + 8;
/// Bytes per point of the fixed-width version 3.
const FIXED_BYTES_PER_POINT: usize = 12 + 12 + 12 + 4 + 4 + 4 + 4 + 4 + 4 + 4;
/// Columns of version 4, in order (each behind its byte length, a u64).
const COLUMNS: [&str; 19] = [
    "t0.x",
    "t0.y",
    "t0.z",
    "r.x",
    "r.y",
    "r.z",
    "normal.x",
    "normal.y",
    "normal.z",
    "anchor",
    "lambda",
    "right",
    "down",
    "edge_limit",
    "segment",
    "source",
    "attitude.x",
    "attitude.y",
    "attitude.z",
];

#[derive(Clone, Debug, PartialEq)]
pub struct TileChunk {
    pub tile: TileKey,
    pub strip: u32,
    pub trajectory: u32,
    /// Absolute coordinates that `t0` is relative to (the tile's south-west corner, z = 0).
    pub origin: [f64; 3],
    /// Scan-head position relative to `origin`.
    pub t0: Vec<[f32; 3]>,
    /// Measurement vector `p − t0` (uncorrected).
    pub r: Vec<[f32; 3]>,
    /// Unit normal facing the scanner, world frame, uncorrected.
    pub normal: Vec<[f32; 3]>,
    pub anchor: Vec<u32>,
    pub lambda: Vec<f32>,
    /// Chunk-local index of the next measurement in the same revolution, or [`NO_NEIGHBOUR`].
    pub right: Vec<u32>,
    /// Chunk-local index of the same measurement row in the next revolution, or [`NO_NEIGHBOUR`].
    pub down: Vec<u32>,
    /// Longest scan-image edge from this point that still counts as continuous surface, metres.
    pub edge_limit: Vec<f32>,
    /// Segment of the point in its strip's scan-image segmentation (ids are per strip).
    pub segment: Vec<u32>,
    /// Index of the point in its strip file (acquisition order).
    pub source: Vec<u32>,
    /// Body attitude as a rotation vector (`R = Exp(θ)`, world frame) at every anchor of
    /// [`Self::anchor_range`], first to last inclusive; empty unless the campaign estimates the
    /// scanners' calibration.
    pub attitude: Vec<[f32; 3]>,
}

#[derive(Clone, Debug, thiserror::Error, PartialEq)]
pub enum ChunkError {
    #[error("chunk is {0} bytes, shorter than its header; it is truncated")]
    TooShort(usize),
    #[error("not a precimap tile chunk (bad magic)")]
    BadMagic,
    #[error("chunk format version {0} is not supported (this build reads versions {VERSION_FIXED} to {VERSION_ATTITUDE}; older chunks lack segment ids or point indices: prepare the strips again)")]
    Version(u8),
    #[error("chunk column {column} (point {index} of {points}) is truncated or corrupt at byte {offset} of the chunk; prepare the strip again")]
    Column { column: &'static str, index: usize, points: u64, offset: usize },
    #[error(
        "chunk header says {points} points ({expected} bytes) but {found} bytes follow; it is truncated or corrupt"
    )]
    Length { points: u64, expected: usize, found: usize },
    #[error("point {index}: neighbour index {neighbour} is out of range")]
    BadNeighbour { index: usize, neighbour: u32 },
}

impl TileChunk {
    pub fn with_capacity(tile: TileKey, strip: u32, trajectory: u32, origin: [f64; 3], n: usize) -> Self {
        Self {
            tile,
            strip,
            trajectory,
            origin,
            t0: Vec::with_capacity(n),
            r: Vec::with_capacity(n),
            normal: Vec::with_capacity(n),
            anchor: Vec::with_capacity(n),
            lambda: Vec::with_capacity(n),
            right: Vec::with_capacity(n),
            down: Vec::with_capacity(n),
            edge_limit: Vec::with_capacity(n),
            segment: Vec::with_capacity(n),
            source: Vec::with_capacity(n),
            attitude: Vec::new(),
        }
    }

    pub fn len(&self) -> usize {
        self.t0.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t0.is_empty()
    }

    #[allow(clippy::too_many_arguments)]
    pub fn push(
        &mut self,
        t0: [f32; 3],
        r: [f32; 3],
        normal: [f32; 3],
        anchor: u32,
        lambda: f32,
        right: u32,
        down: u32,
        edge_limit: f32,
        segment: u32,
        source: u32,
    ) {
        self.t0.push(t0);
        self.r.push(r);
        self.normal.push(normal);
        self.anchor.push(anchor);
        self.lambda.push(lambda);
        self.right.push(right);
        self.down.push(down);
        self.edge_limit.push(edge_limit);
        self.segment.push(segment);
        self.source.push(source);
    }

    /// Smallest and largest anchor index referenced (the upper one includes `anchor + 1`).
    pub fn anchor_range(&self) -> Option<(u32, u32)> {
        let min = *self.anchor.iter().min()?;
        let max = *self.anchor.iter().max()?;
        Some((min, max + 1))
    }

    /// The chunk in the current version: 4, or 6 with the attitudes at its anchors.
    pub fn encode(&self) -> Vec<u8> {
        let n = self.len();
        let with_attitude = !self.attitude.is_empty();
        // Room for ~48 bytes per point (small s1's chunks take 41.4); more grows the buffer.
        let mut out = Vec::with_capacity(HEADER_BYTES + 8 * COLUMNS.len() + 48 * n);
        self.encode_header(&mut out, if with_attitude { VERSION_ATTITUDE } else { VERSION });
        for a in [&self.t0, &self.r, &self.normal] {
            for axis in 0..3 {
                put_column(&mut out, n, deltas(a.iter().map(|v| v[axis].to_bits())));
            }
        }
        put_column(&mut out, n, deltas(self.anchor.iter().copied()));
        put_column(&mut out, n, deltas(self.lambda.iter().map(|v| v.to_bits())));
        for a in [&self.right, &self.down] {
            put_column(&mut out, n, a.iter().enumerate().map(|(k, &v)| neighbour_code(k, v)));
        }
        put_column(&mut out, n, deltas(self.edge_limit.iter().map(|v| v.to_bits())));
        put_column(&mut out, n, deltas(self.segment.iter().copied()));
        put_column(&mut out, n, deltas(self.source.iter().copied()));
        if with_attitude {
            let m = self.attitude.len();
            for axis in 0..3 {
                put_column(&mut out, m, deltas(self.attitude.iter().map(|v| v[axis].to_bits())));
            }
        }
        out
    }

    fn encode_header(&self, out: &mut Vec<u8>, version: u8) {
        out.extend_from_slice(MAGIC);
        out.push(version);
        for v in [self.tile.tx as u32, self.tile.ty as u32, self.strip, self.trajectory] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for v in self.origin {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&(self.len() as u64).to_le_bytes());
    }

    /// A chunk of version 3, 4, 5 or 6.
    pub fn decode(bytes: &[u8]) -> Result<Self, ChunkError> {
        if bytes.len() < HEADER_BYTES {
            return Err(ChunkError::TooShort(bytes.len()));
        }
        if &bytes[..7] != MAGIC {
            return Err(ChunkError::BadMagic);
        }
        let version = bytes[7];
        if ![VERSION_FIXED, VERSION, VERSION_POINT_ATTITUDE, VERSION_ATTITUDE].contains(&version) {
            return Err(ChunkError::Version(version));
        }
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
        let f64_at = |o: usize| f64::from_le_bytes(bytes[o..o + 8].try_into().expect("8 bytes"));
        let tile = TileKey { tx: u32_at(8) as i32, ty: u32_at(12) as i32 };
        let (strip, trajectory) = (u32_at(16), u32_at(20));
        let origin = [f64_at(24), f64_at(32), f64_at(40)];
        let points = u64::from_le_bytes(bytes[48..56].try_into().expect("8 bytes"));
        let mut chunk = Self::with_capacity(tile, strip, trajectory, origin, 0);
        if version == VERSION_FIXED {
            chunk.decode_fixed_body(&bytes[HEADER_BYTES..], points)?;
        } else {
            chunk.decode_body(bytes, points, version)?;
        }
        let n = chunk.len();
        for (index, &neighbour) in chunk.right.iter().chain(chunk.down.iter()).enumerate() {
            if neighbour != NO_NEIGHBOUR && neighbour as usize >= n {
                return Err(ChunkError::BadNeighbour { index: index % n.max(1), neighbour });
            }
        }
        Ok(chunk)
    }

    /// Version 4's columns (and version 6's attitudes; version 5's are skipped) into this chunk
    /// (`bytes` is the whole chunk, for the offsets in errors).
    fn decode_body(&mut self, bytes: &[u8], points: u64, version: u8) -> Result<(), ChunkError> {
        let with_attitude = version != VERSION;
        // Each point takes at least one byte in every column: a count beyond the bytes is corrupt,
        // and found before anything of its size is allocated.
        let body = bytes.len() - HEADER_BYTES;
        if points > body as u64 {
            let columns = if with_attitude { COLUMNS.len() } else { COLUMNS.len() - 3 };
            let expected = (points as usize).saturating_mul(columns);
            return Err(ChunkError::Length { points, expected, found: body });
        }
        let n = points as usize;
        let mut columns = Columns { bytes, at: HEADER_BYTES, points };
        self.t0 = columns.vec3(0, n)?;
        self.r = columns.vec3(3, n)?;
        self.normal = columns.vec3(6, n)?;
        self.anchor = columns.values(9, n)?;
        self.lambda = columns.values(10, n)?.into_iter().map(f32::from_bits).collect();
        self.right = columns.neighbours(11, n)?;
        self.down = columns.neighbours(12, n)?;
        self.edge_limit = columns.values(13, n)?.into_iter().map(f32::from_bits).collect();
        self.segment = columns.values(14, n)?;
        self.source = columns.values(15, n)?;
        if version == VERSION_POINT_ATTITUDE {
            columns.vec3(16, n)?;
        } else if version == VERSION_ATTITUDE {
            let anchors = self.anchor_range().map_or(0, |(first, last)| (last - first + 1) as usize);
            self.attitude = columns.vec3(16, anchors)?;
        }
        if columns.at != bytes.len() {
            return Err(ChunkError::Length { points, expected: columns.at - HEADER_BYTES, found: body });
        }
        Ok(())
    }

    /// Version 3's fixed-width columns into this chunk.
    fn decode_fixed_body(&mut self, body: &[u8], points: u64) -> Result<(), ChunkError> {
        let expected = (points as usize).saturating_mul(FIXED_BYTES_PER_POINT);
        if body.len() != expected {
            return Err(ChunkError::Length { points, expected, found: body.len() });
        }
        let n = points as usize;
        let mut offset = 0usize;
        let mut take = |len: usize| {
            let s = &body[offset..offset + len];
            offset += len;
            s
        };
        let vec3 = |s: &[u8]| -> Vec<[f32; 3]> {
            s.chunks_exact(12)
                .map(|c| {
                    let f = |o: usize| f32::from_le_bytes(c[o..o + 4].try_into().expect("4 bytes"));
                    [f(0), f(4), f(8)]
                })
                .collect()
        };
        let u32s = |s: &[u8]| -> Vec<u32> {
            s.chunks_exact(4).map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes"))).collect()
        };
        let f32s = |s: &[u8]| -> Vec<f32> {
            s.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))).collect()
        };
        self.t0 = vec3(take(12 * n));
        self.r = vec3(take(12 * n));
        self.normal = vec3(take(12 * n));
        self.anchor = u32s(take(4 * n));
        self.right = u32s(take(4 * n));
        self.down = u32s(take(4 * n));
        self.segment = u32s(take(4 * n));
        self.source = u32s(take(4 * n));
        self.lambda = f32s(take(4 * n));
        self.edge_limit = f32s(take(4 * n));
        Ok(())
    }
}

/// Values per block of a version-4 column: each block stores its values in the fewest whole
/// bytes that hold its largest.
const BLOCK: usize = 64;

/// `d` zigzagged: small magnitudes of either sign become small numbers (a 32-bit `d` gives
/// the same value as a 32-bit zigzag would).
#[inline]
fn zigzag(d: i64) -> u64 {
    ((d << 1) ^ (d >> 63)) as u64
}

#[inline]
fn unzigzag(z: u64) -> i64 {
    (z >> 1) as i64 ^ -((z & 1) as i64)
}

/// Zigzagged wrapping differences of consecutive values (the first from 0). In 32 bits, so that
/// `f32`s of opposite sign (bit patterns 2³¹ apart) still take at most 4 bytes.
fn deltas(values: impl Iterator<Item = u32>) -> impl Iterator<Item = u64> {
    let mut previous = 0u32;
    values.map(move |v| {
        let d = v.wrapping_sub(previous) as i32;
        previous = v;
        zigzag(d as i64)
    })
}

/// A neighbour as its offset from point `k`: 0 for none, else the zigzagged offset plus one.
fn neighbour_code(k: usize, neighbour: u32) -> u64 {
    if neighbour == NO_NEIGHBOUR {
        return 0;
    }
    zigzag(neighbour as i64 - k as i64) + 1
}

fn neighbour_from_code(k: usize, code: u64) -> Option<u32> {
    if code == 0 {
        return Some(NO_NEIGHBOUR);
    }
    (k as i64).checked_add(unzigzag(code - 1)).and_then(|v| u32::try_from(v).ok()).filter(|&v| v != NO_NEIGHBOUR)
}

/// Appends one column: its byte length (u64), then its `n` values in blocks of [`BLOCK`], each
/// a byte `w` (0–8) and its values in `w` little-endian bytes each. One width per block keeps
/// the reading loop free of per-value branches. Measured first on small s1's chunks, against
/// version 3's 64 bytes and 5.6 ns per point to read: LEB128 varints per value, 35.2 bytes
/// per point but ~45 ns per point to read; blocks also predicting by the line through the two
/// values before (in 64 bits), 43.6 bytes and 39 ns; these blocks 41.4 bytes and 20 ns.
fn put_column(out: &mut Vec<u8>, n: usize, mut values: impl Iterator<Item = u64>) {
    let start = out.len();
    out.extend_from_slice(&[0; 8]);
    out.reserve(n.div_ceil(BLOCK) + 4 * n);
    let mut block = [0u64; BLOCK];
    let mut left = n;
    while left > 0 {
        let count = left.min(BLOCK);
        for v in &mut block[..count] {
            *v = values.next().unwrap_or_default();
        }
        left -= count;
        let values = &block[..count];
        let largest = values.iter().fold(0, |m, &v| m | v);
        let width = (64 - largest.leading_zeros() as usize).div_ceil(8);
        out.push(width as u8);
        // Room for the block at once, then plain stores (no capacity check per value).
        let at = out.len();
        out.resize(at + count * width, 0);
        let dst = &mut out[at..];
        match width {
            0 => {}
            1 => dst.iter_mut().zip(values).for_each(|(d, &v)| *d = v as u8),
            2 => dst.chunks_exact_mut(2).zip(values).for_each(|(d, &v)| d.copy_from_slice(&(v as u16).to_le_bytes())),
            4 => dst.chunks_exact_mut(4).zip(values).for_each(|(d, &v)| d.copy_from_slice(&(v as u32).to_le_bytes())),
            w => dst.chunks_exact_mut(w).zip(values).for_each(|(d, &v)| d.copy_from_slice(&v.to_le_bytes()[..w])),
        }
    }
    let len = (out.len() - start - 8) as u64;
    out[start..start + 8].copy_from_slice(&len.to_le_bytes());
}

/// Version 4's columns, read in order from byte `at` of the chunk `bytes`.
struct Columns<'a> {
    bytes: &'a [u8],
    at: usize,
    points: u64,
}

impl<'a> Columns<'a> {
    /// Column `index` of [`COLUMNS`]: its length, then its bytes.
    fn next(&mut self, index: usize) -> Result<Column<'a>, ChunkError> {
        let name = COLUMNS[index];
        let corrupt = ChunkError::Column { column: name, index: 0, points: self.points, offset: self.at };
        let len = self.bytes.get(self.at..self.at + 8).ok_or_else(|| corrupt.clone())?;
        let len = u64::from_le_bytes(len.try_into().expect("8 bytes"));
        let start = self.at + 8;
        let end = usize::try_from(len).ok().and_then(|len| start.checked_add(len)).filter(|&e| e <= self.bytes.len());
        let end = end.ok_or(corrupt)?;
        self.at = end;
        Ok(Column { name, bytes: &self.bytes[..end], at: start, points: self.points })
    }

    /// Calls `put(k, value)` for the `n` values of column `index`, stored as differences
    /// ([`deltas`]: of `f32` bit patterns, or of integers).
    fn undelta(&mut self, index: usize, n: usize, mut put: impl FnMut(usize, u32)) -> Result<(), ChunkError> {
        let mut previous = 0u32;
        self.next(index)?.read(n, |k, z| {
            previous = previous.wrapping_add(unzigzag(z) as u32);
            put(k, previous);
        })
    }

    /// `n` values of 32 bits (see [`Self::undelta`]).
    fn values(&mut self, index: usize, n: usize) -> Result<Vec<u32>, ChunkError> {
        let mut out = vec![0u32; n];
        self.undelta(index, n, |k, v| out[k] = v)?;
        Ok(out)
    }

    /// Three `f32` columns from `first` on, as vectors.
    fn vec3(&mut self, first: usize, n: usize) -> Result<Vec<[f32; 3]>, ChunkError> {
        let mut out = vec![[0.0f32; 3]; n];
        for axis in 0..3 {
            self.undelta(first + axis, n, |k, v| out[k][axis] = f32::from_bits(v))?;
        }
        Ok(out)
    }

    /// `n` scan-image neighbours stored as offsets ([`neighbour_code`]).
    fn neighbours(&mut self, index: usize, n: usize) -> Result<Vec<u32>, ChunkError> {
        let mut out = vec![NO_NEIGHBOUR; n];
        let mut bad = None;
        let mut column = self.next(index)?;
        column.read(n, |k, code| match neighbour_from_code(k, code) {
            Some(v) => out[k] = v,
            None => {
                bad.get_or_insert(k);
            }
        })?;
        match bad {
            Some(k) => {
                Err(ChunkError::Column { column: column.name, index: k, points: self.points, offset: column.at })
            }
            None => Ok(out),
        }
    }
}

/// One column of version 4 being read: from `at` to the end of `bytes`.
struct Column<'a> {
    name: &'static str,
    bytes: &'a [u8],
    at: usize,
    points: u64,
}

impl Column<'_> {
    fn error(&self, index: usize) -> ChunkError {
        ChunkError::Column { column: self.name, index, points: self.points, offset: self.at }
    }

    /// Calls `f(k, value)` for the column's `n` values in order; the column must end with them.
    /// A corrupt column can give any values (a neighbour column checks its own), never a panic;
    /// a difference column reads the low 32 bits of values wider than that.
    fn read(&mut self, n: usize, mut f: impl FnMut(usize, u64)) -> Result<(), ChunkError> {
        let mut k = 0;
        while k < n {
            let count = BLOCK.min(n - k);
            let width = match self.bytes.get(self.at) {
                Some(&w) if w <= 8 => w as usize,
                _ => return Err(self.error(k)),
            };
            let start = self.at + 1;
            let src = self.bytes.get(start..start + count * width).ok_or_else(|| self.error(k))?;
            match width {
                0 => (k..k + count).for_each(|k| f(k, 0)),
                1 => src.iter().enumerate().for_each(|(i, &b)| f(k + i, b as u64)),
                2 => {
                    src.chunks_exact(2).enumerate().for_each(|(i, c)| f(k + i, u16::from_le_bytes([c[0], c[1]]) as u64))
                }
                3 => src
                    .chunks_exact(3)
                    .enumerate()
                    .for_each(|(i, c)| f(k + i, u32::from_le_bytes([c[0], c[1], c[2], 0]) as u64)),
                4 => src
                    .chunks_exact(4)
                    .enumerate()
                    .for_each(|(i, c)| f(k + i, u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as u64)),
                w => src.chunks_exact(w).enumerate().for_each(|(i, c)| {
                    let mut b = [0u8; 8];
                    b[..w].copy_from_slice(c);
                    f(k + i, u64::from_le_bytes(b))
                }),
            }
            self.at = start + count * width;
            k += count;
        }
        if self.at == self.bytes.len() {
            Ok(())
        } else {
            Err(self.error(n))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The chunk in the fixed-width version 3 (64 bytes per point), which [`TileChunk::decode`]
    /// still reads.
    fn encode_fixed(c: &TileChunk) -> Vec<u8> {
        let n = c.len();
        let mut out = Vec::with_capacity(HEADER_BYTES + n * FIXED_BYTES_PER_POINT);
        c.encode_header(&mut out, VERSION_FIXED);
        for a in [&c.t0, &c.r, &c.normal] {
            for v in a.iter().flatten() {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        for a in [&c.anchor, &c.right, &c.down, &c.segment, &c.source] {
            for v in a {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        for a in [&c.lambda, &c.edge_limit] {
            for v in a {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out
    }

    #[test]
    fn encode_decode_round_trip_and_corruption() {
        let mut c = TileChunk::with_capacity(TileKey { tx: -3, ty: 386_893 }, 7, 2, [549_795.0, 5_803_395.0, 0.0], 2);
        c.push([1.0, 2.0, 3.0], [4.0, -5.0, 6.5], [0.0, 0.0, 1.0], 17, 0.25, 1, NO_NEIGHBOUR, 0.1, 4, 1_000_001);
        c.push([1.5, 2.0, 3.0], [4.0, -5.5, 6.5], [0.0, 0.6, 0.8], 18, 0.75, NO_NEIGHBOUR, 0, 0.2, 4, 1_000_003);
        let mut with_attitude = c.clone();
        // One attitude per anchor of 17..=19.
        with_attitude.attitude = vec![[0.01, -0.02, 3.1], [0.011, -0.02, 3.099], [0.012, -0.021, 3.098]];
        for (chunk, bytes, version) in [
            (&c, c.encode(), VERSION),
            (&c, encode_fixed(&c), VERSION_FIXED),
            (&with_attitude, with_attitude.encode(), VERSION_ATTITUDE),
        ] {
            assert_eq!(bytes[7], version);
            assert_eq!(&TileChunk::decode(&bytes).unwrap(), chunk);
            assert!(matches!(
                TileChunk::decode(&bytes[..bytes.len() - 1]),
                Err(ChunkError::Length { .. } | ChunkError::Column { .. })
            ));
            assert_eq!(TileChunk::decode(&bytes[..10]), Err(ChunkError::TooShort(10)));
            let mut bad = bytes.clone();
            bad[0] = b'X';
            assert_eq!(TileChunk::decode(&bad), Err(ChunkError::BadMagic));
            let mut bad = bytes;
            bad[7] = 2;
            assert_eq!(TileChunk::decode(&bad), Err(ChunkError::Version(2)));
        }
        assert_eq!(encode_fixed(&c).len(), HEADER_BYTES + 2 * FIXED_BYTES_PER_POINT);
        assert_eq!(c.anchor_range(), Some((17, 19)));
        // Version 5 (one attitude per point) reads without its attitudes.
        let mut v5 = c.encode();
        v5[7] = VERSION_POINT_ATTITUDE;
        for axis in 0..3 {
            put_column(&mut v5, 2, deltas([0.5f32 + axis as f32, 0.25].iter().map(|v| v.to_bits())));
        }
        assert_eq!(TileChunk::decode(&v5).unwrap(), c);
    }

    /// A chunk like the preparation writes: a scan head moving along a street, profiles of
    /// points across it, anchors and strip indices rising, neighbours along the profile and in
    /// the next revolution, a few segments.
    fn street_chunk(revolutions: usize, per_revolution: usize) -> TileChunk {
        let n = revolutions * per_revolution;
        let mut c =
            TileChunk::with_capacity(TileKey { tx: 36_653, ty: 386_893 }, 3, 1, [549_795.0, 5_803_395.0, 0.0], n);
        let mut seed = 17u64;
        let mut noise = move || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for rev in 0..revolutions {
            for row in 0..per_revolution {
                let k = rev * per_revolution + row;
                let time = k as f64 * 5e-7;
                let t0 = [(-2.0 + 12.0 * time) as f32, (7.5 + 0.01 * time) as f32, 41.9f32];
                let angle = row as f64 / per_revolution as f64 * std::f64::consts::PI;
                let range = 8.0 + 2.0 * angle.sin() + 0.005 * noise();
                let r = [0.3 * noise(), range * angle.cos(), -range * angle.sin()].map(|v| v as f32);
                let tilt = 0.02 * noise();
                let normal = [tilt as f32, 0.0, (1.0 - tilt * tilt).sqrt() as f32];
                let distance = 12.0 * time;
                let right = if row + 1 < per_revolution { (k + 1) as u32 } else { NO_NEIGHBOUR };
                let down = if rev + 1 < revolutions { (k + per_revolution) as u32 } else { NO_NEIGHBOUR };
                let edge = (0.01 + 0.002 * range) as f32;
                let segment = 1000 + (row * 4 / per_revolution) as u32;
                let source = 500_000 + 3 * k as u32;
                c.push(
                    t0,
                    r,
                    normal,
                    (distance / 0.5) as u32,
                    (distance / 0.5).fract() as f32,
                    right,
                    down,
                    edge,
                    segment,
                    source,
                );
            }
        }
        c
    }

    /// Version 4 holds every value bit for bit (negative, zero and extreme values too) in fewer
    /// bytes than version 3 (this street: 27.9 per point; small s1's chunks 41.4).
    #[test]
    fn block_columns_keep_every_bit_in_fewer_bytes() {
        let mut c = street_chunk(40, 250);
        // Values whose bit patterns lie far apart: signs, zeros, extremes, and the largest index.
        c.push(
            [-0.0, f32::MAX, f32::MIN_POSITIVE],
            [f32::MIN, 0.0, -1e-30],
            [1.0, -1.0, 0.0],
            u32::MAX,
            1.0,
            0,
            NO_NEIGHBOUR - 1,
            0.0,
            u32::MAX,
            0,
        );
        c.push([0.0; 3], [1.0; 3], [0.0, 0.0, -1.0], 0, 0.0, NO_NEIGHBOUR, NO_NEIGHBOUR, f32::MAX, 0, u32::MAX);
        // The neighbour index beyond the chunk is refused after decoding; put it in range.
        let last = c.len() - 1;
        c.down[last - 1] = last as u32;
        let bytes = c.encode();
        let decoded = TileChunk::decode(&bytes).unwrap();
        let bits3 = |v: &Vec<[f32; 3]>| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
        let bits = |v: &Vec<f32>| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits3(&decoded.t0), bits3(&c.t0));
        assert_eq!(bits3(&decoded.r), bits3(&c.r));
        assert_eq!(bits3(&decoded.normal), bits3(&c.normal));
        assert_eq!(bits(&decoded.lambda), bits(&c.lambda));
        assert_eq!(bits(&decoded.edge_limit), bits(&c.edge_limit));
        assert_eq!(decoded, c);
        let per_point = (bytes.len() - HEADER_BYTES) as f64 / c.len() as f64;
        assert!(per_point < 0.6 * FIXED_BYTES_PER_POINT as f64, "{per_point:.1} bytes per point");
        assert_eq!(TileChunk::decode(&encode_fixed(&c)).unwrap(), c);
    }

    /// A truncated or corrupted chunk is an error naming what is wrong, never a panic or a
    /// chunk of another length.
    #[test]
    fn truncated_or_corrupt_varint_chunks_are_errors() {
        let c = street_chunk(4, 12);
        let bytes = c.encode();
        for len in 0..bytes.len() {
            assert!(TileChunk::decode(&bytes[..len]).is_err(), "{len} of {} bytes decoded", bytes.len());
        }
        // Every byte flipped in turn: an error or a chunk of the same length, never a panic.
        for at in 0..bytes.len() {
            for flip in [0x01u8, 0x80, 0xff] {
                let mut bad = bytes.clone();
                bad[at] ^= flip;
                if let Ok(d) = TileChunk::decode(&bad) {
                    assert_eq!(d.len(), c.len(), "byte {at} ^ {flip:#x}");
                }
            }
        }
        // A column that runs past its length, and a header that claims more points than bytes.
        let mut bad = bytes.clone();
        let first_column = HEADER_BYTES;
        bad[first_column..first_column + 8].copy_from_slice(&1u64.to_le_bytes());
        let err = TileChunk::decode(&bad).unwrap_err();
        assert!(matches!(err, ChunkError::Column { column: "t0.x", .. }), "{err}");
        assert!(err.to_string().contains("prepare the strip again"), "{err}");
        let mut bad = bytes;
        bad[48..56].copy_from_slice(&(1u64 << 40).to_le_bytes());
        assert!(matches!(TileChunk::decode(&bad), Err(ChunkError::Length { .. })));
    }
}
