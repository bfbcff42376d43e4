//! Binary forms of what map and reduce tasks exchange: one tile's normal-equation blocks for one
//! trajectory, and one trajectory's corrections. Little-endian, every `f64` bit-exact (results of
//! the framework equal the in-process path's), with a magic and version so a reader rejects
//! anything else with a clear error.

use precimap_core::corrections::{AnchorCovariance, TrajectoryCorrections};
use precimap_estimate::{AnchorBlock, CalibrationNormals, FieldEquations};

const BLOCKS_MAGIC: &[u8; 8] = b"PMBLOCK1";
/// With the calibration's terms: version 1's blocks each followed by its cross terms (6 × K),
/// then the calibration's normal equations (K × K and K).
const BLOCKS_MAGIC_CALIBRATION: &[u8; 8] = b"PMBLOCK2";
/// A trajectory's share of the calibration's solve: `Y` per anchor.
const SHARE_MAGIC: &[u8; 8] = b"PMSHARE1";
const FIELD_MAGIC: &[u8; 8] = b"PMFIELD1";
/// With the field's heading (`Parameters::common_mode_heading`): version 1 followed by the
/// heading's right-hand side per node and its seven terms per node pair.
const FIELD_MAGIC_HEADING: &[u8; 8] = b"PMFIELD2";
/// With the field's tilt too (`Parameters::common_mode_tilt`): version 2 followed by the tilt's
/// right-hand side per node (2) and its twenty terms per node pair.
const FIELD_MAGIC_TILT: &[u8; 8] = b"PMFIELD3";
const CORRECTIONS_MAGIC: &[u8; 8] = b"PMCORR02";
/// Posterior standard deviations only (before the exported corrections table needed the whole
/// covariance to give them in the vehicle's frame).
const CORRECTIONS_MAGIC_SIGMA: &[u8; 8] = b"PMCORR01";
const POSITIONS_MAGIC: &[u8; 8] = b"PMANPOS2";
/// Horizontal positions only (before the campaign's motion needed the anchors' heights).
const POSITIONS_MAGIC_HORIZONTAL: &[u8; 8] = b"PMANPOS1";

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum CodecError {
    #[error("not a {what} object (bad magic or version); it was written by another program or version")]
    BadMagic { what: &'static str },
    #[error("{what} object is truncated at byte {at} of {len}")]
    Truncated { what: &'static str, at: usize, len: usize },
    #[error("{what} object has {extra} trailing bytes")]
    Trailing { what: &'static str, extra: usize },
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
    what: &'static str,
}

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8], magic: &[u8; 8], what: &'static str) -> Result<Self, CodecError> {
        if bytes.len() < 8 || &bytes[..8] != magic {
            return Err(CodecError::BadMagic { what });
        }
        Ok(Self { bytes, at: 8, what })
    }

    fn take<const N: usize>(&mut self) -> Result<[u8; N], CodecError> {
        let end = self.at + N;
        let slice = self.bytes.get(self.at..end).ok_or(CodecError::Truncated {
            what: self.what,
            at: self.at,
            len: self.bytes.len(),
        })?;
        self.at = end;
        let mut out = [0u8; N];
        out.copy_from_slice(slice);
        Ok(out)
    }

    fn u32(&mut self) -> Result<u32, CodecError> {
        Ok(u32::from_le_bytes(self.take()?))
    }

    fn i64(&mut self) -> Result<i64, CodecError> {
        Ok(i64::from_le_bytes(self.take()?))
    }

    fn u64(&mut self) -> Result<u64, CodecError> {
        Ok(u64::from_le_bytes(self.take()?))
    }

    fn f64(&mut self) -> Result<f64, CodecError> {
        Ok(f64::from_le_bytes(self.take()?))
    }

    fn f64s<const N: usize>(&mut self) -> Result<[f64; N], CodecError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64()?;
        }
        Ok(out)
    }

    /// `n` values, after checking they fit in the remaining bytes.
    fn f64_vec(&mut self, n: usize) -> Result<Vec<f64>, CodecError> {
        if n.saturating_mul(8) > self.bytes.len() - self.at {
            return Err(CodecError::Truncated { what: self.what, at: self.at, len: self.bytes.len() });
        }
        (0..n).map(|_| self.f64()).collect()
    }

    /// A count that must fit in the remaining bytes at `unit` bytes per item (guards allocations
    /// against a corrupt length).
    fn count(&mut self, unit: usize) -> Result<usize, CodecError> {
        let n = self.u32()? as usize;
        if n.saturating_mul(unit) > self.bytes.len() - self.at {
            return Err(CodecError::Truncated { what: self.what, at: self.at, len: self.bytes.len() });
        }
        Ok(n)
    }

    fn finish(self) -> Result<(), CodecError> {
        match self.bytes.len() - self.at {
            0 => Ok(()),
            extra => Err(CodecError::Trailing { what: self.what, extra }),
        }
    }
}

