//! A plaintext listener that answers the standard gRPC health service and nothing else,
//! for probes that cannot speak the services' mutual TLS: the kubelet's gRPC probe has no
//! TLS settings, so with TLS on, a pod's probes ask this port (`--health-listen`). It
//! carries no job data and takes no token.

use tokio::net::TcpListener;

/// The longest a call on the plaintext health port may last (a `Check` answers at once).
pub const PLAINTEXT_CALL_LIMIT: std::time::Duration = std::time::Duration::from_secs(10);

/// Answers `grpc.health.v1.Health/Check` for the whole server ("") with SERVING on
/// `listener` until `shutdown` resolves or the process ends: it proves the process's
/// runtime answers, as the health service on the main port does. Nothing else is served
/// (`Watch` is refused: [`crate::server_setup::CheckOnly`]).
pub async fn serve_plaintext(
    listener: TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), tonic::transport::Error> {
    crate::server_setup::builder(None, PLAINTEXT_CALL_LIMIT)?
        .add_service(crate::server_setup::CheckOnly::server(&[]))
        .serve_with_incoming_shutdown(
            tonic::transport::server::TcpIncoming::from(listener),
            shutdown,
        )
        .await
}

/// Binds `addr` and serves [`serve_plaintext`] on a task of its own for the rest of the
/// process; the bound address is returned (port 0: any free port).
pub async fn spawn_plaintext(addr: std::net::SocketAddr) -> std::io::Result<std::net::SocketAddr> {
    let listener = TcpListener::bind(addr).await?;
    let local = listener.local_addr()?;
    tokio::spawn(async move {
        if let Err(e) = serve_plaintext(listener, std::future::pending()).await {
            tracing::error!(error = %e, "the plaintext health listener stopped");
        }
    });
    Ok(local)
}
