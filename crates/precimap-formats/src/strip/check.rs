//! Opening a strip: the header is sanity-checked against the file before the `las` crate sees it
//! (a damaged header must give an error, never a huge allocation or an arithmetic overflow), and
//! the point count is checked against the data in both directions, so a wrong count is an error
//! rather than dropped or invented points.

use super::{point_error, DAMAGED};
use crate::FormatError;
use las::point::Format;
use las::Header;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

/// What to do about a header whose count disagrees with the data.
const FIX_COUNT: &str = "the header's point count is wrong: re-export the strip, or repair its header";

/// LAZ compressor types (LASzip VLR, first field).
const COMPRESSOR_POINT_WISE: u16 = 1;

/// Reads the header with the checks that keep the `las` crate away from impossible values.
pub(super) fn open_header(path: &Path) -> Result<(File, Header), FormatError> {
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
    if raw_format(path, &raw)?.is_compressed {
        let vlr = laz_vlr(path, &header)?;
        check_laz_count(path, &mut file, file_len, &raw, &header, &vlr)?;
    }
    file.seek(SeekFrom::Start(0)).map_err(|e| FormatError::io(path, "read strip", e))?;
    Ok((file, header))
}

fn raw_format(path: &Path, raw: &las::raw::Header) -> Result<Format, FormatError> {
    Format::new(raw.point_data_record_format).map_err(|_| {
        FormatError::file(
            path,
            format!(
                "header names point format {}, which is not a LAS 1.4 format (0–10); the header is damaged",
                raw.point_data_record_format
            ),
        )
    })
}

/// The point count the header declares (the 64-bit count of LAS 1.4 when the legacy one is 0).
fn declared_points(raw: &las::raw::Header) -> u64 {
    let legacy = u64::from(raw.number_of_point_records);
    if legacy != 0 {
        legacy
    } else {
        raw.large_file.map_or(0, |l| l.number_of_point_records)
    }
}

fn precheck(path: &Path, file: &mut File, file_len: u64, raw: &las::raw::Header) -> Result<(), FormatError> {
    let format = raw_format(path, raw)?;
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
    let n = declared_points(raw);
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
    if !format.is_compressed {
        check_las_count(path, file_len, raw, n, end)?;
    }
    let io = |e| FormatError::io(path, "read strip", e);
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

/// Uncompressed points fill the bytes between the header's point offset and the first thing
/// after them (EVLRs, internal waveform data, or the end of the file). Fewer bytes than the count
/// needs is a cut file; a whole record or more left over means the count is too small, and the
/// points past it would silently be lost.
fn check_las_count(path: &Path, file_len: u64, raw: &las::raw::Header, n: u64, end: u64) -> Result<(), FormatError> {
    let offset = u64::from(raw.offset_to_point_data);
    let record = u64::from(raw.point_data_record_length);
    if end > file_len {
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
    let mut data_end = file_len;
    if let Some(evlr) = raw.evlr.filter(|e| e.number_of_evlrs > 0 && e.start_of_first_evlr >= end) {
        data_end = data_end.min(evlr.start_of_first_evlr);
    }
    if let Some(waveform) = raw.start_of_waveform_data_packet_record.filter(|&w| w >= end) {
        data_end = data_end.min(waveform);
    }
    let extra = (data_end - end) / record.max(1);
    if record > 0 && extra > 0 {
        return Err(FormatError::file(
            path,
            format!(
                "the header declares {n} points, but the file holds {} complete point records ({extra} more); \
                 {FIX_COUNT}",
                n + extra
            ),
        ));
    }
    Ok(())
}

/// A LAZ file's chunk table says how many points its data holds: all of them for variable-size
/// chunks, and for fixed-size chunks a range (the last chunk may be partial). LASzip 1.x
/// point-wise files have no table and are not checked here.
fn check_laz_count(
    path: &Path,
    file: &mut File,
    file_len: u64,
    raw: &las::raw::Header,
    header: &Header,
    vlr: &laz::LazVlr,
) -> Result<(), FormatError> {
    let compressor = header
        .vlrs()
        .iter()
        .find(|v| las::laz::is_laszip_vlr(v))
        .and_then(|v| v.data.get(0..2))
        .map_or(0, |b| u16::from_le_bytes([b[0], b[1]]));
    if compressor == COMPRESSOR_POINT_WISE {
        return Ok(());
    }
    let io = |e| FormatError::io(path, "read strip", e);
    let offset = u64::from(raw.offset_to_point_data);
    if file_len < offset + 8 {
        return Err(FormatError::file(path, format!("the compressed point data is missing; {DAMAGED}")));
    }
    file.seek(SeekFrom::Start(offset)).map_err(io)?;
    let mut table_at = read_u64(file).map_err(io)?;
    if table_at <= offset || table_at == u64::MAX {
        // A writer that could not seek back stores the table's offset in the last 8 bytes.
        file.seek(SeekFrom::End(-8)).map_err(io)?;
        table_at = read_u64(file).map_err(io)?;
        if table_at <= offset || table_at == u64::MAX {
            return Ok(());
        }
    }
    if table_at.saturating_add(8) > file_len {
        return Err(FormatError::file(
            path,
            format!(
                "truncated: the LAZ chunk table should be at byte {table_at}, but the file has only {file_len} bytes; \
                 {DAMAGED}"
            ),
        ));
    }
    // A wild chunk count would make the decoder reserve gigabytes.
    file.seek(SeekFrom::Start(table_at + 4)).map_err(io)?;
    let chunks = u64::from(read_u32(file).map_err(io)?);
    if chunks > file_len {
        return Err(FormatError::file(path, format!("LAZ chunk table claims {chunks} chunks; {DAMAGED}")));
    }
    file.seek(SeekFrom::Start(offset)).map_err(io)?;
    let table = laz::laszip::ChunkTable::read_from(&mut *file, vlr)
        .map_err(|e| FormatError::file(path, format!("cannot read the LAZ chunk table ({e}); {DAMAGED}")))?;
    let n = declared_points(raw);
    let chunks = table.len() as u64;
    let (least, most) = if vlr.uses_variable_size_chunks() {
        let total = table.as_ref().iter().map(|c| c.point_count).sum::<u64>();
        (total, total)
    } else {
        let size = u64::from(vlr.chunk_size());
        // Every chunk but the last is full; the last may even be empty (a writer closing a
        // file without points leaves one).
        (chunks.saturating_sub(1) * size, chunks * size)
    };
    if n < least || n > most {
        let holds = if least == most { format!("{least}") } else { format!("{least}–{most}") };
        let direction = if n < least { "fewer" } else { "more" };
        return Err(FormatError::file(
            path,
            format!(
                "the header declares {n} points, but the compressed data holds {holds} ({chunks} chunks): {direction} \
                 than the data; {FIX_COUNT}"
            ),
        ));
    }
    Ok(())
}

pub(super) fn read_u64(r: &mut impl Read) -> std::io::Result<u64> {
    let mut b = [0u8; 8];
    r.read_exact(&mut b)?;
    Ok(u64::from_le_bytes(b))
}

fn read_u32(r: &mut impl Read) -> std::io::Result<u32> {
    let mut b = [0u8; 4];
    r.read_exact(&mut b)?;
    Ok(u32::from_le_bytes(b))
}

/// The LAZ compression description of a compressed strip, checked against the header: the
/// decoder steps through records by the LAZ item sizes (and panics on zero), so they must describe
/// exactly the header's record length.
pub(super) fn laz_vlr(path: &Path, header: &Header) -> Result<laz::LazVlr, FormatError> {
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
