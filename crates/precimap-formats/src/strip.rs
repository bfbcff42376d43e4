//! Strips: LAS 1.2–1.4 and LAZ point clouds in acquisition order, via the `las` crate.
//!
//! Points are handled as raw records in batches (`PointData`) rather than as `las::Point`s: reading
//! decodes only the fields estimation needs, and rewriting patches x/y/z in place so every other
//! byte of a record (flags, extra bytes, colour, waveform...) is carried over untouched.
//!
//! Headers are sanity-checked against the file size before the `las` crate sees them: a damaged
//! header must give an error, never a huge allocation or an arithmetic overflow.

use crate::atomic::PendingFile;
use crate::gps_time::TimeConvention;
use crate::strip_crs::{declare_crs, header_crs, DeclaredCrs, StripCrs, StripDeclarations};
use crate::FormatError;
use las::point::Format;
use las::{Builder, Header, PointData, PointDataBuilder, Reader, Transform, Vector, Version, Writer};
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// Points per batch: large enough to amortise per-call overhead, small enough to stay in cache-ish
/// memory (64 Ki points × ≤ 67 bytes ≈ 4 MB).
const BATCH: usize = 1 << 16;

/// Record layout (LAS 1.4 R15, tables 7–17). x, y, z are always the first 12 bytes.
mod layout {
    pub const FLAGS2: usize = 15;
    pub const LEGACY_SCAN_RANK: usize = 16;
    pub const LEGACY_GPS: usize = 20;
    pub const EXT_CLASSIFICATION: usize = 16;
    pub const EXT_USER_DATA: usize = 17;
    pub const EXT_SCAN_ANGLE: usize = 18;
    pub const EXT_POINT_SOURCE: usize = 20;
    pub const EXT_GPS: usize = 22;
    pub const FORMAT6_LEN: usize = 30;
}

/// LAS scan angle unit of point formats 6–10, degrees.
const SCAN_ANGLE_UNIT_DEG: f32 = 0.006;

/// What estimation needs from a strip, in file (acquisition) order, struct-of-arrays.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StripPoints {
    pub x: Vec<f64>,
    pub y: Vec<f64>,
    pub z: Vec<f64>,
    pub gps_time: Vec<f64>,
    /// Scan angle in degrees (LAS 1.4 formats 6–10: the f32 the las crate returns for the 0.006°
    /// field; formats 0–5: the rank value as degrees).
    pub scan_angle_deg: Vec<f32>,
    /// Scanner channel (0–3), 0 for formats without it.
    pub channel: Vec<u8>,
}

impl StripPoints {
    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// The first and last GPS time of the points; `None` without points.
    pub fn gps_time_span(&self) -> Option<(f64, f64)> {
        self.gps_time
            .iter()
            .fold(None, |span, &t| Some(span.map_or((t, t), |(first, last): (f64, f64)| (first.min(t), last.max(t)))))
    }

    fn with_capacity(n: usize) -> Self {
        Self {
            x: Vec::with_capacity(n),
            y: Vec::with_capacity(n),
            z: Vec::with_capacity(n),
            gps_time: Vec::with_capacity(n),
            scan_angle_deg: Vec::with_capacity(n),
            channel: Vec::with_capacity(n),
        }
    }
}

/// Header facts about a strip, read without touching the points.
#[derive(Clone, Debug, PartialEq)]
pub struct StripInfo {
    pub point_count: u64,
    pub point_format: u8,
    pub version: (u8, u8),
    pub has_gps_time: bool,
    pub compressed: bool,
    pub bounds_min: [f64; 3],
    pub bounds_max: [f64; 3],
    /// What the point records' GPS times count (the header's global-encoding bit 0).
    pub time_convention: TimeConvention,
    /// The CRS the file declares in its VLRs.
    pub crs: Option<StripCrs>,
}

fn is_laz_path(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("laz"))
}

fn point_error(path: &Path, index: u64, message: impl Into<String>) -> FormatError {
    FormatError::Point { path: path.to_path_buf(), index, message: message.into() }
}

const DAMAGED: &str = "the file is damaged or was cut off in transfer: re-export or copy it again";

// ---------------------------------------------------------------------------------------------
// Opening and checking

