//! LAS/LAZ strips: round trips, attribute preservation on rewrite, and damaged files.

use las::point::{Classification, Format, ScanDirection};
use las::{Builder, Color, Point, Transform, Vector, Version, Vlr};
use precimap_formats::{
    read_strip, rewrite_strip, rewrite_strip_timed, strip_info, FormatError, NewPoint, StripWriter,
};
use std::path::{Path, PathBuf};

const OFFSET: [f64; 3] = [549_800.0, 5_803_400.0, 50.0];
const SCALE: f64 = 1e-4;

fn sample_points(n: usize) -> Vec<NewPoint> {
    (0..n)
        .map(|i| {
            let f = i as f64;
            NewPoint {
                position: [549_812.345_67 + f * 0.013, 5_803_391.0 - (f * 0.01).sin() * 20.0, 48.0 + (f * 0.001).cos()],
                gps_time: 345_600.123_456 + f * 1e-6,
                scan_angle_deg: ((i * 37) % 3600) as f32 * 0.1 - 180.0,
                channel: (i % 4) as u8,
                intensity: (i * 13 % 65_536) as u16,
                return_number: (i % 3 + 1) as u8,
                number_of_returns: 3,
                point_source_id: 7,
                classification: (i % 20) as u8,
            }
        })
        .collect()
}

fn write_strip(path: &Path, points: &[NewPoint]) {
    let mut w = StripWriter::create(path, OFFSET, SCALE, "precimap test", "precimap-formats").unwrap();
    for p in points {
        w.push(p).unwrap();
    }
    assert_eq!(w.finish().unwrap(), points.len() as u64);
}

fn las_points(path: &Path) -> Vec<Point> {
    let mut r = las::Reader::from_path(path).unwrap();
    r.read_all().unwrap().points().map(|p| p.unwrap()).collect()
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

#[test]
fn writer_round_trip_las_and_laz() {
    let dir = tempfile::tempdir().unwrap();
    let points = sample_points(150_000); // more than two internal batches
    for name in ["a.las", "b.laz", "c.LAZ"] {
        let path = dir.path().join(name);
        write_strip(&path, &points);
        let s = read_strip(&path).unwrap();
        assert_eq!(s.len(), points.len());
        for (i, p) in points.iter().enumerate() {
            assert!((s.x[i] - p.position[0]).abs() <= SCALE / 2.0 + 1e-9, "{name} x[{i}]");
            assert!((s.y[i] - p.position[1]).abs() <= SCALE / 2.0 + 1e-9, "{name} y[{i}]");
            assert!((s.z[i] - p.position[2]).abs() <= SCALE / 2.0 + 1e-9, "{name} z[{i}]");
            assert_eq!(s.gps_time[i].to_bits(), p.gps_time.to_bits());
            assert!((s.scan_angle_deg[i] - p.scan_angle_deg).abs() <= 0.003 + 1e-4, "{name} angle[{i}]");
            assert_eq!(s.channel[i], p.channel);
        }
        let info = strip_info(&path).unwrap();
        assert_eq!(info.point_count, points.len() as u64);
        assert_eq!((info.point_format, info.version, info.has_gps_time), (6, (1, 4), true));
        assert_eq!(info.compressed, name != "a.las", "{name}");
        let min = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
        let max = |v: &[f64]| v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        // The las crate rounds header bounds outward to the grid, at most one step.
        for (k, col) in [&s.x, &s.y, &s.z].into_iter().enumerate() {
            let (lo, hi) = (min(col), max(col));
            assert!(info.bounds_min[k] <= lo + 1e-9 && lo - info.bounds_min[k] <= SCALE * 1.01, "{name} axis {k}");
            assert!(info.bounds_max[k] >= hi - 1e-9 && info.bounds_max[k] - hi <= SCALE * 1.01, "{name} axis {k}");
        }
        // Every NewPoint field lands in the right LAS field.
        let lp = las_points(&path);
        for (i, p) in points.iter().enumerate().step_by(997) {
            let q = &lp[i];
            assert_eq!(
                (q.intensity, q.return_number, q.number_of_returns, q.point_source_id, q.scanner_channel),
                (p.intensity, p.return_number, p.number_of_returns, p.point_source_id, p.channel)
            );
            // The las crate reads class 12 (legacy "overlap") as the overlap flag.
            if p.classification != 12 {
                assert_eq!(u8::from(q.classification), p.classification);
            }
        }
    }
    assert_eq!(files_in(dir.path()), ["a.las", "b.laz", "c.LAZ"]);
}

#[test]
fn writer_rejects_bad_points_and_cleans_up() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.laz");
    let mut w = StripWriter::create(&path, OFFSET, SCALE, "t", "t").unwrap();
    let good = sample_points(1)[0];
    w.push(&good).unwrap();
    let far = NewPoint { position: [OFFSET[0] + 1e6, OFFSET[1], OFFSET[2]], ..good };
    let e = w.push(&far).unwrap_err();
    assert!(matches!(e, FormatError::Point { index: 1, .. }) && e.to_string().contains("does not fit"), "{e}");
    let nan = NewPoint { position: [f64::NAN, 0.0, 0.0], ..good };
    assert!(w.push(&nan).unwrap_err().to_string().contains("not finite"));
    assert!(w.push(&NewPoint { gps_time: f64::INFINITY, ..good }).is_err());
    assert!(w.push(&NewPoint { channel: 4, ..good }).is_err());
    assert!(w.push(&NewPoint { scan_angle_deg: 200.0, ..good }).is_err());
    w.push(&good).unwrap();
    // Dropped without finish: nothing appears, no temporary is left.
    drop(w);
    assert!(files_in(dir.path()).is_empty(), "{:?}", files_in(dir.path()));
    assert!(StripWriter::create(&path, OFFSET, 0.0, "t", "t").is_err());
    assert!(StripWriter::create(&path, OFFSET, SCALE, &"x".repeat(33), "t").is_err());
    let w = StripWriter::create(&path, OFFSET, SCALE, "t", "t").unwrap();
    assert_eq!(w.finish().unwrap(), 0);
}