fn put_f64s(out: &mut Vec<u8>, values: &[f64]) {
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
}

const BLOCK_BYTES: usize = 4 + 4 + 8 * (21 + 21 + 6);

pub fn encode_blocks(blocks: &[AnchorBlock]) -> Vec<u8> {
    let mut out = Vec::with_capacity(12 + blocks.len() * BLOCK_BYTES);
    out.extend_from_slice(BLOCKS_MAGIC);
    out.extend_from_slice(&(blocks.len() as u32).to_le_bytes());
    for b in blocks {
        put_block(&mut out, b);
    }
    out
}

/// A tile's blocks of one trajectory, with the calibration's terms where it carries them
/// (version 2; version 1 without).
pub fn encode_trajectory_blocks(blocks: &[AnchorBlock], calibration: Option<&CalibrationNormals>) -> Vec<u8> {
    let Some(normals) = calibration else { return encode_blocks(blocks) };
    let k = normals.len();
    let mut out = Vec::with_capacity(16 + blocks.len() * (BLOCK_BYTES + 48 * k) + 8 * k * (k + 1));
    out.extend_from_slice(BLOCKS_MAGIC_CALIBRATION);
    out.extend_from_slice(&(blocks.len() as u32).to_le_bytes());
    out.extend_from_slice(&(k as u32).to_le_bytes());
    for b in blocks {
        put_block(&mut out, b);
        if b.cross.len() == 6 * k {
            put_f64s(&mut out, &b.cross);
        } else {
            put_f64s(&mut out, &vec![0.0; 6 * k]);
        }
    }
    put_f64s(&mut out, &normals.h);
    put_f64s(&mut out, &normals.b);
    out
}

/// Either version of a tile's blocks of one trajectory, and the calibration's terms of version 2.
pub fn decode_trajectory_blocks(bytes: &[u8]) -> Result<(Vec<AnchorBlock>, Option<CalibrationNormals>), CodecError> {
    if !bytes.starts_with(BLOCKS_MAGIC_CALIBRATION) {
        return Ok((decode_blocks(bytes)?, None));
    }
    let mut r = Reader::new(bytes, BLOCKS_MAGIC_CALIBRATION, "normal-equation blocks")?;
    let n = r.count(BLOCK_BYTES)?;
    let k = r.count(8)?;
    let mut blocks = Vec::with_capacity(n);
    for _ in 0..n {
        let block = read_block(&mut r)?;
        blocks.push(AnchorBlock { cross: r.f64_vec(6 * k)?, ..block });
    }
    let h = r.f64_vec(k * k)?;
    let b = r.f64_vec(k)?;
    r.finish()?;
    Ok((blocks, Some(CalibrationNormals { h, b })))
}

/// A trajectory's `Y` of its calibration share (anchors × 6 × K), from `first_anchor`.
pub fn encode_share(first_anchor: u32, unknowns: usize, y: &[f64]) -> Vec<u8> {
    let mut out = Vec::with_capacity(20 + 8 * y.len());
    out.extend_from_slice(SHARE_MAGIC);
    out.extend_from_slice(&first_anchor.to_le_bytes());
    out.extend_from_slice(&(unknowns as u32).to_le_bytes());
    out.extend_from_slice(&(y.len() as u32).to_le_bytes());
    put_f64s(&mut out, y);
    out
}

/// [`encode_share`]'s `(first_anchor, unknowns, y)`.
pub fn decode_share(bytes: &[u8]) -> Result<(u32, usize, Vec<f64>), CodecError> {
    let mut r = Reader::new(bytes, SHARE_MAGIC, "calibration share")?;
    let first = r.u32()?;
    let k = r.u32()? as usize;
    let n = r.count(8)?;
    let y = r.f64_vec(n)?;
    r.finish()?;
    Ok((first, k, y))
}