/// Reads the header with the checks that keep the `las` crate away from impossible values.
fn open_header(path: &Path) -> Result<(File, Header), FormatError> {
    let mut file = File::open(path).map_err(|e| FormatError::io(path, "open strip", e))?;
    let file_len = file.metadata().map_err(|e| FormatError::io(path, "read strip", e))?.len();
    let raw = las::raw::Header::read_from(BufReader::new(&mut file)).map_err(|e| {
        FormatError::file(
            path,
            format!("not a LAS/LAZ file or its header is damaged ({e}); check that this is a LAS 1.0–1.4 or LAZ file"),
        )
    })?;
    precheck(path, &mut file, file_len, &raw)?;
    file.seek(SeekFrom::Start(0)).map_err(|e| FormatError::io(path, "read strip", e))?;
    let header = Header::new(BufReader::new(&mut file))
        .map_err(|e| FormatError::file(path, format!("cannot read the LAS header or its VLRs ({e}); {DAMAGED}")))?;
    file.seek(SeekFrom::Start(0)).map_err(|e| FormatError::io(path, "read strip", e))?;
    Ok((file, header))
}

fn precheck(path: &Path, file: &mut File, file_len: u64, raw: &las::raw::Header) -> Result<(), FormatError> {
    let format = Format::new(raw.point_data_record_format).map_err(|_| {
        FormatError::file(
            path,
            format!(
                "header names point format {}, which is not a LAS 1.4 format (0–10); the header is damaged",
                raw.point_data_record_format
            ),
        )
    })?;
    let scales = [raw.x_scale_factor, raw.y_scale_factor, raw.z_scale_factor];
    let offsets = [raw.x_offset, raw.y_offset, raw.z_offset];
    if scales.iter().any(|s| !s.is_finite() || *s == 0.0) || offsets.iter().any(|o| !o.is_finite()) {
        return Err(FormatError::file(
            path,
            format!(
                "header scale {scales:?} / offset {offsets:?} cannot turn stored integers into coordinates; {DAMAGED}"
            ),
        ));
    }
    let legacy = u64::from(raw.number_of_point_records);
    let n = if legacy != 0 { legacy } else { raw.large_file.map_or(0, |l| l.number_of_point_records) };
    let offset = u64::from(raw.offset_to_point_data);
    let record = u64::from(raw.point_data_record_length);
    if offset > file_len {
        return Err(FormatError::file(
            path,
            format!("header says the points start at byte {offset}, but the file has only {file_len} bytes; {DAMAGED}"),
        ));
    }
    // The las crate computes this end offset unchecked; garbage here must not overflow.
    let Some(end) = n.checked_mul(record).and_then(|b| b.checked_add(offset)) else {
        return Err(FormatError::file(path, format!("header declares an impossible {n} points; {DAMAGED}")));
    };
    if !format.is_compressed && end > file_len {
        let complete = (file_len - offset) / record.max(1);
        return Err(point_error(
            path,
            complete,
            format!(
                "truncated: the header declares {n} points of {record} bytes, but the file ends after {complete} \
                 complete points (at byte {file_len} of {end}); {DAMAGED}"
            ),
        ));
    }
    let io = |e| FormatError::io(path, "read strip", e);
    if format.is_compressed && file_len >= offset + 8 {
        // LAZ: point data starts with the chunk table's offset; a table past the end means a cut
        // file, and a wild chunk count would make the decoder reserve gigabytes.
        file.seek(SeekFrom::Start(offset)).map_err(io)?;
        let table = read_u64(file).map_err(io)?;
        if table > offset && table != u64::MAX {
            if table.saturating_add(8) > file_len {
                return Err(FormatError::file(
                    path,
                    format!(
                        "truncated: the LAZ chunk table should be at byte {table}, but the file has only {file_len} \
                         bytes; {DAMAGED}"
                    ),
                ));
            }
            file.seek(SeekFrom::Start(table + 4)).map_err(io)?;
            let chunks = u64::from(read_u32(file).map_err(io)?);
            if chunks > file_len {
                return Err(FormatError::file(path, format!("LAZ chunk table claims {chunks} chunks; {DAMAGED}")));
            }
        }
    }
    if let Some(evlr) = raw.evlr.filter(|e| e.number_of_evlrs > 0 && e.start_of_first_evlr > 0) {
        // The las crate reads the first EVLR and allocates its declared (u64) length.
        let start = evlr.start_of_first_evlr;
        let fits = if start.saturating_add(60) <= file_len {
            file.seek(SeekFrom::Start(start + 20)).map_err(io)?;
            let len = read_u64(file).map_err(io)?;
            start.saturating_add(60).saturating_add(len) <= file_len
        } else {
            false
        };
        if !fits {
            return Err(FormatError::file(
                path,
                format!("the extended VLR at byte {start} runs past the end of the file ({file_len} bytes); {DAMAGED}"),
            ));
        }
    }
    Ok(())
}

fn read_u64(r: &mut impl Read) -> std::io::Result<u64> {
    let mut b = [0u8; 8];
    r.read_exact(&mut b)?;
    Ok(u64::from_le_bytes(b))
}

