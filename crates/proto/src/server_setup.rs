//! How every osrt gRPC server is set up — the coordinator's, a worker's collective, the
//! plaintext health port — so that none of them can be held open without bound: HTTP/2
//! pings drop half-open connections, a connection carries at most
//! [`MAX_STREAMS_PER_CONNECTION`] calls at once, a call that names no deadline gets the
//! server's, and the health service answers `Check` only (a `Watch` stream would stay
//! open for as long as its client likes, and the health ports take no token).

use crate::tls::Tls;
use std::time::Duration;
use tonic::transport::Server;
use tonic::{Request, Response, Status};
use tonic_health::pb::health_server::{Health, HealthServer};
use tonic_health::pb::{HealthCheckRequest, HealthCheckResponse, health_check_response};

/// Calls one connection may carry at once: a worker's calls to its coordinator (a
/// heartbeat, a plan's long poll, a progress report, a checkpoint report) and a ring's one
/// `PushChunks` call per all-reduce need a handful.
pub const MAX_STREAMS_PER_CONNECTION: u32 = 32;

/// A server builder with the settings every osrt server shares: `call_limit` is the
/// longest any call may last when its client names no shorter deadline (tonic applies
/// the smaller of it and the client's `grpc-timeout`).
pub fn builder(tls: Option<&Tls>, call_limit: Duration) -> Result<Server, tonic::transport::Error> {
    let mut builder = Server::builder();
    if let Some(tls) = tls {
        builder = builder.tls_config(tls.server())?;
    }
    Ok(builder
        .http2_keepalive_interval(Some(crate::KEEP_ALIVE_INTERVAL))
        .http2_keepalive_timeout(Some(crate::KEEP_ALIVE_TIMEOUT))
        .max_concurrent_streams(MAX_STREAMS_PER_CONNECTION)
        .timeout(call_limit)
        .tcp_nodelay(true))
}

/// The standard gRPC health service, `Check` only: the whole server (`""`) and each of
/// `services` are SERVING, any other name NOT_FOUND. `Watch` answers UNIMPLEMENTED,
/// which the protocol tells clients to take as "not supported" (probes use `Check`).
#[derive(Debug, Clone)]
pub struct CheckOnly {
    services: Vec<String>,
}

impl CheckOnly {
    pub fn server(services: &[&str]) -> HealthServer<Self> {
        HealthServer::new(Self {
            services: services.iter().map(|s| s.to_string()).collect(),
        })
    }
}

#[tonic::async_trait]
impl Health for CheckOnly {
    async fn check(
        &self,
        request: Request<HealthCheckRequest>,
    ) -> Result<Response<HealthCheckResponse>, Status> {
        let name = request.into_inner().service;
        if !name.is_empty() && !self.services.contains(&name) {
            return Err(Status::not_found(format!("no service `{name}` here")));
        }
        Ok(Response::new(HealthCheckResponse {
            status: health_check_response::ServingStatus::Serving as i32,
        }))
    }

    type WatchStream = tonic::codegen::tokio_stream::Empty<Result<HealthCheckResponse, Status>>;

    async fn watch(
        &self,
        _request: Request<HealthCheckRequest>,
    ) -> Result<Response<Self::WatchStream>, Status> {
        Err(Status::unimplemented("Watch is not served here; use Check"))
    }
}