pub fn decode_blocks(bytes: &[u8]) -> Result<Vec<AnchorBlock>, CodecError> {
    let mut r = Reader::new(bytes, BLOCKS_MAGIC, "normal-equation blocks")?;
    let n = r.count(BLOCK_BYTES)?;
    let mut blocks = Vec::with_capacity(n);
    for _ in 0..n {
        blocks.push(read_block(&mut r)?);
    }
    r.finish()?;
    Ok(blocks)
}

/// One block as both versions store it (version 2 follows it with its cross terms).
fn put_block(out: &mut Vec<u8>, b: &AnchorBlock) {
    out.extend_from_slice(&b.anchor.to_le_bytes());
    out.extend_from_slice(&b.observations.to_le_bytes());
    put_f64s(out, &b.diag);
    put_f64s(out, &b.next);
    put_f64s(out, &b.rhs);
}

fn read_block(r: &mut Reader) -> Result<AnchorBlock, CodecError> {
    let anchor = r.u32()?;
    let observations = r.u32()?;
    let diag = r.f64s::<21>()?;
    let next = r.f64s::<21>()?;
    let rhs = r.f64s::<6>()?;
    Ok(AnchorBlock { anchor, diag, next, rhs, observations, cross: Vec::new() })
}

/// The field object's version by what it carries (the tilt always comes with the heading).
fn field_magic(heading: bool, tilt: bool) -> &'static [u8; 8] {
    match (heading, tilt) {
        (_, true) => FIELD_MAGIC_TILT,
        (true, false) => FIELD_MAGIC_HEADING,
        (false, false) => FIELD_MAGIC,
    }
}

/// One tile's common-mode field equations: nodes, node-pair blocks, right-hand sides.
/// Equations without the heading keep version 1, byte for byte, and without the tilt version 2.
pub fn encode_field(f: &FieldEquations) -> Vec<u8> {
    let tilt = !f.tilt_pairs.is_empty() || !f.tilt_rhs.is_empty();
    let heading = tilt || !f.heading_pairs.is_empty() || !f.heading_rhs.is_empty();
    let mut out = Vec::with_capacity(28 + f.nodes.len() * 48 + f.pairs.len() * 136);
    out.extend_from_slice(field_magic(heading, tilt));
    out.extend_from_slice(&f.observations.to_le_bytes());
    out.extend_from_slice(&(f.nodes.len() as u32).to_le_bytes());
    for (node, rhs) in f.nodes.iter().zip(&f.rhs) {
        out.extend_from_slice(&node.0.to_le_bytes());
        out.extend_from_slice(&node.1.to_le_bytes());
        put_f64s(&mut out, rhs);
    }
    out.extend_from_slice(&(f.pairs.len() as u32).to_le_bytes());
    for (a, b, m) in &f.pairs {
        out.extend_from_slice(&a.to_le_bytes());
        out.extend_from_slice(&b.to_le_bytes());
        put_f64s(&mut out, m);
    }
    if heading {
        // Lengths written, not assumed: a reader checks them against the nodes and pairs.
        out.extend_from_slice(&(f.heading_rhs.len() as u32).to_le_bytes());
        put_f64s(&mut out, &f.heading_rhs);
        out.extend_from_slice(&(f.heading_pairs.len() as u32).to_le_bytes());
        for x in &f.heading_pairs {
            put_f64s(&mut out, x);
        }
    }
    if tilt {
        out.extend_from_slice(&(f.tilt_rhs.len() as u32).to_le_bytes());
        for r in &f.tilt_rhs {
            put_f64s(&mut out, r);
        }
        out.extend_from_slice(&(f.tilt_pairs.len() as u32).to_le_bytes());
        for y in &f.tilt_pairs {
            put_f64s(&mut out, y);
        }
    }
    out
}

