//! The status page served at `/`: the queue, the current item's progress, the latest DoLP and
//! AoP images, the sun's elevation and the next scheduled start, the disk and health. The page
//! itself holds nothing secret; it asks for a read key (kept in the browser tab) and reads the
//! API with it.

use axum::response::Html;

/// The page (one file: HTML, CSS and script, no outside resource).
pub const PAGE: &str = include_str!("page.html");

/// `GET /`.
pub async fn index() -> Html<&'static str> {
    Html(PAGE)
}
