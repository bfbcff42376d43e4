//! The HTTP client behind `precimap submit`, `status` and `results`.

use crate::types::{CampaignStatus, ErrorBody, ResultEntry, Submitted, Uploaded};
use futures::TryStreamExt;
use precimap_formats::Manifest;
use std::path::Path;
use tokio::io::AsyncWriteExt;
use uuid::Uuid;

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("cannot reach {url}: {source}")]
    Http {
        url: String,
        #[source]
        source: reqwest::Error,
    },
    #[error("{url}: HTTP {status}: {body}")]
    Status { url: String, status: u16, body: String },
    #[error("{}: {source}", path.display())]
    Io {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Manifest(#[from] precimap_formats::ManifestError),
    #[error("{0}")]
    Invalid(String),
}

#[derive(Clone, Debug)]
pub struct Client {
    base: String,
    token: Option<String>,
    http: reqwest::Client,
}

impl Client {
    pub fn new(server: &str, token: Option<String>) -> Self {
        Self { base: server.trim_end_matches('/').to_string(), token, http: reqwest::Client::new() }
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    fn authed(&self, rb: reqwest::RequestBuilder) -> reqwest::RequestBuilder {
        match &self.token {
            Some(t) => rb.bearer_auth(t),
            None => rb,
        }
    }

    async fn send(&self, rb: reqwest::RequestBuilder, url: &str) -> Result<reqwest::Response, ClientError> {
        let response = rb.send().await.map_err(|source| ClientError::Http { url: url.to_string(), source })?;
        if response.status().is_success() {
            return Ok(response);
        }
        let status = response.status().as_u16();
        let text = response.text().await.unwrap_or_default();
        let body = match serde_json::from_str::<ErrorBody>(&text) {
            Ok(e) if e.problems.is_empty() => e.error,
            Ok(e) => {
                let lines: Vec<String> = e.problems.iter().map(|p| format!("  {}: {}", p.path, p.message)).collect();
                format!("{}\n{}", e.error, lines.join("\n"))
            }
            Err(_) => text,
        };
        Err(ClientError::Status { url: url.to_string(), status, body })
    }

    async fn json<T: serde::de::DeserializeOwned>(
        &self,
        response: reqwest::Response,
        url: &str,
    ) -> Result<T, ClientError> {
        response.json().await.map_err(|source| ClientError::Http { url: url.to_string(), source })
    }

    /// Streams a local file to the server's store under `key` (which must start with `inputs/`).
    pub async fn upload(&self, key: &str, file: &Path) -> Result<u64, ClientError> {
        let url = self.url(&format!("/v1/objects/{key}"));
        let f =
            tokio::fs::File::open(file).await.map_err(|source| ClientError::Io { path: file.to_path_buf(), source })?;
        let len = f.metadata().await.map_err(|source| ClientError::Io { path: file.to_path_buf(), source })?.len();
        let body = reqwest::Body::wrap_stream(tokio_util::io::ReaderStream::new(f));
        let rb = self.authed(self.http.put(&url)).header(reqwest::header::CONTENT_LENGTH, len).body(body);
        let uploaded: Uploaded = self.json(self.send(rb, &url).await?, &url).await?;
        Ok(uploaded.bytes)
    }

    /// Posts a manifest whose URIs already name objects in the server's store.
    pub async fn submit_manifest(&self, manifest: &Manifest) -> Result<Submitted, ClientError> {
        let url = self.url("/v1/campaigns");
        let rb = self.authed(self.http.post(&url)).json(manifest);
        self.json(self.send(rb, &url).await?, &url).await
    }

    /// Checks that the server accepts this client's token for writes.
    pub async fn check_token(&self) -> Result<(), ClientError> {
        let url = self.url("/v1/token");
        self.send(self.authed(self.http.get(&url)), &url).await.map(|_| ())
    }

    /// Uploads every file a local manifest names under `inputs/{upload id}/`, then submits the
    /// manifest with its URIs pointing there. The manifest and the token are checked first, so a
    /// wrong token is reported before any upload starts.
    pub async fn submit_local(
        &self,
        manifest_path: &Path,
        mut on_upload: impl FnMut(&str, u64),
    ) -> Result<Submitted, ClientError> {
        let (manifest, files) = precimap_framework::plan_local_upload(manifest_path).map_err(|e| match e {
            precimap_framework::FrameworkError::Manifest(m) => ClientError::Manifest(m),
            other => ClientError::Invalid(other.to_string()),
        })?;
        self.check_token().await?;
        for (src, key) in &files {
            let bytes = self.upload(key, src).await?;
            on_upload(key, bytes);
        }
        self.submit_manifest(&manifest).await
    }

    pub async fn status(&self, id: Uuid) -> Result<CampaignStatus, ClientError> {
        let url = self.url(&format!("/v1/campaigns/{id}"));
        self.json(self.send(self.http.get(&url), &url).await?, &url).await
    }

    pub async fn cancel(&self, id: Uuid) -> Result<(), ClientError> {
        let url = self.url(&format!("/v1/campaigns/{id}/cancel"));
        self.send(self.authed(self.http.post(&url)), &url).await.map(|_| ())
    }

    pub async fn delete(&self, id: Uuid) -> Result<(), ClientError> {
        let url = self.url(&format!("/v1/campaigns/{id}"));
        self.send(self.authed(self.http.delete(&url)), &url).await.map(|_| ())
    }

    /// Downloads every result into `dir` (the layout of `precimap run`).
    pub async fn results(&self, id: Uuid, dir: &Path) -> Result<Vec<String>, ClientError> {
        let url = self.url(&format!("/v1/campaigns/{id}/results"));
        let entries: Vec<ResultEntry> = self.json(self.send(self.http.get(&url), &url).await?, &url).await?;
        let mut names = Vec::with_capacity(entries.len());
        for e in entries {
            precimap_framework::validate_key(&e.name).map_err(ClientError::Invalid)?;
            let file_url = self.url(&e.href);
            let response = self.send(self.http.get(&file_url), &file_url).await?;
            let dst = dir.join(&e.name);
            let io = |source| ClientError::Io { path: dst.clone(), source };
            if let Some(parent) = dst.parent() {
                tokio::fs::create_dir_all(parent).await.map_err(io)?;
            }
            let tmp = dst.with_extension("download");
            let mut out = tokio::fs::File::create(&tmp).await.map_err(io)?;
            let mut stream = response.bytes_stream();
            while let Some(chunk) =
                stream.try_next().await.map_err(|source| ClientError::Http { url: file_url.clone(), source })?
            {
                out.write_all(&chunk).await.map_err(io)?;
            }
            out.flush().await.map_err(io)?;
            tokio::fs::rename(&tmp, &dst).await.map_err(io)?;
            names.push(e.name);
        }
        Ok(names)
    }
}
