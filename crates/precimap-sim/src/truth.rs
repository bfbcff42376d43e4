//! What the simulator knows and the estimation never sees: per point, in acquisition order, the
//! noise-free position on the true surface, the true surface normal, the surface id and its class.
//!
//! `truth/{strip}.truth` is little-endian binary: the magic `PMTRUTH1`, a `u32` format version
//! (1), a `u32` record size in bytes (41), a `u64` point count, then one 41-byte record per point:
//! `x, y, z: f64` (absolute, metres), `nx, ny, nz: f32`, `surface_id: u32`, `class: u8`.

use std::fs::File;
use std::io::{self, BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

pub const TRUTH_MAGIC: &[u8; 8] = b"PMTRUTH1";
pub const TRUTH_VERSION: u32 = 1;
const RECORD_BYTES: usize = 41;
const HEADER_BYTES: u64 = 24;

/// What kind of thing a simulated point hit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum SurfaceClass {
    Road = 1,
    Sidewalk = 2,
    Curb = 3,
    Facade = 4,
    Pole = 5,
    Car = 6,
    Roof = 7,
    /// Tree foliage: clutter with no well-defined surface.
    Foliage = 8,
}

impl SurfaceClass {
    pub fn from_u8(v: u8) -> Option<Self> {
        use SurfaceClass::*;
        Some(match v {
            1 => Road,
            2 => Sidewalk,
            3 => Curb,
            4 => Facade,
            5 => Pole,
            6 => Car,
            7 => Roof,
            8 => Foliage,
            _ => return None,
        })
    }

    /// True for points on a well-defined surface (everything but foliage).
    pub fn is_surface(self) -> bool {
        self != SurfaceClass::Foliage
    }

    pub fn name(self) -> &'static str {
        use SurfaceClass::*;
        match self {
            Road => "road",
            Sidewalk => "sidewalk",
            Curb => "curb",
            Facade => "facade",
            Pole => "pole",
            Car => "car",
            Roof => "roof",
            Foliage => "foliage",
        }
    }
}

/// The truth of one point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TruthPoint {
    pub position: [f64; 3],
    pub normal: [f32; 3],
    pub surface_id: u32,
    pub class: SurfaceClass,
}

#[derive(Debug, thiserror::Error)]
pub enum TruthError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: io::Error },
    #[error("{path}: not a precimap truth file (bad magic or version {version})")]
    BadHeader { path: PathBuf, version: u32 },
    #[error("{path}: record {index} has unknown surface class {class}")]
    BadClass { path: PathBuf, index: u64, class: u8 },
    #[error("{path}: header says {expected} points but the file holds {found}")]
    Truncated { path: PathBuf, expected: u64, found: u64 },
}

/// Streams truth records to a file; the point count in the header is patched on [`finish`].
///
/// [`finish`]: TruthWriter::finish
#[derive(Debug)]
pub struct TruthWriter {
    path: PathBuf,
    out: BufWriter<File>,
    count: u64,
}

impl TruthWriter {
    pub fn create(path: &Path) -> Result<Self, TruthError> {
        let io_err = |source| TruthError::Io { path: path.to_path_buf(), source };
        let mut out = BufWriter::with_capacity(1 << 20, File::create(path).map_err(io_err)?);
        out.write_all(TRUTH_MAGIC).map_err(io_err)?;
        out.write_all(&TRUTH_VERSION.to_le_bytes()).map_err(io_err)?;
        out.write_all(&(RECORD_BYTES as u32).to_le_bytes()).map_err(io_err)?;
        out.write_all(&0u64.to_le_bytes()).map_err(io_err)?;
        Ok(Self { path: path.to_path_buf(), out, count: 0 })
    }

    pub fn push(&mut self, p: &TruthPoint) -> Result<(), TruthError> {
        let mut rec = [0u8; RECORD_BYTES];
        for k in 0..3 {
            rec[k * 8..k * 8 + 8].copy_from_slice(&p.position[k].to_le_bytes());
            rec[24 + k * 4..28 + k * 4].copy_from_slice(&p.normal[k].to_le_bytes());
        }
        rec[36..40].copy_from_slice(&p.surface_id.to_le_bytes());
        rec[40] = p.class as u8;
        self.out.write_all(&rec).map_err(|source| TruthError::Io { path: self.path.clone(), source })?;
        self.count += 1;
        Ok(())
    }

