//! The exported latent map (`OUT/latent/{tile}.las`): LAS 1.4, point format 6 with extra bytes
//! described by the standard Extra Bytes VLR (LAS 1.4 R15 §2.5.4), so that PDAL, CloudCompare
//! or LAStools read the normals and the agreement figures by name.
//!
//! Per point: x, y, z at 0.1 mm (the map is meant to be good to millimetres), the synthetic
//! flag (derived, not measured), GPS time 0, and the extra bytes `NormalX`, `NormalY`,
//! `NormalZ` (f32), `StdDev` (f32, metres), `Observations` (u32) and `Passes` (u16).
//!
//! A field campaign's map is written in grid coordinates of its processing CRS, the CRS as a
//! WKT VLR, as its strips are; normals keep the processing frame's axes (parallel to the grid
//! at the frame's origin).

use crate::atomic::PendingFile;
use crate::FormatError;
use las::point::Format;
use las::{Builder, Point, Reader, Transform, Vector, Version, Vlr, Writer};
use precimap_core::LatentMapPoint;
use std::io::{Cursor, Write};
use std::path::Path;

/// Coordinate resolution of the map (metres).
pub const LATENT_MAP_SCALE_M: f64 = 0.0001;

/// The extra-bytes fields in record order: name, LAS data type code (R15 table 24), bytes.
const FIELDS: [(&str, u8, usize, &str); 6] = [
    ("NormalX", 9, 4, "surface normal x"),
    ("NormalY", 9, 4, "surface normal y"),
    ("NormalZ", 9, 4, "surface normal z"),
    ("StdDev", 9, 4, "strips' spread about the map (m)"),
    ("Observations", 5, 4, "points averaged"),
    ("Passes", 3, 2, "strip passes seen"),
];
const EXTRA_BYTES: usize = 4 * 5 + 2;
const DESCRIPTOR_LEN: usize = 192;

fn extra_bytes_vlr() -> Vlr {
    let mut data = Vec::with_capacity(DESCRIPTOR_LEN * FIELDS.len());
    for (name, data_type, _, description) in FIELDS {
        let mut d = [0u8; DESCRIPTOR_LEN];
        d[2] = data_type;
        d[4..4 + name.len()].copy_from_slice(name.as_bytes());
        d[160..160 + description.len()].copy_from_slice(description.as_bytes());
        data.extend_from_slice(&d);
    }
    Vlr { user_id: "LASF_Spec".into(), record_id: 4, description: "Extra Bytes Record".into(), data }
}

/// The map as the bytes of a LAS file (what the job framework stores as one object per tile),
/// declaring the CRS `wkt` when given.
pub fn encode_latent_map(points: &[LatentMapPoint], wkt: Option<&str>) -> Result<Vec<u8>, las::Error> {
    let mut b = Builder::from(Version::new(1, 4));
    b.point_format = Format::new(6)?;
    b.point_format.extra_bytes = EXTRA_BYTES as u16;
    // Offsets at whole kilometres below the first point keep every coordinate of a tile (and of
    // any campaign within ±200 km) inside the 32-bit range at 0.1 mm.
    let first = points.first().map_or([0.0; 3], |p| p.position);
    let axis = |o: f64| Transform { scale: LATENT_MAP_SCALE_M, offset: (o / 1000.0).floor() * 1000.0 };
    b.transforms = Vector { x: axis(first[0]), y: axis(first[1]), z: axis(first[2]) };
    b.system_identifier = "precimap latent map".into();
    b.generating_software = "precimap".into();
    b.vlrs.push(extra_bytes_vlr());
    let mut header = b.into_header()?;
    if let Some(wkt) = wkt {
        header.set_wkt_crs(wkt.as_bytes().to_vec())?;
    }
    let mut w = Writer::new(Cursor::new(Vec::new()), header)?;
    for p in points {
        let mut extra = Vec::with_capacity(EXTRA_BYTES);
        for v in p.normal.iter().chain([&p.std_m]) {
            extra.extend_from_slice(&v.to_le_bytes());
        }
        extra.extend_from_slice(&p.observations.to_le_bytes());
        extra.extend_from_slice(&p.passes.to_le_bytes());
        w.write_point(Point {
            x: p.position[0],
            y: p.position[1],
            z: p.position[2],
            return_number: 1,
            number_of_returns: 1,
            is_synthetic: true,
            gps_time: Some(0.0),
            extra_bytes: extra,
            ..Default::default()
        })?;
    }
    w.close()?;
    Ok(w.into_inner()?.into_inner())
}

