//! The osrt gRPC protocol (`proto/osrt/v1/osrt.proto`), generated at build time with a
//! vendored protoc. Hand-written conversions to domain types live with the services that
//! use them and reject missing fields with typed errors.

/// Protocol version: peers of another version are refused.
pub const PROTOCOL_VERSION: u32 = 1;

#[allow(clippy::all, missing_docs)]
pub mod v1 {
    tonic::include_proto!("osrt.v1");
}
