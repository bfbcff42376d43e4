//! Strips: LAS 1.2–1.4 and LAZ point clouds in acquisition order, via the `las` crate.
//!
//! Points are handled as raw records in batches (`PointData`) rather than as `las::Point`s: reading
//! decodes only the fields estimation needs, and rewriting patches x/y/z in place so every other
//! byte of a record (flags, extra bytes, colour, waveform...) is carried over untouched.
//!
//! Opening checks the header against the file ([`check`]); reading checks what the points hold
//! (coordinates, GPS time) and that the strip can be written back ([`rewrite::plan_output`]), so
//! a strip is refused when it is read, not after the work on it.

mod check;
mod rewrite;
mod write;

use crate::gps_time::TimeConvention;
use crate::strip_crs::{header_crs, StripCrs};
use crate::FormatError;
use check::{laz_vlr, open_header};
use las::{Header, PointData, PointDataBuilder, Reader, Transform, Vector};
use precimap_core::RingSource;
use std::fs::File;
use std::io::{BufReader, Seek, SeekFrom};
use std::path::{Path, PathBuf};

pub use rewrite::{rewrite_strip, rewrite_strip_declaring, rewrite_strip_timed};
pub use write::{NewPoint, StripWriter};

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
    /// The same byte in every point format.
    pub const USER_DATA: usize = 17;
    pub const EXT_SCAN_ANGLE: usize = 18;
    pub const EXT_POINT_SOURCE: usize = 20;
    pub const EXT_GPS: usize = 22;
    pub const FORMAT6_LEN: usize = 30;
}

/// The largest coordinate magnitude accepted, in file units: a hundred times any projected,
/// geocentric or geographic coordinate on Earth, in metres or feet.
const MAX_COORDINATE: f64 = 1e9;

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
    /// A multi-beam head's ring number per point, when read with a ring source
    /// ([`read_strip_with_ring`]); empty otherwise.
    pub ring: Vec<u8>,
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
            ring: Vec::new(),
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

/// Where a strip's records come from: the `las` reader for LAS; for LAZ the decoder itself, so
/// that reading decodes only the fields it needs and LASzip 1.x point-wise files decode too.
enum Records {
    Las(Reader),
    Laz(Box<laz::LasZipDecompressor<'static, BufReader<File>>>),
}

/// A strip opened for reading point batches.
struct Source {
    path: PathBuf,
    header: Header,
    records: Records,
    fields: laz::DecompressionSelection,
    n: u64,
    next: u64,
}

/// LAZ compressor type of LASzip 1.x point-wise files: one chunk, no chunk table.
const COMPRESSOR_POINT_WISE: u16 = 1;

/// Offset of the chunk size in the LASzip VLR (after compressor, coder, version and options).
const LASZIP_CHUNK_SIZE_AT: usize = 12;

/// The LAZ description the decoder gets. A point-wise file may carry the variable-size-chunks
/// marker as its chunk size, which would make the decoder look for a chunk table it has no use
/// for; any fixed size describes its single chunk.
fn decoder_vlr(path: &Path, header: &Header) -> Result<laz::LazVlr, FormatError> {
    let vlr = laz_vlr(path, header)?;
    let raw = header.vlrs().iter().find(|v| las::laz::is_laszip_vlr(v)).map(|v| v.data.clone()).unwrap_or_default();
    let point_wise = raw.get(0..2).is_some_and(|b| u16::from_le_bytes([b[0], b[1]]) == COMPRESSOR_POINT_WISE);
    if !(point_wise && vlr.uses_variable_size_chunks() && raw.len() >= LASZIP_CHUNK_SIZE_AT + 4) {
        return Ok(vlr);
    }
    let mut data = raw;
    data[LASZIP_CHUNK_SIZE_AT..LASZIP_CHUNK_SIZE_AT + 4].copy_from_slice(&50_000u32.to_le_bytes());
    laz::LazVlr::from_buffer(&data)
        .map_err(|e| FormatError::file(path, format!("cannot read the LAZ compression description ({e}); {DAMAGED}")))
}

impl Source {
    /// Every field of every record.
    fn open(path: &Path) -> Result<Self, FormatError> {
        Self::open_with(path, laz::DecompressionSelection::all())
    }

