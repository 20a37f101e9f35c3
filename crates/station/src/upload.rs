//! Finished runs pushed to an S3-compatible bucket (`[upload]` in the station file), through the
//! `object_store` crate.
//!
//! A run directory `runs/NAME` goes to `s3://BUCKET/PREFIX/NAME/...`, file by file (the journal,
//! the plan, the log and every file of `run.zarr/`; hidden files such as a crash's `.partial`
//! leftovers are skipped). Objects already in the bucket with the file's size are not sent again,
//! so an upload that a power cut or a network fault interrupted resumes where it stopped. Each
//! object is written whole (a single PUT, or a multipart upload completed at the end for files
//! over [`MULTIPART_BYTES`]), so a reader never sees a torn object. The completion marker
//! [`MARKER`] is written last: it lists every file with its size and SHA-256, and a run without
//! it is not complete in the bucket. Requests are retried by `object_store` (with backoff); a
//! run whose upload fails is tried again later, up to the station's next restart and beyond.

use crate::config::UploadConfig;
use crate::error::StationError;
use object_store::aws::AmazonS3Builder;
use object_store::path::Path as ObjPath;
use object_store::{ObjectStore, PutPayload, RetryConfig};
use serde::Serialize;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

/// The completion marker's name, beside the run's files.
pub const MARKER: &str = "_upload_complete.json";

/// Files at least this large go up as multipart uploads.
pub const MULTIPART_BYTES: u64 = 32 << 20;

/// What an upload sent.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Uploaded {
    /// `s3://bucket/prefix/name`.
    pub url: String,
    /// Files in the run.
    pub files: u64,
    /// Of them, sent now (the rest were already in the bucket).
    pub sent: u64,
    /// Bytes of every file.
    pub bytes: u64,
}

/// The bucket of `config`, with its credentials from the station file's `access_key_id` and
/// `secret_access_key_file`, or else the environment (`AWS_ACCESS_KEY_ID`, ...).
pub fn bucket(config: &UploadConfig) -> Result<Arc<dyn ObjectStore>, StationError> {
    let mut b = AmazonS3Builder::from_env()
        .with_bucket_name(&config.bucket)
        .with_region(&config.region)
        .with_allow_http(config.allow_http)
        .with_retry(RetryConfig {
            max_retries: 5,
            retry_timeout: Duration::from_secs(120),
            ..RetryConfig::default()
        });
    if let Some(e) = &config.endpoint {
        // An S3-compatible server answers at ENDPOINT/BUCKET/KEY (path style).
        b = b.with_endpoint(e).with_virtual_hosted_style_request(false);
    }
    if let Some(id) = &config.access_key_id {
        b = b.with_access_key_id(id);
    }
    if let Some(file) = &config.secret_access_key_file {
        let secret = std::fs::read_to_string(file).map_err(|e| {
            StationError::Upload(format!(
                "upload.secret_access_key_file = {}: {e}",
                file.display()
            ))
        })?;
        b = b.with_secret_access_key(secret.trim());
    }
    let store = b.build().map_err(|e| StationError::Upload(e.to_string()))?;
    Ok(Arc::new(store))
}

/// Every file under `dir` but hidden ones, as (path relative to `dir` with `/`, full path),
/// sorted.
fn files_of(dir: &Path) -> std::io::Result<Vec<(String, PathBuf)>> {
    let mut out = Vec::new();
    let mut stack = vec![(String::new(), dir.to_path_buf())];
    while let Some((rel, path)) = stack.pop() {
        for e in std::fs::read_dir(&path)? {
            let e = e?;
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') {
                continue;
            }
            let key = if rel.is_empty() {
                name
            } else {
                format!("{rel}/{name}")
            };
            let t = e.file_type()?;
            if t.is_dir() {
                stack.push((key, e.path()));
            } else if t.is_file() {
                out.push((key, e.path()));
            }
        }
    }
    out.sort();
    Ok(out)
}

fn upload_err(what: impl std::fmt::Display, e: impl std::fmt::Display) -> StationError {
    StationError::Upload(format!("{what}: {e}"))
}

/// Whether `key` is in the bucket with `bytes` bytes.
async fn already_there(store: &dyn ObjectStore, key: &ObjPath, bytes: u64) -> bool {
    matches!(store.head(key).await, Ok(meta) if meta.size == bytes)
}

/// Sends one file: a PUT, or a multipart upload for a large one.
async fn send(
    store: &Arc<dyn ObjectStore>,
    key: &ObjPath,
    data: Vec<u8>,
) -> Result<(), object_store::Error> {
    if (data.len() as u64) < MULTIPART_BYTES {
        store.put(key, PutPayload::from(data)).await.map(|_| ())
    } else {
        let mut w = object_store::WriteMultipart::new(store.put_multipart(key).await?);
        w.write(&data);
        w.finish().await.map(|_| ())
    }
}

