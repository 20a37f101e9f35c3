//! The command line's client of a station: JSON over HTTP or HTTPS (rustls; the station's CA
//! from `--ca-file`, else Mozilla's roots) with the key from a file (never from the command
//! line, where other users' `ps` would see it).

use crate::error::StationError;
use serde_json::Value;
use std::path::Path;
use std::time::Duration;

/// A station's address and key.
pub struct Client {
    base: String,
    key: Option<String>,
    agent: ureq::Agent,
}

/// rustls with aws-lc-rs, trusting `ca_file`'s certificates or Mozilla's roots.
fn tls(ca_file: Option<&Path>) -> Result<ureq::tls::TlsConfig, StationError> {
    use ureq::tls::{PemItem, RootCerts, TlsConfig, TlsProvider};
    let roots = match ca_file {
        None => RootCerts::WebPki,
        Some(p) => {
            let pem = std::fs::read(p).map_err(|e| StationError::io(p, e))?;
            let certs: Vec<_> = ureq::tls::parse_pem(&pem)
                .filter_map(|item| match item {
                    Ok(PemItem::Certificate(c)) => Some(c),
                    _ => None,
                })
                .collect();
            if certs.is_empty() {
                return Err(StationError::Client(format!(
                    "--ca-file {}: no PEM certificate in it",
                    p.display()
                )));
            }
            RootCerts::Specific(std::sync::Arc::new(certs))
        }
    };
    Ok(TlsConfig::builder()
        .provider(TlsProvider::Rustls)
        .root_certs(roots)
        .unversioned_rustls_crypto_provider(std::sync::Arc::new(
            rustls::crypto::aws_lc_rs::default_provider(),
        ))
        .build())
}

impl Client {
    /// A client of the station at `url` (e.g. `http://127.0.0.1:8750`), with the key in
    /// `key_file` (its first line); HTTPS trusts the certificates in `ca_file` (PEM), else
    /// Mozilla's roots.
    pub fn new(
        url: &str,
        key_file: Option<&Path>,
        ca_file: Option<&Path>,
    ) -> Result<Client, StationError> {
        if !(url.starts_with("http://") || url.starts_with("https://")) {
            return Err(StationError::Client(format!(
                "--url {url:?}: write the station's address as http://HOST:PORT (or https://)"
            )));
        }
        let key = match key_file {
            None => None,
            Some(p) => {
                let text = std::fs::read_to_string(p).map_err(|e| StationError::io(p, e))?;
                let k = text.lines().next().unwrap_or("").trim().to_string();
                if k.is_empty() {
                    return Err(StationError::Client(format!(
                        "--key-file {}: the file is empty; it holds the key `station key create` printed",
                        p.display()
                    )));
                }
                Some(k)
            }
        };
        let agent = ureq::Agent::config_builder()
            .tls_config(tls(ca_file)?)
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(60)))
            .build()
            .into();
        Ok(Client {
            base: url.trim_end_matches('/').to_string(),
            key,
            agent,
        })
    }

    /// `GET path`.
    pub fn get(&self, path: &str) -> Result<Value, StationError> {
        let mut req = self.agent.get(format!("{}{path}", self.base));
        if let Some(k) = &self.key {
            req = req.header("Authorization", format!("Bearer {k}"));
        }
        Self::answer(path, req.call())
    }

    /// `GET path` of a binary answer (a product's PNG), at most 64 MiB.
    pub fn get_bytes(&self, path: &str) -> Result<Vec<u8>, StationError> {
        let mut req = self.agent.get(format!("{}{path}", self.base));
        if let Some(k) = &self.key {
            req = req.header("Authorization", format!("Bearer {k}"));
        }
        let mut resp = req
            .call()
            .map_err(|e| StationError::Client(format!("{path}: cannot reach the station: {e}")))?;
        let status = resp.status();
        let bytes = resp
            .body_mut()
            .with_config()
            .limit(64 << 20)
            .read_to_vec()
            .map_err(|e| StationError::Client(format!("{path}: {e}")))?;
        if status.is_success() {
            Ok(bytes)
        } else {
            let text = String::from_utf8_lossy(&bytes);
            Err(StationError::Client(format!(
                "{path}: {} {text}",
                status.as_u16()
            )))
        }
    }

    /// `POST path` with a JSON body.
    pub fn post(&self, path: &str, body: &Value) -> Result<Value, StationError> {
        let mut req = self
            .agent
            .post(format!("{}{path}", self.base))
            .header("Content-Type", "application/json");
        if let Some(k) = &self.key {
            req = req.header("Authorization", format!("Bearer {k}"));
        }
        Self::answer(path, req.send(body.to_string()))
    }

    /// `DELETE path`.
    pub fn delete(&self, path: &str) -> Result<Value, StationError> {
        let mut req = self.agent.delete(format!("{}{path}", self.base));
        if let Some(k) = &self.key {
            req = req.header("Authorization", format!("Bearer {k}"));
        }
        Self::answer(path, req.call())
    }

    fn answer(
        path: &str,
        r: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    ) -> Result<Value, StationError> {
        let mut resp =
            r.map_err(|e| StationError::Client(format!("{path}: cannot reach the station: {e}")))?;
        let status = resp.status();
        let text = resp
            .body_mut()
            .read_to_string()
            .map_err(|e| StationError::Client(format!("{path}: {e}")))?;
        let v: Value = serde_json::from_str(&text).unwrap_or(Value::String(text));
        if status.is_success() || (path == "/healthz" && status.as_u16() == 503) {
            return Ok(v);
        }
        let field = v["field"].as_str().filter(|f| !f.is_empty());
        Err(StationError::Client(format!(
            "{path}: {} {}{}",
            status.as_u16(),
            v["error"].as_str().unwrap_or(&v.to_string()),
            field.map_or(String::new(), |f| format!(" (field: {f})"))
        )))
    }
}