/// A source strip exercising every attribute: colour, NIR, extra bytes, all flags, VLRs, EVLR.
fn write_rich_source(path: &Path, format: u8, version: (u8, u8), n: usize) -> Vec<Point> {
    let mut b = Builder::from(Version::new(version.0, version.1));
    b.point_format = Format::new(format).unwrap();
    b.point_format.extra_bytes = 3;
    b.point_format.is_compressed = path.extension().is_some_and(|e| e == "laz");
    b.transforms = Vector {
        x: Transform { scale: 0.001, offset: 549_000.0 },
        y: Transform { scale: 0.0005, offset: 5_803_000.0 },
        z: Transform { scale: 0.00025, offset: 0.0 },
    };
    b.system_identifier = "rich source".into();
    b.generating_software = "hand made".into();
    b.file_source_id = 42;
    b.guid = las::Builder::default().guid;
    b.vlrs.push(Vlr { user_id: "precimap".into(), record_id: 7, description: "a vlr".into(), data: vec![1, 2, 3, 4] });
    if version.1 >= 4 {
        b.evlrs.push(Vlr {
            user_id: "precimap".into(),
            record_id: 8,
            description: "an evlr".into(),
            data: vec![9; 10],
        });
    }
    let header = b.into_header().unwrap();
    let extended = header.point_format().is_extended;
    let fmt = *header.point_format();
    let mut w = las::Writer::from_path(path, header).unwrap();
    let mut points = Vec::new();
    for i in 0..n {
        let classes = [Classification::Ground, Classification::Building, Classification::HighVegetation];
        let p = Point {
            x: 549_123.456 + i as f64 * 0.01,
            y: 5_803_210.5 + (i % 100) as f64 * 0.0005,
            z: 45.0 + i as f64 * 0.00025,
            intensity: (i * 31) as u16,
            return_number: (i % 5) as u8 + 1,
            number_of_returns: 5,
            scan_direction: if i % 2 == 0 { ScanDirection::LeftToRight } else { ScanDirection::RightToLeft },
            is_edge_of_flight_line: i % 3 == 0,
            classification: classes[i % 3],
            is_synthetic: i % 4 == 0,
            is_key_point: i % 5 == 0,
            is_withheld: i % 6 == 0,
            is_overlap: extended && i % 7 == 0,
            scanner_channel: if extended { (i % 4) as u8 } else { 0 },
            scan_angle: if extended { (i % 1000) as f32 * 0.006 - 3.0 } else { ((i % 181) as i32 - 90) as f32 },
            user_data: (i % 256) as u8,
            point_source_id: (i % 65_535) as u16,
            gps_time: fmt.has_gps_time.then_some(1000.0 + i as f64 * 1e-5),
            color: fmt.has_color.then(|| Color::new(i as u16, (i * 2) as u16, (i * 3) as u16)),
            waveform: None,
            nir: fmt.has_nir.then_some(1 + (i % 1000) as u16),
            extra_bytes: vec![i as u8, (i >> 8) as u8, 0xA5],
        };
        w.write_point(p.clone()).unwrap();
        points.push(p);
    }
    w.close().unwrap();
    points
}

