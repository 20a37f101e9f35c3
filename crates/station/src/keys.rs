//! API keys: 32 random bytes each, shown once when created and stored only as a SHA-256 hash,
//! with scopes, an expiry and a note; a presented key is compared with the stored hash in
//! constant time. A key reads `pst_<id>_<64 hex digits>`: the id (not secret) finds the record.
//!
//! Scopes: `read` (status, queue, history, events), `queue` (add, validate, remove one's own
//! items), `control` (queue start/stop, run pause/resume/abort), `admin` (everything, and
//! other keys' items). Every key can read.

use crate::error::StationError;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use subtle::ConstantTimeEq;

/// What a key may do (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Scope {
    /// Status, queue, history, events.
    Read,
    /// Add and validate plans; remove one's own items.
    Queue,
    /// Queue start/stop; pause, resume and abort the running item.
    Control,
    /// Everything, including other keys' items and the keys themselves.
    Admin,
}

impl Scope {
    /// The scopes' names, as written.
    pub const NAMES: [&'static str; 4] = ["read", "queue", "control", "admin"];

    /// A scope from its name.
    pub fn parse(name: &str) -> Result<Scope, StationError> {
        match name.trim() {
            "read" => Ok(Scope::Read),
            "queue" => Ok(Scope::Queue),
            "control" => Ok(Scope::Control),
            "admin" => Ok(Scope::Admin),
            other => Err(StationError::Key(format!(
                "scope {other:?} is not one of: {}",
                Scope::NAMES.join(", ")
            ))),
        }
    }

    /// The scope's name.
    pub fn name(self) -> &'static str {
        Scope::NAMES[self as usize]
    }
}

/// One key as stored: never the key itself.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct KeyRecord {
    /// The key's public id (in the key's text, the audit log and item owners).
    pub id: String,
    /// SHA-256 of the whole key text, hex.
    pub sha256: String,
    /// What the key may do.
    pub scopes: Vec<Scope>,
    /// When it was made, Unix seconds.
    pub created_unix: u64,
    /// When it stops working, Unix seconds (`None`: never).
    pub expires_unix: Option<u64>,
    /// The note given when it was made (who holds it, what for).
    pub note: String,
    /// When it was revoked, Unix seconds.
    pub revoked_unix: Option<u64>,
}

impl KeyRecord {
    /// Whether the key may do what `scope` allows (admin may do everything; every key reads).
    pub fn allows(&self, scope: Scope) -> bool {
        scope == Scope::Read || self.scopes.contains(&scope) || self.scopes.contains(&Scope::Admin)
    }
}

/// Why a presented key was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum AuthError {
    /// No `Authorization: Bearer` header.
    #[error("no API key: send the header `Authorization: Bearer KEY`")]
    Missing,
    /// Not a key's shape.
    #[error("the API key is malformed: a key reads pst_<id>_<64 hex digits>")]
    Malformed,
    /// No key with this id and text.
    #[error("the API key is not known to this station")]
    Unknown,
    /// Past its expiry.
    #[error("the API key has expired")]
    Expired,
    /// Revoked.
    #[error("the API key has been revoked")]
    Revoked,
}

/// The keys of a station, in its data directory (owner-readable only).
#[derive(Debug, Clone)]
pub struct KeyStore {
    path: PathBuf,
    /// The records.
    pub keys: Vec<KeyRecord>,
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn sha256_hex(text: &str) -> String {
    hex(&Sha256::digest(text.as_bytes()))
}

fn random_bytes<const N: usize>() -> Result<[u8; N], StationError> {
    let mut b = [0u8; N];
    getrandom::fill(&mut b)
        .map_err(|e| StationError::Key(format!("the system's random source failed: {e}")))?;
    Ok(b)
}

impl KeyStore {
    /// The keys in `path` (none yet when it does not exist).
    pub fn load(path: &Path) -> Result<KeyStore, StationError> {
        let keys = crate::atomic::read_json(path)?.unwrap_or_default();
        Ok(KeyStore {
            path: path.to_path_buf(),
            keys,
        })
    }

    /// Makes a key and saves its hash; the key's text, to be shown once.
    pub fn create(
        &mut self,
        scopes: Vec<Scope>,
        expires_in_s: Option<u64>,
        note: &str,
        now_unix: u64,
    ) -> Result<(KeyRecord, String), StationError> {
        if scopes.is_empty() {
            return Err(StationError::Key(format!(
                "a key needs at least one scope: {}",
                Scope::NAMES.join(", ")
            )));
        }
        let id = hex(&random_bytes::<6>()?);
        let text = format!("pst_{id}_{}", hex(&random_bytes::<32>()?));
        let record = KeyRecord {
            id,
            sha256: sha256_hex(&text),
            scopes,
            created_unix: now_unix,
            expires_unix: expires_in_s.map(|s| now_unix.saturating_add(s)),
            note: note.to_string(),
            revoked_unix: None,
        };
        self.keys.push(record.clone());
        self.save()?;
        Ok((record, text))
    }