    /// For LAZ, decodes only `fields`: LAS 1.4 point formats 6–10 are compressed in layers, one
    /// per field group, and the decoder skips the layers not asked for without decoding them (the
    /// bytes of skipped fields in the records are not meaningful). Formats 0–5 are decoded whole.
    fn open_with(path: &Path, fields: laz::DecompressionSelection) -> Result<Self, FormatError> {
        let (mut file, header) = open_header(path)?;
        let n = header.number_of_points();
        let start = |e: &dyn std::fmt::Display| {
            FormatError::file(path, format!("cannot start decoding the point data ({e}); {DAMAGED}"))
        };
        let records = if header.point_format().is_compressed {
            let vlr = decoder_vlr(path, &header)?;
            // The file's own offset: one recomputed from the header can miss padding before the points.
            let offset = las::raw::Header::read_from(&mut file).map_err(|e| start(&e))?.offset_to_point_data;
            let mut input = BufReader::with_capacity(1 << 20, file);
            input.seek(SeekFrom::Start(u64::from(offset))).map_err(|e| FormatError::io(path, "read strip", e))?;
            let decompressor = laz::LasZipDecompressor::selective(input, vlr, fields).map_err(|e| start(&e))?;
            Records::Laz(Box::new(decompressor))
        } else {
            Records::Las(Reader::new(BufReader::with_capacity(1 << 20, file)).map_err(|e| start(&e))?)
        };
        Ok(Self { path: path.to_path_buf(), header, records, fields, n, next: 0 })
    }

    fn batch_buffer(&self) -> PointData {
        PointDataBuilder::new().for_header(&self.header).build()
    }