#[test]
fn rewrite_keeps_every_attribute() {
    let dir = tempfile::tempdir().unwrap();
    let shift = [1.2345, -2.5, 0.01];
    for (format, version) in [(8u8, (1u8, 4u8)), (3, (1, 2)), (6, (1, 4))] {
        for src_name in ["src.las", "src.laz"] {
            let src = dir.path().join(format!("f{format}-{src_name}"));
            write_rich_source(&src, format, version, 70_000);
            let before = las_points(&src);
            let src_header = las::Reader::from_path(&src).unwrap().header().clone();
            for dst_name in ["out.las", "out.laz"] {
                let dst = dir.path().join(format!("f{format}-{src_name}-{dst_name}"));
                let mut expected_index = 0;
                let n = rewrite_strip(&src, &dst, |i, p| {
                    assert_eq!(i, expected_index);
                    expected_index += 1;
                    [p[0] + shift[0], p[1] + shift[1], p[2] + shift[2]]
                })
                .unwrap();
                assert_eq!(n, before.len() as u64);
                let after = las_points(&dst);
                assert_eq!(after.len(), before.len());
                for (a, b) in before.iter().zip(&after) {
                    let moved = Point { x: a.x + shift[0], y: a.y + shift[1], z: a.z + shift[2], ..a.clone() };
                    assert!((b.x - moved.x).abs() < 0.0006 && (b.y - moved.y).abs() < 0.0003);
                    assert!((b.z - moved.z).abs() < 0.00013);
                    assert_eq!(
                        Point { x: 0.0, y: 0.0, z: 0.0, ..b.clone() },
                        Point { x: 0.0, y: 0.0, z: 0.0, ..a.clone() }
                    );
                }
                let h = las::Reader::from_path(&dst).unwrap().header().clone();
                assert_eq!(h.version(), src_header.version());
                assert_eq!(h.point_format().to_u8().unwrap(), format);
                assert_eq!(h.point_format().extra_bytes, 3);
                assert_eq!(h.point_format().is_compressed, dst_name.ends_with("laz"));
                assert_eq!(h.transforms(), src_header.transforms());
                assert_eq!(h.guid(), src_header.guid());
                assert_eq!(h.file_source_id(), 42);
                assert_eq!((h.system_identifier(), h.generating_software()), ("rich source", "hand made"));
                assert_eq!(h.gps_time_type(), src_header.gps_time_type());
                let user_vlrs = |h: &las::Header| -> Vec<Vlr> {
                    h.all_vlrs().filter(|v| !las::laz::is_laszip_vlr(v)).cloned().collect()
                };
                assert_eq!(user_vlrs(&h), user_vlrs(&src_header));
                assert_eq!(
                    h.all_vlrs().filter(|v| las::laz::is_laszip_vlr(v)).count(),
                    usize::from(dst_name.ends_with("laz"))
                );
                let b = h.bounds();
                let xs = after.iter().map(|p| p.x);
                let (lo, hi) = (xs.clone().fold(f64::INFINITY, f64::min), xs.fold(f64::NEG_INFINITY, f64::max));
                assert!(
                    b.min.x <= lo + 1e-9 && lo - b.min.x <= 0.00101 && b.max.x >= hi - 1e-9 && b.max.x - hi <= 0.00101
                );
            }
        }
    }
}

