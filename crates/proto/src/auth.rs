//! The job's shared token. Every call carries `authorization: Bearer <token>`; servers
//! refuse a call without it, or with another job's, as `unauthenticated` and log it.
//!
//! The token comes from `OSRT_TOKEN`, or from a file named by `OSRT_TOKEN_FILE` (a mounted
//! Kubernetes Secret), or is generated per local run by the launcher.

use rand::Rng;
use std::sync::Arc;
use thiserror::Error;
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::{Request, Status};

pub const TOKEN_ENV: &str = "OSRT_TOKEN";
pub const TOKEN_FILE_ENV: &str = "OSRT_TOKEN_FILE";

#[derive(Debug, Error)]
pub enum TokenError {
    #[error(
        "no job token: set {TOKEN_ENV}, or {TOKEN_FILE_ENV} to a file holding it (the launcher generates one for local runs)"
    )]
    Missing,
    #[error("token file {path}: {reason}")]
    File { path: String, reason: String },
    #[error("the job token must be 16 to 256 visible ASCII characters")]
    Invalid,
}

/// A job's shared secret.
#[derive(Clone)]
pub struct Token(Arc<str>);

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(…)")
    }
}

impl Token {
    pub fn new(s: &str) -> Result<Self, TokenError> {
        let s = s.trim();
        let ok = (16..=256).contains(&s.len()) && s.bytes().all(|b| b.is_ascii_graphic());
        if !ok {
            return Err(TokenError::Invalid);
        }
        Ok(Self(s.into()))
    }

    /// 32 random hex characters.
    pub fn generate() -> Self {
        let mut rng = rand::rng();
        let s: String = (0..32)
            .map(|_| char::from_digit(rng.random_range(0..16), 16).expect("hex digit"))
            .collect();
        Self(s.into())
    }

    /// From `OSRT_TOKEN` or the file named by `OSRT_TOKEN_FILE`.
    pub fn from_env() -> Result<Self, TokenError> {
        if let Ok(t) = std::env::var(TOKEN_ENV) {
            return Self::new(&t);
        }
        if let Ok(path) = std::env::var(TOKEN_FILE_ENV) {
            let text = std::fs::read_to_string(&path).map_err(|e| TokenError::File {
                path: path.clone(),
                reason: e.to_string(),
            })?;
            return Self::new(&text);
        }
        Err(TokenError::Missing)
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// The `authorization` value every call carries: `Bearer <token>`.
    pub fn header(&self) -> MetadataValue<tonic::metadata::Ascii> {
        format!("Bearer {}", self.0)
            .parse()
            .expect("a validated token is a valid header value")
    }

    /// Compares without an early exit, so timing does not reveal a prefix.
    fn matches(&self, presented: &[u8]) -> bool {
        let want = format!("Bearer {}", self.0);
        let want = want.as_bytes();
        if presented.len() != want.len() {
            return false;
        }
        presented
            .iter()
            .zip(want)
            .fold(0u8, |acc, (a, b)| acc | (a ^ b))
            == 0
    }
}

/// Server side: refuses calls without the job's token.
#[derive(Clone)]
pub struct CheckToken {
    token: Token,
    service: &'static str,
}

impl CheckToken {
    pub fn new(token: Token, service: &'static str) -> Self {
        Self { token, service }
    }
}

impl Interceptor for CheckToken {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        match req.metadata().get("authorization") {
            Some(v) if self.token.matches(v.as_bytes()) => Ok(req),
            got => {
                let peer = req
                    .remote_addr()
                    .map_or("unknown peer".to_string(), |a| a.to_string());
                let why = if got.is_some() {
                    "wrong token"
                } else {
                    "no token"
                };
                tracing::warn!(service = self.service, %peer, why, "call refused");
                Err(Status::unauthenticated(format!(
                    "{why}: calls to this job need its token"
                )))
            }
        }
    }
}

/// Client side: attaches the job's token to every call.
#[derive(Clone)]
pub struct AttachToken(pub Token);

impl Interceptor for AttachToken {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        req.metadata_mut().insert("authorization", self.0.header());
        Ok(req)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_are_validated_and_compared_whole() {
        assert!(Token::new("short").is_err());
        assert!(Token::new("has a space in the middle of it").is_err());
        let t = Token::new("0123456789abcdef0123").unwrap();
        assert!(t.matches(b"Bearer 0123456789abcdef0123"));
        assert!(!t.matches(b"Bearer 0123456789abcdef012"));
        assert!(!t.matches(b"Bearer 0123456789abcdef0124"));
        assert!(!t.matches(b"0123456789abcdef0123"));
        let g = Token::generate();
        assert_eq!(g.as_str().len(), 32);
        assert!(Token::new(g.as_str()).is_ok());
    }

    #[test]
    fn interceptors_agree() {
        let t = Token::generate();
        let req = AttachToken(t.clone()).call(Request::new(())).unwrap();
        assert!(CheckToken::new(t, "test").call(req).is_ok());
        let bare = Request::new(());
        let e = CheckToken::new(Token::generate(), "test")
            .call(bare)
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated);
        let other = AttachToken(Token::generate())
            .call(Request::new(()))
            .unwrap();
        let e = CheckToken::new(Token::generate(), "test")
            .call(other)
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated);
    }
}
