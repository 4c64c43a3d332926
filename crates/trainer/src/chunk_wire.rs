//! `PushChunk` on the wire without tonic's codec buffers.
//!
//! A gradient chunk is up to 1 MiB of floats behind ~60 bytes of gRPC framing and protobuf
//! keys. tonic's codec copies every message into its encode buffer on the way out and
//! every received DATA frame into its decode buffer on the way in; on 2 busy cores those
//! two copies cost about as much as the kernel's own socket copies (perf of `osrt bench
//! allreduce`). This module speaks exactly the same bytes — a standard gRPC unary call
//! `/osrt.v1.Collective/PushChunk` whose message is a protobuf `Chunk` — but passes the
//! payload through as the `Bytes` it already is: the client sends the framing and the
//! payload as two body frames, the server slices the payload out of the HTTP/2 DATA frame
//! it arrived in (copying only when the payload was split across frames).
//!
//! Any gRPC client or server of `osrt.v1.Collective` interoperates with it; the tests call
//! the server with tonic's generated client and check the bytes against prost's encoding.

use bytes::{BufMut, Bytes, BytesMut};
use futures::future::BoxFuture;
use http_body::Frame;
use http_body_util::{BodyExt, StreamBody};
use osrt_proto::v1::{Chunk, ChunkTag};
use prost::Message;
use std::collections::VecDeque;
use std::convert::Infallible;
use std::task::{Context, Poll};
use std::time::Duration;
use tonic::Status;
use tonic::body::Body;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::transport::Channel;
use tower_service::Service;

/// The method's HTTP/2 path.
pub const PATH: &str = "/osrt.v1.Collective/PushChunk";

/// Protobuf keys of `Chunk`'s fields: field number << 3 | wire type 2 (length-delimited).
const TAG_KEY: u8 = (1 << 3) | 2;
const DATA_KEY: u8 = (2 << 3) | 2;

/// The gRPC request body of a `PushChunk`: the 5-byte message prefix, the tag and the
/// payload's key and length in one small buffer, then the payload itself, uncopied.
/// Together they are byte for byte what prost and tonic would send for
/// `Chunk { tag, data }`.
pub fn encode_request(tag: &ChunkTag, data: Bytes) -> [Bytes; 2] {
    let tag_len = tag.encoded_len();
    let framing = 1
        + prost::length_delimiter_len(tag_len)
        + tag_len
        + 1
        + prost::length_delimiter_len(data.len());
    let mut head = BytesMut::with_capacity(5 + framing);
    head.put_u8(0); // not compressed
    head.put_u32((framing + data.len()) as u32);
    head.put_u8(TAG_KEY);
    // BytesMut grows: encoding into it cannot fail.
    prost::encode_length_delimiter(tag_len, &mut head).expect("growable buffer");
    tag.encode(&mut head).expect("growable buffer");
    head.put_u8(DATA_KEY);
    prost::encode_length_delimiter(data.len(), &mut head).expect("growable buffer");
    [head.freeze(), data]
}

/// A message received as a list of frames, read front to back across frame boundaries.
struct Frames {
    parts: VecDeque<Bytes>,
    remaining: usize,
}

impl Frames {
    fn new(parts: Vec<Bytes>) -> Self {
        let remaining = parts.iter().map(Bytes::len).sum();
        Self {
            parts: parts.into(),
            remaining,
        }
    }

    /// The next `n` bytes: a slice of one frame when they lie in one, else a copy.
    fn take(&mut self, n: usize) -> Option<Bytes> {
        if n > self.remaining {
            return None;
        }
        self.remaining -= n;
        while self.parts.front().is_some_and(Bytes::is_empty) {
            self.parts.pop_front();
        }
        match self.parts.front_mut() {
            None => return Some(Bytes::new()),
            Some(front) if front.len() >= n => return Some(front.split_to(n)),
            Some(_) => {}
        }
        let mut out = BytesMut::with_capacity(n);
        while out.len() < n {
            let front = self
                .parts
                .front_mut()
                .expect("remaining counts these bytes");
            let k = (n - out.len()).min(front.len());
            out.extend_from_slice(&front.split_to(k));
            if front.is_empty() {
                self.parts.pop_front();
            }
        }
        Some(out.freeze())
    }

    fn varint(&mut self) -> Option<u64> {
        let mut v = 0u64;
        for i in 0..10 {
            let b = self.take(1)?[0];
            v |= u64::from(b & 0x7f) << (7 * i);
            if b < 0x80 {
                return Some(v);
            }
        }
        None
    }