fn read_u32(r: &mut impl Read) -> std::io::Result<u32> {
    let mut b = [0u8; 4];
    r.read_exact(&mut b)?;
    Ok(u32::from_le_bytes(b))
}

/// A strip opened for reading point batches.
struct Source {
    path: PathBuf,
    reader: Reader,
    n: u64,
    next: u64,
}

/// The LAZ compression description of a compressed strip, checked against the header: the
/// decoder steps through records by the LAZ item sizes (and panics on zero), so they must describe
/// exactly the header's record length.
fn laz_vlr(path: &Path, header: &Header) -> Result<laz::LazVlr, FormatError> {
    let record = u64::from(header.point_format().len());
    let vlr = header.laz_vlr().map_err(|e| {
        FormatError::file(path, format!("cannot read the LAZ compression description ({e}); {DAMAGED}"))
    })?;
    let items = vlr.items_size();
    if items != record {
        return Err(FormatError::file(
            path,
            format!("LAZ items describe {items}-byte points but the header says {record} bytes; {DAMAGED}"),
        ));
    }
    Ok(vlr)
}

impl Source {
    fn open(path: &Path) -> Result<Self, FormatError> {
        let (file, header) = open_header(path)?;
        let n = header.number_of_points();
        if header.point_format().is_compressed {
            laz_vlr(path, &header)?;
        }
        let reader = Reader::new(BufReader::with_capacity(1 << 20, file))
            .map_err(|e| FormatError::file(path, format!("cannot start decoding the point data ({e}); {DAMAGED}")))?;
        Ok(Self { path: path.to_path_buf(), reader, n, next: 0 })
    }

    fn batch_buffer(&self) -> PointData {
        PointDataBuilder::new().for_header(self.reader.header()).build()
    }

    /// Fills `pd` with the next batch; returns the index of its first point, or None at the end.
    fn next_batch(&mut self, pd: &mut PointData) -> Result<Option<u64>, FormatError> {
        if self.next >= self.n {
            return Ok(None);
        }
        let first = self.next;
        match self.reader.fill_points(BATCH as u64, pd) {
            Ok(0) => Err(point_error(&self.path, first, format!("point data ends early; {DAMAGED}"))),
            Ok(k) => {
                self.next += k;
                Ok(Some(first))
            }
            Err(e) => Err(self.locate_failure(first, e)),
        }
    }

    fn locate_failure(&self, first: u64, batch_error: las::Error) -> FormatError {
        locate_failure(&self.path, self.n, first, &batch_error)
    }
}

/// Batches fail as a whole; re-decode the failed batch point by point to name the bad point.
fn locate_failure(path: &Path, n: u64, first: u64, batch_error: &dyn std::fmt::Display) -> FormatError {
    let last = (first + BATCH as u64).min(n);
    let found = (|| {
        let file = File::open(path).ok()?;
        let mut r = Reader::new(BufReader::new(file)).ok()?;
        r.seek(first).ok()?;
        let mut one = PointDataBuilder::new().for_header(r.header()).build();
        (first..last).find_map(|i| r.fill_points(1, &mut one).err().map(|e| (i, e)))
    })();
    match found {
        Some((i, e)) => point_error(path, i, format!("cannot decode point data ({e}); {DAMAGED}")),
        None => point_error(path, first, format!("cannot decode points {first}..{last} ({batch_error}); {DAMAGED}")),
    }
}

/// A LAZ strip opened for decoding only the fields [`read_strip`] needs: x, y, z, return and
/// channel, scan angle and GPS time. LAS 1.4 point formats 6–10 are compressed in layers, one per
/// field group, and the decoder skips the layers not asked for (intensity, classification, flags,
/// user data, point source id, colour, waveform, extra bytes) without decoding them; the bytes of
/// skipped fields in the records are not meaningful. Formats 0–5 are decoded whole.
struct LazFieldSource {
    path: PathBuf,
    decompressor: laz::LasZipDecompressor<'static, BufReader<File>>,
    record_len: usize,
    n: u64,
    next: u64,
    buffer: Vec<u8>,
}

