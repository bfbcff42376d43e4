//! Output files appear complete or not at all: we write a hidden sibling and rename it into place,
//! so a crash or an error never leaves a half-written strip or trajectory under the final name.

use crate::FormatError;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

static COUNTER: AtomicU64 = AtomicU64::new(0);

#[derive(Debug)]
pub(crate) struct PendingFile {
    tmp: PathBuf,
    dst: PathBuf,
    committed: bool,
}

impl PendingFile {
    pub(crate) fn create(dst: &Path) -> Result<(Self, File), FormatError> {
        let name = dst
            .file_name()
            .ok_or_else(|| FormatError::file(dst, "output path has no file name; give a path like out/strip.laz"))?;
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let tmp = dst.with_file_name(format!(".{}.{}-{}.partial", name.to_string_lossy(), std::process::id(), n));
        let file = File::create(&tmp).map_err(|e| FormatError::io(dst, "create file", e))?;
        Ok((Self { tmp, dst: dst.to_path_buf(), committed: false }, file))
    }

    pub(crate) fn commit(mut self) -> Result<(), FormatError> {
        std::fs::rename(&self.tmp, &self.dst)
            .map_err(|e| FormatError::io(&self.dst, "move finished file into place", e))?;
        self.committed = true;
        Ok(())
    }
}

impl Drop for PendingFile {
    fn drop(&mut self) {
        if !self.committed {
            // Best effort: the temporary is hidden and uniquely named, a leftover harms nobody.
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Writes `bytes` to `dst` atomically.
pub(crate) fn write_bytes(dst: &Path, bytes: &[u8]) -> Result<(), FormatError> {
    use std::io::Write;
    let (pending, mut file) = PendingFile::create(dst)?;
    file.write_all(bytes).map_err(|e| FormatError::io(dst, "write file", e))?;
    pending.commit()
}