    fn length(&mut self) -> Option<usize> {
        usize::try_from(self.varint()?).ok()
    }
}

fn malformed(what: impl std::fmt::Display) -> Status {
    Status::invalid_argument(format!("malformed PushChunk request: {what}"))
}

/// Parses a `PushChunk` request body (the frames of one unary call) into its `Chunk`; the
/// payload stays a slice of the frame it arrived in. Unknown fields are skipped, as
/// protobuf requires; anything else that does not parse is `invalid_argument`.
pub fn decode_request(parts: Vec<Bytes>) -> Result<Chunk, Status> {
    let mut f = Frames::new(parts);
    let prefix = f
        .take(5)
        .ok_or_else(|| malformed("shorter than the 5-byte gRPC message prefix"))?;
    if prefix[0] != 0 {
        return Err(Status::unimplemented(
            "compressed PushChunk messages are not supported",
        ));
    }
    let len = u32::from_be_bytes([prefix[1], prefix[2], prefix[3], prefix[4]]) as usize;
    if len != f.remaining {
        return Err(malformed(format!(
            "the prefix announces {len} bytes, the body holds {} (one message per call)",
            f.remaining
        )));
    }
    let mut chunk = Chunk::default();
    while f.remaining > 0 {
        let key = f.varint().ok_or_else(|| malformed("truncated field key"))?;
        let (field, wire) = (key >> 3, key & 7);
        let truncated = || malformed(format!("field {field} truncated"));
        match (field, wire) {
            (1 | 2, 2) => {
                let n = f.length().ok_or_else(truncated)?;
                let bytes = f.take(n).ok_or_else(truncated)?;
                if field == 1 {
                    // Repeated occurrences of a message field merge (protobuf's rule).
                    chunk
                        .tag
                        .get_or_insert_default()
                        .merge(bytes)
                        .map_err(|e| malformed(format!("tag: {e}")))?;
                } else {
                    chunk.data = bytes;
                }
            }
            (1 | 2, _) => {
                return Err(malformed(format!("field {field} has wire type {wire}")));
            }
            (_, 0) => {
                f.varint().ok_or_else(truncated)?;
            }
            (_, 1) => {
                f.take(8).ok_or_else(truncated)?;
            }
            (_, 2) => {
                let n = f.length().ok_or_else(truncated)?;
                f.take(n).ok_or_else(truncated)?;
            }
            (_, 5) => {
                f.take(4).ok_or_else(truncated)?;
            }
            _ => return Err(malformed(format!("unknown wire type {wire}"))),
        }
    }
    Ok(chunk)
}

/// The data frames of a request body, refusing bodies over `limit` bytes.
async fn read_body(mut body: Body, limit: usize) -> Result<Vec<Bytes>, Status> {
    let mut parts = Vec::new();
    let mut n = 0;
    while let Some(frame) = body.frame().await {
        if let Ok(data) = frame?.into_data() {
            n += data.len();
            if n > limit {
                return Err(Status::resource_exhausted(format!(
                    "PushChunk request over {limit} bytes"
                )));
            }
            parts.push(data);
        }
    }
    Ok(parts)
}

/// A body of the given frames.
fn body_of(frames: Vec<Frame<Bytes>>) -> Body {
    Body::new(StreamBody::new(futures::stream::iter(
        frames.into_iter().map(Ok::<_, Infallible>),
    )))
}

/// The response to an accepted chunk: an empty `ChunkAck` and `grpc-status: 0`.
fn ok_response() -> http::Response<Body> {
    let mut trailers = http::HeaderMap::new();
    trailers.insert(Status::GRPC_STATUS, http::HeaderValue::from_static("0"));
    let mut response = http::Response::new(body_of(vec![
        Frame::data(Bytes::from_static(&[0, 0, 0, 0, 0])),
        Frame::trailers(trailers),
    ]));
    response.headers_mut().insert(
        http::header::CONTENT_TYPE,
        http::HeaderValue::from_static("application/grpc"),
    );
    response
}

/// Server side: the `osrt.v1.Collective` service, handing each decoded chunk to
/// `accept` (whose error becomes the call's status).
#[derive(Clone)]
pub struct PushChunkServer<A> {
    accept: A,
    limit: usize,
}

