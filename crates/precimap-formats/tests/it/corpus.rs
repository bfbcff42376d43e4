//! Real LAS/LAZ files from public test suites (`tests/data/lidar`, listed with their sources,
//! licences and expected outcomes in `corpus.tsv`) and hand-made broken files: every file gives
//! its expected outcome (the values an independent reader finds, or a named error) without a
//! panic, and a rewritten file keeps every point, attribute and (E)VLR.
//!
//! With `PRECIMAP_TEST_LASPY` naming a Python with laspy and LASzip (`scripts/services.sh` sets it
//! up), every rewritten file is also checked by that independent reader.

use las::point::Format;
use las::{Builder, Point, PointDataBuilder, Transform, Vector, Version, Vlr};
use precimap_formats::{read_strip, read_trajectory_csv, rewrite_strip, strip_info};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};

fn corpus_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/lidar")
}

#[derive(Debug, PartialEq)]
enum Expect {
    Ok,
    /// Rewritten as LAS 1.4 (the source's version cannot hold its points).
    Raised,
    Error(String),
}

impl Expect {
    fn parse(s: &str) -> Self {
        match s {
            "ok" => Self::Ok,
            "ok 1.4" => Self::Raised,
            e => Self::Error(e.strip_prefix("error: ").unwrap_or_else(|| panic!("bad outcome {e:?}")).to_string()),
        }
    }
}

#[derive(Debug)]
struct Row {
    file: String,
    points: Option<u64>,
    format: Option<u8>,
    version: Option<(u8, u8)>,
    first: Option<[f64; 3]>,
    gps: Option<(f64, f64)>,
    read: Expect,
    rewrite: Expect,
}

fn numbers(s: &str) -> Option<Vec<f64>> {
    (s != "-").then(|| s.split(' ').map(|v| v.parse().unwrap()).collect())
}

fn corpus() -> Vec<Row> {
    let text = std::fs::read_to_string(corpus_dir().join("corpus.tsv")).unwrap();
    let mut lines = text.lines().filter(|l| !l.starts_with('#') && !l.trim().is_empty());
    let header: Vec<&str> = lines.next().unwrap().split('\t').collect();
    assert_eq!(header[..8], ["file", "points", "format", "version", "first_xyz", "gps_span", "read", "rewrite"]);
    lines
        .map(|line| {
            let f: Vec<&str> = line.split('\t').collect();
            assert!(f.len() >= 10, "corpus.tsv: {line}");
            let version = (f[3] != "-").then(|| {
                let (a, b) = f[3].split_once('.').unwrap();
                (a.parse().unwrap(), b.parse().unwrap())
            });
            Row {
                file: f[0].to_string(),
                points: (f[1] != "-").then(|| f[1].parse().unwrap()),
                format: (f[2] != "-").then(|| f[2].parse().unwrap()),
                version,
                first: numbers(f[4]).map(|v| [v[0], v[1], v[2]]),
                gps: numbers(f[5]).map(|v| (v[0], v[1])),
                read: Expect::parse(f[6]),
                rewrite: Expect::parse(f[7]),
            }
        })
        .collect()
}

/// A Python with laspy and LASzip, if the environment names one.
fn independent_reader() -> Option<String> {
    match std::env::var("PRECIMAP_TEST_LASPY") {
        Ok(python) if !python.is_empty() => Some(python),
        _ => {
            assert!(
                std::env::var("PRECIMAP_REQUIRE_SERVICES").is_err(),
                "PRECIMAP_TEST_LASPY is not set; scripts/services.sh sets it"
            );
            eprintln!("PRECIMAP_TEST_LASPY not set: rewritten files are not checked with laspy + LASzip");
            None
        }
    }
}