impl LazFieldSource {
    fn open(path: &Path) -> Result<(Self, Header), FormatError> {
        let (file, header) = open_header(path)?;
        let vlr = laz_vlr(path, &header)?;
        let offset = header
            .clone()
            .into_raw()
            .map_err(|e| FormatError::file(path, format!("cannot read the LAS header ({e}); {DAMAGED}")))?
            .offset_to_point_data;
        let mut input = BufReader::with_capacity(1 << 20, file);
        input.seek(SeekFrom::Start(u64::from(offset))).map_err(|e| FormatError::io(path, "read strip", e))?;
        let fields = laz::DecompressionSelection::base().decompress_z().decompress_scan_angle().decompress_gps_time();
        let decompressor = laz::LasZipDecompressor::selective(input, vlr, fields)
            .map_err(|e| FormatError::file(path, format!("cannot start decoding the point data ({e}); {DAMAGED}")))?;
        let record_len = usize::from(header.point_format().len());
        let n = header.number_of_points();
        let source = Self { path: path.to_path_buf(), decompressor, record_len, n, next: 0, buffer: Vec::new() };
        Ok((source, header))
    }

    /// Decodes the next batch; returns the index of its first point and its records.
    fn next_batch(&mut self) -> Result<Option<(u64, &[u8])>, FormatError> {
        if self.next >= self.n {
            return Ok(None);
        }
        let first = self.next;
        let k = (self.n - first).min(BATCH as u64) as usize;
        self.buffer.resize(k * self.record_len, 0);
        if let Err(e) = self.decompressor.decompress_many(&mut self.buffer) {
            return Err(locate_failure(&self.path, self.n, first, &e));
        }
        self.next += k as u64;
        Ok(Some((first, &self.buffer)))
    }
}

// ---------------------------------------------------------------------------------------------
// Reading

/// Header facts only: cheap, does not decode points.
pub fn strip_info(path: &Path) -> Result<StripInfo, FormatError> {
    let (_, header) = open_header(path)?;
    let format = header.point_format();
    let number = format
        .to_u8()
        .map_err(|e| FormatError::file(path, format!("unsupported point format ({e}); re-export as LAS 1.2–1.4")))?;
    let b = header.bounds();
    Ok(StripInfo {
        point_count: header.number_of_points(),
        point_format: number,
        version: (header.version().major, header.version().minor),
        has_gps_time: format.has_gps_time,
        compressed: format.is_compressed,
        bounds_min: [b.min.x, b.min.y, b.min.z],
        bounds_max: [b.max.x, b.max.y, b.max.z],
        time_convention: time_convention(&header),
        crs: header_crs(&header),
    })
}

fn time_convention(header: &Header) -> TimeConvention {
    if header.gps_time_type().is_standard() {
        TimeConvention::AdjustedStandard
    } else {
        TimeConvention::WeekSeconds
    }
}

/// Reads the fields estimation needs. The whole strip is held in memory (bounded by strip size).
/// LAZ strips decode only those fields ([`LazFieldSource`]).
pub fn read_strip(path: &Path) -> Result<StripPoints, FormatError> {
    if strip_info(path)?.compressed {
        let (mut src, header) = LazFieldSource::open(path)?;
        let mut out = StripReader::new(path, &header, src.n)?;
        let record_len = src.record_len;
        while let Some((first, records)) = src.next_batch()? {
            out.push_records(first, records, record_len)?;
        }
        return Ok(out.points);
    }
    let mut src = Source::open(path)?;
    let mut out = StripReader::new(path, src.reader.header(), src.n)?;
    let mut pd = src.batch_buffer();
    while let Some(first) = src.next_batch(&mut pd)? {
        out.push_records(first, pd.raw_bytes(), pd.record_len())?;
    }
    Ok(out.points)
}

/// Turns raw records into [`StripPoints`].
struct StripReader<'a> {
    path: &'a Path,
    points: StripPoints,
    transforms: Vector<Transform>,
    gps_at: usize,
    extended: bool,
}

impl<'a> StripReader<'a> {
    fn new(path: &'a Path, header: &Header, n: u64) -> Result<Self, FormatError> {
        let format = *header.point_format();
        if !format.has_gps_time {
            let number = format.to_u8().unwrap_or(0);
            return Err(FormatError::file(
                path,
                format!(
                    "point format {number} has no GPS time, which is required to place points on the trajectory; \
                 re-export with GPS time: point format 1, 3 or 6–10"
                ),
            ));
        }
        if n == 0 {
            return Err(FormatError::file(
                path,
                "has no points; export the strip again or remove it from the manifest",
            ));
        }
        // LAS sizes were checked against the file; a LAZ header's count is not trusted for reservation.
        let reserve = if format.is_compressed { n.min(1 << 24) } else { n };
        let gps_at = if format.is_extended { layout::EXT_GPS } else { layout::LEGACY_GPS };
        Ok(Self {
            path,
            points: StripPoints::with_capacity(usize::try_from(reserve).unwrap_or(0)),
            transforms: *header.transforms(),
            gps_at,
            extended: format.is_extended,
        })
    }