/// Uploads run directory `run_dir` (named `name` in the bucket) under `config.prefix`, marker
/// last. Files already in the bucket at their size are skipped.
pub async fn upload_run(
    store: &Arc<dyn ObjectStore>,
    config: &UploadConfig,
    run_dir: &Path,
    name: &str,
) -> Result<Uploaded, StationError> {
    let base = format!("{}/{name}", config.prefix.trim_end_matches('/'));
    let files = files_of(run_dir).map_err(|e| upload_err(run_dir.display(), e))?;
    let (mut sent, mut bytes) = (0, 0);
    let mut manifest = Vec::with_capacity(files.len());
    for (rel, path) in &files {
        let data = tokio::fs::read(path)
            .await
            .map_err(|e| upload_err(path.display(), e))?;
        let len = data.len() as u64;
        let key = ObjPath::from(format!("{base}/{rel}"));
        let sha = format!("{:x}", Sha256::digest(&data));
        if !already_there(store.as_ref(), &key, len).await {
            send(store, &key, data)
                .await
                .map_err(|e| upload_err(&key, e))?;
            sent += 1;
        }
        bytes += len;
        manifest.push(serde_json::json!({"key": rel, "bytes": len, "sha256": sha}));
    }
    let marker = serde_json::json!({
        "run": name,
        "files": manifest,
        "bytes": bytes,
        "uploaded_unix": crate::now_unix(),
    });
    let key = ObjPath::from(format!("{base}/{MARKER}"));
    let body = serde_json::to_vec_pretty(&marker).unwrap_or_default();
    store
        .put(&key, PutPayload::from(body))
        .await
        .map_err(|e| upload_err(&key, e))?;
    Ok(Uploaded {
        url: format!("s3://{}/{base}", config.bucket),
        files: files.len() as u64,
        sent,
        bytes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use object_store::memory::InMemory;

    fn config() -> UploadConfig {
        UploadConfig {
            bucket: "runs".into(),
            prefix: "roof-1".into(),
            endpoint: None,
            region: "us-east-1".into(),
            allow_http: false,
            access_key_id: None,
            secret_access_key_file: None,
        }
    }

    #[test]
    fn an_unreadable_secret_file_is_named() {
        let mut c = config();
        c.secret_access_key_file = Some("/nonexistent/s3.secret".into());
        let e = bucket(&c).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(
            e.contains("upload.secret_access_key_file") && e.contains("/nonexistent/s3.secret"),
            "{e}"
        );
    }

    #[test]
    fn an_interrupted_upload_resumes_and_the_marker_lists_every_file() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("7-capture");
        std::fs::create_dir_all(run.join("run.zarr/frames/pixels/c/0/0")).unwrap();
        std::fs::write(run.join("journal.jsonl"), b"{}\n").unwrap();
        std::fs::write(run.join("run.zarr/zarr.json"), b"{\"zarr_format\": 3}").unwrap();
        std::fs::write(run.join("run.zarr/frames/pixels/c/0/0/0"), vec![7u8; 1000]).unwrap();
        // A crash's leftover: never uploaded.
        std::fs::write(run.join("run.zarr/.zarr.json.1-0.partial"), b"x").unwrap();
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let store: Arc<dyn ObjectStore> = Arc::new(InMemory::new());
        let first = rt
            .block_on(upload_run(&store, &config(), &run, "7-capture"))
            .unwrap();
        assert_eq!((first.files, first.sent, first.bytes), (3, 3, 1021));
        assert_eq!(first.url, "s3://runs/roof-1/7-capture");
        // An interruption that left one object out and no marker: only that one goes again.
        let gone = ObjPath::from("roof-1/7-capture/run.zarr/frames/pixels/c/0/0/0");
        let marker = ObjPath::from(format!("roof-1/7-capture/{MARKER}"));
        rt.block_on(store.delete(&gone)).unwrap();
        rt.block_on(store.delete(&marker)).unwrap();
        let again = rt
            .block_on(upload_run(&store, &config(), &run, "7-capture"))
            .unwrap();
        assert_eq!((again.files, again.sent), (3, 1));
        let body = rt
            .block_on(async { store.get(&marker).await?.bytes().await })
            .unwrap();
        let m: serde_json::Value = serde_json::from_slice(&body).unwrap();
        let keys: Vec<&str> = m["files"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["key"].as_str().unwrap())
            .collect();
        assert_eq!(
            keys,
            [
                "journal.jsonl",
                "run.zarr/frames/pixels/c/0/0/0",
                "run.zarr/zarr.json"
            ]
        );
        assert_eq!(
            m["files"][1]["sha256"],
            format!("{:x}", Sha256::digest(vec![7u8; 1000]))
        );
    }
}
