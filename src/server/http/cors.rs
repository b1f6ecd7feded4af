//! Which browser pages may write ([`OriginPolicy`], `server.allowed_origins`), and the middleware that
//! answers CORS preflights and refuses writes from other origins ([`origin_policy`]).

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{header, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

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

const CORS_METHODS: &str = "GET, HEAD, POST, DELETE";
const CORS_HEADERS: &str = "content-type, x-api-key, authorization";

/// Browser pages of other origins must not write (a form or a simple `fetch` needs no preflight, so without
/// this any page could create maps on a loopback server without keys): a request with an `Origin` that is
/// not allowed is refused unless it is a GET or HEAD. CORS preflights (OPTIONS) are answered by the same
/// policy, and responses to allowed origins carry `Access-Control-Allow-Origin`.
pub async fn origin_policy(State(policy): State<Arc<OriginPolicy>>, req: Request, next: Next) -> Response {
    let origin = req.headers().get(header::ORIGIN).map(|v| v.to_str().unwrap_or("(not text)").to_string());
    let host =
        req.headers().get(header::HOST).and_then(|v| v.to_str().ok()).or(req.uri().authority().map(|a| a.as_str()));
    let allowed = origin.as_deref().is_some_and(|o| policy.allows(o) || policy.is_same_host(o, host));
    let cors = |resp: &mut Response, origin: &str| {
        let h = resp.headers_mut();
        if let Ok(v) = HeaderValue::from_str(origin) {
            h.insert(header::ACCESS_CONTROL_ALLOW_ORIGIN, v);
        }
        h.insert(header::ACCESS_CONTROL_EXPOSE_HEADERS, HeaderValue::from_static("x-scone-matches, x-scone-inliers"));
        h.append(header::VARY, HeaderValue::from_static("origin"));
    };
    if req.method() == Method::OPTIONS {
        return match origin {
            Some(o) if allowed => {
                let mut resp = StatusCode::NO_CONTENT.into_response();
                cors(&mut resp, &o);
                let h = resp.headers_mut();
                h.insert(header::ACCESS_CONTROL_ALLOW_METHODS, HeaderValue::from_static(CORS_METHODS));
                h.insert(header::ACCESS_CONTROL_ALLOW_HEADERS, HeaderValue::from_static(CORS_HEADERS));
                h.insert(header::ACCESS_CONTROL_MAX_AGE, HeaderValue::from_static("600"));
                resp
            }
            Some(o) => ApiError::ForeignOrigin { origin: o }.into_response(),
            None => {
                let mut resp = StatusCode::NO_CONTENT.into_response();
                resp.headers_mut().insert(header::ALLOW, HeaderValue::from_static("GET, HEAD, POST, DELETE, OPTIONS"));
                resp
            }
        };
    }
    let write = !matches!(*req.method(), Method::GET | Method::HEAD);
    match origin {
        Some(o) if write && !allowed => ApiError::ForeignOrigin { origin: o }.into_response(),
        Some(o) if allowed => {
            let mut resp = next.run(req).await;
            cors(&mut resp, &o);
            resp
        }
        _ => next.run(req).await,
    }
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