fn independent_check(python: &str, src: &Path, dst: &Path) -> Result<(), String> {
    let out = std::process::Command::new(python)
        .arg(corpus_dir().join("independent_check.py"))
        .arg(src)
        .arg(dst)
        .output()
        .map_err(|e| format!("cannot run {python}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!("laspy + LASzip: {}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
    }
}

fn is_layout_record(v: &Vlr) -> bool {
    las::laz::is_laszip_vlr(v) || v.user_id == "copc"
}

/// Every point record byte for byte, the point format, transforms, counts and (E)VLRs (less the
/// LASzip and COPC records, which the rewrite must drop).
fn compare_round_trip(src: &Path, dst: &Path, raised: bool) -> Result<(), String> {
    match catch_unwind(|| compare_with_las(src, dst, raised)) {
        Ok(result) => result,
        // The las crate's reader panics on some valid LASzip 1.x point-wise files (variable chunk
        // size marker without a table); those are compared by the independent reader only.
        Err(_) => {
            eprintln!("{}: the las crate cannot read the source; compared with laspy + LASzip only", src.display());
            Ok(())
        }
    }
}

fn compare_with_las(src: &Path, dst: &Path, raised: bool) -> Result<(), String> {
    let mut a = las::Reader::from_path(src).map_err(|e| format!("las cannot read the source: {e}"))?;
    let mut b = las::Reader::from_path(dst).map_err(|e| format!("las cannot read the rewritten file: {e}"))?;
    let (ha, hb) = (a.header().clone(), b.header().clone());
    let number = |h: &las::Header| (h.point_format().to_u8().unwrap(), h.point_format().extra_bytes);
    if number(&ha) != number(&hb) {
        return Err(format!("point format {:?}, source {:?}", number(&hb), number(&ha)));
    }
    let version = if raised { Version::new(1, 4) } else { ha.version() };
    if hb.version() != version {
        return Err(format!("version {}, expected {version}", hb.version()));
    }
    if ha.transforms() != hb.transforms() || ha.number_of_points() != hb.number_of_points() {
        return Err(format!(
            "transforms or point count differ ({} vs {})",
            hb.number_of_points(),
            ha.number_of_points()
        ));
    }
    if !raised && points_by_return(src) != points_by_return(dst) {
        return Err(format!("points by return {:?}, source {:?}", points_by_return(dst), points_by_return(src)));
    }
    let kept = |v: &[Vlr]| v.iter().filter(|v| !is_layout_record(v)).cloned().collect::<Vec<_>>();
    if kept(ha.vlrs()) != kept(hb.vlrs()) || kept(ha.evlrs()) != kept(hb.evlrs()) {
        return Err("VLRs or EVLRs differ".into());
    }
    if hb.vlrs().iter().chain(hb.evlrs()).any(|v| v.user_id == "copc") {
        return Err("COPC records kept over recompressed data".into());
    }
    let mut pa = PointDataBuilder::new().for_header(&ha).build();
    let mut pb = PointDataBuilder::new().for_header(&hb).build();
    let mut index = 0u64;
    loop {
        let na = a.fill_points(10_000, &mut pa).map_err(|e| format!("source point {index}: {e}"))?;
        let nb = b.fill_points(10_000, &mut pb).map_err(|e| format!("rewritten point {index}: {e}"))?;
        if na != nb {
            return Err(format!("{nb} points read after {index}, source {na}"));
        }
        if na == 0 {
            return Ok(());
        }
        if pa.raw_bytes() != pb.raw_bytes() {
            return Err(format!("point records {index}..{} differ", index + na));
        }
        index += na;
    }
}

/// The header's points by return as stored: LAS 1.4's 15 counts, or the five of earlier versions.
fn points_by_return(path: &Path) -> Vec<u64> {
    let raw = las::raw::Header::read_from(std::fs::File::open(path).unwrap()).unwrap();
    match raw.large_file {
        Some(large) => large.number_of_points_by_return.to_vec(),
        None => raw.number_of_points_by_return.iter().map(|&n| u64::from(n)).collect(),
    }
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-6 * a.abs().max(1.0)
}

/// Reads and (when the row says so) rewrites one corpus file; `Err` says how it differs.
fn check_row(row: &Row, dir: &Path, python: Option<&str>) -> Result<(), String> {
    let path = corpus_dir().join(&row.file);
    let read = catch_unwind(AssertUnwindSafe(|| read_strip(&path))).map_err(|_| "read_strip panicked".to_string())?;
    match (&row.read, read) {
        (Expect::Ok, Ok(points)) => {
            let info = strip_info(&path).map_err(|e| e.to_string())?;
            let expected = (row.points, row.format, row.version);
            let found = (Some(points.len() as u64), Some(info.point_format), Some(info.version));
            if expected != found || info.point_count != points.len() as u64 {
                return Err(format!("read {found:?} (header {} points), expected {expected:?}", info.point_count));
            }
            let first = [points.x[0], points.y[0], points.z[0]];
            if !row.first.is_some_and(|e| (0..3).all(|k| close(e[k], first[k]))) {
                return Err(format!("first point {first:?}, expected {:?}", row.first));
            }
            let span = points.gps_time_span().unwrap();
            if !row.gps.is_some_and(|(lo, hi)| close(lo, span.0) && close(hi, span.1)) {
                return Err(format!("GPS time span {span:?}, expected {:?}", row.gps));
            }
        }
        (Expect::Error(needle), Err(e)) => {
            let message = e.to_string();
            if !message.contains(needle.as_str()) || !message.contains(&path.display().to_string()) {
                return Err(format!("error {message:?} does not name the file and {needle:?}"));
            }
        }
        (expected, got) => return Err(format!("read: expected {expected:?}, got {:?}", got.map(|p| p.len()))),
    }
    let dst = dir.join(&row.file);
    let written = catch_unwind(AssertUnwindSafe(|| rewrite_strip(&path, &dst, |_, xyz| xyz)))
        .map_err(|_| "rewrite_strip panicked".to_string())?;
    match (&row.rewrite, written) {
        (Expect::Ok | Expect::Raised, Ok(n)) => {
            if Some(n) != row.points {
                return Err(format!("rewrote {n} points, expected {:?}", row.points));
            }
            compare_round_trip(&path, &dst, row.rewrite == Expect::Raised)?;
            if let Some(python) = python {
                independent_check(python, &path, &dst)?;
            }
        }
        (Expect::Error(needle), Err(e)) if e.to_string().contains(needle.as_str()) => {}
        (expected, got) => return Err(format!("rewrite: expected {expected:?}, got {got:?}")),
    }
    Ok(())
}

#[test]
fn every_corpus_file_gives_its_expected_outcome() {
    let dir = tempfile::tempdir().unwrap();
    let python = independent_reader();
    let rows = corpus();
    let listed: std::collections::BTreeSet<_> = rows.iter().map(|r| r.file.clone()).collect();
    let on_disk: std::collections::BTreeSet<_> = std::fs::read_dir(corpus_dir())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".las") || n.ends_with(".laz"))
        .collect();
    assert_eq!(listed, on_disk, "corpus.tsv must list exactly the LAS/LAZ files beside it");
    let failures: Vec<String> = rows
        .iter()
        .filter_map(|row| check_row(row, dir.path(), python.as_deref()).err().map(|e| format!("{}: {e}", row.file)))
        .collect();
    assert!(failures.is_empty(), "{} of {} corpus files:\n{}", failures.len(), rows.len(), failures.join("\n"));
}