#[test]
fn rewrite_rejects_unrepresentable_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("s.las");
    write_strip(&src, &sample_points(100));
    let dst = dir.path().join("d.laz");
    let e = rewrite_strip(&src, &dst, |i, p| if i == 37 { [p[0] + 1e6, p[1], p[2]] } else { p }).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, FormatError::Point { index: 37, .. }), "{e:?}");
    assert!(msg.contains("s.las") && msg.contains("d.laz") && msg.contains("does not fit"), "{msg}");
    let e = rewrite_strip(&src, &dst, |i, p| if i == 5 { [p[0], f64::NAN, p[2]] } else { p }).unwrap_err();
    assert!(matches!(e, FormatError::Point { index: 5, .. }) && e.to_string().contains("not finite"), "{e}");
    assert_eq!(files_in(dir.path()), ["s.las"]);
    // In place works: the destination only replaces the source once complete.
    assert_eq!(rewrite_strip(&src, &src, |_, p| [p[0], p[1], p[2] + 1.0]).unwrap(), 100);
    assert!((read_strip(&src).unwrap().z[0] - sample_points(1)[0].position[2] - 1.0).abs() < 1e-4);
}

fn expect_err(path: &Path) -> (FormatError, String) {
    let e = read_strip(path).unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains(&*path.file_name().unwrap().to_string_lossy()), "message must name the file: {msg}");
    (e, msg)
}

fn valid_las(dir: &Path, name: &str, n: usize) -> (PathBuf, Vec<u8>) {
    let path = dir.join(name);
    write_strip(&path, &sample_points(n));
    let bytes = std::fs::read(&path).unwrap();
    (path, bytes)
}

#[test]
fn cannot_open_and_not_las() {
    let dir = tempfile::tempdir().unwrap();
    let (e, _) = expect_err(&dir.path().join("missing.las"));
    assert!(matches!(e, FormatError::Io { .. }));
    let text = dir.path().join("notes.las");
    std::fs::write(&text, "this is not a point cloud, just some text that is long enough ".repeat(10)).unwrap();
    let (_, msg) = expect_err(&text);
    assert!(msg.contains("not a LAS/LAZ file"), "{msg}");
    std::fs::write(&text, "LASF").unwrap();
    let (_, msg) = expect_err(&text);
    assert!(msg.contains("not a LAS/LAZ file"), "{msg}");
    assert!(strip_info(&text).is_err());
}

#[test]
fn garbled_header() {
    let dir = tempfile::tempdir().unwrap();
    let (path, good) = valid_las(dir.path(), "g.las", 1000);
    let garble = |patches: &[(usize, &[u8])]| {
        let mut b = good.clone();
        for (at, bytes) in patches {
            b[*at..*at + bytes.len()].copy_from_slice(bytes);
        }
        std::fs::write(&path, b).unwrap();
    };
    garble(&[(0, b"LASX")]);
    assert!(expect_err(&path).1.contains("not a LAS/LAZ file"));
    garble(&[(104, &[77])]); // point data record format
    let msg = expect_err(&path).1;
    assert!(msg.contains("point format 77"), "{msg}");
    garble(&[(139, &0f64.to_le_bytes())]); // y scale factor
    let msg = expect_err(&path).1;
    assert!(msg.contains("scale"), "{msg}");
    garble(&[(96, &u32::MAX.to_le_bytes())]); // offset to point data
    let msg = expect_err(&path).1;
    assert!(msg.contains("points start at byte 4294967295"), "{msg}");
    // LAS 1.4 64-bit point count with the legacy count zeroed: would overflow the end offset.
    garble(&[(107, &0u32.to_le_bytes()), (247, &u64::MAX.to_le_bytes())]);
    let msg = expect_err(&path).1;
    assert!(msg.contains("impossible"), "{msg}");
    garble(&[(107, &5000u32.to_le_bytes())]); // legacy count larger than the data
    let (e, msg) = expect_err(&path);
    assert!(matches!(e, FormatError::Point { index: 1000, .. }) && msg.contains("truncated"), "{msg}");
    // An EVLR starting 10 bytes before the end cannot hold its own 60-byte header.
    garble(&[(235, &(good.len() as u64 - 10).to_le_bytes()), (243, &1u32.to_le_bytes())]);
    let msg = expect_err(&path).1;
    assert!(msg.contains("extended VLR"), "{msg}");
    // An EVLR claiming an enormous length must not make anyone allocate it.
    let mut b = good.clone();
    let at = b.len() as u64;
    b[235..243].copy_from_slice(&at.to_le_bytes());
    b[243..247].copy_from_slice(&1u32.to_le_bytes());
    b.extend_from_slice(&[0u8; 20]);
    b.extend_from_slice(&(u64::MAX / 2).to_le_bytes());
    b.extend_from_slice(&[0u8; 32]);
    std::fs::write(&path, b).unwrap();
    let msg = expect_err(&path).1;
    assert!(msg.contains("extended VLR"), "{msg}");
    assert!(strip_info(&path).is_err());
}