    fn push_records(&mut self, first: u64, records: &[u8], record_len: usize) -> Result<(), FormatError> {
        let (t, gps_at, out) = (&self.transforms, self.gps_at, &mut self.points);
        for (j, rec) in records.chunks_exact(record_len).enumerate() {
            let [x, y, z] = decode_xyz(rec, t);
            let gps = f64::from_le_bytes(bytes8(rec, gps_at));
            if !gps.is_finite() {
                return Err(point_error(
                    self.path,
                    first + j as u64,
                    format!("GPS time is {gps}, not a finite number; the point data is damaged: re-export the strip"),
                ));
            }
            let (angle, channel) = if self.extended {
                let raw = i16::from_le_bytes([rec[layout::EXT_SCAN_ANGLE], rec[layout::EXT_SCAN_ANGLE + 1]]);
                (f32::from(raw) * SCAN_ANGLE_UNIT_DEG, (rec[layout::FLAGS2] >> 4) & 3)
            } else {
                (f32::from(rec[layout::LEGACY_SCAN_RANK] as i8), 0)
            };
            out.x.push(x);
            out.y.push(y);
            out.z.push(z);
            out.gps_time.push(gps);
            out.scan_angle_deg.push(angle);
            out.channel.push(channel);
        }
        Ok(())
    }
}

#[inline]
fn bytes4(rec: &[u8], at: usize) -> [u8; 4] {
    [rec[at], rec[at + 1], rec[at + 2], rec[at + 3]]
}

#[inline]
fn bytes8(rec: &[u8], at: usize) -> [u8; 8] {
    let mut b = [0u8; 8];
    b.copy_from_slice(&rec[at..at + 8]);
    b
}

#[inline]
fn decode_xyz(rec: &[u8], t: &Vector<Transform>) -> [f64; 3] {
    [
        t.x.direct(i32::from_le_bytes(bytes4(rec, 0))),
        t.y.direct(i32::from_le_bytes(bytes4(rec, 4))),
        t.z.direct(i32::from_le_bytes(bytes4(rec, 8))),
    ]
}

/// Integer coordinates for `xyz` on the file's grid, or a message saying why they do not fit.
/// One grid step of margin at each end keeps the header's rounded bounds inside i32 as well.
fn quantize(xyz: [f64; 3], t: &Vector<Transform>) -> Result<[i32; 3], String> {
    if xyz.iter().any(|v| !v.is_finite()) {
        return Err(format!("coordinates ({}, {}, {}) are not finite numbers", xyz[0], xyz[1], xyz[2]));
    }
    let mut out = [0i32; 3];
    for (k, (v, tr)) in xyz.iter().zip([t.x, t.y, t.z]).enumerate() {
        let q = ((v - tr.offset) / tr.scale).round();
        let (lo, hi) = (f64::from(i32::MIN) + 1.0, f64::from(i32::MAX) - 1.0);
        if !(lo..=hi).contains(&q) {
            let axis = ["x", "y", "z"][k];
            return Err(format!(
                "{axis} = {v} does not fit the file's coordinate grid (scale {}, offset {}: representable {} to {}); \
                 use an offset near the data or a coarser scale",
                tr.scale,
                tr.offset,
                tr.direct(i32::MIN + 1),
                tr.direct(i32::MAX - 1)
            ));
        }
        out[k] = q as i32;
    }
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// Writing

/// The file under a `las::Writer`. Once poisoned (after any error) it swallows all output while
/// keeping consistent positions: the `las` writer finalises itself on drop and panics if that
/// fails, so an abandoned writer must be able to "finish" into the void.
struct Sink {
    inner: BufWriter<File>,
    poisoned: Arc<AtomicBool>,
    pos: u64,
    len: u64,
}

impl Sink {
    fn fail<T>(&self, e: std::io::Error) -> std::io::Result<T> {
        self.poisoned.store(true, Ordering::Relaxed);
        Err(e)
    }
}

impl Write for Sink {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = if self.poisoned.load(Ordering::Relaxed) {
            buf.len()
        } else {
            match self.inner.write(buf) {
                Ok(n) => n,
                Err(e) => return self.fail(e),
            }
        };
        self.pos += n as u64;
        self.len = self.len.max(self.pos);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        if self.poisoned.load(Ordering::Relaxed) {
            return Ok(());
        }
        self.inner.flush().or_else(|e| self.fail(e))
    }
}

impl Seek for Sink {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        if self.poisoned.load(Ordering::Relaxed) {
            let base = match to {
                SeekFrom::Start(p) => return Ok(self.set_pos(p)),
                SeekFrom::Current(d) => self.pos.checked_add_signed(d),
                SeekFrom::End(d) => self.len.checked_add_signed(d),
            };
            return Ok(self.set_pos(base.unwrap_or(0)));
        }
        match self.inner.seek(to) {
            Ok(p) => Ok(self.set_pos(p)),
            Err(e) => self.fail(e),
        }
    }
}