// ---------------------------------------------------------------------------------------------
// Hand-made broken files

/// `n` points along a line, 1 ms apart, returns 1–3 of 3.
fn points(n: usize) -> Vec<Point> {
    (0..n)
        .map(|i| Point {
            x: 500_000.0 + i as f64 * 0.01,
            y: 5_400_000.0 + (i as f64 * 0.01).sin(),
            z: 100.0 + (i % 7) as f64 * 0.1,
            gps_time: Some(300_000.0 + i as f64 * 1e-3),
            return_number: (i % 3 + 1) as u8,
            number_of_returns: 3,
            intensity: (i % 1000) as u16,
            ..Default::default()
        })
        .collect()
}

fn write_las(path: &Path, version: (u8, u8), format: u8, points: &[Point]) {
    let mut b = Builder::from(Version::new(version.0, version.1));
    b.point_format = Format::new(format).unwrap();
    b.point_format.is_compressed = path.extension().is_some_and(|e| e == "laz");
    let t = |offset| Transform { scale: 0.001, offset };
    b.transforms = Vector { x: t(500_000.0), y: t(5_400_000.0), z: t(0.0) };
    let mut w = las::Writer::from_path(path, b.into_header().unwrap()).unwrap();
    for p in points {
        w.write_point(p.clone()).unwrap();
    }
    w.close().unwrap();
}

fn patch(path: &Path, at: usize, bytes: &[u8]) {
    let mut data = std::fs::read(path).unwrap();
    data[at..at + bytes.len()].copy_from_slice(bytes);
    std::fs::write(path, data).unwrap();
}

/// LAS header fields (LAS 1.2–1.4, table 3).
const POINT_OFFSET_AT: usize = 96;
const RECORD_LEN_AT: usize = 105;
const LEGACY_COUNT_AT: usize = 107;
const X_SCALE_AT: usize = 131;

