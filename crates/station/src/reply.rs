//! How the API answers: errors as JSON naming the field (`{"error": ..., "field": ...}`),
//! request bodies read with the field at fault named, and edits audited with their key's id.

use crate::shared::{EditError, Station};
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::json;

/// An error answer: a status and `{"error": MESSAGE, "field": FIELD}`.
#[derive(Debug)]
pub struct ApiError {
    /// The HTTP status.
    pub status: StatusCode,
    /// What is wrong, in the user's words.
    pub message: String,
    /// The request's field at fault, if one is.
    pub field: Option<String>,
}

impl ApiError {
    /// An error with no field.
    pub fn new(status: StatusCode, message: impl Into<String>) -> ApiError {
        ApiError {
            status,
            message: message.into(),
            field: None,
        }
    }

    /// A 400 naming `field`.
    pub fn field(field: impl Into<String>, message: impl Into<String>) -> ApiError {
        ApiError {
            status: StatusCode::BAD_REQUEST,
            message: message.into(),
            field: Some(field.into()),
        }
    }

    /// A 409: the station is not in a state where this can be done.
    pub fn conflict(message: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::CONFLICT, message)
    }

    /// A 500 from a state that could not be saved or a task that failed.
    pub fn internal(message: impl std::fmt::Display) -> ApiError {
        ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, message.to_string())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = json!({"error": self.message, "field": self.field});
        (self.status, Json(body)).into_response()
    }
}

/// A JSON body, or a 400 naming the field serde could not read (axum's own rejection says
/// too little and is not JSON).
pub fn parse_body<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, ApiError> {
    let mut de = serde_json::Deserializer::from_slice(bytes);
    serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let field = e.path().to_string();
        ApiError::field(
            if field == "." { String::new() } else { field },
            format!("the request body: {}", e.into_inner()),
        )
    })
}

/// A request body, its 413 (over `max_body_kb`) and read errors as JSON.
pub fn body(b: Result<Bytes, BytesRejection>) -> Result<Bytes, ApiError> {
    b.map_err(|e| ApiError::new(e.status(), format!("the request body: {}", e.body_text())))
}

/// An edit's outcome, audited with the key's id: its value, or the refusal (a state that
/// could not be saved is a 500).
pub fn audited<T>(
    st: &Station,
    key: &str,
    action: &str,
    target: impl Fn(&T) -> String,
    r: Result<T, EditError<ApiError>>,
) -> Result<T, ApiError> {
    let r = r.map_err(|e| match e {
        EditError::Refused(e) => e,
        EditError::Save(e) => {
            ApiError::internal(format!("the station's state could not be saved: {e}"))
        }
    });
    match &r {
        Ok(v) => st.audit.record(key, action, &target(v), true, ""),
        Err(e) => st.audit.record(key, action, "", false, &e.message),
    }
    r
}
