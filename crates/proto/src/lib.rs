//! The osrt gRPC protocol (`proto/osrt/v1/osrt.proto`), generated at build time with a
//! vendored protoc; the shared-token authentication both services use ([`auth`]); and the
//! one place where protocol messages become domain types ([`convert`]), rejecting missing
//! fields with typed errors.

pub mod auth;
pub mod convert;
pub mod tls;

/// Protocol version: peers of another version are refused at registration.
/// 2: the ring sends its chunks with the client-streaming `PushChunks`.
pub const PROTOCOL_VERSION: u32 = 2;

#[allow(clippy::all, missing_docs)]
pub mod v1 {
    tonic::include_proto!("osrt.v1");
}