fn header_u32(path: &Path, at: usize) -> u32 {
    let d = std::fs::read(path).unwrap();
    u32::from_le_bytes([d[at], d[at + 1], d[at + 2], d[at + 3]])
}

fn read_error(path: &Path) -> String {
    let e = read_strip(path).unwrap_err().to_string();
    assert!(e.contains(&path.display().to_string()), "{e}");
    e
}

#[test]
fn truncated_las_and_laz_are_named_as_cut() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["cut.las", "cut.laz"] {
        let path = dir.path().join(name);
        write_las(&path, (1, 2), 1, &points(3000));
        let len = std::fs::metadata(&path).unwrap().len();
        let data = std::fs::read(&path).unwrap();
        std::fs::write(&path, &data[..(len as usize) * 2 / 3]).unwrap();
        let e = read_error(&path);
        assert!(e.contains("truncated") || e.contains("cut off"), "{name}: {e}");
    }
}

#[test]
fn las_header_count_smaller_or_larger_than_the_data_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("count.las");
    write_las(&path, (1, 2), 1, &points(1000));
    patch(&path, LEGACY_COUNT_AT, &900u32.to_le_bytes());
    let e = read_error(&path);
    assert!(e.contains("declares 900 points") && e.contains("1000 complete point records"), "{e}");
    assert!(rewrite_strip(&path, &dir.path().join("out.las"), |_, p| p).is_err());
    patch(&path, LEGACY_COUNT_AT, &1100u32.to_le_bytes());
    let e = read_error(&path);
    assert!(e.contains("truncated") && e.contains("declares 1100 points"), "{e}");
    // Less than one record of trailing bytes is padding, not points.
    let mut data = std::fs::read(&path).unwrap();
    data.extend([0u8; 2]);
    std::fs::write(&path, data).unwrap();
    patch(&path, LEGACY_COUNT_AT, &1000u32.to_le_bytes());
    assert_eq!(read_strip(&path).unwrap().len(), 1000);
}

#[test]
fn laz_header_count_smaller_or_larger_than_the_data_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("count.laz");
    // Three chunks of at most 50 000 points.
    write_las(&path, (1, 2), 1, &points(120_000));
    for (count, word) in [(60_000u32, "fewer"), (200_000, "more")] {
        patch(&path, LEGACY_COUNT_AT, &count.to_le_bytes());
        let e = read_error(&path);
        assert!(e.contains(&format!("declares {count} points")) && e.contains(word), "{e}");
    }
    patch(&path, LEGACY_COUNT_AT, &120_000u32.to_le_bytes());
    assert_eq!(read_strip(&path).unwrap().len(), 120_000);
}

#[test]
fn absurd_scale_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scale.las");
    write_las(&path, (1, 2), 1, &points(100));
    patch(&path, X_SCALE_AT, &1e300f64.to_le_bytes());
    let e = read_error(&path);
    assert!(e.contains("beyond any place on Earth") && e.contains("scale"), "{e}");
}

#[test]
fn constant_or_non_increasing_gps_time_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("constant.las");
    let mut same = points(500);
    same.iter_mut().for_each(|p| p.gps_time = Some(1234.5));
    write_las(&path, (1, 2), 1, &same);
    let e = read_error(&path);
    assert!(e.contains("all 500 points have the same GPS time"), "{e}");
    let path = dir.path().join("backwards.las");
    let mut backwards = points(500);
    backwards.reverse();
    write_las(&path, (1, 2), 1, &backwards);
    let e = read_error(&path);
    assert!(e.contains("never increases"), "{e}");
    // Interleaved channels go back and forth but advance: accepted.
    let path = dir.path().join("interleaved.las");
    let mut interleaved = points(500);
    interleaved
        .iter_mut()
        .enumerate()
        .for_each(|(i, p)| p.gps_time = Some(10.0 + (i / 2) as f64 - (i % 2) as f64 * 0.5));
    write_las(&path, (1, 2), 1, &interleaved);
    assert_eq!(read_strip(&path).unwrap().len(), 500);
}

#[test]
fn copc_input_is_rewritten_as_plain_laz() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["lasrs-autzen.copc.laz", "laspy-simple.copc.laz"] {
        let src = corpus_dir().join(name);
        let before = las::Reader::from_path(&src).unwrap().header().clone();
        assert!(before.vlrs().iter().any(|v| v.user_id == "copc"), "{name} is COPC");
        let dst = dir.path().join(name);
        let n = rewrite_strip(&src, &dst, |_, p| p).unwrap();
        assert_eq!(n, before.number_of_points());
        compare_round_trip(&src, &dst, false).unwrap();
        if let Some(python) = independent_reader() {
            independent_check(&python, &src, &dst).unwrap();
        }
    }
}