    /// Fills `pd` with the next batch; returns the index of its first point, or None at the end.
    fn next_batch(&mut self, pd: &mut PointData) -> Result<Option<u64>, FormatError> {
        if self.next >= self.n {
            return Ok(None);
        }
        let first = self.next;
        let read = match &mut self.records {
            Records::Las(reader) => reader.fill_points(BATCH as u64, pd).map_err(|e| e.to_string()),
            Records::Laz(decoder) => {
                let k = (self.n - first).min(BATCH as u64);
                let bytes = pd.resize_for(k as usize);
                decoder.decompress_many(bytes).map(|()| k).map_err(|e| e.to_string())
            }
        };
        match read {
            Ok(0) => Err(point_error(&self.path, first, format!("point data ends early; {DAMAGED}"))),
            Ok(k) => {
                self.next += k;
                Ok(Some(first))
            }
            Err(e) => Err(locate_failure(&self.path, self.fields, self.n, first, &e)),
        }
    }
}

/// Batches fail as a whole; re-decode point by point to name the bad point (LAZ from the start,
/// as chunks need not be indexed).
fn locate_failure(
    path: &Path,
    fields: laz::DecompressionSelection,
    n: u64,
    first: u64,
    batch_error: &str,
) -> FormatError {
    let last = (first + BATCH as u64).min(n);
    let found = (|| {
        let mut source = Source::open_with(path, fields).ok()?;
        let mut one = source.batch_buffer();
        match &mut source.records {
            Records::Las(r) => {
                r.seek(first).ok()?;
                (first..last).find_map(|i| r.fill_points(1, &mut one).err().map(|e| (i, e.to_string())))
            }
            Records::Laz(d) => {
                let bytes = one.resize_for(1);
                (0..last).find_map(|i| d.decompress_one(bytes).err().map(|e| (i, e.to_string())))
            }
        }
    })();
    match found {
        Some((i, e)) => point_error(path, i, format!("cannot decode point data ({e}); {DAMAGED}")),
        None => point_error(path, first, format!("cannot decode points {first}..{last} ({batch_error}); {DAMAGED}")),
    }
}

// ---------------------------------------------------------------------------------------------
// Reading

/// Header facts only: cheap, does not decode points.
pub fn strip_info(path: &Path) -> Result<StripInfo, FormatError> {
    let (file, header) = open_header(path)?;
    // The las crate raises the version of a file that uses a later version's features; this
    // reports what the file says.
    let raw = las::raw::Header::read_from(BufReader::new(file))
        .map_err(|e| FormatError::file(path, format!("cannot read the LAS header ({e}); {DAMAGED}")))?;
    let format = header.point_format();
    let number = format
        .to_u8()
        .map_err(|e| FormatError::file(path, format!("unsupported point format ({e}); re-export as LAS 1.2–1.4")))?;
    let b = header.bounds();
    Ok(StripInfo {
        point_count: header.number_of_points(),
        point_format: number,
        version: (raw.version.major, raw.version.minor),
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

/// Reads the fields estimation needs (x, y, z, return and channel, scan angle, GPS time). The
/// whole strip is held in memory (bounded by strip size); LAZ strips decode only those fields.
///
/// Besides damage, this refuses what would make the work on a strip wrong or wasted: coordinates
/// no real place has, GPS time that never advances, and a strip that could not be written back
/// with corrected coordinates.
pub fn read_strip(path: &Path) -> Result<StripPoints, FormatError> {
    read_strip_with_ring(path, None)
}

/// [`read_strip`], and with `ring` each point's ring number from that source into
/// [`StripPoints::ring`]. A named extra-bytes field the file does not have, or one that is not
/// an integer of 1 or 2 bytes, is an error naming the fields it has.
pub fn read_strip_with_ring(path: &Path, ring: Option<&RingSource>) -> Result<StripPoints, FormatError> {
    let mut fields = laz::DecompressionSelection::base().decompress_z().decompress_scan_angle().decompress_gps_time();
    match ring {
        Some(RingSource::UserData) => fields = fields.decompress_user_data(),
        Some(RingSource::ExtraBytes(_)) => fields = fields.decompress_extra_bytes(),
        Some(RingSource::ScannerChannel) | None => {}
    }
    let mut src = Source::open_with(path, fields)?;
    rewrite::plan_output(path, &src.header, is_laz_path(path))?;
    let mut out = StripReader::new(path, &src.header, src.n)?;
    out.ring = match ring {
        None => RingField::None,
        Some(RingSource::UserData) => RingField::Byte(layout::USER_DATA),
        Some(RingSource::ScannerChannel) => RingField::Channel,
        Some(RingSource::ExtraBytes(name)) => extra_bytes_field(path, &src.header, name)?,
    };
    if !matches!(out.ring, RingField::None) {
        out.points.ring.reserve(out.points.x.capacity());
    }
    let mut pd = src.batch_buffer();
    while let Some(first) = src.next_batch(&mut pd)? {
        out.push_records(first, pd.raw_bytes(), pd.record_len())?;
    }
    let points = out.points;
    check_gps_time(path, &points.gps_time)?;
    Ok(points)
}

/// Points are in acquisition order, so their GPS time must advance through the strip (several
/// channels may interleave, so not at every point). Time that never increases is missing (one
/// value for all) or not acquisition time, and would place every point at one pose.
fn check_gps_time(path: &Path, times: &[f64]) -> Result<(), FormatError> {
    let (Some(&first), Some(&last)) = (times.first(), times.last()) else { return Ok(()) };
    if times.len() < 2 || times.windows(2).any(|w| w[1] > w[0]) {
        return Ok(());
    }
    let message = if times.iter().all(|&t| t == first) {
        format!(
            "all {} points have the same GPS time ({first} s), so they cannot be placed on the trajectory; \
             re-export the strip with each point's acquisition time",
            times.len()
        )
    } else {
        format!(
            "GPS time never increases from one point to the next ({first} s to {last} s); points must be in \
             acquisition order with their acquisition time: re-export the strip"
        )
    };
    Err(FormatError::file(path, message))
}

/// Turns raw records into [`StripPoints`].
struct StripReader<'a> {
    path: &'a Path,
    points: StripPoints,
    transforms: Vector<Transform>,
    gps_at: usize,
    extended: bool,
    ring: RingField,
}

/// Where the ring number of a record is.
#[derive(Clone, Copy, Debug)]
enum RingField {
    None,
    Channel,
    Byte(usize),
    /// A signed or unsigned little-endian integer of 2 bytes at this offset.
    Word {
        at: usize,
        signed: bool,
    },
    SignedByte(usize),
}

/// The extra-bytes field `name` of the file's Extra Bytes VLR as a [`RingField`].
fn extra_bytes_field(path: &Path, header: &Header, name: &str) -> Result<RingField, FormatError> {
    const DESCRIPTOR_LEN: usize = 192;
    let format = header.point_format();
    let base = usize::from(format.len()) - usize::from(format.extra_bytes);
    let vlr = header
        .vlrs()
        .iter()
        .chain(header.evlrs())
        .find(|v| v.user_id.trim_end_matches('\0') == "LASF_Spec" && v.record_id == 4);
    let mut names = Vec::new();
    let mut at = base;
    for d in vlr.map(|v| v.data.chunks_exact(DESCRIPTOR_LEN)).into_iter().flatten() {
        let field = String::from_utf8_lossy(&d[4..36]).trim_end_matches('\0').to_string();
        let data_type = d[2];
        // LAS 1.4 R15 table 25: 1–10 are u8, i8, u16, i16, u32, i32, u64, i64, f32, f64; 0 is
        // `options` bytes of undocumented data.
        let size = match data_type {
            0 => usize::from(d[3]),
            1 | 2 => 1,
            3 | 4 => 2,
            5 | 6 | 9 => 4,
            7 | 8 | 10 => 8,
            _ => {
                return Err(FormatError::file(
                    path,
                    format!("extra-bytes field {field:?} has data type {data_type}, which LAS 1.4 does not define; re-export the strip"),
                ))
            }
        };
        if field == name {
            return match data_type {
                1 => Ok(RingField::Byte(at)),
                2 => Ok(RingField::SignedByte(at)),
                3 | 4 => Ok(RingField::Word { at, signed: data_type == 4 }),
                _ => Err(FormatError::file(
                    path,
                    format!(
                        "extra-bytes field {name:?} (data type {data_type}) is not an integer of 1 or 2 bytes, so it \
                         cannot hold a ring number; name another field in parameters.ring"
                    ),
                )),
            };
        }
        names.push(field);
        at += size;
    }
    Err(FormatError::file(
        path,
        format!(
            "parameters.ring names the extra-bytes field {name:?}, but the file has {}; name one of its fields, or \
             use user_data or scanner_channel",
            if names.is_empty() { "no extra-bytes fields".to_string() } else { format!("only {}", names.join(", ")) }
        ),
    ))
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
            ring: RingField::None,
        })
    }