#[test]
fn truncated_las_names_the_point() {
    let dir = tempfile::tempdir().unwrap();
    let (path, good) = valid_las(dir.path(), "t.las", 5000);
    let offset = u32::from_le_bytes(good[96..100].try_into().unwrap()) as usize;
    std::fs::write(&path, &good[..offset + 30 * 1234 + 17]).unwrap();
    let (e, msg) = expect_err(&path);
    assert!(matches!(e, FormatError::Point { index: 1234, .. }), "{e:?}");
    assert!(msg.contains("truncated") && msg.contains("5000 points"), "{msg}");
}

#[test]
fn truncated_and_corrupt_laz() {
    let dir = tempfile::tempdir().unwrap();
    let (path, good) = valid_las(dir.path(), "t.laz", 200_000);
    std::fs::write(&path, &good[..good.len() / 2]).unwrap();
    let (_, msg) = expect_err(&path);
    assert!(msg.contains("truncated"), "{msg}");
    // Cut inside the chunk table (the last bytes of a LAZ file).
    for cut in [good.len() - 20, good.len() - 4] {
        std::fs::write(&path, &good[..cut]).unwrap();
        expect_err(&path);
    }
    // The header promises more points than the chunk table holds.
    let mut b = good.clone();
    b[107..111].copy_from_slice(&300_000u32.to_le_bytes());
    b[247..255].copy_from_slice(&300_000u64.to_le_bytes());
    std::fs::write(&path, &b).unwrap();
    let (e, msg) = expect_err(&path);
    assert!(matches!(e, FormatError::File { .. }) && msg.contains("declares 300000 points"), "{msg}");
    // A LAZ description with no items would make the decoder step by zero bytes.
    let mut b = good.clone();
    let user_id = b.windows(14).position(|w| w == b"laszip encoded").unwrap();
    let items_at = user_id - 2 + 54 + 32;
    b[items_at..items_at + 2].copy_from_slice(&0u16.to_le_bytes());
    std::fs::write(&path, &b).unwrap();
    let msg = expect_err(&path).1;
    assert!(msg.contains("LAZ items describe 0-byte points"), "{msg}");
    // Garbage in the compressed stream: an error naming the file, or (LAZ cannot always tell)
    // some points; never a panic.
    let mut b = good.clone();
    let mid = b.len() / 3;
    for (k, byte) in b[mid..mid + 4096].iter_mut().enumerate() {
        *byte ^= (k * 151 % 251) as u8 | 1;
    }
    std::fs::write(&path, &b).unwrap();
    if let Err(e) = read_strip(&path) {
        assert!(e.to_string().contains("t.laz"), "{e}");
    }
}

fn write_with_las(path: &Path, format: u8, points: impl IntoIterator<Item = Point>) {
    let mut b = Builder::from(Version::new(1, 2));
    b.point_format = Format::new(format).unwrap();
    let mut w = las::Writer::from_path(path, b.into_header().unwrap()).unwrap();
    for p in points {
        w.write_point(p).unwrap();
    }
    w.close().unwrap();
}

#[test]
fn point_format_without_gps_time() {
    let dir = tempfile::tempdir().unwrap();
    for format in [0u8, 2] {
        let path = dir.path().join(format!("f{format}.las"));
        let color = (format == 2).then(|| Color::new(1, 2, 3));
        write_with_las(&path, format, (0..10).map(|i| Point { x: i as f64, color, ..Default::default() }));
        let (e, msg) = expect_err(&path);
        assert!(matches!(e, FormatError::File { .. }));
        assert!(msg.contains(&format!("point format {format} has no GPS time")), "{msg}");
        assert!(msg.contains("re-export with GPS time: point format 1, 3 or 6–10"), "{msg}");
        assert!(!strip_info(&path).unwrap().has_gps_time);
    }
}