#[test]
fn return_number_6_in_las_1_2_is_written_as_las_1_4() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("returns.las");
    write_las(&src, (1, 2), 1, &points(2000));
    // The las writer refuses return 6 in LAS 1.2, so it is patched in: return 6 of 7.
    let offset = header_u32(&src, POINT_OFFSET_AT) as usize;
    let record = u16::from_le_bytes(std::fs::read(&src).unwrap()[RECORD_LEN_AT..RECORD_LEN_AT + 2].try_into().unwrap());
    for i in [5usize, 1500] {
        patch(&src, offset + i * usize::from(record) + 14, &[(7 << 3) | 6]);
    }
    assert_eq!(read_strip(&src).unwrap().len(), 2000, "readable: refused nowhere");
    for name in ["out.las", "out.laz"] {
        let dst = dir.path().join(name);
        assert_eq!(rewrite_strip(&src, &dst, |_, p| [p[0] + 1.0, p[1], p[2]]).unwrap(), 2000);
        let mut r = las::Reader::from_path(&dst).unwrap();
        assert_eq!(r.header().version(), Version::new(1, 4));
        assert_eq!(points_by_return(&dst)[5], 2, "return 6 counted");
        let p: Vec<Point> = r.read_all().unwrap().points().map(|p| p.unwrap()).collect();
        assert_eq!(p.len(), 2000);
        assert_eq!((p[5].return_number, p[1500].return_number, p[6].return_number), (6, 6, 1));
        assert!((p[7].x - points(8)[7].x - 1.0).abs() < 1e-6);
    }
}

#[test]
fn las_1_2_with_a_las_1_4_point_format_is_written_as_las_1_4() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("mixed.las");
    write_las(&src, (1, 4), 6, &points(300));
    patch(&src, 25, &[2]); // version minor: LAS 1.2, which has no point format 6
    let dst = dir.path().join("out.las");
    match read_strip(&src) {
        Ok(p) => {
            assert_eq!(p.len(), 300);
            assert_eq!(rewrite_strip(&src, &dst, |_, p| p).unwrap(), 300);
            assert_eq!(las::Reader::from_path(&dst).unwrap().header().version(), Version::new(1, 4));
        }
        // Refused when read, never after the work.
        Err(e) => assert!(e.to_string().contains("mixed.las"), "{e}"),
    }
}

#[test]
fn sbet_named_as_a_csv_trajectory_is_recognised() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("traj.csv");
    let mut bytes = Vec::new();
    for i in 0..200 {
        let mut r = [0f64; 17];
        r[0] = 345_600.0 + f64::from(i) * 0.005;
        r[1] = 0.84;
        r[2] = -1.9;
        r[3] = 52.0;
        bytes.extend(r.iter().flat_map(|v| v.to_le_bytes()));
    }
    std::fs::write(&path, bytes).unwrap();
    let e = read_trajectory_csv(&path).unwrap_err().to_string();
    assert!(e.contains("traj.csv") && e.contains("SBET") && e.contains("name its format in the manifest"), "{e}");
    assert!(e.len() < 300 && !e.contains('\u{fffd}'), "short and without raw bytes: {e}");
}

#[test]
fn text_named_as_las_is_not_a_las_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("strip.las");
    std::fs::write(&path, "time,x,y,z,roll,pitch,yaw\n1,2,3,4,5,6,7\n").unwrap();
    let e = read_error(&path);
    assert!(e.contains("not a LAS/LAZ file"), "{e}");
}

#[test]
fn laszip_1_point_wise_laz_is_read() {
    let src = corpus_dir().join("lazrs-point-version-1-point-wise.laz");
    let info = strip_info(&src).unwrap();
    assert_eq!((info.point_count, info.point_format, info.version), (11_781, 0, (1, 0)));
    let dir = tempfile::tempdir().unwrap();
    let dst = dir.path().join("out.laz");
    assert_eq!(rewrite_strip(&src, &dst, |_, p| p).unwrap(), 11_781);
    compare_round_trip(&src, &dst, false).unwrap();
}
