//! What a member of a job presents and checks on every connection: the job's token
//! ([`crate::auth`]) and, where set, mutual TLS ([`crate::tls`]). One value, read once
//! from the environment, handed to every client and server a process opens (the
//! coordinator's service, a worker's link to it, the ring's collective service and its
//! connections to the next rank), so that none of them takes the two halves apart.

use crate::auth::{AttachToken, CheckToken, Token, TokenError};
use crate::tls::{Tls, TlsError};
use std::time::Duration;
use thiserror::Error;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::transport::{Endpoint, Server};

#[derive(Debug, Error)]
pub enum CredentialsError {
    #[error(transparent)]
    Token(#[from] TokenError),
    #[error(transparent)]
    Tls(#[from] TlsError),
}

/// The job's token and this process's TLS identity (none: plaintext).
#[derive(Debug, Clone)]
pub struct Credentials {
    token: Token,
    /// `Bearer <token>`, made once: the ring puts it on every chunk stream it opens.
    authorization: MetadataValue<Ascii>,
    tls: Option<Tls>,
}

impl Credentials {
    pub fn new(token: Token, tls: Option<Tls>) -> Self {
        Self {
            authorization: token.header(),
            token,
            tls,
        }
    }

    /// The token from `OSRT_TOKEN` or `OSRT_TOKEN_FILE`, TLS from `OSRT_TLS_CERT`,
    /// `OSRT_TLS_KEY` and `OSRT_TLS_CA` (all three or none).
    pub fn from_env() -> Result<Self, CredentialsError> {
        Ok(Self::new(Token::from_env()?, Tls::from_env()?))
    }

    pub fn token(&self) -> &Token {
        &self.token
    }

    /// The `authorization` value every call carries (`Bearer <token>`).
    pub fn authorization(&self) -> &MetadataValue<Ascii> {
        &self.authorization
    }

    pub fn tls(&self) -> Option<&Tls> {
        self.tls.as_ref()
    }

    /// `https` with TLS, else `http`: the scheme of every member's address.
    pub fn scheme(&self) -> &'static str {
        match self.tls {
            Some(_) => "https",
            None => "http",
        }
    }

    /// A client endpoint for `addr`, verifying the server and presenting this process's
    /// certificate where TLS is set; the caller adds its own timeouts and windows.
    pub fn endpoint(&self, addr: &str) -> Result<Endpoint, tonic::transport::Error> {
        let endpoint = Endpoint::from_shared(addr.to_string())?;
        match &self.tls {
            Some(tls) => endpoint.tls_config(tls.client()),
            None => Ok(endpoint),
        }
    }

    /// The client interceptor that puts the token on every call.
    pub fn attach(&self) -> AttachToken {
        AttachToken(self.token.clone())
    }

    /// The server interceptor that refuses calls to `service` without the token.
    pub fn check(&self, service: &'static str) -> CheckToken {
        CheckToken::new(self.token.clone(), service)
    }

    /// A server builder with the settings every osrt server shares
    /// ([`crate::server_setup::builder`]), requiring client certificates where TLS is set.
    pub fn server(&self, call_limit: Duration) -> Result<Server, tonic::transport::Error> {
        crate::server_setup::builder(self.tls.as_ref(), call_limit)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::Request;
    use tonic::service::Interceptor;

    /// The interceptors of one value agree with each other and refuse another job's; the
    /// scheme and endpoint follow the TLS setting; a bad address is an error, not a panic.
    #[test]
    fn one_value_makes_both_ends() {
        let a = Credentials::new(Token::generate(), None);
        let b = Credentials::new(Token::generate(), None);
        let req = a.attach().call(Request::new(())).unwrap();
        assert!(a.check("test").call(req).is_ok());
        let req = b.attach().call(Request::new(())).unwrap();
        let e = a.check("test").call(req).unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated);
        assert_eq!(a.scheme(), "http");
        assert!(a.tls().is_none());
        assert!(a.endpoint("http://127.0.0.1:7070").is_ok());
        assert!(a.endpoint("not a uri").is_err());
        assert_eq!(a.token().as_str().len(), 32);
        assert_eq!(a.authorization(), &a.token().header());
    }
}