impl<A> PushChunkServer<A>
where
    A: Fn(Chunk) -> Result<(), Status> + Clone + Send + Sync + 'static,
{
    /// Requests over `limit` bytes are refused before they are parsed.
    pub fn new(accept: A, limit: usize) -> Self {
        Self { accept, limit }
    }
}

impl<A> tonic::server::NamedService for PushChunkServer<A> {
    const NAME: &'static str = osrt_proto::v1::collective_server::SERVICE_NAME;
}

impl<A> Service<http::Request<Body>> for PushChunkServer<A>
where
    A: Fn(Chunk) -> Result<(), Status> + Clone + Send + Sync + 'static,
{
    type Response = http::Response<Body>;
    type Error = Infallible;
    type Future = BoxFuture<'static, Result<Self::Response, Infallible>>;

    fn poll_ready(&mut self, _cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        Poll::Ready(Ok(()))
    }

    fn call(&mut self, req: http::Request<Body>) -> Self::Future {
        let (accept, limit) = (self.accept.clone(), self.limit);
        Box::pin(async move {
            if req.uri().path() != PATH {
                let status = Status::unimplemented(format!("no method {}", req.uri().path()));
                return Ok(status.into_http());
            }
            let result = async {
                let parts = read_body(req.into_body(), limit).await?;
                accept(decode_request(parts)?)
            }
            .await;
            Ok(match result {
                Ok(()) => ok_response(),
                Err(status) => {
                    tracing::warn!(code = ?status.code(), message = status.message(), "chunk rejected");
                    status.into_http()
                }
            })
        })
    }
}

/// Client side: one `PushChunk` call on `channel`, carrying `auth` as its
/// `authorization` header, with `timeout` as its deadline.
pub async fn push(
    mut channel: Channel,
    auth: &MetadataValue<Ascii>,
    timeout: Duration,
    tag: &ChunkTag,
    data: Bytes,
) -> Result<(), Status> {
    let [head, data] = encode_request(tag, data);
    let auth = http::HeaderValue::from_bytes(auth.as_encoded_bytes())
        .map_err(|e| Status::internal(format!("authorization header: {e}")))?;
    // grpc-timeout allows at most 8 digits.
    let millis = timeout.as_millis().clamp(1, 99_999_999);
    let request = http::Request::builder()
        .method(http::Method::POST)
        .uri(PATH)
        .header(http::header::CONTENT_TYPE, "application/grpc")
        .header(http::header::TE, "trailers")
        .header(http::header::AUTHORIZATION, auth)
        .header("grpc-timeout", format!("{millis}m"))
        .body(body_of(vec![Frame::data(head), Frame::data(data)]))
        .map_err(|e| Status::internal(format!("PushChunk request: {e}")))?;
    let transport = |e: tonic::transport::Error| Status::from_error(Box::new(e));
    futures::future::poll_fn(|cx| channel.poll_ready(cx))
        .await
        .map_err(transport)?;
    let response = tokio::time::timeout(timeout, channel.call(request))
        .await
        .map_err(|_| Status::deadline_exceeded(format!("no response within {timeout:?}")))?
        .map_err(transport)?;
    if response.status() != http::StatusCode::OK {
        return Err(Status::unknown(format!(
            "PushChunk answered HTTP {}",
            response.status()
        )));
    }
    // A trailers-only response carries the status in its headers.
    if let Some(status) = Status::from_header_map(response.headers()) {
        return result_of(status);
    }
    let collected = tokio::time::timeout(timeout, response.into_body().collect())
        .await
        .map_err(|_| Status::deadline_exceeded(format!("no response within {timeout:?}")))??;
    match collected.trailers().and_then(Status::from_header_map) {
        Some(status) => result_of(status),
        None => Err(Status::internal("PushChunk response without grpc-status")),
    }
}

