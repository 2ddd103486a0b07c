//! The dashboard: a static single-page app embedded in the binary (HTML, CSS and ES modules from
//! `ui/`, no build step, no CDN), served at `/` and `/ui/...`. It reads only the public JSON API,
//! so it works offline and against another server (`?api=http://host:port`, which must then
//! allow this origin: `--cors-allow-origin`).

use super::AppState;
use axum::Router;
use axum::extract::Path;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;

/// The app's page: every dashboard path answers it, and the script routes on the path.
const INDEX: &str = include_str!("../../../../ui/index.html");

/// `(file name, content type, content)` of each asset under `/ui/assets/`.
const ASSETS: &[(&str, &str, &str)] = &[
    (
        "api.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../ui/api.js"),
    ),
    (
        "app.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../ui/app.js"),
    ),
    (
        "charts.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../ui/charts.js"),
    ),
    (
        "dom.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../ui/dom.js"),
    ),
    (
        "format.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../ui/format.js"),
    ),
    (
        "pages.js",
        "text/javascript; charset=utf-8",
        include_str!("../../../../ui/pages.js"),
    ),
    (
        "style.css",
        "text/css; charset=utf-8",
        include_str!("../../../../ui/style.css"),
    ),
];

/// Scripts and styles only from this server; API calls to any HTTP(S) origin (a remote server).
const CSP: &str = "default-src 'self'; connect-src 'self' http: https:; img-src 'self' data: blob:; \
                   style-src 'self'; script-src 'self'; object-src 'none'; base-uri 'none'; \
                   frame-ancestors 'none'";

fn with_headers(content_type: &'static str, body: &'static str) -> Response {
    let mut r = (StatusCode::OK, body).into_response();
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    // Embedded: a new binary may carry new files, so revalidate rather than cache blindly.
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    r
}

/// `GET /`, `GET /ui`, `GET /ui/{*page}`: the app's page.
async fn dashboard_page() -> Response {
    with_headers("text/html; charset=utf-8", INDEX)
}

/// `GET /ui/assets/{file}`: an embedded script or stylesheet.
async fn dashboard_asset(Path(file): Path<String>) -> Response {
    match ASSETS.iter().find(|(name, _, _)| *name == file) {
        Some((_, content_type, body)) => with_headers(content_type, body),
        None => super::error::ApiError::not_found(format!("no dashboard asset {file:?}"))
            .into_response(),
    }
}

/// The dashboard's routes (outside the API's route table and its contract).
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/", get(dashboard_page))
        .route("/ui", get(dashboard_page))
        .route("/ui/assets/{file}", get(dashboard_asset))
        .route("/ui/{*page}", get(dashboard_page))
}
