//! The command line's client of a station: JSON over HTTP (or HTTPS) with the key from a file
//! (never from the command line, where other users' `ps` would see it).

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

impl Client {
    /// A client of the station at `url` (e.g. `http://127.0.0.1:8750`), with the key in
    /// `key_file` (its first line).
    pub fn new(url: &str, key_file: Option<&Path>) -> Result<Client, StationError> {
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