    fn push_records(&mut self, first: u64, records: &[u8], record_len: usize) -> Result<(), FormatError> {
        let (t, gps_at, out) = (&self.transforms, self.gps_at, &mut self.points);
        for (j, rec) in records.chunks_exact(record_len).enumerate() {
            let [x, y, z] = decode_xyz(rec, t);
            if !(x.abs() <= MAX_COORDINATE && y.abs() <= MAX_COORDINATE && z.abs() <= MAX_COORDINATE) {
                return Err(point_error(
                    self.path,
                    first + j as u64,
                    format!(
                        "coordinates ({x:e}, {y:e}, {z:e}) are beyond any place on Earth (header scale {} {} {}, \
                         offset {} {} {}); the header's scale or offset is wrong: re-export the strip",
                        t.x.scale, t.y.scale, t.z.scale, t.x.offset, t.y.offset, t.z.offset
                    ),
                ));
            }
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
            let ring = match self.ring {
                RingField::None => continue,
                RingField::Channel => i64::from(channel),
                RingField::Byte(at) => i64::from(rec[at]),
                RingField::SignedByte(at) => i64::from(rec[at] as i8),
                RingField::Word { at, signed } => {
                    let b = [rec[at], rec[at + 1]];
                    if signed {
                        i64::from(i16::from_le_bytes(b))
                    } else {
                        i64::from(u16::from_le_bytes(b))
                    }
                }
            };
            let ring = u8::try_from(ring).map_err(|_| {
                point_error(
                    self.path,
                    first + j as u64,
                    format!("ring number {ring} is outside 0–255; check parameters.ring names the ring's field"),
                )
            })?;
            out.ring.push(ring);
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
