//! The collective server (`serve`): a mailbox behind the hand-framed `PushChunks` service,
//! token check and health service, and the HTTP/2 window and frame sizes both ends of a
//! collective connection use.

use crate::Mailbox;
use crate::chunk_wire::PushChunkServer;
use osrt_proto::MAX_CHUNK_FLOATS;
use osrt_proto::credentials::Credentials;
use std::sync::Arc;
use std::time::Duration;
use tonic::service::interceptor::InterceptedService;

/// HTTP/2 flow-control window of collective connections (several chunks in flight).
pub(crate) const WINDOW_BYTES: u32 = 16 << 20;

/// HTTP/2 frame size both ends advertise: a whole chunk fits one DATA frame instead of 64
/// frames of the default 16 KiB, each with its own header, poll and flow-control update.
pub(crate) const FRAME_BYTES: u32 = (MAX_CHUNK_FLOATS * 4 + 4096) as u32;

/// The longest a `PushChunks` call may last when its client names no deadline (ours
/// always do: the per-chunk timeout for every chunk of the all-reduce).
pub const CALL_LIMIT: Duration = Duration::from_secs(3600);

/// Serves a collective mailbox on `listener` until `shutdown` resolves, with the standard
/// gRPC health service beside it; every collective call must carry the job's token; with
/// TLS in `credentials`, connections are mutual TLS.
pub async fn serve(
    listener: tokio::net::TcpListener,
    mailbox: Arc<Mailbox>,
    credentials: Credentials,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), tonic::transport::Error> {
    let health_service = osrt_proto::server_setup::CheckOnly::server(&[
        osrt_proto::v1::collective_server::SERVICE_NAME,
    ]);
    let accept = move |chunk| mailbox.accept(chunk);
    let service = PushChunkServer::new(accept, MAX_CHUNK_FLOATS * 4 + 4096);
    credentials
        .server(CALL_LIMIT)?
        .initial_stream_window_size(WINDOW_BYTES)
        .initial_connection_window_size(WINDOW_BYTES)
        .max_frame_size(FRAME_BYTES)
        .add_service(health_service)
        .add_service(InterceptedService::new(
            service,
            credentials.check("collective"),
        ))
        .serve_with_incoming_shutdown(
            // Our own listener: its sockets need TCP_NODELAY here (the builder's setting
            // applies only to listeners it binds), or Nagle delays the small acks.
            tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true)),
            shutdown,
        )
        .await
}