impl Sink {
    fn set_pos(&mut self, p: u64) -> u64 {
        self.pos = p;
        self.len = self.len.max(p);
        p
    }
}

/// A strip being written to a hidden temporary that is renamed into place by `finish`.
struct OutStrip {
    path: PathBuf,
    writer: Option<Writer<Sink>>,
    poisoned: Arc<AtomicBool>,
    pending: Option<PendingFile>,
}

impl OutStrip {
    fn create(path: &Path, header: Header) -> Result<Self, FormatError> {
        let (pending, file) = PendingFile::create(path)?;
        let poisoned = Arc::new(AtomicBool::new(false));
        let sink = Sink { inner: BufWriter::with_capacity(1 << 20, file), poisoned: poisoned.clone(), pos: 0, len: 0 };
        let writer = Writer::new(sink, header)
            .map_err(|e| FormatError::file(path, format!("cannot start writing the strip: {e}")))?;
        Ok(Self { path: path.to_path_buf(), writer: Some(writer), poisoned, pending: Some(pending) })
    }

    fn broken(&self) -> FormatError {
        FormatError::file(&self.path, "an earlier write to this strip failed; the file was not created")
    }

    fn write(&mut self, pd: &PointData) -> Result<(), FormatError> {
        let Some(w) = self.writer.as_mut().filter(|_| !self.poisoned.load(Ordering::Relaxed)) else {
            return Err(self.broken());
        };
        w.write_points(pd).map_err(|e| {
            self.poisoned.store(true, Ordering::Relaxed);
            FormatError::file(&self.path, format!("cannot write points: {e}"))
        })
    }

    fn finish(mut self) -> Result<(), FormatError> {
        let Some(mut w) = self.writer.take().filter(|_| !self.poisoned.load(Ordering::Relaxed)) else {
            return Err(self.broken());
        };
        if let Err(e) = w.close() {
            // A writer whose close failed would retry (and panic) on drop; leaking it in this
            // already-failed case is the only safe exit.
            self.poisoned.store(true, Ordering::Relaxed);
            std::mem::forget(w);
            return Err(FormatError::file(&self.path, format!("cannot finish the strip: {e}")));
        }
        let sink =
            w.into_inner().map_err(|e| FormatError::file(&self.path, format!("cannot finish the strip: {e}")))?;
        if sink.poisoned.load(Ordering::Relaxed) {
            return Err(self.broken());
        }
        sink.inner.into_inner().map_err(|e| FormatError::io(&self.path, "write strip", e.into_error()))?;
        match self.pending.take() {
            Some(p) => p.commit(),
            None => Err(self.broken()),
        }
    }
}

impl Drop for OutStrip {
    fn drop(&mut self) {
        if let Some(w) = self.writer.take() {
            // Abandoned (error or early drop): finish into the void; `pending` then deletes the temporary.
            self.poisoned.store(true, Ordering::Relaxed);
            drop(w);
        }
    }
}

/// One point for [`StripWriter::push`].
#[derive(Clone, Copy, Debug, Default)]
pub struct NewPoint {
    pub position: [f64; 3],
    pub gps_time: f64,
    /// Degrees, −180..=180; stored in 0.006° units.
    pub scan_angle_deg: f32,
    /// Scanner channel 0–3.
    pub channel: u8,
    pub intensity: u16,
    /// 0–15.
    pub return_number: u8,
    /// 0–15.
    pub number_of_returns: u8,
    pub point_source_id: u16,
    pub classification: u8,
}

/// Writes a new strip: LAS 1.4, point format 6, given offset and scale, LAZ if the path ends in
/// `.laz`. The file appears under its name only when [`StripWriter::finish`] succeeds.
pub struct StripWriter {
    out: OutStrip,
    transforms: Vector<Transform>,
    batch: PointData,
    batch_len: usize,
    written: u64,
}

impl std::fmt::Debug for StripWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StripWriter")
            .field("path", &self.out.path)
            .field("points", &(self.written + self.batch_len as u64))
            .finish_non_exhaustive()
    }
}

impl StripWriter {
    pub fn create(
        path: &Path,
        offset: [f64; 3],
        scale: f64,
        system_identifier: &str,
        generating_software: &str,
    ) -> Result<Self, FormatError> {
        Self::create_with(path, offset, scale, system_identifier, generating_software, StripDeclarations::default())
    }

