//! API keys: write keys may do everything, read keys only what changes nothing. Keys are kept as SHA-256
//! digests and compared in constant time, so neither memory dumps nor timing give them away.

use sha2::{Digest, Sha256};

use crate::server::operation::Operation;
use crate::service::ServiceError;
use crate::settings::Access;

/// Proof that a request's key was checked for the access its operation needs ([`Keys::authorize`]), made
/// before the request's body is read. The one entry point to the CPU pool ([`crate::server::app::App::call`])
/// takes it, so a key is checked once per request, and once per stream of keyframes.
#[derive(Debug, Clone, Copy)]
pub struct Authorized(Operation);

impl Authorized {
    /// The operation the key was checked for.
    pub fn operation(self) -> Operation {
        self.0
    }
}

/// The configured keys.
pub struct Keys {
    digests: Vec<([u8; 32], Access)>,
    anonymous: bool,
}

fn digest(key: &str) -> [u8; 32] {
    Sha256::digest(key.as_bytes()).into()
}

fn same(a: &[u8; 32], b: &[u8; 32]) -> bool {
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl Keys {
    /// With no key at all, every request is allowed (settings only permit that on loopback, or when
    /// `auth.allow_anonymous` is set).
    pub fn new(keys: Vec<(String, Access)>) -> Self {
        Self { digests: keys.iter().map(|(k, a)| (digest(k), *a)).collect(), anonymous: keys.is_empty() }
    }

    pub fn len(&self) -> usize {
        self.digests.len()
    }

    pub fn is_empty(&self) -> bool {
        self.digests.is_empty()
    }

    /// `presented` checked for `operation`: the proof, or why not.
    pub fn authorize(&self, presented: Option<&str>, operation: Operation) -> Result<Authorized, ServiceError> {
        self.check(presented, operation.access(), operation.name()).map(|()| Authorized(operation))
    }

    /// Whether `presented` may perform an operation needing `needed`.
    pub fn check(&self, presented: Option<&str>, needed: Access, operation: &str) -> Result<(), ServiceError> {
        if self.anonymous {
            return Ok(());
        }
        let Some(key) = presented else { return Err(ServiceError::Unauthenticated) };
        let d = digest(key);
        let mut granted: Option<Access> = None;
        for (k, a) in &self.digests {
            if same(k, &d) {
                granted = granted.max(Some(*a));
            }
        }
        match granted {
            None => Err(ServiceError::Unauthenticated),
            Some(a) if a >= needed => Ok(()),
            Some(_) => Err(ServiceError::PermissionDenied { operation: operation.to_string() }),
        }
    }
}

/// The API key of a request (HTTP, or gRPC metadata): `x-api-key`, or `Authorization: Bearer`.
pub fn request_key(headers: &axum::http::HeaderMap) -> Option<String> {
    let get = |name: &str| headers.get(name).and_then(|v| v.to_str().ok());
    key_from_headers(get("x-api-key"), get("authorization")).map(str::to_string)
}

/// The key in a header value: `x-api-key: K` or `authorization: Bearer K`.
pub fn key_from_headers<'a>(x_api_key: Option<&'a str>, authorization: Option<&'a str>) -> Option<&'a str> {
    x_api_key.map(str::trim).filter(|k| !k.is_empty()).or_else(|| {
        authorization.and_then(|a| a.trim().strip_prefix("Bearer ")).map(str::trim).filter(|k| !k.is_empty())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::ErrorKind;

    #[test]
    fn read_keys_read_write_keys_write_others_nothing() {
        let keys = Keys::new(vec![("w".repeat(16), Access::Write), ("r".repeat(16), Access::Read)]);
        let w = "w".repeat(16);
        let r = "r".repeat(16);
        assert!(keys.check(Some(&w), Access::Write, "CreateMap").is_ok());
        assert!(keys.check(Some(&r), Access::Read, "Localize").is_ok());
        assert_eq!(keys.check(Some(&r), Access::Write, "CreateMap").unwrap_err().kind(), ErrorKind::PermissionDenied);
        assert_eq!(keys.check(None, Access::Read, "Localize").unwrap_err().kind(), ErrorKind::Unauthenticated);
        assert_eq!(keys.check(Some("nope"), Access::Read, "Localize").unwrap_err().kind(), ErrorKind::Unauthenticated);
    }

    #[test]
    fn no_keys_means_open() {
        assert!(Keys::new(vec![]).check(None, Access::Write, "DeleteMap").is_ok());
    }

    #[test]
    fn bearer_or_header() {
        assert_eq!(key_from_headers(Some("k1"), Some("Bearer k2")), Some("k1"));
        assert_eq!(key_from_headers(None, Some("Bearer k2")), Some("k2"));
        assert_eq!(key_from_headers(None, Some("Basic k2")), None);
        assert_eq!(key_from_headers(Some(" "), None), None);
    }
}
