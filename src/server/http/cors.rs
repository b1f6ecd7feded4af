//! Which browser pages may write ([`OriginPolicy`], `server.allowed_origins`). The CORS answers (preflights,
//! `Access-Control-*` headers) are tower-http's [`CorsLayer`], configured from the policy ([`OriginPolicy::cors`]);
//! [`refuse_foreign_writes`] is written here because `CorsLayer` never refuses a request (it only withholds its
//! headers, while a form or a simple `fetch` writes without a preflight), and a refusal must carry the API's JSON
//! error.

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderName, Method, Uri};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use tower_http::cors::{AllowOrigin, CorsLayer};

use crate::server::http::error::ApiError;

/// Which browser origins may write and get CORS answers (`server.allowed_origins`).
#[derive(Debug, Clone)]
pub struct OriginPolicy {
    any: bool,
    allowed: Vec<String>,
    /// Whether a page served by this server (its Origin is `http(s)://` + the request's Host) may write.
    same_host: bool,
}

impl OriginPolicy {
    /// `configured` as given, or, when empty, the origins a browser shows for the listener at `addr`.
    pub fn new(configured: &[String], addr: SocketAddr) -> Self {
        let any = configured.iter().any(|o| o == "*");
        let mut allowed: Vec<String> =
            configured.iter().filter(|o| *o != "*").map(|o| o.trim_end_matches('/').to_ascii_lowercase()).collect();
        if configured.is_empty() {
            let port = addr.port();
            let mut hosts = vec![match addr.ip() {
                IpAddr::V4(ip) => ip.to_string(),
                IpAddr::V6(ip) => format!("[{ip}]"),
            }];
            if addr.ip().is_loopback() {
                hosts.push("localhost".into());
            }
            for host in hosts {
                allowed.push(format!("http://{host}:{port}"));
                if port == 80 {
                    allowed.push(format!("http://{host}"));
                }
            }
        }
        Self { any, allowed, same_host: false }
    }

    /// Also lets pages of this server's own host write (the console, when it is reached under a name or address
    /// that is not in the list). Only with API keys on: without keys, a page whose name was rebound to this
    /// server's address (DNS rebinding) would pass this check, so the explicit list is all that holds.
    pub fn with_same_host(mut self, on: bool) -> Self {
        self.same_host = on;
        self
    }

    /// Whether `origin` is the page of the host the request was sent to.
    fn is_same_host(&self, origin: &str, host: Option<&str>) -> bool {
        self.same_host
            && host.is_some_and(|h| {
                let o = origin.to_ascii_lowercase();
                let h = h.trim().to_ascii_lowercase();
                o == format!("http://{h}") || o == format!("https://{h}")
            })
    }

    fn allows(&self, origin: &str) -> bool {
        self.any || self.allowed.iter().any(|a| a.eq_ignore_ascii_case(origin))
    }
}

/// The request's Host (HTTP/1.1) or authority (HTTP/2).
fn host_of<'a>(headers: &'a HeaderMap, uri: &'a Uri) -> Option<&'a str> {
    headers.get(header::HOST).and_then(|v| v.to_str().ok()).or(uri.authority().map(|a| a.as_str()))
}

impl OriginPolicy {
    /// Whether a page of `origin` may write to (and read the answers of) the host `host`.
    fn admits(&self, origin: &str, host: Option<&str>) -> bool {
        self.allows(origin) || self.is_same_host(origin, host)
    }

    /// The policy's CORS answers: preflights (OPTIONS) are answered here, and answers to allowed origins carry
    /// `Access-Control-Allow-Origin` (the origin itself, `"*"` included) and expose the match counts.
    pub fn cors(self: &Arc<Self>) -> CorsLayer {
        let policy = Arc::clone(self);
        CorsLayer::new()
            .allow_origin(AllowOrigin::predicate(move |origin, parts| {
                origin.to_str().is_ok_and(|o| policy.admits(o, host_of(&parts.headers, &parts.uri)))
            }))
            .allow_methods([Method::GET, Method::HEAD, Method::POST, Method::DELETE])
            .allow_headers([header::CONTENT_TYPE, HeaderName::from_static("x-api-key"), header::AUTHORIZATION])
            .expose_headers([HeaderName::from_static("x-scone-matches"), HeaderName::from_static("x-scone-inliers")])
            .max_age(Duration::from_secs(600))
    }
}

/// Browser pages of other origins must not write (a form or a simple `fetch` needs no preflight, so without
/// this any page could create maps on a loopback server without keys): a request with an `Origin` that is
/// not allowed is refused (403) unless it is a GET or HEAD, a preflight (OPTIONS) included. It runs before
/// [`OriginPolicy::cors`], so a refusal carries no CORS headers.
pub async fn refuse_foreign_writes(State(policy): State<Arc<OriginPolicy>>, req: Request, next: Next) -> Response {
    if matches!(*req.method(), Method::GET | Method::HEAD) {
        return next.run(req).await;
    }
    let Some(origin) = req.headers().get(header::ORIGIN) else { return next.run(req).await };
    let origin = origin.to_str().unwrap_or("(not text)");
    if policy.admits(origin, host_of(req.headers(), req.uri())) {
        return next.run(req).await;
    }
    ApiError::ForeignOrigin { origin: origin.to_string() }.into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_origins_are_the_listeners_own() {
        let p = OriginPolicy::new(&[], "127.0.0.1:8080".parse().unwrap());
        assert!(p.allows("http://127.0.0.1:8080") && p.allows("http://localhost:8080"));
        assert!(!p.allows("http://127.0.0.1:8081") && !p.allows("https://evil.example") && !p.allows("null"));
        let p = OriginPolicy::new(&["https://App.example.com/".into()], "127.0.0.1:8080".parse().unwrap());
        assert!(p.allows("https://app.example.com") && !p.allows("http://127.0.0.1:8080"));
        assert!(OriginPolicy::new(&["*".into()], "0.0.0.0:80".parse().unwrap()).allows("https://any.where"));
        // The server's own host: only with keys on (a rebound name must not pass a keyless server).
        let open = OriginPolicy::new(&[], "0.0.0.0:8080".parse().unwrap());
        assert!(!open.is_same_host("http://maps.example:8080", Some("maps.example:8080")));
        let keyed = open.with_same_host(true);
        assert!(keyed.is_same_host("http://maps.example:8080", Some("maps.example:8080")));
        assert!(keyed.is_same_host("https://Maps.Example", Some("maps.example")));
        assert!(!keyed.is_same_host("http://evil.example", Some("maps.example:8080")));
        assert!(!keyed.is_same_host("http://maps.example:8080", None));
    }
}
