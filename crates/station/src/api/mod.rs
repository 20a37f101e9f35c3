//! The HTTP API: the router over [`crate::routes::ROUTES`] (errors: [`crate::reply`]; who
//! asks: [`crate::auth`]).
//!
//! * [`read`]: health, status, queue, history, events, the OpenAPI description;
//! * [`edit`]: adding, validating, removing and moving items, queue start and stop;
//! * [`control`]: pause, resume and abort of the current item.

pub mod control;
pub mod edit;
pub mod read;

use crate::auth::{AppState, Throttle};
use crate::reply::ApiError;
use crate::shared::Station;
use axum::extract::DefaultBodyLimit;
use axum::http::StatusCode;
use axum::routing::{get, post};
use axum::Router;
use std::sync::Arc;

/// The router: every route of [`crate::routes::ROUTES`], request bodies limited to the
/// station's `max_body_kb`, unknown paths answered with JSON.
pub fn router(st: Arc<Station>) -> Router {
    let limit = st.config.max_body_bytes;
    let state = AppState {
        st,
        throttle: Arc::new(Throttle::default()),
    };
    Router::new()
        .route("/", get(crate::page::index))
        .route("/healthz", get(read::healthz))
        .route("/api/v1/products/latest/{name}", get(read::product))
        .route("/api/v1/openapi.json", get(read::openapi))
        .route("/api/v1/status", get(read::status))
        .route(
            "/api/v1/queue",
            get(read::queue).post(edit::submit).delete(edit::clear),
        )
        .route("/api/v1/queue/validate", post(edit::validate))
        .route("/api/v1/queue/start", post(edit::start))
        .route("/api/v1/queue/stop", post(edit::stop))
        .route("/api/v1/queue/{id}", axum::routing::delete(edit::remove))
        .route("/api/v1/queue/{id}/move", post(edit::move_item))
        .route("/api/v1/run/pause", post(control::pause))
        .route("/api/v1/run/resume", post(control::resume))
        .route("/api/v1/run/abort", post(control::abort))
        .route("/api/v1/history", get(read::history))
        .route("/api/v1/events", get(read::events))
        .fallback(|| async {
            ApiError::new(
                StatusCode::NOT_FOUND,
                "no such endpoint (GET /api/v1/openapi.json lists them)",
            )
        })
        .layer(DefaultBodyLimit::max(limit))
        .with_state(state)
}
