//! The API's endpoints in one table: the router, the scope checks' documentation, the OpenAPI
//! description and the docs check all read it.

use crate::keys::Scope;

/// One endpoint.
#[derive(Debug, Clone, Copy)]
pub struct Route {
    /// `GET`, `POST` or `DELETE`.
    pub method: &'static str,
    /// The path, `{id}` for an item's id.
    pub path: &'static str,
    /// The scope a key needs (`None`: no key).
    pub scope: Option<Scope>,
    /// What it does.
    pub summary: &'static str,
}

const fn r(
    method: &'static str,
    path: &'static str,
    scope: Option<Scope>,
    summary: &'static str,
) -> Route {
    Route {
        method,
        path,
        scope,
        summary,
    }
}

/// Every endpoint of the station.
pub const ROUTES: &[Route] = &[
    r(
        "GET",
        "/",
        None,
        "The status page (HTML; it reads the API with a key the user gives).",
    ),
    r(
        "GET",
        "/healthz",
        None,
        "Health: devices reachable, disk, clock, queue, last error (503 when unhealthy).",
    ),
    r(
        "GET",
        "/api/v1/openapi.json",
        None,
        "This API's OpenAPI 3.1 description.",
    ),
    r(
        "GET",
        "/api/v1/status",
        Some(Scope::Read),
        "The queue, the current item and its progress, the last change id.",
    ),
    r(
        "GET",
        "/api/v1/queue",
        Some(Scope::Read),
        "The queued items in order.",
    ),
    r(
        "POST",
        "/api/v1/queue",
        Some(Scope::Queue),
        "Add a plan (or a batch, all or nothing); answers the items' ids.",
    ),
    r(
        "DELETE",
        "/api/v1/queue",
        Some(Scope::Queue),
        "Clear the queue (one's own items; admin: all).",
    ),
    r(
        "POST",
        "/api/v1/queue/validate",
        Some(Scope::Queue),
        "Check a plan as `plan check` does, without queuing: the forecast.",
    ),
    r(
        "DELETE",
        "/api/v1/queue/{id}",
        Some(Scope::Queue),
        "Remove an item (one's own; admin: any); a paused current item leaves as stopped.",
    ),
    r(
        "POST",
        "/api/v1/queue/{id}/move",
        Some(Scope::Queue),
        "Move an item to a position in the queue (one's own; admin: any).",
    ),
    r(
        "POST",
        "/api/v1/queue/start",
        Some(Scope::Control),
        "Start taking items from the queue.",
    ),
    r(
        "POST",
        "/api/v1/queue/stop",
        Some(Scope::Control),
        "Stop taking items after the current one.",
    ),
    r(
        "POST",
        "/api/v1/run/pause",
        Some(Scope::Control),
        "Pause the running item at its next set boundary.",
    ),
    r(
        "POST",
        "/api/v1/run/resume",
        Some(Scope::Control),
        "Resume the paused item.",
    ),
    r(
        "POST",
        "/api/v1/run/abort",
        Some(Scope::Control),
        "Abort the current item (one's own; admin: any); what was acquired stays.",
    ),
    r(
        "GET",
        "/api/v1/history",
        Some(Scope::Read),
        "Items that left the station, with exit states and run directories.",
    ),
    r(
        "GET",
        "/api/v1/events",
        Some(Scope::Read),
        "Server-sent events: status and log events with change ids.",
    ),
];
