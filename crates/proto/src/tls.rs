//! Optional TLS (rustls) for both services. Three PEM files, named by environment
//! variables so a pod mounts them from a Secret:
//!
//! - `OSRT_TLS_CERT`, `OSRT_TLS_KEY`: this process's certificate chain and private key;
//! - `OSRT_TLS_CA`: the CA that signed every member's certificate.
//!
//! With TLS every connection is mutual: servers require a client certificate from the
//! CA, clients verify the server's against it, and addresses are `https://`. Set all
//! three or none; the job token is checked on top.

use std::path::PathBuf;
use thiserror::Error;
use tonic::transport::{Certificate, ClientTlsConfig, Identity, ServerTlsConfig};

pub const CERT_ENV: &str = "OSRT_TLS_CERT";
pub const KEY_ENV: &str = "OSRT_TLS_KEY";
pub const CA_ENV: &str = "OSRT_TLS_CA";

#[derive(Debug, Error)]
pub enum TlsError {
    #[error("TLS needs {CERT_ENV}, {KEY_ENV} and {CA_ENV} together; {missing} is not set")]
    Partial { missing: &'static str },
    #[error("TLS file {path}: {reason}")]
    File { path: String, reason: String },
}

/// This process's identity and the job's CA.
#[derive(Debug, Clone)]
pub struct Tls {
    identity: Identity,
    ca: Certificate,
}

fn read(var: &'static str) -> Result<Option<Vec<u8>>, TlsError> {
    let Some(path) = std::env::var_os(var).map(PathBuf::from) else {
        return Ok(None);
    };
    let bytes = std::fs::read(&path).map_err(|e| TlsError::File {
        path: path.display().to_string(),
        reason: e.to_string(),
    })?;
    if !bytes.starts_with(b"-----BEGIN") {
        return Err(TlsError::File {
            path: path.display().to_string(),
            reason: "not a PEM file".into(),
        });
    }
    Ok(Some(bytes))
}

impl Tls {
    /// `None` when none of the three variables is set.
    pub fn from_env() -> Result<Option<Self>, TlsError> {
        let (cert, key, ca) = (read(CERT_ENV)?, read(KEY_ENV)?, read(CA_ENV)?);
        match (cert, key, ca) {
            (None, None, None) => Ok(None),
            (Some(cert), Some(key), Some(ca)) => Ok(Some(Self {
                identity: Identity::from_pem(cert, key),
                ca: Certificate::from_pem(ca),
            })),
            (c, k, _) => Err(TlsError::Partial {
                missing: if c.is_none() {
                    CERT_ENV
                } else if k.is_none() {
                    KEY_ENV
                } else {
                    CA_ENV
                },
            }),
        }
    }

    /// Server side: present our certificate, require one from the CA.
    pub fn server(&self) -> ServerTlsConfig {
        ServerTlsConfig::new()
            .identity(self.identity.clone())
            .client_ca_root(self.ca.clone())
    }

    /// Client side: verify the server against the CA, present our certificate.
    pub fn client(&self) -> ClientTlsConfig {
        ClientTlsConfig::new()
            .ca_certificate(self.ca.clone())
            .identity(self.identity.clone())
    }
}
