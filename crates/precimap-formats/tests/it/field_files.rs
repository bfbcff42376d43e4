//! Public SBET, SMRMSG and georeferenced LAZ files (tests/data/field, sources and licences in its
//! README), read and checked against the values their sources' own tests document.

// The expected values are copied digit for digit from the sources' tests.
#![allow(clippy::excessive_precision)]

use precimap_formats::sbet::{read_sbet, read_smrmsg};
use precimap_formats::{read_strip, strip_info};
use std::path::PathBuf;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/field").join(name)
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

#[test]
fn pdal_sbet_reads_as_pdal_documents() {
    let s = read_sbet(&data("pdal-2-points.sbet")).unwrap();
    assert_eq!(s.len(), 2);
    // PDAL's SbetReaderTest (radians): time, latitude, longitude, altitude, roll, pitch,
    // heading (platform heading) and wander; the true heading is their difference.
    let want = [
        (
            1.516310028360710e+05,
            5.680211852972264e-01,
            -2.041654392303940,
            1.077152953296560e+02,
            -2.813407149321339e-02,
            -2.429905393889139e-02,
            3.046773230278662,
            -2.198414736922658e-02,
        ),
        (
            1.516310078318641e+05,
            5.680211834722869e-01,
            -2.041654392034053,
            1.077151424357507e+02,
            -2.813856631423094e-02,
            -2.425215669392169e-02,
            3.047131105236811,
            -2.198416007932108e-02,
        ),
    ];
    for (i, w) in want.iter().enumerate() {
        assert!(close(s.times[i], w.0, 1e-6), "{i}");
        let [lon, lat, h] = s.coordinates[i];
        assert!(close(lat, w.1, 1e-12) && close(lon, w.2, 1e-12) && close(h, w.3, 1e-9), "{i}: {:?}", s.coordinates[i]);
        let [roll, pitch, heading] = s.attitude[i];
        assert!(close(roll, w.4, 1e-12) && close(pitch, w.5, 1e-12), "{i}");
        assert!(close(heading, w.6 - w.7, 1e-12), "{i}: {heading}");
    }
    let e = read_sbet(&data("pdal-badfile.sbet")).unwrap_err().to_string();
    assert!(e.contains("pdal-badfile.sbet") && e.contains("truncated SBET"), "{e}");
}

#[test]
fn pdal_smrmsg_reads_as_pdal_documents() {
    let a = read_smrmsg(&data("pdal-smrmsg-100.smrmsg")).unwrap();
    assert_eq!(a.times.len(), 100);
    // PDAL's SmrmsgReaderTest, records 0 and 2 (attitude RMS in arc minutes there, degrees here).
    assert_eq!(a.times[0], 536_258.0);
    assert!(close(a.position_sigma_m[0][0], 0.056279, 1e-6) && close(a.position_sigma_m[0][2], 0.070774, 1e-6));
    assert!(close(a.attitude_sigma_deg[0][2] * 60.0, 3.010802, 1e-6), "{:?}", a.attitude_sigma_deg[0]);
    assert_eq!(a.times[2], 536_260.0);
    assert!(
        close(a.position_sigma_m[2][1], 0.054339, 1e-6) && close(a.attitude_sigma_deg[2][0] * 60.0, 0.235108, 1e-6)
    );
}

#[test]
fn las_rs_files_declare_their_crs() {
    // A WKT compound CRS: NAD83 / Oregon GIC Lambert (ft) + NAVD88 height (ftUS).
    let autzen = strip_info(&data("las-rs-autzen.copc.laz")).unwrap();
    let crs = autzen.crs.unwrap();
    assert_eq!((crs.epsg, crs.wkt), (Some(2992), true), "{crs}");
    // GeoTIFF keys: ETRS89 / UTM zone 32N (+ a vertical key).
    let norway = strip_info(&data("las-rs-32-1-472-150-76.laz")).unwrap();
    let crs = norway.crs.unwrap();
    assert_eq!((crs.epsg, crs.wkt), (Some(25832), false), "{crs}");
    // Every file reads or is refused with a message naming it; none panics.
    for name in ["las-rs-autzen.copc.laz", "las-rs-32-1-472-150-76.laz"] {
        match read_strip(&data(name)) {
            Ok(points) => assert_eq!(points.len() as u64, strip_info(&data(name)).unwrap().point_count),
            Err(e) => assert!(e.to_string().contains(name), "{e}"),
        }
    }
}