#[test]
fn non_finite_gps_time_names_the_point() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nan.las");
    let gps = |i: usize| if i == 6 { f64::NAN } else { i as f64 };
    write_with_las(&path, 1, (0..10).map(|i| Point { x: i as f64, gps_time: Some(gps(i)), ..Default::default() }));
    let (e, msg) = expect_err(&path);
    assert!(matches!(e, FormatError::Point { index: 6, .. }), "{e:?}");
    assert!(msg.contains("GPS time is NaN"), "{msg}");
}

#[test]
fn legacy_format_scan_rank_and_zero_channel() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("legacy.las");
    write_with_las(
        &path,
        1,
        (0..10).map(|i| Point { gps_time: Some(i as f64), scan_angle: i as f32 * 10.0 - 45.0, ..Default::default() }),
    );
    let s = read_strip(&path).unwrap();
    assert_eq!(s.scan_angle_deg[9], 45.0);
    assert_eq!(s.channel, vec![0; 10]);
    assert_eq!(strip_info(&path).unwrap().version, (1, 2));
}

#[test]
fn zero_points() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("empty.laz");
    StripWriter::create(&path, OFFSET, SCALE, "t", "t").unwrap().finish().unwrap();
    let (_, msg) = expect_err(&path);
    assert!(msg.contains("has no points"), "{msg}");
    assert_eq!(strip_info(&path).unwrap().point_count, 0);
}

/// Throughput on ~2M points. `cargo test --release -p precimap-formats --test it strip:: -- --ignored --nocapture`
#[test]
#[ignore]
fn throughput_2m_points() {
    let dir = tempfile::tempdir().unwrap();
    let n = 2_000_000;
    let points = sample_points(n);
    for name in ["big.las", "big.laz"] {
        let path = dir.path().join(name);
        let t = std::time::Instant::now();
        write_strip(&path, &points);
        let w = t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let s = read_strip(&path).unwrap();
        let r = t.elapsed().as_secs_f64();
        assert_eq!(s.len(), n);
        let out = dir.path().join(format!("re-{name}"));
        let t = std::time::Instant::now();
        rewrite_strip(&path, &out, |_, p| [p[0] + 0.01, p[1], p[2]]).unwrap();
        let rw = t.elapsed().as_secs_f64();
        let mb = std::fs::metadata(&path).unwrap().len() as f64 / 1e6;
        eprintln!(
            "{name}: {n} points, {mb:.1} MB; write {:.2} M pts/s, read_strip {:.2} M pts/s, rewrite {:.2} M pts/s",
            n as f64 / w / 1e6,
            n as f64 / r / 1e6,
            n as f64 / rw / 1e6
        );
    }
}

/// The timed rewrite hands every point its own GPS time, in one pass; a source without GPS time
/// is refused.
#[test]
fn timed_rewrite_passes_gps_time() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["s.las", "s.laz"] {
        let src = dir.path().join(name);
        let points = sample_points(300);
        write_strip(&src, &points);
        let mut seen = Vec::new();
        let dst = dir.path().join(format!("out-{name}"));
        let n = rewrite_strip_timed(&src, &dst, |i, xyz, t| {
            seen.push((i, t));
            xyz
        })
        .unwrap();
        assert_eq!(n, 300);
        for (k, (i, t)) in seen.iter().enumerate() {
            assert_eq!(*i, k);
            assert_eq!(*t, points[k].gps_time, "point {k}");
        }
    }
    let no_time = dir.path().join("format0.las");
    write_rich_source(&no_time, 0, (1, 2), 10);
    let err = rewrite_strip_timed(&no_time, &dir.path().join("x.las"), |_, xyz, _| xyz).unwrap_err();
    assert!(err.to_string().contains("GPS time"), "{err}");
}