    /// [`StripWriter::create`] with a CRS and a GPS time convention declared in the header.
    pub fn create_with(
        path: &Path,
        offset: [f64; 3],
        scale: f64,
        system_identifier: &str,
        generating_software: &str,
        declarations: StripDeclarations<'_>,
    ) -> Result<Self, FormatError> {
        if !(scale.is_finite() && scale > 0.0) || offset.iter().any(|o| !o.is_finite()) {
            return Err(FormatError::file(
                path,
                format!("cannot create strip: scale {scale} must be a positive number and offsets {offset:?} finite"),
            ));
        }
        for (what, s) in [("system identifier", system_identifier), ("generating software", generating_software)] {
            if s.len() > 32 || !s.is_ascii() {
                return Err(FormatError::file(
                    path,
                    format!("cannot create strip: {what} {s:?} must be ASCII of at most 32 bytes"),
                ));
            }
        }
        let mut b = Builder::from(Version::new(1, 4));
        b.point_format = Format::new(6).map_err(|e| FormatError::file(path, e.to_string()))?;
        b.point_format.is_compressed = is_laz_path(path);
        let axis = |o: f64| Transform { scale, offset: o };
        b.transforms = Vector { x: axis(offset[0]), y: axis(offset[1]), z: axis(offset[2]) };
        b.system_identifier = system_identifier.to_string();
        b.generating_software = generating_software.to_string();
        if declarations.adjusted_standard_time {
            b.gps_time_type = las::GpsTimeType::Standard;
        }
        let mut header =
            b.into_header().map_err(|e| FormatError::file(path, format!("cannot create strip header: {e}")))?;
        if let Some(wkt) = declarations.wkt {
            header
                .set_wkt_crs(wkt.as_bytes().to_vec())
                .map_err(|e| FormatError::file(path, format!("cannot declare the CRS: {e}")))?;
        }
        let transforms = *header.transforms();
        let batch = PointDataBuilder::new().for_header(&header).build();
        let out = OutStrip::create(path, header)?;
        Ok(Self { out, transforms, batch, batch_len: 0, written: 0 })
    }