/// Writes the map to `path` (atomically: the file appears complete or not at all), declaring the
/// CRS `wkt` when given.
pub fn write_latent_map(path: &Path, points: &[LatentMapPoint], wkt: Option<&str>) -> Result<(), FormatError> {
    let bytes = encode_latent_map(points, wkt)
        .map_err(|e| FormatError::file(path, format!("cannot encode the latent map: {e}")))?;
    let (pending, mut file) = PendingFile::create(path)?;
    file.write_all(&bytes).map_err(|e| FormatError::io(path, "write latent map", e))?;
    pending.commit()
}

/// Reads a map [`write_latent_map`] wrote; a LAS file without its extra bytes is an error.
pub fn read_latent_map(path: &Path) -> Result<Vec<LatentMapPoint>, FormatError> {
    let bad = |m: String| FormatError::file(path, m);
    let mut reader = Reader::from_path(path).map_err(|e| bad(format!("not a readable LAS file: {e}")))?;
    let header = reader.header();
    let described = header.vlrs().iter().find(|v| v.user_id == "LASF_Spec" && v.record_id == 4);
    let names_match = described.is_some_and(|v| {
        v.data.len() == DESCRIPTOR_LEN * FIELDS.len()
            && FIELDS.iter().enumerate().all(|(i, (name, data_type, _, _))| {
                let d = &v.data[i * DESCRIPTOR_LEN..(i + 1) * DESCRIPTOR_LEN];
                d[2] == *data_type && d[4..36].split(|&c| c == 0).next() == Some(name.as_bytes())
            })
    });
    if header.point_format().extra_bytes as usize != EXTRA_BYTES || !names_match {
        return Err(bad(format!(
            "not a precimap latent map: its extra bytes are not {} ({} bytes); write it with `precimap run`",
            FIELDS.map(|f| f.0).join(", "),
            EXTRA_BYTES
        )));
    }
    let data = reader.read_all().map_err(|e| bad(format!("cannot read its points: {e}")))?;
    let mut out = Vec::with_capacity(data.len());
    for (i, p) in data.points().enumerate() {
        let p = p.map_err(|e| bad(format!("point {i}: {e}")))?;
        let e = &p.extra_bytes;
        if e.len() != EXTRA_BYTES {
            return Err(bad(format!("point {i}: {} extra bytes, expected {EXTRA_BYTES}", e.len())));
        }
        let f32_at = |k: usize| f32::from_le_bytes([e[4 * k], e[4 * k + 1], e[4 * k + 2], e[4 * k + 3]]);
        out.push(LatentMapPoint {
            position: [p.x, p.y, p.z],
            normal: [f32_at(0), f32_at(1), f32_at(2)],
            std_m: f32_at(3),
            observations: u32::from_le_bytes([e[16], e[17], e[18], e[19]]),
            passes: u16::from_le_bytes([e[20], e[21]]),
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_latent_map_survives_writing_and_reading_to_a_tenth_of_a_millimetre() {
        let dir = std::env::temp_dir().join(format!("precimap-latent-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let points = vec![
            LatentMapPoint {
                position: [500_123.456_78, 5_400_321.123_44, 101.234_56],
                normal: [0.0, 0.6, 0.8],
                std_m: 0.0021,
                observations: 17,
                passes: 4,
            },
            LatentMapPoint {
                position: [500_130.0, 5_400_330.0, 99.0],
                normal: [-1.0, 0.0, 0.0],
                std_m: 0.0,
                observations: 1,
                passes: 2,
            },
        ];
        let path = dir.join("0_0.las");
        write_latent_map(&path, &points, None).unwrap();
        let back = read_latent_map(&path).unwrap();
        assert_eq!(back.len(), 2);
        for (a, b) in points.iter().zip(&back) {
            for k in 0..3 {
                assert!((a.position[k] - b.position[k]).abs() <= LATENT_MAP_SCALE_M / 2.0 + 1e-9, "{a:?} {b:?}");
            }
            assert_eq!((a.normal, a.std_m, a.observations, a.passes), (b.normal, b.std_m, b.observations, b.passes));
        }
        // An empty tile is a valid (empty) map; a strip is not a map.
        write_latent_map(&path, &[], None).unwrap();
        assert!(read_latent_map(&path).unwrap().is_empty());
        let strip = dir.join("strip.las");
        let mut w = crate::StripWriter::create(&strip, [0.0; 3], 0.001, "t", "t").unwrap();
        w.push(&crate::NewPoint { gps_time: 1.0, ..Default::default() }).unwrap();
        w.finish().unwrap();
        let e = read_latent_map(&strip).unwrap_err().to_string();
        assert!(e.contains("not a precimap latent map") && e.contains("strip.las"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
