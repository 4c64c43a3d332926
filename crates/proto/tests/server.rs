//! Every osrt server's shared limits, checked from outside as a client meets them: the
//! stream limit a connection announces, the server's deadline for a call that names none,
//! and a health service that answers `Check` and refuses `Watch` (on the main ports and
//! the plaintext one).

use osrt_proto::server_setup::{CheckOnly, MAX_STREAMS_PER_CONNECTION, builder};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::health_server::{Health, HealthServer};
use tonic_health::pb::{HealthCheckRequest, HealthCheckResponse};

/// Serves `service` with [`builder`]'s settings on a free port; returns its address.
async fn serve<S>(service: S, call_limit: Duration) -> std::net::SocketAddr
where
    S: tonic::codegen::Service<
            http::Request<tonic::body::Body>,
            Response = http::Response<tonic::body::Body>,
            Error = std::convert::Infallible,
        > + tonic::server::NamedService
        + Clone
        + Send
        + Sync
        + 'static,
    S::Future: Send + 'static,
{
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(
        builder(None, call_limit)
            .unwrap()
            .add_service(service)
            .serve_with_incoming(tonic::transport::server::TcpIncoming::from(listener)),
    );
    addr
}

async fn client(addr: std::net::SocketAddr) -> HealthClient<tonic::transport::Channel> {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    HealthClient::new(channel)
}

fn ask(service: &str) -> HealthCheckRequest {
    HealthCheckRequest {
        service: service.into(),
    }
}

/// The HTTP/2 settings a server sends first, read off the wire (`(id, value)` pairs).
async fn server_settings(addr: std::net::SocketAddr) -> Vec<(u16, u32)> {
    let mut tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    tcp.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n")
        .await
        .unwrap();
    // An empty SETTINGS frame: length 0, type 4, no flags, stream 0.
    tcp.write_all(&[0, 0, 0, 4, 0, 0, 0, 0, 0]).await.unwrap();
    loop {
        let mut head = [0u8; 9];
        tcp.read_exact(&mut head).await.unwrap();
        let len = u32::from_be_bytes([0, head[0], head[1], head[2]]) as usize;
        let mut payload = vec![0u8; len];
        tcp.read_exact(&mut payload).await.unwrap();
        let (kind, ack) = (head[3], head[4] & 1 == 1);
        if kind == 4 && !ack {
            return payload
                .chunks_exact(6)
                .map(|e| {
                    (
                        u16::from_be_bytes([e[0], e[1]]),
                        u32::from_be_bytes([e[2], e[3], e[4], e[5]]),
                    )
                })
                .collect();
        }
    }
}

#[tokio::test]
async fn a_connection_carries_a_bounded_number_of_calls() {
    let addr = serve(CheckOnly::server(&[]), Duration::from_secs(10)).await;
    let settings = server_settings(addr).await;
    // SETTINGS_MAX_CONCURRENT_STREAMS is setting 0x3.
    assert!(
        settings.contains(&(3, MAX_STREAMS_PER_CONNECTION)),
        "{settings:?}"
    );
}

#[tokio::test]
async fn the_health_service_answers_check_and_refuses_watch() {
    let addr = serve(
        CheckOnly::server(&["osrt.v1.Collective"]),
        Duration::from_secs(10),
    )
    .await;
    let mut c = client(addr).await;
    for name in ["", "osrt.v1.Collective"] {
        let r = c.check(ask(name)).await.unwrap().into_inner();
        assert_eq!(r.status, ServingStatus::Serving as i32, "`{name}`");
    }
    let e = c.check(ask("osrt.v1.Other")).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::NotFound, "{e}");
    let e = c.watch(ask("")).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::Unimplemented, "{e}");
    // The plaintext health port is the same service.
    let plain = osrt_proto::health::spawn_plaintext("127.0.0.1:0".parse().unwrap())
        .await
        .unwrap();
    let mut c = client(plain).await;
    let r = c.check(ask("")).await.unwrap().into_inner();
    assert_eq!(r.status, ServingStatus::Serving as i32);
    let e = c.watch(ask("")).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::Unimplemented, "{e}");
}

/// A health service whose `Check` never answers: a call held open.
#[derive(Clone)]
struct Hangs;

#[tonic::async_trait]
impl Health for Hangs {
    async fn check(
        &self,
        _: tonic::Request<HealthCheckRequest>,
    ) -> Result<tonic::Response<HealthCheckResponse>, tonic::Status> {
        std::future::pending().await
    }

    type WatchStream =
        tonic::codegen::tokio_stream::Empty<Result<HealthCheckResponse, tonic::Status>>;

    async fn watch(
        &self,
        _: tonic::Request<HealthCheckRequest>,
    ) -> Result<tonic::Response<Self::WatchStream>, tonic::Status> {
        std::future::pending().await
    }
}

#[tokio::test]
async fn a_call_without_a_deadline_gets_the_servers() {
    let addr = serve(HealthServer::new(Hangs), Duration::from_millis(300)).await;
    let mut c = client(addr).await;
    let t = Instant::now();
    let e = tokio::time::timeout(Duration::from_secs(10), c.check(ask("")))
        .await
        .expect("the server ended the call")
        .unwrap_err();
    assert!(t.elapsed() < Duration::from_secs(3), "{:?}", t.elapsed());
    assert_ne!(e.code(), tonic::Code::Ok, "{e}");
}
