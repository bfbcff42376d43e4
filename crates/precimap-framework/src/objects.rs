//! The object store every task exchanges data through: `file:///abs/path` (the embedded default)
//! or `s3://bucket/prefix` (any S3-compatible server, configured by the usual `AWS_*` variables).
//!
//! Keys are relative, `/`-separated paths. Nothing outside the configured store can be named: a
//! key with `..`, a scheme, a leading `/`, a backslash or control characters is rejected before
//! it reaches the store. A `file://` store also refuses any key whose file or folder is a
//! symbolic link leading outside its root: it neither reads, writes, lists nor deletes through
//! such a link.

use crate::error::FrameworkError;
use crate::metrics;
use bytes::Bytes;
use futures::{StreamExt, TryStreamExt};
use object_store::aws::AmazonS3Builder;
use object_store::local::LocalFileSystem;
use object_store::path::Path as StorePath;
use object_store::prefix::PrefixStore;
use object_store::{ObjectStore, PutPayload};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tokio::io::AsyncWriteExt;

/// An object as a listing shows it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StoredObject {
    pub key: String,
    pub bytes: u64,
    /// Last modification, milliseconds since the Unix epoch.
    pub modified_ms: i64,
}

/// Whether `key` names a temporary file of a write in progress (or abandoned by a crash): an
/// upload's `NAME.upload-…`, a task output's `NAME.partial` / `NAME.partial.EXT`, or the file
/// store's own staging file `NAME#N`. Such a key is never a complete object: manifests may not
/// name one and input listings leave them out.
pub fn is_temporary_key(key: &str) -> bool {
    let name = key.rsplit('/').next().unwrap_or(key);
    if let Some((_, n)) = name.rsplit_once('#') {
        if !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()) {
            return true;
        }
    }
    let mut parts = name.split('.').skip(1);
    parts.any(|ext| ext == "partial" || ext.starts_with("upload-"))
}

/// Handle on the configured store. Cheap to clone.
#[derive(Clone, Debug)]
pub struct Objects {
    inner: Arc<dyn ObjectStore>,
    /// Root folder of a `file://` store: tasks read and write its files in place instead of
    /// copying them through temporary files.
    local_root: Option<PathBuf>,
    url: String,
}

/// Checks that `key` names an object inside the store.
pub fn validate_key(key: &str) -> Result<(), String> {
    if key.is_empty() {
        return Err("the key is empty".into());
    }
    if key.len() > 1024 {
        return Err(format!("the key is {} bytes long; at most 1024 are allowed", key.len()));
    }
    if key.chars().any(char::is_control) {
        return Err(format!("key {key:?} contains a control character"));
    }
    if key.contains('\\') {
        return Err(format!("key {key:?} contains a backslash; separate folders with '/'"));
    }
    if key.contains(':') {
        return Err(format!("key {key:?} contains ':' (a scheme or drive); name an object inside the store"));
    }
    if key.starts_with('/') {
        return Err(format!("key {key:?} is absolute; name an object relative to the store's root"));
    }
    for part in key.split('/') {
        if part.is_empty() || part == "." || part == ".." {
            return Err(format!("key {key:?} has an empty, '.' or '..' component; name an object inside the store"));
        }
        // File systems limit a name to 255 bytes; the same rule holds for every store.
        if part.len() > MAX_KEY_COMPONENT_BYTES {
            return Err(format!(
                "a component of key {key:?} is {} bytes long; at most {MAX_KEY_COMPONENT_BYTES} are allowed",
                part.len()
            ));
        }
    }
    Ok(())
}

/// The longest `/`-separated component of a key, in bytes.
pub const MAX_KEY_COMPONENT_BYTES: usize = 255;

/// Refuses `path` (the file of `key` under `root`) when it, or the deepest folder of it that
/// exists, resolves outside `root` through a symbolic link. A path that does not exist yet
/// (nor its folders) is inside: creating it creates real folders.
fn confined(root: &Path, key: &str, path: &Path) -> Result<(), FrameworkError> {
    let mut existing = path;
    let resolved = loop {
        match existing.canonicalize() {
            Ok(resolved) => break resolved,
            Err(_) => match existing.parent() {
                Some(parent) if parent.starts_with(root) && parent != root => existing = parent,
                _ => return Ok(()),
            },
        }
    };
    if resolved.starts_with(root) {
        Ok(())
    } else {
        // The target stays in the log; the error (which may reach a client) names the key only.
        tracing::warn!(key, target = %resolved.display(), "refused a symbolic link leading outside the file store");
        Err(FrameworkError::BadKey {
            key: key.to_string(),
            message: "leads outside the store through a symbolic link, which the file store does not follow".into(),
        })
    }
}

