//! Writing new strips, and the file under every strip writer: written to a hidden temporary that
//! is renamed into place only when complete.

use super::{is_laz_path, layout, point_error, quantize, BATCH, SCAN_ANGLE_UNIT_DEG};
use crate::atomic::PendingFile;
use crate::strip_crs::StripDeclarations;
use crate::FormatError;
use las::point::Format;
use las::{Builder, Header, PointData, PointDataBuilder, Transform, Vector, Version, Writer};
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
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
pub(super) struct OutStrip {
    path: PathBuf,
    writer: Option<Writer<Sink>>,
    poisoned: Arc<AtomicBool>,
    pending: Option<PendingFile>,
}

impl OutStrip {
    pub(super) fn create(path: &Path, header: Header) -> Result<Self, FormatError> {
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

    pub(super) fn write(&mut self, pd: &PointData) -> Result<(), FormatError> {
        let Some(w) = self.writer.as_mut().filter(|_| !self.poisoned.load(Ordering::Relaxed)) else {
            return Err(self.broken());
        };
        w.write_points(pd).map_err(|e| {
            self.poisoned.store(true, Ordering::Relaxed);
            FormatError::file(&self.path, format!("cannot write points: {e}"))
        })
    }

    pub(super) fn finish(mut self) -> Result<(), FormatError> {
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
        self.push_with_user_data(p, 0)
    }

    /// [`StripWriter::push`] with the LAS user-data byte set (a multi-beam head's ring number).
    pub fn push_with_user_data(&mut self, p: &NewPoint, user_data: u8) -> Result<(), FormatError> {
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
        rec[layout::EXT_USER_DATA] = user_data;
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
