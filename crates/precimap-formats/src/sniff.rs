//! Recognising binary files where text is expected, so that the message says what the file
//! looks like instead of showing its bytes as a bad header line.

/// Bytes looked at: enough for any header line and several records.
const WINDOW: usize = 4096;

/// An SBET record: 17 little-endian f64 (time, latitude, longitude, height, velocities, angles,
/// accelerations, angular rates); angles in radians.
const SBET_RECORD: usize = 17 * 8;

/// `None` for text; otherwise what the binary file looks like and what to do, for a file that was
/// expected to be a `what` (e.g. "CSV trajectory").
pub(crate) fn binary_problem(bytes: &[u8], what: &str) -> Option<String> {
    let head = &bytes[..bytes.len().min(WINDOW)];
    let control = head.iter().filter(|&&b| b == 0 || (b < 0x20 && !matches!(b, b'\t' | b'\n' | b'\r'))).count();
    let text = std::str::from_utf8(head).is_ok()
        || std::str::from_utf8(&head[..head.len().saturating_sub(3)]).is_ok()
        || head.len() < 4;
    if control == 0 && text {
        return None;
    }
    let looks_like = if head.starts_with(b"LASF") {
        "a LAS/LAZ point cloud; check which file the manifest names here".to_string()
    } else if looks_like_sbet(bytes) {
        format!(
            "an SBET binary trajectory ({} records of 17 numbers); name its format in the manifest",
            bytes.len() / SBET_RECORD
        )
    } else {
        "binary data; give a text file, or name its format in the manifest".to_string()
    };
    Some(format!("this is not a {what}: it looks like {looks_like}"))
}

/// Whole SBET records whose first one holds a time of week, a latitude and a longitude in radians.
fn looks_like_sbet(bytes: &[u8]) -> bool {
    if bytes.len() < SBET_RECORD || !bytes.len().is_multiple_of(SBET_RECORD) {
        return false;
    }
    let f = |k: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&bytes[k * 8..k * 8 + 8]);
        f64::from_le_bytes(b)
    };
    let (time, lat, lon) = (f(0), f(1), f(2));
    time.is_finite()
        && time >= 0.0
        && lat.abs() <= std::f64::consts::FRAC_PI_2
        && lon.abs() <= 2.0 * std::f64::consts::PI
        && (0..17).all(|k| f(k).is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sbet(records: usize) -> Vec<u8> {
        let mut v = Vec::new();
        for i in 0..records {
            let mut r = [0f64; 17];
            r[0] = 345_600.0 + i as f64 * 0.005;
            r[1] = 0.9;
            r[2] = 0.2;
            r[3] = 100.0;
            v.extend(r.iter().flat_map(|x| x.to_le_bytes()));
        }
        v
    }

    #[test]
    fn text_passes_and_binary_is_named() {
        assert_eq!(binary_problem(b"time,x,y,z,roll,pitch,yaw\n1,2,3,4,5,6,7\n", "CSV trajectory"), None);
        assert_eq!(binary_problem("\u{feff}zeit,x\n\u{e9}t\u{e9}\n".as_bytes(), "CSV trajectory"), None);
        let m = binary_problem(&sbet(20), "CSV trajectory").unwrap();
        assert!(m.contains("SBET") && m.contains("20 records") && m.contains("name its format"), "{m}");
        let m = binary_problem(b"LASF\x00\x00\x01\x02", "CSV trajectory").unwrap();
        assert!(m.contains("LAS/LAZ"), "{m}");
        let mut odd = sbet(3);
        odd.push(0);
        let m = binary_problem(&odd, "CSV trajectory").unwrap();
        assert!(m.contains("binary data") && !m.contains("SBET"), "{m}");
    }
}