    /// Revokes the key `id` (kept in the file, so the audit log's ids stay explained).
    pub fn revoke(&mut self, id: &str, now_unix: u64) -> Result<(), StationError> {
        let k = self
            .keys
            .iter_mut()
            .find(|k| k.id == id)
            .ok_or_else(|| StationError::Key(format!("no key has the id {id:?}")))?;
        k.revoked_unix.get_or_insert(now_unix);
        self.save()
    }

    fn save(&self) -> Result<(), StationError> {
        crate::atomic::write_json(&self.path, &self.keys, true)
    }

    /// The record of the presented key text, if it is a live key of this station. The hash
    /// is compared in constant time, and an unknown id costs the same hash and comparison.
    pub fn authenticate(&self, presented: &str, now_unix: u64) -> Result<&KeyRecord, AuthError> {
        let id = parse_id(presented).ok_or(AuthError::Malformed)?;
        let digest = sha256_hex(presented);
        let found = self.keys.iter().find(|k| k.id == id);
        let stored = found.map_or("0".repeat(64), |k| k.sha256.clone());
        let same: bool = digest.as_bytes().ct_eq(stored.as_bytes()).into();
        let record = match found {
            Some(k) if same => k,
            _ => return Err(AuthError::Unknown),
        };
        if record.revoked_unix.is_some() {
            return Err(AuthError::Revoked);
        }
        if record.expires_unix.is_some_and(|t| now_unix >= t) {
            return Err(AuthError::Expired);
        }
        Ok(record)
    }
}

/// The id of a key's text, if it has a key's shape.
fn parse_id(text: &str) -> Option<&str> {
    let rest = text.strip_prefix("pst_")?;
    let (id, secret) = rest.split_once('_')?;
    let hex_digits = |s: &str, n: usize| s.len() == n && s.bytes().all(|b| b.is_ascii_hexdigit());
    (hex_digits(id, 12) && hex_digits(secret, 64)).then_some(id)
}

/// `30d`, `12h`, `90m`: a key's lifetime in seconds (humantime's units).
pub fn parse_duration_s(text: &str) -> Result<u64, StationError> {
    humantime::parse_duration(text)
        .map(|d| d.as_secs())
        .map_err(|e| {
            StationError::Key(format!(
                "--expires-in {text:?}: {e}; write e.g. 30d, 12h or 90m"
            ))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn store() -> (tempfile::TempDir, KeyStore) {
        let dir = tempfile::tempdir().unwrap();
        let s = KeyStore::load(&dir.path().join("keys.json")).unwrap();
        (dir, s)
    }

    #[test]
    fn a_key_authenticates_only_as_itself_and_is_stored_as_a_hash() {
        let (dir, mut s) = store();
        let (rec, text) = s.create(vec![Scope::Queue], None, "roof", 1000).unwrap();
        assert_eq!(
            text.len(),
            4 + 12 + 1 + 64,
            "32 random bytes in hex after the id"
        );
        let file = std::fs::read_to_string(dir.path().join("keys.json")).unwrap();
        assert!(!file.contains(&text[17..]), "the secret is never written");
        let again = KeyStore::load(&dir.path().join("keys.json")).unwrap();
        assert_eq!(again.authenticate(&text, 1001).unwrap().id, rec.id);
        // One hex digit changed: refused.
        let mut wrong = text.clone();
        let last = if wrong.ends_with('0') { "1" } else { "0" };
        wrong.replace_range(wrong.len() - 1.., last);
        assert_eq!(
            again.authenticate(&wrong, 1001).unwrap_err(),
            AuthError::Unknown
        );
        assert_eq!(
            again.authenticate("pst_x", 1001).unwrap_err(),
            AuthError::Malformed
        );
    }

    #[test]
    fn expired_and_revoked_keys_are_refused() {
        let (_dir, mut s) = store();
        let (_, short) = s.create(vec![Scope::Read], Some(60), "", 1000).unwrap();
        assert!(s.authenticate(&short, 1059).is_ok());
        assert_eq!(
            s.authenticate(&short, 1060).unwrap_err(),
            AuthError::Expired
        );
        let (rec, text) = s.create(vec![Scope::Admin], None, "", 1000).unwrap();
        s.revoke(&rec.id, 1100).unwrap();
        assert_eq!(s.authenticate(&text, 1101).unwrap_err(), AuthError::Revoked);
        assert!(s.revoke("nobody", 1).is_err());
    }

    #[test]
    fn scopes_admin_allows_all_and_every_key_reads() {
        let k = |scopes| KeyRecord {
            id: String::new(),
            sha256: String::new(),
            scopes,
            created_unix: 0,
            expires_unix: None,
            note: String::new(),
            revoked_unix: None,
        };
        assert!(k(vec![Scope::Queue]).allows(Scope::Read));
        assert!(!k(vec![Scope::Queue]).allows(Scope::Control));
        assert!(k(vec![Scope::Admin]).allows(Scope::Control));
        assert!(Scope::parse("write").is_err());
        assert_eq!(parse_duration_s("30d").unwrap(), 30 * 86400);
    }
}