fn store_path(key: &str) -> Result<StorePath, FrameworkError> {
    validate_key(key).map_err(|message| FrameworkError::BadKey { key: key.to_string(), message })?;
    StorePath::parse(key).map_err(|e| FrameworkError::BadKey { key: key.to_string(), message: e.to_string() })
}

impl Objects {
    /// Opens the store named by `url`: `file:///absolute/folder` (created if missing) or
    /// `s3://bucket[/prefix]`, the latter configured from `AWS_ACCESS_KEY_ID`,
    /// `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`, `AWS_ENDPOINT` (a local server such as Garage or
    /// MinIO), `AWS_ALLOW_HTTP=true` for plain HTTP and `AWS_VIRTUAL_HOSTED_STYLE_REQUEST`
    /// (path style unless set).
    pub fn from_url(url: &str) -> Result<Self, FrameworkError> {
        let bad = |message: String| FrameworkError::BadStoreUrl { url: url.to_string(), message };
        if let Some(path) = url.strip_prefix("file://") {
            let root = PathBuf::from(path);
            if !root.is_absolute() {
                return Err(bad("a file store needs an absolute folder, e.g. file:///var/lib/precimap".into()));
            }
            std::fs::create_dir_all(&root).map_err(|e| bad(format!("cannot create {}: {e}", root.display())))?;
            let root = root.canonicalize().map_err(|e| bad(format!("cannot open {}: {e}", root.display())))?;
            let fs = LocalFileSystem::new_with_prefix(&root).map_err(|e| bad(e.to_string()))?;
            return Ok(Self { inner: Arc::new(fs), local_root: Some(root), url: url.to_string() });
        }
        if let Some(rest) = url.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            if bucket.is_empty() {
                return Err(bad("name the bucket: s3://bucket[/prefix]".into()));
            }
            let s3 = AmazonS3Builder::from_env()
                .with_bucket_name(bucket)
                .build()
                .map_err(|e| bad(format!("{e}; set AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_REGION and, for a local server, AWS_ENDPOINT and AWS_ALLOW_HTTP=true")))?;
            let prefix = prefix.trim_matches('/');
            let inner: Arc<dyn ObjectStore> = if prefix.is_empty() {
                Arc::new(s3)
            } else {
                validate_key(prefix).map_err(bad)?;
                Arc::new(PrefixStore::new(s3, prefix))
            };
            return Ok(Self { inner, local_root: None, url: url.to_string() });
        }
        Err(bad("use file:///absolute/folder or s3://bucket[/prefix]".into()))
    }

    pub fn url(&self) -> &str {
        &self.url
    }

    /// Where `key` lives on disk, for a `file://` store. `None` for other stores, and for a key
    /// the file store refuses (one leading outside it through a link): the store's own methods
    /// then report why.
    pub fn local_path(&self, key: &str) -> Option<PathBuf> {
        let root = self.local_root.as_ref()?;
        validate_key(key).ok()?;
        let path = root.join(key);
        confined(root, key, &path).ok()?;
        Some(path)
    }

    /// Checks that a `file://` store may touch `key` (see [`confined`]); other stores have no
    /// links.
    fn check_confined(&self, key: &str) -> Result<(), FrameworkError> {
        match &self.local_root {
            Some(root) => confined(root, key, &root.join(key)),
            None => Ok(()),
        }
    }

    pub async fn put(&self, key: &str, bytes: Bytes) -> Result<(), FrameworkError> {
        let path = store_path(key)?;
        self.check_confined(key)?;
        let n = bytes.len() as u64;
        self.inner.put(&path, PutPayload::from_bytes(bytes)).await.map_err(|e| FrameworkError::store(key, e))?;
        metrics::store_written(n);
        Ok(())
    }

    pub async fn get(&self, key: &str) -> Result<Bytes, FrameworkError> {
        let path = store_path(key)?;
        self.check_confined(key)?;
        let result = self.inner.get(&path).await.map_err(|e| FrameworkError::store(key, e))?;
        let bytes = result.bytes().await.map_err(|e| FrameworkError::store(key, e))?;
        metrics::store_read(bytes.len() as u64);
        Ok(bytes)
    }

    /// The file of `key` in a `file://` store; a key outside the store is `BadKey`.
    fn local_file(&self, key: &str) -> Result<PathBuf, FrameworkError> {
        store_path(key)?;
        self.check_confined(key)?;
        self.local_path(key).ok_or_else(|| FrameworkError::Internal(format!("{key}: not a file store")))
    }

    /// Several objects, in order. A `file://` store reads them all in one blocking call (each
    /// `get` through `object_store` costs two thread hand-offs, which measured as a third of the
    /// framework's CPU overhead on small); a remote store fetches up to 8 at a time.
    pub async fn get_many(&self, keys: &[String]) -> Result<Vec<Bytes>, FrameworkError> {
        if self.local_root.is_some() {
            let paths = keys
                .iter()
                .map(|key| Ok((key.clone(), self.local_file(key)?)))
                .collect::<Result<Vec<_>, FrameworkError>>()?;
            return crate::cpu::run(move || {
                paths
                    .into_iter()
                    .map(|(key, path)| match std::fs::read(&path) {
                        Ok(bytes) => {
                            metrics::store_read(bytes.len() as u64);
                            Ok(Bytes::from(bytes))
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(FrameworkError::store(
                            &key,
                            object_store::Error::NotFound { path: key.clone(), source: Box::new(e) },
                        )),
                        Err(e) => Err(FrameworkError::io(&path, e)),
                    })
                    .collect()
            })
            .await
            .map_err(|e| FrameworkError::Internal(format!("object read thread stopped: {e}")))?;
        }
        // Owned futures: borrowed ones in a stream combinator are not `Send` for every lifetime.
        let requests: Vec<_> = keys
            .iter()
            .map(|key| {
                let (store, key) = (self.clone(), key.clone());
                async move { store.get(&key).await }
            })
            .collect();
        futures::stream::iter(requests).buffered(8).try_collect().await
    }

    /// Several objects written, each visible only once complete. A `file://` store writes them
    /// all in one blocking call (through a temporary name each, renamed into place); a remote
    /// store uploads up to 8 at a time.
    pub async fn put_many(&self, objects: Vec<(String, Bytes)>) -> Result<(), FrameworkError> {
        if self.local_root.is_some() {
            let files = objects
                .into_iter()
                .map(|(key, bytes)| Ok((self.local_file(&key)?, bytes)))
                .collect::<Result<Vec<_>, FrameworkError>>()?;
            return crate::cpu::run(move || {
                for (path, bytes) in files {
                    if let Some(dir) = path.parent() {
                        std::fs::create_dir_all(dir).map_err(|e| FrameworkError::io(dir, e))?;
                    }
                    // Keys are attempt-specific, so the temporary name is too.
                    let mut name = path.file_name().unwrap_or_default().to_os_string();
                    name.push(".partial");
                    let tmp = path.with_file_name(name);
                    std::fs::write(&tmp, &bytes).map_err(|e| FrameworkError::io(&tmp, e))?;
                    std::fs::rename(&tmp, &path).map_err(|e| FrameworkError::io(&path, e))?;
                    metrics::store_written(bytes.len() as u64);
                }
                Ok(())
            })
            .await
            .map_err(|e| FrameworkError::Internal(format!("object write thread stopped: {e}")))?;
        }
        let requests: Vec<_> = objects
            .into_iter()
            .map(|(key, bytes)| {
                let store = self.clone();
                async move { store.put(&key, bytes).await }
            })
            .collect();
        futures::stream::iter(requests).buffer_unordered(8).try_collect::<Vec<()>>().await.map(|_| ())
    }

    pub async fn exists(&self, key: &str) -> Result<bool, FrameworkError> {
        let path = store_path(key)?;
        self.check_confined(key)?;
        match self.inner.head(&path).await {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(FrameworkError::store(key, e)),
        }
    }

    /// Uploads a local file (in parts, so a strip of many gigabytes never sits in memory).
    pub async fn put_file(&self, key: &str, file: &Path) -> Result<u64, FrameworkError> {
        let path = store_path(key)?;
        self.check_confined(key)?;
        if let Some(dst) = self.local_path(key) {
            // Same machine: a copy through a temporary name, renamed into place.
            if let Some(dir) = dst.parent() {
                tokio::fs::create_dir_all(dir).await.map_err(|e| FrameworkError::io(dir, e))?;
            }
            let tmp = dst.with_extension("upload-partial");
            let n = tokio::fs::copy(file, &tmp).await.map_err(|e| FrameworkError::io(file, e))?;
            tokio::fs::rename(&tmp, &dst).await.map_err(|e| FrameworkError::io(&dst, e))?;
            metrics::store_written(n);
            return Ok(n);
        }
        let mut upload = object_store::WriteMultipart::new_with_chunk_size(
            self.inner.put_multipart(&path).await.map_err(|e| FrameworkError::store(key, e))?,
            16 << 20,
        );
        let mut reader = tokio::fs::File::open(file).await.map_err(|e| FrameworkError::io(file, e))?;
        let mut buf = vec![0u8; 8 << 20];
        let mut total = 0u64;
        loop {
            let n =
                tokio::io::AsyncReadExt::read(&mut reader, &mut buf).await.map_err(|e| FrameworkError::io(file, e))?;
            if n == 0 {
                break;
            }
            upload.wait_for_capacity(4).await.map_err(|e| FrameworkError::store(key, e))?;
            upload.write(&buf[..n]);
            total += n as u64;
        }
        upload.finish().await.map_err(|e| FrameworkError::store(key, e))?;
        metrics::store_written(total);
        Ok(total)
    }

    /// Stores a byte stream of at most `limit` bytes under `key`; a longer stream is refused and
    /// nothing is stored. Returns the number of bytes.
    pub async fn put_stream<S, E>(&self, key: &str, mut stream: S, limit: u64) -> Result<u64, FrameworkError>
    where
        S: futures::Stream<Item = Result<Bytes, E>> + Unpin,
        E: std::fmt::Display,
    {
        let path = store_path(key)?;
        self.check_confined(key)?;
        let too_big = || FrameworkError::TooLarge { key: key.to_string(), limit };
        let broken = |e: E| FrameworkError::Invalid(format!("upload of {key} broke off: {e}"));
        let mut total = 0u64;
        if let Some(dst) = self.local_path(key) {
            if let Some(dir) = dst.parent() {
                tokio::fs::create_dir_all(dir).await.map_err(|e| FrameworkError::io(dir, e))?;
            }
            let tmp = dst.with_extension(format!("upload-{}", uuid::Uuid::new_v4().simple()));
            // Removes the temporary file on every way out but success, a dropped request included.
            let guard = TempFileGuard(Some(tmp.clone()));
            let mut out = tokio::fs::File::create(&tmp).await.map_err(|e| FrameworkError::io(&tmp, e))?;
            while let Some(chunk) = stream.try_next().await.map_err(broken)? {
                total += chunk.len() as u64;
                if total > limit {
                    return Err(too_big());
                }
                out.write_all(&chunk).await.map_err(|e| FrameworkError::io(&tmp, e))?;
            }
            out.flush().await.map_err(|e| FrameworkError::io(&tmp, e))?;
            drop(out);
            // A hard link never replaces an existing file (a rename would): the object appears
            // complete or not at all, and an existing one stays as it is.
            let linked = tokio::fs::hard_link(&tmp, &dst).await;
            // The temporary name goes either way; a linked object keeps its data.
            drop(guard);
            return match linked {
                Ok(()) => {
                    metrics::store_written(total);
                    Ok(total)
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    Err(FrameworkError::Exists { key: key.to_string() })
                }
                Err(e) => Err(FrameworkError::io(&dst, e)),
            };
        }
        // S3 has no create-only multipart upload: refuse a key that exists now (a concurrent
        // upload of the same key may still win the race).
        if self.exists(key).await? {
            return Err(FrameworkError::Exists { key: key.to_string() });
        }
        let mut upload = object_store::WriteMultipart::new_with_chunk_size(
            self.inner.put_multipart(&path).await.map_err(|e| FrameworkError::store(key, e))?,
            16 << 20,
        );
        let result: Result<(), FrameworkError> = async {
            while let Some(chunk) = stream.try_next().await.map_err(broken)? {
                total += chunk.len() as u64;
                if total > limit {
                    return Err(too_big());
                }
                upload.wait_for_capacity(4).await.map_err(|e| FrameworkError::store(key, e))?;
                upload.write(&chunk);
            }
            Ok(())
        }
        .await;
        match result {
            Ok(()) => {
                upload.finish().await.map_err(|e| FrameworkError::store(key, e))?;
                metrics::store_written(total);
                Ok(total)
            }
            Err(e) => {
                let _ = upload.abort().await;
                Err(e)
            }
        }
    }

    /// Downloads `key` into `file` (streamed).
    pub async fn get_to_file(&self, key: &str, file: &Path) -> Result<u64, FrameworkError> {
        let path = store_path(key)?;
        self.check_confined(key)?;
        let result = self.inner.get(&path).await.map_err(|e| FrameworkError::store(key, e))?;
        let mut stream = result.into_stream();
        if let Some(dir) = file.parent() {
            tokio::fs::create_dir_all(dir).await.map_err(|e| FrameworkError::io(dir, e))?;
        }
        let mut out = tokio::fs::File::create(file).await.map_err(|e| FrameworkError::io(file, e))?;
        let mut total = 0u64;
        while let Some(chunk) = stream.try_next().await.map_err(|e| FrameworkError::store(key, e))? {
            out.write_all(&chunk).await.map_err(|e| FrameworkError::io(file, e))?;
            total += chunk.len() as u64;
        }
        out.flush().await.map_err(|e| FrameworkError::io(file, e))?;
        metrics::store_read(total);
        Ok(total)
    }

    /// A byte stream of `key` (for HTTP downloads), with its size.
    pub async fn stream(
        &self,
        key: &str,
    ) -> Result<(u64, futures::stream::BoxStream<'static, object_store::Result<Bytes>>), FrameworkError> {
        let path = store_path(key)?;
        self.check_confined(key)?;
        let result = self.inner.get(&path).await.map_err(|e| FrameworkError::store(key, e))?;
        let size = result.meta.size;
        metrics::store_read(size);
        Ok((size, result.into_stream()))
    }

    /// Every key under `prefix` (a folder, without the trailing '/').
    pub async fn list(&self, prefix: &str) -> Result<Vec<String>, FrameworkError> {
        let path = store_path(prefix)?;
        self.check_confined(prefix)?;
        let metas: Vec<_> =
            self.inner.list(Some(&path)).try_collect().await.map_err(|e| FrameworkError::store(prefix, e))?;
        // A file store lists through links; what lies outside it is not the store's.
        Ok(metas.into_iter().map(|m| m.location.to_string()).filter(|key| self.check_confined(key).is_ok()).collect())
    }

    pub async fn delete(&self, key: &str) -> Result<(), FrameworkError> {
        let path = store_path(key)?;
        self.check_confined(key)?;
        match self.inner.delete(&path).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(FrameworkError::store(key, e)),
        }
    }

    /// The size of `key`'s object, `None` if there is none.
    pub async fn size(&self, key: &str) -> Result<Option<u64>, FrameworkError> {
        let path = store_path(key)?;
        self.check_confined(key)?;
        match self.inner.head(&path).await {
            Ok(meta) => Ok(Some(meta.size)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(FrameworkError::store(key, e)),
        }
    }

    /// Every object under `prefix` with its size and last-modified time (ms since the epoch).
    pub async fn list_meta(&self, prefix: &str) -> Result<Vec<StoredObject>, FrameworkError> {
        let path = store_path(prefix)?;
        self.check_confined(prefix)?;
        let metas: Vec<_> =
            self.inner.list(Some(&path)).try_collect().await.map_err(|e| FrameworkError::store(prefix, e))?;
        Ok(metas
            .into_iter()
            .filter(|m| self.check_confined(m.location.as_ref()).is_ok())
            .map(|m| StoredObject {
                key: m.location.to_string(),
                bytes: m.size,
                modified_ms: m.last_modified.timestamp_millis(),
            })
            .collect())
    }

    /// The folders directly under `prefix` (e.g. `c/0123…` under `c`), as keys.
    pub async fn list_folders(&self, prefix: &str) -> Result<Vec<String>, FrameworkError> {
        let path = store_path(prefix)?;
        self.check_confined(prefix)?;
        let listed = self.inner.list_with_delimiter(Some(&path)).await.map_err(|e| FrameworkError::store(prefix, e))?;
        Ok(listed
            .common_prefixes
            .into_iter()
            .map(|p| p.to_string())
            .filter(|key| self.check_confined(key).is_ok())
            .collect())
    }

    /// Deletes every object under `prefix`; returns how many.
    pub async fn delete_prefix(&self, prefix: &str) -> Result<usize, FrameworkError> {
        let keys = self.list(prefix).await?;
        for key in &keys {
            self.delete(key).await?;
        }
        if let Some(dir) = self.local_path(prefix) {
            // The file store leaves empty folders behind.
            let _ = tokio::fs::remove_dir_all(dir).await;
        }
        Ok(keys.len())
    }
}