fn result_of(status: Status) -> Result<(), Status> {
    if status.code() == tonic::Code::Ok {
        Ok(())
    } else {
        Err(status)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tag() -> ChunkTag {
        ChunkTag {
            job: "job-1".into(),
            generation: 3,
            step: 300,
            bucket: 2,
            phase: 1,
            round: 0,
            chunk: 129,
            from_rank: 1,
        }
    }

    /// What prost (and so tonic) sends for a chunk, gRPC prefix included.
    fn prost_body(chunk: &Chunk) -> Vec<u8> {
        let msg = chunk.encode_to_vec();
        let mut out = vec![0u8];
        out.extend((msg.len() as u32).to_be_bytes());
        out.extend(msg);
        out
    }

    #[test]
    fn request_bytes_are_prosts() {
        for n in [1usize, 127, 128, 300, 1 << 14, (1 << 20) + 4] {
            let data = Bytes::from((0..n).map(|i| (i * 7) as u8).collect::<Vec<u8>>());
            let [head, payload] = encode_request(&tag(), data.clone());
            assert_eq!(payload.as_ptr(), data.as_ptr(), "the payload is not copied");
            let ours = [head.as_ref(), payload.as_ref()].concat();
            let chunk = Chunk {
                tag: Some(tag()),
                data,
            };
            assert_eq!(ours, prost_body(&chunk), "{n} bytes");
        }
    }

    /// Decoding gives prost's `Chunk` back however the body was cut into frames, and a
    /// payload that arrived in one frame is a slice of it, not a copy.
    #[test]
    fn decoding_any_framing_gives_the_chunk_back() {
        let data = Bytes::from((0..1000u32).map(|i| i as u8).collect::<Vec<u8>>());
        let chunk = Chunk {
            tag: Some(tag()),
            data: data.clone(),
        };
        let whole = Bytes::from(prost_body(&chunk));
        for cut in [1usize, 3, 5, 7, 40, 63, 64, 500, whole.len() - 1] {
            let parts = vec![whole.slice(..cut), whole.slice(cut..)];
            assert_eq!(decode_request(parts).unwrap(), chunk, "cut at {cut}");
        }
        let bytewise: Vec<Bytes> = (0..whole.len()).map(|i| whole.slice(i..i + 1)).collect();
        assert_eq!(decode_request(bytewise).unwrap(), chunk);
        let [head, payload] = encode_request(&tag(), data);
        let decoded = decode_request(vec![head, payload.clone()]).unwrap();
        assert_eq!(decoded.data.as_ptr(), payload.as_ptr());
    }

    #[test]
    fn unknown_fields_are_skipped() {
        let mut msg = Chunk {
            tag: Some(tag()),
            data: Bytes::from_static(b"abcd"),
        }
        .encode_to_vec();
        // field 9 varint 300, field 10 fixed64, field 11 bytes, field 12 fixed32
        msg.extend([9 << 3, 0xac, 0x02]);
        msg.extend([(10 << 3) | 1, 1, 2, 3, 4, 5, 6, 7, 8]);
        msg.extend([(11 << 3) | 2, 2, 0xff, 0xfe]);
        msg.extend([(12 << 3) | 5, 1, 2, 3, 4]);
        let mut body = vec![0u8];
        body.extend((msg.len() as u32).to_be_bytes());
        body.extend(msg);
        let c = decode_request(vec![Bytes::from(body)]).unwrap();
        assert_eq!(c.data, Bytes::from_static(b"abcd"));
        assert_eq!(c.tag, Some(tag()));
    }

    #[test]
    fn malformed_bodies_are_invalid_argument() {
        let good = prost_body(&Chunk {
            tag: Some(tag()),
            data: Bytes::from_static(b"abcdefgh"),
        });
        let cases: Vec<(&str, Vec<u8>)> = vec![
            ("empty", vec![]),
            ("prefix only, short", vec![0, 0, 0]),
            ("length too long", {
                let mut b = good.clone();
                b[4] += 1;
                b
            }),
            ("length too short", {
                let mut b = good.clone();
                b[4] -= 1;
                b
            }),
            ("truncated payload", {
                let mut b = good[..good.len() - 3].to_vec();
                let n = (b.len() - 5) as u32;
                b[1..5].copy_from_slice(&n.to_be_bytes());
                b
            }),
            ("tag as varint", vec![0, 0, 0, 0, 2, 1 << 3, 5]),
            ("wire type 7", vec![0, 0, 0, 0, 2, (5 << 3) | 7, 0]),
            ("endless varint", vec![0, 0, 0, 0, 3, 9 << 3, 0xff, 0xff]),
            ("garbage tag", vec![0, 0, 0, 0, 4, TAG_KEY, 2, 0xff, 0xff]),
        ];
        for (what, body) in cases {
            let e = decode_request(vec![Bytes::from(body)]).unwrap_err();
            assert_eq!(e.code(), tonic::Code::InvalidArgument, "{what}: {e}");
        }
        let mut compressed = good;
        compressed[0] = 1;
        let e = decode_request(vec![Bytes::from(compressed)]).unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unimplemented);
    }
}
