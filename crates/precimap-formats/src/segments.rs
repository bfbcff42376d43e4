//! Per-point id files that `precimap run` writes next to the corrected strips, one per strip:
//! little-endian, an 8-byte magic, a `u32` format version (1), a `u32` (0), a `u64` point count,
//! then one `u32` per point in file order, `u32::MAX` for none.
//!
//! - `OUT/segments/{strip}.seg` (magic `PMSEGMNT`): the point's segment id in its strip, or none
//!   (no normal, removed small region, or a revolution dropped at standstill).
//! - `OUT/assignments/{strip}.asg` (magic `PMASSIGN`, `run --assignments`): the surface model of
//!   the latent map the point was compared with in a last map pass over the final corrections
//!   (ids unique within the campaign), or none (not an observation: outside every tile core, no
//!   model or latent surface, or beyond the outlier threshold).

use crate::FormatError;
use std::path::Path;

/// Magic, what the file holds, and the action named in I/O errors.
type Kind = (&'static [u8; 8], &'static str, &'static str);
const SEGMENTS: Kind = (b"PMSEGMNT", "segment", "read segment file");
const ASSIGNMENTS: Kind = (b"PMASSIGN", "assignment", "read assignment file");
const VERSION: u32 = 1;
const HEADER_BYTES: usize = 24;

fn encode_ids(magic: &[u8; 8], ids: &[u32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + 4 * ids.len());
    out.extend_from_slice(magic);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out.extend_from_slice(&(ids.len() as u64).to_le_bytes());
    for id in ids {
        out.extend_from_slice(&id.to_le_bytes());
    }
    out
}

fn decode_ids((magic, what, _): Kind, bytes: &[u8]) -> Result<Vec<u32>, String> {
    if bytes.len() < HEADER_BYTES || &bytes[..8] != magic {
        return Err(format!("not a precimap {what} file (bad magic or shorter than its header)"));
    }
    let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
    if version != VERSION {
        return Err(format!("{what} file version {version} is not supported (this build reads {VERSION})"));
    }
    let mut count = [0u8; 8];
    count.copy_from_slice(&bytes[16..24]);
    let count = u64::from_le_bytes(count);
    let body = &bytes[HEADER_BYTES..];
    if body.len() as u64 != count.saturating_mul(4) {
        return Err(format!(
            "header says {count} points but {} bytes follow (expected {}); the file is truncated or corrupt",
            body.len(),
            count.saturating_mul(4)
        ));
    }
    Ok(body.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
}

fn read_ids(kind: Kind, path: &Path) -> Result<Vec<u32>, FormatError> {
    let bytes = std::fs::read(path).map_err(|e| FormatError::io(path, kind.2, e))?;
    decode_ids(kind, &bytes).map_err(|m| FormatError::file(path, m))
}

pub fn encode_segments(ids: &[u32]) -> Vec<u8> {
    encode_ids(SEGMENTS.0, ids)
}

pub fn decode_segments(bytes: &[u8]) -> Result<Vec<u32>, String> {
    decode_ids(SEGMENTS, bytes)
}

/// Reads a segment file; every problem names the file.
pub fn read_segments(path: &Path) -> Result<Vec<u32>, FormatError> {
    read_ids(SEGMENTS, path)
}

pub fn encode_assignments(ids: &[u32]) -> Vec<u8> {
    encode_ids(ASSIGNMENTS.0, ids)
}

/// Reads an assignment file; every problem names the file.
pub fn read_assignments(path: &Path) -> Result<Vec<u32>, FormatError> {
    read_ids(ASSIGNMENTS, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_truncation() {
        let ids = vec![0, 5, u32::MAX, 7];
        let bytes = encode_segments(&ids);
        assert_eq!(decode_segments(&bytes).unwrap(), ids);
        assert!(decode_segments(&bytes[..bytes.len() - 2]).unwrap_err().contains("truncated"));
        assert!(decode_segments(b"PMCHUNK").is_err());
        let bytes = encode_assignments(&ids);
        assert_eq!(decode_ids(ASSIGNMENTS, &bytes).unwrap(), ids);
        assert!(decode_segments(&bytes).unwrap_err().contains("not a precimap segment file"));
    }
}
