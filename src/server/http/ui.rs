//! The web console under `/ui`: its page, script and style, and the browser libraries it uses (three.js,
//! Swagger UI; npm packages pinned in `ui/package-lock.json`, installed by `scripts/setup` with `npm ci`),
//! all compiled into the binary so the console works offline and needs nothing at run time.
//!
//! The files need no key (they hold no data); everything the console shows comes from the API with the key
//! typed into its header, under the API's rules. Caching: an ETag per file (a hash of its bytes), revalidated
//! on every use (`no-cache`; unchanged files cost a 304).

use std::sync::LazyLock;

use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};

use super::body::ApiPath;
use super::error::{ApiError, ApiErrors, ApiResult};

/// One served file.
struct Asset {
    name: &'static str,
    content_type: &'static str,
    bytes: &'static [u8],
}

macro_rules! file {
    ($path:literal) => {
        include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/ui/", $path))
    };
}

const JS: &str = "text/javascript; charset=utf-8";
const CSS: &str = "text/css; charset=utf-8";
const HTML: &str = "text/html; charset=utf-8";

static ASSETS: &[Asset] = &[
    Asset { name: "index.html", content_type: HTML, bytes: file!("index.html") },
    Asset { name: "api.html", content_type: HTML, bytes: file!("api.html") },
    Asset { name: "console.js", content_type: JS, bytes: file!("console.js") },
    Asset { name: "api.js", content_type: JS, bytes: file!("api.js") },
    Asset { name: "console.css", content_type: CSS, bytes: file!("console.css") },
    Asset { name: "three.module.js", content_type: JS, bytes: file!("node_modules/three/build/three.module.js") },
    Asset { name: "three.core.js", content_type: JS, bytes: file!("node_modules/three/build/three.core.js") },
    Asset {
        name: "OrbitControls.js",
        content_type: JS,
        bytes: file!("node_modules/three/examples/jsm/controls/OrbitControls.js"),
    },
    Asset {
        name: "swagger-ui-bundle.js",
        content_type: JS,
        bytes: file!("node_modules/swagger-ui-dist/swagger-ui-bundle.js"),
    },
    Asset { name: "swagger-ui.css", content_type: CSS, bytes: file!("node_modules/swagger-ui-dist/swagger-ui.css") },
];

static ETAGS: LazyLock<Vec<String>> = LazyLock::new(|| {
    ASSETS.iter().map(|a| format!("\"{}\"", &format!("{:x}", Sha256::digest(a.bytes))[..20])).collect()
});

fn serve(index: usize, headers: &HeaderMap) -> Response {
    let asset = &ASSETS[index];
    let etag = &ETAGS[index];
    // Revalidated every time (a 304 when unchanged): file names carry no version, so an hour's caching could
    // pair a new three.module.js with an old three.core.js after an upgrade.
    let cache = "no-cache";
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"));
    let mut resp = if fresh { StatusCode::NOT_MODIFIED.into_response() } else { asset.bytes.into_response() };
    let h = resp.headers_mut();
    if !fresh {
        h.insert(header::CONTENT_TYPE, HeaderValue::from_static(asset.content_type));
    }
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
    h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    if let Ok(v) = HeaderValue::from_str(etag) {
        h.insert(header::ETAG, v);
    }
    resp
}

/// The console.
#[utoipa::path(get, path = "/ui", tag = "console",
    responses((status = 200, description = "The console page", body = String, content_type = "text/html"),
              (status = 304, description = "Not modified (If-None-Match)")))]
pub async fn console(headers: HeaderMap) -> Response {
    serve(0, &headers)
}

/// A file of the console: its pages (`api.html`, the API reference), script, style, and libraries.
#[utoipa::path(get, path = "/ui/{file}", tag = "console",
    params(("file" = String, Path, description = "index.html, api.html, console.js, console.css, three.module.js, ...",
        example = "console.css")),
    responses((status = 200, description = "The file, with its content type", content(
        (String = "text/html"), (String = "text/javascript"), (String = "text/css"))),
        (status = 304, description = "Not modified (If-None-Match)"), ApiErrors))]
pub async fn asset(ApiPath(file): ApiPath<String>, headers: HeaderMap) -> ApiResult<Response> {
    match ASSETS.iter().position(|a| a.name == file) {
        Some(i) => Ok(serve(i, &headers)),
        None => Err(ApiError::NoRoute { path: format!("/ui/{file}") }),
    }
}
