//! The osrt gRPC protocol (`proto/osrt/v1/osrt.proto`), generated at build time with a
//! vendored protoc; the shared-token authentication both services use ([`auth`]), held
//! with the optional TLS in one value ([`credentials`]); and the one place where protocol
//! messages become domain types ([`convert`]), rejecting missing fields with typed errors.

pub mod auth;
pub mod convert;
pub mod credentials;
pub mod health;
pub mod server_setup;
pub mod tls;

/// The stop of a server that the coordinator, a worker or the local launcher runs:
/// [`Shutdown::new`] gives the trigger and the future the server's graceful shutdown
/// awaits. Triggering the stop, or dropping the trigger, resolves the future.
pub struct Shutdown(Option<tokio::sync::oneshot::Sender<()>>);

impl Shutdown {
    pub fn new() -> (Self, impl std::future::Future<Output = ()> + Send + 'static) {
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        (Self(Some(tx)), async move {
            let _ = rx.await;
        })
    }

    /// Stops the server (once; later calls do nothing).
    pub fn trigger(&mut self) {
        if let Some(tx) = self.0.take() {
            let _ = tx.send(());
        }
    }
}

/// Protocol version: peers of another version are refused at registration. Version 3:
/// the ring sends its chunks with the client-streaming `PushChunks` only.
pub const PROTOCOL_VERSION: u32 = 3;

/// Metrics records one progress report may carry: the coordinator refuses more, and a
/// worker holds at most as many unsent.
pub const MAX_RECORDS_PER_REPORT: usize = 10_000;

/// Largest chunk payload of the collective: 1 MiB of f32.
pub const MAX_CHUNK_FLOATS: usize = 1 << 18;

/// HTTP/2 pings on every connection of both services, both ways: a peer that answers
/// none within the timeout is gone (a half-open TCP connection otherwise looks alive
/// forever).
pub const KEEP_ALIVE_INTERVAL: std::time::Duration = std::time::Duration::from_secs(5);
pub const KEEP_ALIVE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);

#[allow(clippy::all, missing_docs)]
pub mod v1 {
    tonic::include_proto!("osrt.v1");
}