    pub fn finish(mut self) -> Result<u64, TruthError> {
        let path = self.path.clone();
        let io_err = |source| TruthError::Io { path: path.clone(), source };
        self.out.flush().map_err(io_err)?;
        let mut file = self.out.into_inner().map_err(|e| io_err(e.into_error()))?;
        file.seek(SeekFrom::Start(16)).map_err(io_err)?;
        file.write_all(&self.count.to_le_bytes()).map_err(io_err)?;
        Ok(self.count)
    }
}

/// Reads a truth file sequentially.
#[derive(Debug)]
pub struct TruthReader {
    path: PathBuf,
    input: BufReader<File>,
    remaining: u64,
    index: u64,
    count: u64,
}

impl TruthReader {
    pub fn open(path: &Path) -> Result<Self, TruthError> {
        let io_err = |source| TruthError::Io { path: path.to_path_buf(), source };
        let file = File::open(path).map_err(io_err)?;
        let len = file.metadata().map_err(io_err)?.len();
        let mut input = BufReader::with_capacity(1 << 20, file);
        let mut header = [0u8; HEADER_BYTES as usize];
        input.read_exact(&mut header).map_err(io_err)?;
        let version = u32::from_le_bytes(header[8..12].try_into().expect("4 bytes"));
        let record = u32::from_le_bytes(header[12..16].try_into().expect("4 bytes"));
        if &header[..8] != TRUTH_MAGIC || version != TRUTH_VERSION || record as usize != RECORD_BYTES {
            return Err(TruthError::BadHeader { path: path.to_path_buf(), version });
        }
        let count = u64::from_le_bytes(header[16..24].try_into().expect("8 bytes"));
        let found = (len - HEADER_BYTES) / RECORD_BYTES as u64;
        if found != count {
            return Err(TruthError::Truncated { path: path.to_path_buf(), expected: count, found });
        }
        Ok(Self { path: path.to_path_buf(), input, remaining: count, index: 0, count })
    }

    pub fn len(&self) -> u64 {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Reads every remaining record.
    pub fn read_all(mut self) -> Result<Vec<TruthPoint>, TruthError> {
        let mut out = Vec::with_capacity(self.remaining as usize);
        while let Some(p) = self.next_point()? {
            out.push(p);
        }
        Ok(out)
    }

    pub fn next_point(&mut self) -> Result<Option<TruthPoint>, TruthError> {
        if self.remaining == 0 {
            return Ok(None);
        }
        let mut rec = [0u8; RECORD_BYTES];
        self.input.read_exact(&mut rec).map_err(|source| TruthError::Io { path: self.path.clone(), source })?;
        let f64_at = |o: usize| f64::from_le_bytes(rec[o..o + 8].try_into().expect("8 bytes"));
        let f32_at = |o: usize| f32::from_le_bytes(rec[o..o + 4].try_into().expect("4 bytes"));
        let class = SurfaceClass::from_u8(rec[40]).ok_or(TruthError::BadClass {
            path: self.path.clone(),
            index: self.index,
            class: rec[40],
        })?;
        self.remaining -= 1;
        self.index += 1;
        Ok(Some(TruthPoint {
            position: [f64_at(0), f64_at(8), f64_at(16)],
            normal: [f32_at(24), f32_at(28), f32_at(32)],
            surface_id: u32::from_le_bytes(rec[36..40].try_into().expect("4 bytes")),
            class,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.truth");
        let pts = vec![
            TruthPoint {
                position: [549_800.123_456_7, 5_803_400.5, 55.25],
                normal: [0.0, 0.0, 1.0],
                surface_id: 7,
                class: SurfaceClass::Road,
            },
            TruthPoint {
                position: [1.0, 2.0, 3.0],
                normal: [1.0, 0.0, 0.0],
                surface_id: 9,
                class: SurfaceClass::Foliage,
            },
        ];
        let mut w = TruthWriter::create(&path).unwrap();
        for p in &pts {
            w.push(p).unwrap();
        }
        assert_eq!(w.finish().unwrap(), 2);
        let r = TruthReader::open(&path).unwrap();
        assert_eq!(r.len(), 2);
        assert_eq!(r.read_all().unwrap(), pts);
        // Truncation is detected.
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        assert!(matches!(TruthReader::open(&path), Err(TruthError::Truncated { .. })));
    }
}
