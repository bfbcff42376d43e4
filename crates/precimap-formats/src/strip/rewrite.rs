//! Rewriting a strip with new coordinates, every other byte of every record carried over.
//!
//! The output is always a file other readers accept: records that describe the input's byte
//! layout (LASzip, COPC) are dropped, and when the input's LAS version cannot describe what its
//! points hold (return numbers 6–7 before LAS 1.4, a point format its version does not define),
//! the output is LAS 1.4. [`plan_output`] decides this when a strip is read, so a strip that could
//! not be written back is refused before any work is done on it.

use super::check::open_header;
use super::write::OutStrip;
use super::{bytes8, decode_xyz, is_laz_path, layout, point_error, quantize, Source};
use crate::strip_crs::{declare_crs, DeclaredCrs};
use crate::FormatError;
use las::{Builder, Header, Version, Vlr, Writer};
use std::path::Path;

/// User id of the COPC info VLR and hierarchy EVLR: both hold byte offsets into the input's
/// compressed data, so copied over recompressed data they would make COPC readers find no points.
const COPC_USER_ID: &str = "copc";

/// Byte 14 of every record: return number in bits 0–2 (formats 0–5) or 0–3 (formats 6–10).
const RETURN_BYTE: usize = 14;

/// The highest return number LAS 1.0–1.3 headers can count (five returns).
const LEGACY_MAX_RETURN: u8 = 5;

fn describes_input_layout(v: &Vlr) -> bool {
    las::laz::is_laszip_vlr(v) || v.user_id == COPC_USER_ID
}

fn output_header(source: &Header, compressed: bool, version: Option<Version>) -> Result<Header, las::Error> {
    let mut b = Builder::from(source.clone());
    b.vlrs.retain(|v| !describes_input_layout(v));
    b.evlrs.retain(|v| !describes_input_layout(v));
    b.point_format.is_compressed = compressed;
    if let Some(version) = version {
        b.version = version;
    }
    b.into_header()
}

/// Writes the header and its (E)VLRs to memory and finalises them, as a rewrite will.
fn dry_run(header: Header) -> Result<Header, las::Error> {
    let mut w = Writer::new(std::io::Cursor::new(Vec::new()), header.clone())?;
    if let Err(e) = w.close() {
        // A writer whose close failed retries on drop and panics; it holds only memory.
        std::mem::forget(w);
        return Err(e);
    }
    Ok(header)
}

/// The header a rewrite of `path` (header `source`) to LAS (or LAZ if `compressed`) will write:
/// the source's, or LAS 1.4 when the source's version cannot hold it. An error says why the strip
/// cannot be written back at all.
pub(super) fn plan_output(path: &Path, source: &Header, compressed: bool) -> Result<Header, FormatError> {
    let las14 = Version::new(1, 4);
    match output_header(source, compressed, None).and_then(dry_run) {
        Ok(header) => Ok(header),
        Err(first) if source.version() < las14 => {
            let header = output_header(source, compressed, Some(las14)).and_then(dry_run).map_err(|e| {
                FormatError::file(
                    path,
                    format!("cannot be written back ({first}; as LAS 1.4: {e}); re-export the strip"),
                )
            })?;
            tracing::warn!(strip = %path.display(), reason = %first, "the corrected strip will be LAS 1.4");
            Ok(header)
        }
        Err(e) => Err(FormatError::file(path, format!("cannot be written back ({e}); re-export the strip"))),
    }
}

/// Rewrites a strip point by point with new coordinates, keeping every other attribute (all
/// record bytes including extra bytes, VLRs and EVLRs, point format, scale and offset); LAZ if
/// `dst` ends in `.laz`. `new_xyz(index, old_xyz)` returns the new coordinates. Streams in
/// batches; `dst` appears only on success (so `dst == src` is safe).
///
/// The output drops the input's LASzip and COPC records (a COPC input gives plain LAZ), and is
/// LAS 1.4 when the input's version cannot hold its points. In the one case found only while
/// writing (a return number above 5 in a LAS 1.0–1.3 file) the rewrite starts again as LAS 1.4,
/// so `new_xyz` must depend only on its arguments.
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

/// Why a rewrite stopped.
enum Stop {
    Failed(FormatError),
    /// A return number the output's LAS version cannot count.
    ReturnNumber {
        index: u64,
        value: u8,
    },
}

impl From<FormatError> for Stop {
    fn from(e: FormatError) -> Self {
        Self::Failed(e)
    }
}

fn rewrite(
    src: &Path,
    dst: &Path,
    need_time: bool,
    declare: Option<DeclaredCrs<'_>>,
    mut new_xyz: impl FnMut(usize, [f64; 3], f64) -> [f64; 3],
) -> Result<u64, FormatError> {
    let declaring = |mut header: Header| -> Result<Header, FormatError> {
        if let Some(crs) = declare {
            declare_crs(src, &mut header, crs)?;
        }
        Ok(header)
    };
    let (_, source) = open_header(src)?;
    if need_time && !source.point_format().has_gps_time {
        return Err(FormatError::file(src, "point format has no GPS time; re-export with point format 1, 3 or 6–10"));
    }
    let compressed = is_laz_path(dst);
    let header = declaring(plan_output(src, &source, compressed)?)?;
    match rewrite_as(src, dst, header, need_time, &mut new_xyz) {
        Ok(n) => Ok(n),
        Err(Stop::Failed(e)) => Err(e),
        Err(Stop::ReturnNumber { index, value }) => {
            let raised = output_header(&source, compressed, Some(Version::new(1, 4))).map_err(|e| {
                FormatError::file(src, format!("cannot be written back as LAS 1.4 ({e}); re-export it"))
            })?;
            let raised = declaring(raised)?;
            tracing::warn!(
                strip = %src.display(),
                point = index,
                return_number = value,
                "LAS {} cannot count return numbers above 5: the corrected strip is LAS 1.4",
                source.version()
            );
            rewrite_as(src, dst, raised, need_time, &mut new_xyz).map_err(|stop| match stop {
                Stop::Failed(e) => e,
                Stop::ReturnNumber { index, value } => point_error(src, index, format!("return number {value}")),
            })
        }
    }
}

fn rewrite_as(
    src: &Path,
    dst: &Path,
    header: Header,
    need_time: bool,
    new_xyz: &mut impl FnMut(usize, [f64; 3], f64) -> [f64; 3],
) -> Result<u64, Stop> {
    let mut source = Source::open(src)?;
    let format = *source.header.point_format();
    // Records without GPS time pass NaN; only the timed variant reads it, and it refuses them.
    let gps_at = (need_time && format.has_gps_time).then_some(if format.is_extended {
        layout::EXT_GPS
    } else {
        layout::LEGACY_GPS
    });
    let legacy_returns = !format.is_extended && header.version() < Version::new(1, 4);
    let t = *header.transforms();
    let mut out = OutStrip::create(dst, header)?;
    let mut pd = source.batch_buffer();
    while let Some(first) = source.next_batch(&mut pd)? {
        let n = pd.len();
        let record_len = pd.record_len();
        let bytes = pd.resize_for(n);
        for (j, rec) in bytes.chunks_exact_mut(record_len).enumerate() {
            let index = first + j as u64;
            let returns = rec[RETURN_BYTE] & 0x07;
            if legacy_returns && returns > LEGACY_MAX_RETURN {
                return Err(Stop::ReturnNumber { index, value: returns });
            }
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