pub fn decode_field(bytes: &[u8]) -> Result<FieldEquations, CodecError> {
    const WHAT: &str = "common-mode field equations";
    let tilt = bytes.starts_with(FIELD_MAGIC_TILT);
    let heading = tilt || bytes.starts_with(FIELD_MAGIC_HEADING);
    let mut r = Reader::new(bytes, field_magic(heading, tilt), WHAT)?;
    let observations = r.u64()?;
    let n = r.count(40)?;
    let (mut nodes, mut rhs) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for _ in 0..n {
        nodes.push((r.i64()?, r.i64()?));
        rhs.push(r.f64s::<3>()?);
    }
    let m = r.count(80)?;
    let mut pairs = Vec::with_capacity(m);
    for _ in 0..m {
        let (a, b) = (r.u32()?, r.u32()?);
        if a as usize >= n || b as usize >= n {
            return Err(CodecError::Truncated { what: WHAT, at: r.at, len: bytes.len() });
        }
        pairs.push((a, b, r.f64s::<9>()?));
    }
    let (mut heading_rhs, mut heading_pairs) = (Vec::new(), Vec::new());
    if heading {
        if r.count(8)? != n {
            return Err(CodecError::Truncated { what: WHAT, at: r.at, len: bytes.len() });
        }
        for _ in 0..n {
            heading_rhs.push(r.f64()?);
        }
        if r.count(56)? != m {
            return Err(CodecError::Truncated { what: WHAT, at: r.at, len: bytes.len() });
        }
        for _ in 0..m {
            heading_pairs.push(r.f64s::<7>()?);
        }
    }
    let (mut tilt_rhs, mut tilt_pairs) = (Vec::new(), Vec::new());
    if tilt {
        if r.count(16)? != n {
            return Err(CodecError::Truncated { what: WHAT, at: r.at, len: bytes.len() });
        }
        for _ in 0..n {
            tilt_rhs.push(r.f64s::<2>()?);
        }
        if r.count(160)? != m {
            return Err(CodecError::Truncated { what: WHAT, at: r.at, len: bytes.len() });
        }
        for _ in 0..m {
            tilt_pairs.push(r.f64s::<20>()?);
        }
    }
    r.finish()?;
    Ok(FieldEquations { nodes, pairs, rhs, observations, heading_pairs, heading_rhs, tilt_pairs, tilt_rhs })
}

/// Corrections with the optional posterior covariances of the final iteration.
pub fn encode_corrections(c: &TrajectoryCorrections, covariance: Option<&[AnchorCovariance]>) -> Vec<u8> {
    let covariance = covariance.unwrap_or(&[]);
    let mut out = Vec::with_capacity(20 + c.values.len() * 48 + covariance.len() * 168);
    out.extend_from_slice(CORRECTIONS_MAGIC);
    out.extend_from_slice(&c.first_anchor.to_le_bytes());
    out.extend_from_slice(&(c.values.len() as u32).to_le_bytes());
    for v in &c.values {
        put_f64s(&mut out, v);
    }
    out.extend_from_slice(&(covariance.len() as u32).to_le_bytes());
    for s in covariance {
        put_f64s(&mut out, &s.0);
    }
    out
}

/// Reads what [`encode_corrections`] wrote, and the version before it (standard deviations
/// alone, read as a covariance without correlations).
#[allow(clippy::type_complexity)]
pub fn decode_corrections(bytes: &[u8]) -> Result<(TrajectoryCorrections, Option<Vec<AnchorCovariance>>), CodecError> {
    let sigma_only = bytes.starts_with(CORRECTIONS_MAGIC_SIGMA);
    let magic = if sigma_only { CORRECTIONS_MAGIC_SIGMA } else { CORRECTIONS_MAGIC };
    let mut r = Reader::new(bytes, magic, "trajectory corrections")?;
    let first_anchor = r.u32()?;
    let n = r.count(48)?;
    let mut values = Vec::with_capacity(n);
    for _ in 0..n {
        values.push(r.f64s::<6>()?);
    }
    let m = r.count(if sigma_only { 48 } else { 168 })?;
    let mut covariance = Vec::with_capacity(m);
    for _ in 0..m {
        covariance.push(if sigma_only {
            AnchorCovariance::from_sigma(r.f64s::<6>()?)
        } else {
            AnchorCovariance(r.f64s::<21>()?)
        });
    }
    r.finish()?;
    if values.is_empty() {
        return Err(CodecError::Truncated { what: "trajectory corrections", at: 12, len: bytes.len() });
    }
    Ok((TrajectoryCorrections { first_anchor, values }, (m > 0).then_some(covariance)))
}

