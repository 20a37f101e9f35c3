//! Who is asking: the bearer key against the station's keys, the scope the endpoint needs, and
//! a delay that grows with recent failed attempts (at most [`MAX_DELAY`]), so guessing keys is
//! slow as well as hopeless.

use crate::keys::{AuthError, KeyRecord, Scope};
use crate::reply::ApiError;
use crate::shared::Station;
use axum::http::{HeaderMap, StatusCode};
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What every handler has.
#[derive(Clone)]
pub struct AppState {
    /// The station.
    pub st: Arc<Station>,
    /// Failed authentications.
    pub throttle: Arc<Throttle>,
}

impl AppState {
    /// The asking key, if it authenticates and allows `scope` ([`authorize`]).
    pub async fn key(
        &self,
        headers: &HeaderMap,
        scope: Scope,
        action: &str,
    ) -> Result<KeyRecord, ApiError> {
        authorize(&self.st, &self.throttle, headers, scope, action).await
    }
}

/// The window over which failed attempts count.
const WINDOW: Duration = Duration::from_secs(60);
/// Added delay per failed attempt in the window.
const STEP: Duration = Duration::from_millis(100);
/// The longest delay.
pub const MAX_DELAY: Duration = Duration::from_secs(3);

/// Recent failed authentications.
#[derive(Default)]
pub struct Throttle {
    failures: Mutex<VecDeque<Instant>>,
}

impl Throttle {
    /// Records a failure; how long to wait before answering it.
    fn fail(&self) -> Duration {
        let now = Instant::now();
        let Ok(mut f) = self.failures.lock() else {
            return MAX_DELAY;
        };
        while f.front().is_some_and(|t| now.duration_since(*t) > WINDOW) {
            f.pop_front();
        }
        if f.len() < 10_000 {
            f.push_back(now);
        }
        (STEP * f.len() as u32).min(MAX_DELAY)
    }
}

/// The key in `Authorization: Bearer KEY`, if it authenticates and allows `scope`. A refusal
/// waits (the throttle), and a refused write is audited.
pub async fn authorize(
    st: &Station,
    throttle: &Throttle,
    headers: &HeaderMap,
    scope: Scope,
    action: &str,
) -> Result<KeyRecord, ApiError> {
    let outcome = check(st, headers, scope);
    if let Err(e) = &outcome {
        if e.status == StatusCode::UNAUTHORIZED {
            tokio::time::sleep(throttle.fail()).await;
        }
        if scope != Scope::Read {
            st.audit.record("-", action, "", false, &e.message);
        }
    }
    outcome
}

fn check(st: &Station, headers: &HeaderMap, scope: Scope) -> Result<KeyRecord, ApiError> {
    let unauthorized = |e: AuthError| ApiError::new(StatusCode::UNAUTHORIZED, e.to_string());
    let header = headers
        .get(axum::http::header::AUTHORIZATION)
        .ok_or(AuthError::Missing)
        .map_err(unauthorized)?;
    let text = header
        .to_str()
        .ok()
        .and_then(|h| h.strip_prefix("Bearer "))
        .ok_or(AuthError::Malformed)
        .map_err(unauthorized)?;
    let keys = st
        .key_store()
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    let record = keys
        .store
        .authenticate(text.trim(), crate::now_unix())
        .map_err(unauthorized)?
        .clone();
    if !record.allows(scope) {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            format!(
                "key {} has the scopes {:?}; this needs {:?} (or admin)",
                record.id,
                record.scopes.iter().map(|s| s.name()).collect::<Vec<_>>(),
                scope.name()
            ),
        ));
    }
    Ok(record)
}