    /// Appends a point. An invalid point is rejected with an error naming its index and is not
    /// written; the writer stays usable.
    pub fn push(&mut self, p: &NewPoint) -> Result<(), FormatError> {
        let index = self.written + self.batch_len as u64;
        let bad = |m: String| point_error(&self.out.path, index, m);
        let xyz = quantize(p.position, &self.transforms).map_err(bad)?;
        if !p.gps_time.is_finite() {
            return Err(bad(format!("GPS time {} is not a finite number", p.gps_time)));
        }
        if !(p.scan_angle_deg.is_finite() && (-180.0..=180.0).contains(&p.scan_angle_deg)) {
            return Err(bad(format!("scan angle {}° is outside −180°..180°", p.scan_angle_deg)));
        }
        if p.channel > 3 || p.return_number > 15 || p.number_of_returns > 15 {
            return Err(bad(format!(
                "channel {} (0–3), return number {} or number of returns {} (0–15) out of range",
                p.channel, p.return_number, p.number_of_returns
            )));
        }
        let scan = (p.scan_angle_deg / SCAN_ANGLE_UNIT_DEG).round() as i16;

        let at = self.batch_len * layout::FORMAT6_LEN;
        let bytes = self.batch.resize_for(self.batch_len + 1);
        let rec = &mut bytes[at..at + layout::FORMAT6_LEN];
        rec[0..4].copy_from_slice(&xyz[0].to_le_bytes());
        rec[4..8].copy_from_slice(&xyz[1].to_le_bytes());
        rec[8..12].copy_from_slice(&xyz[2].to_le_bytes());
        rec[12..14].copy_from_slice(&p.intensity.to_le_bytes());
        rec[14] = (p.number_of_returns << 4) | p.return_number;
        rec[layout::FLAGS2] = p.channel << 4;
        rec[layout::EXT_CLASSIFICATION] = p.classification;
        rec[layout::EXT_USER_DATA] = 0;
        rec[layout::EXT_SCAN_ANGLE..layout::EXT_SCAN_ANGLE + 2].copy_from_slice(&scan.to_le_bytes());
        rec[layout::EXT_POINT_SOURCE..layout::EXT_POINT_SOURCE + 2].copy_from_slice(&p.point_source_id.to_le_bytes());
        rec[layout::EXT_GPS..layout::EXT_GPS + 8].copy_from_slice(&p.gps_time.to_le_bytes());
        self.batch_len += 1;
        if self.batch_len == BATCH {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), FormatError> {
        if self.batch_len > 0 {
            self.out.write(&self.batch)?;
            self.written += self.batch_len as u64;
            self.batch_len = 0;
            self.batch.resize_for(0);
        }
        Ok(())
    }

    /// Completes the file (header bounds and counts) and moves it into place; returns the number
    /// of points written.
    pub fn finish(mut self) -> Result<u64, FormatError> {
        self.flush()?;
        let n = self.written;
        self.out.finish()?;
        Ok(n)
    }
}

// ---------------------------------------------------------------------------------------------
// Rewriting

/// Rewrites a strip point by point with new coordinates, keeping every other attribute (all
/// record bytes including extra bytes, VLRs and EVLRs, point format, version, scale and offset);
/// LAZ if `dst` ends in `.laz`. `new_xyz(index, old_xyz)` returns the new coordinates. Streams in
/// batches; `dst` appears only on success (so `dst == src` is safe).
pub fn rewrite_strip(
    src: &Path,
    dst: &Path,
    mut new_xyz: impl FnMut(usize, [f64; 3]) -> [f64; 3],
) -> Result<u64, FormatError> {
    rewrite(src, dst, false, None, |i, xyz, _| new_xyz(i, xyz))
}

/// [`rewrite_strip`] that also hands `new_xyz` each point's GPS time, so a caller that places
/// points on a trajectory needs only this one pass over the strip. A strip without GPS time is
/// an error.
pub fn rewrite_strip_timed(
    src: &Path,
    dst: &Path,
    new_xyz: impl FnMut(usize, [f64; 3], f64) -> [f64; 3],
) -> Result<u64, FormatError> {
    rewrite(src, dst, true, None, new_xyz)
}

/// [`rewrite_strip_timed`] that makes the copy declare `crs` when the source declares no CRS: a
/// WKT VLR in LAS 1.4, GeoTIFF keys before. A source that declares one keeps its own VLRs (the
/// caller checks that it is the same CRS).
pub fn rewrite_strip_declaring(
    src: &Path,
    dst: &Path,
    crs: DeclaredCrs<'_>,
    new_xyz: impl FnMut(usize, [f64; 3], f64) -> [f64; 3],
) -> Result<u64, FormatError> {
    rewrite(src, dst, true, Some(crs), new_xyz)
}

fn rewrite(
    src: &Path,
    dst: &Path,
    need_time: bool,
    declare: Option<DeclaredCrs<'_>>,
    mut new_xyz: impl FnMut(usize, [f64; 3], f64) -> [f64; 3],
) -> Result<u64, FormatError> {
    let mut source = Source::open(src)?;
    let format = *source.reader.header().point_format();
    if need_time && !format.has_gps_time {
        return Err(FormatError::file(src, "point format has no GPS time; re-export with point format 1, 3 or 6–10"));
    }
    // Records without GPS time pass NaN; only the timed variant reads it, and it refuses them.
    let gps_at = format.has_gps_time.then_some(if format.is_extended { layout::EXT_GPS } else { layout::LEGACY_GPS });
    let mut b = Builder::from(source.reader.header().clone());
    // The compressor adds its own laszip VLR; the source's would be stale or duplicated.
    b.vlrs.retain(|v| !las::laz::is_laszip_vlr(v));
    b.evlrs.retain(|v| !las::laz::is_laszip_vlr(v));
    b.point_format.is_compressed = is_laz_path(dst);
    let mut header = b.into_header().map_err(|e| FormatError::file(src, format!("cannot copy the header: {e}")))?;
    if let Some(crs) = declare {
        declare_crs(src, &mut header, crs)?;
    }
    let t = *header.transforms();
    let mut out = OutStrip::create(dst, header)?;
    let mut pd = source.batch_buffer();
    while let Some(first) = source.next_batch(&mut pd)? {
        let n = pd.len();
        let record_len = pd.record_len();
        let bytes = pd.resize_for(n);
        for (j, rec) in bytes.chunks_exact_mut(record_len).enumerate() {
            let index = first + j as u64;
            let time = gps_at.map_or(f64::NAN, |at| f64::from_le_bytes(bytes8(rec, at)));
            let new = new_xyz(index as usize, decode_xyz(rec, &t), time);
            let q = quantize(new, &t).map_err(|m| {
                point_error(src, index, format!("new coordinates cannot be stored in {}: {m}", dst.display()))
            })?;
            rec[0..4].copy_from_slice(&q[0].to_le_bytes());
            rec[4..8].copy_from_slice(&q[1].to_le_bytes());
            rec[8..12].copy_from_slice(&q[2].to_le_bytes());
        }
        out.write(&pd)?;
    }
    out.finish()?;
    Ok(source.next)
}