/// Every trajectory's anchor positions (metres), in trajectory order.
pub fn encode_positions(positions: &[Vec<[f64; 3]>]) -> Vec<u8> {
    let points: usize = positions.iter().map(Vec::len).sum();
    let mut out = Vec::with_capacity(12 + positions.len() * 4 + points * 24);
    out.extend_from_slice(POSITIONS_MAGIC);
    out.extend_from_slice(&(positions.len() as u32).to_le_bytes());
    for p in positions {
        out.extend_from_slice(&(p.len() as u32).to_le_bytes());
        for xyz in p {
            put_f64s(&mut out, xyz);
        }
    }
    out
}

/// [`encode_positions`]' objects, and the horizontal ones of version 1 (without heights):
/// their anchors all get height 0, so the campaign's motion turns them about
/// their common height (what a campaign on level ground needs).
pub fn decode_positions(bytes: &[u8]) -> Result<Vec<Vec<[f64; 3]>>, CodecError> {
    let horizontal = bytes.starts_with(POSITIONS_MAGIC_HORIZONTAL);
    let magic = if horizontal { POSITIONS_MAGIC_HORIZONTAL } else { POSITIONS_MAGIC };
    let mut r = Reader::new(bytes, magic, "anchor positions")?;
    let trajectories = r.count(4)?;
    let mut out = Vec::with_capacity(trajectories);
    for _ in 0..trajectories {
        let n = r.count(if horizontal { 16 } else { 24 })?;
        let mut p = Vec::with_capacity(n);
        for _ in 0..n {
            p.push(if horizontal {
                let [x, y] = r.f64s::<2>()?;
                [x, y, 0.0]
            } else {
                r.f64s::<3>()?
            });
        }
        out.push(p);
    }
    r.finish()?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block(anchor: u32, seed: f64) -> AnchorBlock {
        let mut b = AnchorBlock::new(anchor);
        for k in 0..21 {
            b.diag[k] = seed * (k as f64 + 0.1).sqrt();
            b.next[k] = -seed / (k as f64 + 1.3);
        }
        b.rhs = [seed, -1e-300, f64::MIN_POSITIVE, 1e300, 0.0, -0.0];
        b.observations = 7 + anchor;
        b
    }

    #[test]
    fn field_round_trip_bit_exact() {
        let f = FieldEquations {
            nodes: vec![(-3, 7), (16_667, 180_000)],
            pairs: vec![(0, 0, [1.5; 9]), (0, 1, std::array::from_fn(|k| -1e-300 * k as f64)), (1, 1, [0.25; 9])],
            rhs: vec![[0.1, -0.2, 1e300], [f64::MIN_POSITIVE, -0.0, 3.0]],
            observations: 1 << 40,
            ..Default::default()
        };
        let bytes = encode_field(&f);
        let back = decode_field(&bytes).unwrap();
        assert_eq!(back.nodes, f.nodes);
        assert_eq!(back.observations, f.observations);
        let bits = |e: &FieldEquations| -> Vec<u64> {
            e.rhs.iter().flatten().chain(e.pairs.iter().flat_map(|p| p.2.iter())).map(|v| v.to_bits()).collect()
        };
        assert_eq!(bits(&back), bits(&f));
        assert!(decode_field(&bytes[..bytes.len() - 3]).is_err());
        let mut bad = bytes.clone();
        // The second pair's node index points past the nodes.
        let at = 8 + 8 + 4 + 2 * 40 + 4 + 80;
        bad[at..at + 4].copy_from_slice(&9u32.to_le_bytes());
        assert!(decode_field(&bad).is_err());
    }

    #[test]
    fn field_with_heading_round_trips_and_without_keeps_version_1() {
        let mut f = FieldEquations {
            nodes: vec![(-3, 7), (16_667, 180_000)],
            pairs: vec![(0, 0, [1.5; 9]), (0, 1, [-2.0; 9])],
            rhs: vec![[0.1, -0.2, 1e300], [f64::MIN_POSITIVE, -0.0, 3.0]],
            observations: 12,
            heading_pairs: vec![std::array::from_fn(|k| k as f64 - 0.5), [-0.0, 1e-300, 3.0, 4.0, 5.0, 6.0, 7.0]],
            heading_rhs: vec![0.25, -1e200],
            tilt_pairs: Vec::new(),
            tilt_rhs: Vec::new(),
        };
        let bytes = encode_field(&f);
        assert_eq!(&bytes[..8], FIELD_MAGIC_HEADING);
        let back = decode_field(&bytes).unwrap();
        let bits = |e: &FieldEquations| -> Vec<u64> {
            e.heading_rhs.iter().chain(e.heading_pairs.iter().flatten()).map(|v| v.to_bits()).collect()
        };
        assert_eq!(bits(&back), bits(&f));
        assert_eq!((back.nodes.clone(), back.pairs.len(), back.observations), (f.nodes.clone(), 2, 12));
        assert!(decode_field(&bytes[..bytes.len() - 8]).is_err());
        // The heading's pair count must match the pairs'.
        let mut bad = bytes.clone();
        let at = bytes.len() - 2 * 56 - 4;
        bad[at..at + 4].copy_from_slice(&1u32.to_le_bytes());
        assert!(decode_field(&bad).is_err());
        // With the tilt: version 3, every term bit-exact, its counts checked.
        let mut tilted = f.clone();
        tilted.tilt_pairs = vec![std::array::from_fn(|k| k as f64 * 1e-7), std::array::from_fn(|k| -(k as f64))];
        tilted.tilt_pairs[1][19] = -0.0;
        tilted.tilt_rhs = vec![[1.5, -2.5], [f64::MAX, 1e-310]];
        let bytes = encode_field(&tilted);
        assert_eq!(&bytes[..8], FIELD_MAGIC_TILT);
        let back = decode_field(&bytes).unwrap();
        let tilt_bits = |e: &FieldEquations| -> Vec<u64> {
            e.tilt_rhs.iter().flatten().chain(e.tilt_pairs.iter().flatten()).map(|v| v.to_bits()).collect()
        };
        assert_eq!((bits(&back), tilt_bits(&back)), (bits(&tilted), tilt_bits(&tilted)));
        assert!(decode_field(&bytes[..bytes.len() - 8]).is_err());
        let mut bad = bytes.clone();
        let at = bytes.len() - 2 * 160 - 4;
        bad[at..at + 4].copy_from_slice(&3u32.to_le_bytes());
        assert!(decode_field(&bad).is_err());
        // Without the heading: version 1, as every earlier field object.
        f.heading_pairs.clear();
        f.heading_rhs.clear();
        let plain = encode_field(&f);
        assert_eq!(&plain[..8], FIELD_MAGIC);
        assert_eq!(decode_field(&plain).unwrap(), f);
    }

    /// Blocks with the calibration's terms and a share's `Y` come back bit for bit; blocks
    /// without them keep version 1, which the reader of both versions takes.
    #[test]
    fn calibration_blocks_and_shares_round_trip_bit_exact() {
        let k = 3;
        let mut blocks: Vec<_> = (0..4).map(|i| block(7 + i, 0.3 + i as f64 / 7.0)).collect();
        for (i, b) in blocks.iter_mut().enumerate() {
            b.cross = (0..6 * k).map(|j| (i * 31 + j) as f64 / 17.0 - 1.1).collect();
        }
        let normals = CalibrationNormals { h: (0..k * k).map(|j| j as f64 * 0.37).collect(), b: vec![0.1, -0.2, 1e-9] };
        let bytes = encode_trajectory_blocks(&blocks, Some(&normals));
        let (back, back_normals) = decode_trajectory_blocks(&bytes).unwrap();
        assert_eq!(back, blocks);
        assert_eq!(back_normals, Some(normals));
        assert!(decode_trajectory_blocks(&bytes[..bytes.len() - 1]).is_err());
        let plain: Vec<_> = blocks.iter().map(|b| AnchorBlock { cross: Vec::new(), ..b.clone() }).collect();
        let v1 = encode_trajectory_blocks(&plain, None);
        assert_eq!(v1, encode_blocks(&plain));
        assert_eq!(decode_trajectory_blocks(&v1).unwrap(), (plain, None));
        let y: Vec<f64> = (0..5 * 6 * k).map(|j| (j as f64).sin()).collect();
        let share = encode_share(42, k, &y);
        assert_eq!(decode_share(&share).unwrap(), (42, k, y));
        assert!(decode_share(&share[..share.len() - 8]).is_err());
    }

    #[test]
    fn blocks_round_trip_bit_exact() {
        let blocks: Vec<_> = (0..5).map(|i| block(100 + i, 0.1 + i as f64 / 3.0)).collect();
        let bytes = encode_blocks(&blocks);
        let back = decode_blocks(&bytes).unwrap();
        assert_eq!(back.len(), blocks.len());
        for (a, b) in blocks.iter().zip(&back) {
            assert_eq!(a.anchor, b.anchor);
            assert_eq!(a.observations, b.observations);
            assert!(a
                .diag
                .iter()
                .chain(&a.next)
                .chain(&a.rhs)
                .zip(b.diag.iter().chain(&b.next).chain(&b.rhs))
                .all(|(x, y)| x.to_bits() == y.to_bits()));
        }
        assert!(decode_blocks(&bytes[..bytes.len() - 1]).is_err());
        assert!(matches!(decode_blocks(b"PMCORR01xxxx"), Err(CodecError::BadMagic { .. })));
        let mut extra = bytes.clone();
        extra.push(0);
        assert!(matches!(decode_blocks(&extra), Err(CodecError::Trailing { .. })));
        // A corrupt count cannot make the reader allocate beyond the object.
        let mut huge = encode_blocks(&[]);
        huge[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(decode_blocks(&huge), Err(CodecError::Truncated { .. })));
    }

    #[test]
    fn positions_round_trip_bit_exact() {
        let p = vec![
            vec![[549_795.25, 5_803_395.125, 57.5], [-0.0, f64::MIN_POSITIVE, -1e-300]],
            vec![],
            vec![[1e300, -1e-300, 0.0]],
        ];
        let bytes = encode_positions(&p);
        let back = decode_positions(&bytes).unwrap();
        let bits = |v: &[Vec<[f64; 3]>]| -> Vec<u64> { v.iter().flatten().flatten().map(|x| x.to_bits()).collect() };
        assert_eq!(back.iter().map(Vec::len).collect::<Vec<_>>(), vec![2, 0, 1]);
        assert_eq!(bits(&back), bits(&p));
        assert!(decode_positions(&bytes[..bytes.len() - 1]).is_err());
        // A horizontal object of an earlier version: its anchors at height 0.
        let mut old = b"PMANPOS1".to_vec();
        old.extend_from_slice(&1u32.to_le_bytes());
        old.extend_from_slice(&1u32.to_le_bytes());
        old.extend_from_slice(&549_795.25f64.to_le_bytes());
        old.extend_from_slice(&5_803_395.125f64.to_le_bytes());
        assert_eq!(decode_positions(&old).unwrap(), vec![vec![[549_795.25, 5_803_395.125, 0.0]]]);
        assert!(decode_positions(&old[..old.len() - 1]).is_err());
        assert!(matches!(
            decode_positions(&encode_field(&FieldEquations::default())),
            Err(CodecError::BadMagic { .. })
        ));
    }

    #[test]
    fn corrections_round_trip_with_and_without_covariance() {
        let c = TrajectoryCorrections { first_anchor: 42, values: vec![[0.1, -0.2, 0.3, 1e-5, -2e-5, 3e-5]; 4] };
        let (back, covariance) = decode_corrections(&encode_corrections(&c, None)).unwrap();
        assert_eq!(back, c);
        assert!(covariance.is_none());
        let s: Vec<AnchorCovariance> =
            (0..4).map(|k| AnchorCovariance::from_fn(|a, b| 1e-6 * (k + 1) as f64 / (1 + a + b) as f64)).collect();
        let (back, covariance) = decode_corrections(&encode_corrections(&c, Some(&s))).unwrap();
        assert_eq!(back, c);
        assert_eq!(covariance.unwrap(), s);
        assert!(decode_corrections(&encode_corrections(&c, None)[..20]).is_err());
        assert!(decode_corrections(&encode_corrections(&c, Some(&s))[..300]).is_err());
        // The version before: standard deviations alone, read as a covariance without correlations.
        let mut old = b"PMCORR01".to_vec();
        old.extend_from_slice(&42u32.to_le_bytes());
        old.extend_from_slice(&4u32.to_le_bytes());
        c.values.iter().flatten().for_each(|v| old.extend_from_slice(&v.to_le_bytes()));
        old.extend_from_slice(&4u32.to_le_bytes());
        let sigma: [f64; 6] = [1e-3, 2e-3, 3e-3, 1e-5, 2e-5, 3e-5];
        (0..4).for_each(|_| sigma.iter().for_each(|v| old.extend_from_slice(&v.to_le_bytes())));
        let (back, covariance) = decode_corrections(&old).unwrap();
        assert_eq!(back, c);
        assert_eq!(covariance.unwrap(), vec![AnchorCovariance::from_sigma(sigma); 4]);
    }
}