/// LAZ strips decode only the fields `read_strip` needs (layered formats skip the other layers):
/// they must come out exactly as a full decode gives them, whatever the other fields hold, for
/// legacy and extended formats with colour, NIR and extra bytes.
#[test]
fn selective_laz_decoding_matches_full_decoding() {
    let dir = tempfile::tempdir().unwrap();
    for (format, version) in [(1u8, (1, 2)), (3, (1, 2)), (6, (1, 4)), (7, (1, 4)), (8, (1, 4))] {
        let path = dir.path().join(format!("rich{format}.laz"));
        let points = write_rich_source(&path, format, version, 70_000);
        let s = read_strip(&path).unwrap();
        assert_eq!(s.len(), points.len());
        let full = las_points(&path);
        for (i, p) in full.iter().enumerate() {
            assert_eq!([s.x[i], s.y[i], s.z[i]], [p.x, p.y, p.z], "format {format} point {i}");
            assert_eq!(s.gps_time[i], p.gps_time.unwrap(), "format {format} point {i}");
            assert!((s.scan_angle_deg[i] - p.scan_angle).abs() < 1e-4, "format {format} point {i}");
            assert_eq!(s.channel[i], p.scanner_channel, "format {format} point {i}");
            assert_eq!(s.channel[i], points[i].scanner_channel);
        }
    }
}

/// A multi-beam head's ring number from the user-data byte (LAS and LAZ), the scanner channel,
/// or a named extra-bytes field; a field the file lacks is an error naming the fields it has.
#[test]
fn ring_numbers_from_user_data_channel_and_extra_bytes() {
    use precimap_core::RingSource;
    use precimap_formats::read_strip_with_ring;
    let dir = tempfile::tempdir().unwrap();
    let points = sample_points(70_000);
    for name in ["r.las", "r.laz"] {
        let path = dir.path().join(name);
        let mut w = StripWriter::create(&path, OFFSET, SCALE, "precimap test", "precimap-formats").unwrap();
        for (i, p) in points.iter().enumerate() {
            w.push_with_user_data(p, (i % 32) as u8).unwrap();
        }
        w.finish().unwrap();
        let s = read_strip_with_ring(&path, Some(&RingSource::UserData)).unwrap();
        assert!(s.ring.iter().enumerate().all(|(i, &r)| r == (i % 32) as u8), "{name}");
        assert_eq!(read_strip_with_ring(&path, Some(&RingSource::ScannerChannel)).unwrap().ring, s.channel);
        assert!(read_strip(&path).unwrap().ring.is_empty());
        let e = read_strip_with_ring(&path, Some(&RingSource::ExtraBytes("ring".into()))).unwrap_err().to_string();
        assert!(e.contains("\"ring\"") && e.contains("no extra-bytes fields"), "{e}");
    }
    // Extra bytes: a 1-byte field before a 2-byte "laser" field.
    let path = dir.path().join("extra.las");
    let mut b = Builder::from(Version::new(1, 4));
    b.point_format = Format::new(6).unwrap();
    b.point_format.extra_bytes = 3;
    let mut data = Vec::new();
    for (field, data_type) in [("pad", 1u8), ("laser", 3u8)] {
        let mut d = [0u8; 192];
        d[2] = data_type;
        d[4..4 + field.len()].copy_from_slice(field.as_bytes());
        data.extend_from_slice(&d);
    }
    b.vlrs.push(Vlr { user_id: "LASF_Spec".into(), record_id: 4, description: "Extra Bytes Record".into(), data });
    let mut w = las::Writer::from_path(&path, b.into_header().unwrap()).unwrap();
    for i in 0..100u16 {
        let laser = 200 + i % 50;
        w.write_point(Point {
            x: 1.0 + f64::from(i),
            y: 2.0,
            z: 3.0,
            gps_time: Some(f64::from(i)),
            extra_bytes: vec![7, laser.to_le_bytes()[0], laser.to_le_bytes()[1]],
            ..Default::default()
        })
        .unwrap();
    }
    w.close().unwrap();
    let s = read_strip_with_ring(&path, Some(&RingSource::ExtraBytes("laser".into()))).unwrap();
    assert!(s.ring.iter().enumerate().all(|(i, &r)| u16::from(r) == 200 + i as u16 % 50));
    let e = read_strip_with_ring(&path, Some(&RingSource::ExtraBytes("ring".into()))).unwrap_err().to_string();
    assert!(e.contains("only pad, laser"), "{e}");
}
