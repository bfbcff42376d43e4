//! Per-strip segment ids (`OUT/segments/{strip}.seg`, written by `precimap run`): little-endian,
//! the magic `PMSEGMNT`, a `u32` format version (1), a `u32` (0), a `u64` point count, then one
//! `u32` per point in file order: the point's segment id in its strip, or `u32::MAX` for none
//! (no normal, removed small region, or a revolution dropped at standstill).

use crate::FormatError;
use std::path::Path;

const MAGIC: &[u8; 8] = b"PMSEGMNT";
const VERSION: u32 = 1;
const HEADER_BYTES: usize = 24;

pub fn encode_segments(ids: &[u32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + 4 * ids.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out.extend_from_slice(&(ids.len() as u64).to_le_bytes());
    for id in ids {
        out.extend_from_slice(&id.to_le_bytes());
    }
    out
}

/// Reads a segment file; every problem names the file.
pub fn read_segments(path: &Path) -> Result<Vec<u32>, FormatError> {
    let bytes = std::fs::read(path).map_err(|e| FormatError::io(path, "read segment file", e))?;
    decode_segments(&bytes).map_err(|m| FormatError::file(path, m))
}

pub fn decode_segments(bytes: &[u8]) -> Result<Vec<u32>, String> {
    if bytes.len() < HEADER_BYTES || &bytes[..8] != MAGIC {
        return Err("not a precimap segment file (bad magic or shorter than its header)".into());
    }
    let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
    if version != VERSION {
        return Err(format!("segment file version {version} is not supported (this build reads {VERSION})"));
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
    }
}