/// Deletes its file when dropped, unless disarmed.
#[derive(Debug)]
struct TempFileGuard(Option<PathBuf>);

impl Drop for TempFileGuard {
    fn drop(&mut self) {
        if let Some(path) = self.0.take() {
            let _ = std::fs::remove_file(path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_outside_the_store_are_rejected() {
        for bad in
            ["", "/etc/passwd", "../x", "a/../../b", "a//b", "file:///etc/passwd", "s3://b/k", "a\\b", "a\0b", "./a"]
        {
            assert!(validate_key(bad).is_err(), "{bad:?} accepted");
        }
        for good in ["a", "inputs/1/strips/p01.las", "c/x/tiles/1_-2/s.chunk"] {
            assert!(validate_key(good).is_ok(), "{good:?} rejected");
        }
    }

    #[tokio::test]
    async fn file_store_round_trip_list_and_delete() {
        let dir = tempfile::tempdir().unwrap();
        let objects = Objects::from_url(&format!("file://{}", dir.path().display())).unwrap();
        objects.put("c/1/a.bin", Bytes::from_static(b"hello")).await.unwrap();
        objects.put("c/1/b/c.bin", Bytes::from_static(b"world")).await.unwrap();
        objects.put("c/2/a.bin", Bytes::from_static(b"other")).await.unwrap();
        assert_eq!(&objects.get("c/1/a.bin").await.unwrap()[..], b"hello");
        assert!(objects.exists("c/1/b/c.bin").await.unwrap());
        assert!(!objects.exists("c/1/none").await.unwrap());
        let mut keys = objects.list("c/1").await.unwrap();
        keys.sort();
        assert_eq!(keys, ["c/1/a.bin", "c/1/b/c.bin"]);
        assert_eq!(objects.delete_prefix("c/1").await.unwrap(), 2);
        assert!(objects.list("c/1").await.unwrap().is_empty());
        assert_eq!(&objects.get("c/2/a.bin").await.unwrap()[..], b"other");
        assert!(objects.get("../x").await.is_err());
        assert!(Objects::from_url("file://relative/path").is_err());
        assert!(Objects::from_url("http://example.com").is_err());
    }

    #[tokio::test]
    async fn the_file_store_refuses_links_leading_outside_it() {
        let dir = tempfile::tempdir().unwrap();
        let outside = tempfile::tempdir().unwrap();
        std::fs::write(outside.path().join("secret"), "TOP-SECRET").unwrap();
        let objects = Objects::from_url(&format!("file://{}", dir.path().join("store").display())).unwrap();
        objects.put("inputs/real.csv", Bytes::from_static(b"ok")).await.unwrap();
        let inputs = dir.path().join("store").join("inputs");
        std::os::unix::fs::symlink(outside.path().join("secret"), inputs.join("file-link")).unwrap();
        std::os::unix::fs::symlink(outside.path(), inputs.join("dir-link")).unwrap();
        // A link inside the store to another of its objects is fine.
        std::os::unix::fs::symlink(inputs.join("real.csv"), inputs.join("inner-link")).unwrap();
        assert_eq!(&objects.get("inputs/inner-link").await.unwrap()[..], b"ok");
        for key in ["inputs/file-link", "inputs/dir-link/secret"] {
            let refused = objects.get(key).await.unwrap_err();
            assert!(matches!(refused, FrameworkError::BadKey { .. }), "{key}: {refused}");
            assert!(!refused.to_string().contains("TOP-SECRET") && !refused.to_string().contains("/tmp"), "{refused}");
            assert!(objects.exists(key).await.is_err());
            assert!(objects.get_many(&[key.to_string()]).await.is_err());
            assert!(objects.local_path(key).is_none());
            assert!(objects.delete(key).await.is_err());
        }
        let planted = objects.put_stream(
            "inputs/dir-link/planted",
            futures::stream::iter([Ok::<_, String>(Bytes::from_static(b"x"))]),
            10,
        );
        assert!(matches!(planted.await, Err(FrameworkError::BadKey { .. })));
        assert!(!outside.path().join("planted").exists());
        assert!(objects.put("inputs/dir-link/planted", Bytes::new()).await.is_err());
        let mut listed = objects.list("inputs").await.unwrap();
        listed.sort();
        assert_eq!(listed, ["inputs/inner-link", "inputs/real.csv"]);
        assert!(outside.path().join("secret").exists());
    }

    #[tokio::test]
    async fn a_failed_upload_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let objects = Objects::from_url(&format!("file://{}", dir.path().display())).unwrap();
        let chunks =
            || futures::stream::iter([Ok::<_, String>(Bytes::from_static(b"12345")), Ok(Bytes::from_static(b"6789"))]);
        // Too long, broken off, and linked onto a folder (refused like an existing object).
        assert!(matches!(objects.put_stream("inputs/a/x", chunks(), 6).await, Err(FrameworkError::TooLarge { .. })));
        let broken = futures::stream::iter([Ok(Bytes::from_static(b"12")), Err("reset".to_string())]);
        assert!(matches!(objects.put_stream("inputs/a/x", broken, 100).await, Err(FrameworkError::Invalid(_))));
        objects.put("inputs/a/x/y", Bytes::from_static(b"y")).await.unwrap();
        assert!(matches!(objects.put_stream("inputs/a/x", chunks(), 100).await, Err(FrameworkError::Exists { .. })));
        // A request dropped mid-upload.
        let endless = futures::stream::pending::<Result<Bytes, String>>();
        let dropped =
            tokio::time::timeout(std::time::Duration::from_millis(50), objects.put_stream("inputs/a/z", endless, 100));
        assert!(dropped.await.is_err());
        let mut left: Vec<_> = walk(dir.path());
        left.sort();
        assert_eq!(left, [dir.path().join("inputs/a/x/y")], "temporary files left behind");
        assert_eq!(objects.put_stream("inputs/b", chunks(), 9).await.unwrap(), 9);
        assert!(validate_key(&format!("inputs/{}", "n".repeat(256))).is_err());
        assert!(validate_key(&format!("inputs/{}", "n".repeat(255))).is_ok());
    }

    fn walk(dir: &Path) -> Vec<PathBuf> {
        let mut out = Vec::new();
        for entry in std::fs::read_dir(dir).unwrap().flatten() {
            if entry.path().is_dir() {
                out.extend(walk(&entry.path()));
            } else {
                out.push(entry.path());
            }
        }
        out
    }

    #[tokio::test]
    async fn batched_reads_and_writes_match_single_ones() {
        let dir = tempfile::tempdir().unwrap();
        let objects = Objects::from_url(&format!("file://{}", dir.path().display())).unwrap();
        let written: Vec<(String, Bytes)> =
            (0..5).map(|i| (format!("c/it/{i}/x.{i}.blk"), Bytes::from(vec![i as u8; 1000 * i + 1]))).collect();
        objects.put_many(written.clone()).await.unwrap();
        // Visible to the store's own listing and reads, with no temporary file left behind.
        let mut listed = objects.list("c").await.unwrap();
        listed.sort();
        assert_eq!(listed, written.iter().map(|(k, _)| k.clone()).collect::<Vec<_>>());
        for (key, bytes) in &written {
            assert_eq!(&objects.get(key).await.unwrap(), bytes);
        }
        // In the order asked, duplicates included.
        let keys = vec![written[3].0.clone(), written[0].0.clone(), written[3].0.clone()];
        let read = objects.get_many(&keys).await.unwrap();
        assert_eq!(read, vec![written[3].1.clone(), written[0].1.clone(), written[3].1.clone()]);
        assert!(objects.get_many(&[]).await.unwrap().is_empty());
        // A missing object is "not found" (a permanent task error), as for a single read.
        let missing = objects.get_many(&[written[0].0.clone(), "c/none".into()]).await.unwrap_err();
        assert!(missing.is_not_found(), "{missing}");
        assert!(objects.get("c/none").await.unwrap_err().is_not_found());
        // Keys outside the store are refused before anything is read or written.
        assert!(matches!(objects.get_many(&["../x".into()]).await, Err(FrameworkError::BadKey { .. })));
        let refused = objects.put_many(vec![("c/ok".into(), Bytes::new()), ("/etc/x".into(), Bytes::new())]).await;
        assert!(matches!(refused, Err(FrameworkError::BadKey { .. })));
        assert!(!objects.exists("c/ok").await.unwrap());
    }
}
