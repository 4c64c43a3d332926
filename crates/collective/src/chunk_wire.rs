//! The collective's chunk traffic on the wire without tonic's codec buffers.
//!
//! A gradient chunk is up to 1 MiB of floats behind ~60 bytes of gRPC framing and protobuf
//! keys. tonic's codec copies every message into its encode buffer on the way out and
//! every received DATA frame into its decode buffer on the way in; on 2 busy cores those
//! two copies cost about as much as the kernel's own socket copies (perf of `osrt bench
//! allreduce`). This module speaks exactly the same bytes — standard gRPC calls of
//! `osrt.v1.Collective` whose messages are protobuf `Chunk`s — but passes each payload
//! through as the `Bytes` it already is: the client sends a message's framing and its
//! payload as two body frames, the server slices the payload out of the HTTP/2 DATA frame
//! it arrived in (copying only when the payload was split across frames).
//!
//! One method: `PushChunks`, client streaming, one call per all-reduce, a chunk per
//! message. (A unary call per chunk costs a request's headers, a response with trailers
//! and a server task per chunk, which made chunks smaller than 1 MiB slower than large
//! ones and left buffers of a few MB with too few chunks to pipeline: docs/performance.md.)
//!
//! Any gRPC client or server of `osrt.v1.Collective` interoperates with it; the tests call
//! the server with tonic's generated client and the client against tonic's generated
//! server, and check the bytes against prost's encoding.

use bytes::{BufMut, Bytes, BytesMut};
use futures::future::BoxFuture;
use http_body::Frame;
use http_body_util::{BodyExt, StreamBody};
use osrt_proto::v1::{Chunk, ChunkTag};
use prost::Message;
use std::collections::VecDeque;
use std::convert::Infallible;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::sync::mpsc;
use tonic::Status;
use tonic::body::Body;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::transport::Channel;
use tower_service::Service;

/// The method's HTTP/2 path.
pub const STREAM_PATH: &str = "/osrt.v1.Collective/PushChunks";

/// Protobuf keys of `Chunk`'s fields: field number << 3 | wire type 2 (length-delimited).
const TAG_KEY: u8 = (1 << 3) | 2;
const DATA_KEY: u8 = (2 << 3) | 2;

/// One gRPC message carrying `Chunk { tag, data }`: the 5-byte message prefix, the tag and
/// the payload's key and length in one small buffer, then the payload itself, uncopied.
/// Together they are byte for byte what prost and tonic would send.
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

/// Bytes received as a list of frames, read front to back across frame boundaries. Each
/// part remembers the length of the DATA frame it was cut from: a slice keeps its whole
/// frame alive.
#[derive(Default)]
struct Frames {
    parts: VecDeque<(Bytes, usize)>,
    remaining: usize,
}

impl Frames {
    /// A received DATA frame.
    fn push(&mut self, frame: Bytes) {
        let len = frame.len();
        self.push_cut(frame, len);
    }

    /// A part cut from a frame of `frame_len` bytes.
    fn push_cut(&mut self, part: Bytes, frame_len: usize) {
        self.remaining += part.len();
        if !part.is_empty() {
            self.parts.push_back((part, frame_len));
        }
    }

    /// The next `n` bytes as frames of their own, without copying.
    fn split(&mut self, mut n: usize) -> Option<Frames> {
        if n > self.remaining {
            return None;
        }
        let mut out = Frames::default();
        while n > 0 {
            let (front, frame_len) = self
                .parts
                .front_mut()
                .expect("remaining counts these bytes");
            let k = n.min(front.len());
            out.push_cut(front.split_to(k), *frame_len);
            if front.is_empty() {
                self.parts.pop_front();
            }
            self.remaining -= k;
            n -= k;
        }
        Some(out)
    }

    /// The next `n` bytes: a slice of one frame when they lie in one, else a copy.
    fn take(&mut self, n: usize) -> Option<Bytes> {
        let mut f = self.split(n)?;
        Some(match f.parts.len() {
            0 => Bytes::new(),
            1 => f.parts.pop_front().expect("one part").0,
            _ => {
                let mut out = BytesMut::with_capacity(n);
                f.parts.iter().for_each(|(p, _)| out.extend_from_slice(p));
                out.freeze()
            }
        })
    }

    /// [`Frames::take`] for a payload that may be kept a while (a mailbox's early chunk):
    /// a slice less than half of the frame it lies in is copied out, so what it keeps
    /// alive is at most twice its length. A peer that pads a small payload with unknown
    /// fields (or packs it beside other bytes) cannot make a counted byte hold a frame.
    fn take_payload(&mut self, n: usize) -> Option<Bytes> {
        let frame_len = match self.parts.front() {
            Some((front, len)) if front.len() >= n => *len,
            // Spread over frames: `take` copies it into an allocation of its own.
            _ => return self.take(n),
        };
        let data = self.take(n)?;
        Some(if frame_len > 2 * n {
            Bytes::copy_from_slice(&data)
        } else {
            data
        })
    }

    /// The first `N` bytes, left in place.
    fn peek<const N: usize>(&self) -> Option<[u8; N]> {
        if self.remaining < N {
            return None;
        }
        let mut out = [0u8; N];
        let bytes = self.parts.iter().flat_map(|(p, _)| p.iter());
        out.iter_mut().zip(bytes).for_each(|(o, b)| *o = *b);
        Some(out)
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

    /// The next whole gRPC message (prefix removed), or `None` while its bytes have not
    /// all arrived. Messages over `limit` bytes are refused as soon as their prefix is in.
    fn next_message(&mut self, limit: usize) -> Result<Option<Frames>, Status> {
        let Some(prefix) = self.peek::<5>() else {
            return Ok(None);
        };
        if prefix[0] != 0 {
            return Err(Status::unimplemented(
                "compressed chunk messages are not supported",
            ));
        }
        let len = u32::from_be_bytes([prefix[1], prefix[2], prefix[3], prefix[4]]) as usize;
        if len > limit {
            return Err(Status::resource_exhausted(format!(
                "chunk message of {len} bytes, at most {limit} accepted"
            )));
        }
        if self.remaining < 5 + len {
            return Ok(None);
        }
        self.split(5);
        Ok(self.split(len))
    }
}

fn malformed(what: impl std::fmt::Display) -> Status {
    Status::invalid_argument(format!("malformed chunk message: {what}"))
}

/// Parses one protobuf `Chunk`; the payload stays a slice of the frame it arrived in.
/// Unknown fields are skipped, as protobuf requires; anything else that does not parse is
/// `invalid_argument`.
fn decode_chunk(mut f: Frames) -> Result<Chunk, Status> {
    let mut chunk = Chunk::default();
    while f.remaining > 0 {
        let key = f.varint().ok_or_else(|| malformed("truncated field key"))?;
        let (field, wire) = (key >> 3, key & 7);
        // Protobuf's keys are 32-bit and its field numbers start at 1: anything else is
        // malformed, not an unknown field to skip (prost refuses it too).
        if key > u64::from(u32::MAX) || field == 0 {
            return Err(malformed(format!("invalid field key {key}")));
        }
        let truncated = || malformed(format!("field {field} truncated"));
        match (field, wire) {
            (1 | 2, 2) => {
                let n = f.length().ok_or_else(truncated)?;
                let bytes = if field == 1 {
                    f.take(n)
                } else {
                    f.take_payload(n)
                }
                .ok_or_else(truncated)?;
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

/// Hands every chunk of a `PushChunks` body to `accept` as soon as its message is whole;
/// the first refusal (or malformed message) ends the call.
async fn accept_stream<A>(mut body: Body, accept: &A, limit: usize) -> Result<(), Status>
where
    A: Fn(Chunk) -> Result<(), Status>,
{
    let mut f = Frames::default();
    loop {
        while let Some(message) = f.next_message(limit)? {
            accept(decode_chunk(message)?)?;
        }
        match body.frame().await {
            Some(frame) => {
                if let Ok(data) = frame?.into_data() {
                    f.push(data);
                }
            }
            None if f.remaining == 0 => return Ok(()),
            None => {
                return Err(malformed(format!(
                    "the stream ends {} bytes into a message",
                    f.remaining
                )));
            }
        }
    }
}

/// A body of the given frames.
fn body_of(frames: Vec<Frame<Bytes>>) -> Body {
    Body::new(StreamBody::new(futures::stream::iter(
        frames.into_iter().map(Ok::<_, Infallible>),
    )))
}

/// The response to accepted chunks: an empty `ChunkAck` and `grpc-status: 0`.
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
    /// Messages over `limit` bytes are refused before they are parsed.
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
            let result = match req.uri().path() {
                STREAM_PATH => accept_stream(req.into_body(), &accept, limit).await,
                other => Err(Status::unimplemented(format!("no method {other}"))),
            };
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

/// The body of a `PushChunks` call: the messages handed to its [`ChunkStream`], each as
/// its framing and its payload.
struct StreamedChunks {
    messages: mpsc::Receiver<[Bytes; 2]>,
    payload: Option<Bytes>,
}

impl http_body::Body for StreamedChunks {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
        if let Some(payload) = self.payload.take() {
            return Poll::Ready(Some(Ok(Frame::data(payload))));
        }
        self.messages.poll_recv(cx).map(|m| {
            m.map(|[head, payload]| {
                self.payload = Some(payload);
                Ok(Frame::data(head))
            })
        })
    }
}

/// Opens a `PushChunks` call on `channel`, with `auth` as its `authorization` header;
/// `deadline` bounds the whole call (sent as `grpc-timeout`, and enforced here).
///
/// The call runs on its own task. Chunks go in through the [`ChunkSender`] (at most
/// `capacity` wait in its queue, beyond what HTTP/2 flow control lets through); the
/// [`ChunkCall`] ends the call and returns its status, or resolves early with the
/// server's refusal or a transport error.
pub fn open_stream(
    channel: Channel,
    auth: &MetadataValue<Ascii>,
    deadline: Duration,
    capacity: usize,
) -> Result<(ChunkSender, ChunkCall), Status> {
    let auth = http::HeaderValue::from_bytes(auth.as_encoded_bytes())
        .map_err(|e| Status::internal(format!("authorization header: {e}")))?;
    let (tx, rx) = mpsc::channel(capacity.max(1));
    // grpc-timeout allows at most 8 digits.
    let millis = deadline.as_millis().clamp(1, 99_999_999);
    let request = http::Request::builder()
        .method(http::Method::POST)
        .uri(STREAM_PATH)
        .header(http::header::CONTENT_TYPE, "application/grpc")
        .header(http::header::TE, "trailers")
        .header(http::header::AUTHORIZATION, auth)
        .header("grpc-timeout", format!("{millis}m"))
        .body(Body::new(StreamedChunks {
            messages: rx,
            payload: None,
        }))
        .map_err(|e| Status::internal(format!("PushChunks request: {e}")))?;
    let task = tokio::spawn(async move {
        tokio::time::timeout(deadline, call(channel, request))
            .await
            .map_err(|_| Status::deadline_exceeded(format!("no response within {deadline:?}")))?
    });
    Ok((ChunkSender(tx), ChunkCall(task)))
}

/// The sending half of a `PushChunks` call.
pub struct ChunkSender(mpsc::Sender<[Bytes; 2]>);

/// Room for one chunk in a [`ChunkSender`]'s queue.
pub struct ChunkPermit<'a>(mpsc::Permit<'a, [Bytes; 2]>);

impl ChunkSender {
    /// Waits for room for one chunk; an error means the call has ended
    /// ([`ChunkCall::ended`] says why).
    pub async fn reserve(&self) -> Result<ChunkPermit<'_>, Status> {
        self.0
            .reserve()
            .await
            .map(ChunkPermit)
            .map_err(|_| Status::unavailable("the PushChunks call has ended"))
    }

    /// Room for one chunk if there is some now.
    pub fn try_reserve(&self) -> Option<ChunkPermit<'_>> {
        self.0.try_reserve().ok().map(ChunkPermit)
    }
}

impl ChunkPermit<'_> {
    pub fn send(self, tag: &ChunkTag, data: Bytes) {
        self.0.send(encode_request(tag, data));
    }
}

/// The status half of a `PushChunks` call.
pub struct ChunkCall(tokio::task::JoinHandle<Result<(), Status>>);

impl ChunkCall {
    /// Resolves only if the call ends before [`ChunkCall::finish`]: with the server's
    /// refusal, a transport error, or (a protocol error) a success before the last chunk.
    /// Not to be awaited again once it has resolved.
    pub async fn ended(&mut self) -> Status {
        match (&mut self.0).await {
            Ok(Err(status)) => status,
            Ok(Ok(())) => Status::internal("PushChunks ended before its last chunk"),
            Err(e) => Status::internal(format!("PushChunks task: {e}")),
        }
    }

    /// [`ChunkCall::ended`] once the call is known to be over (its queue closed), waiting
    /// at most `timeout` for the status to arrive.
    pub async fn status_within(&mut self, timeout: Duration) -> Status {
        tokio::time::timeout(timeout, self.ended())
            .await
            .unwrap_or_else(|_| {
                Status::unavailable(format!(
                    "the PushChunks call closed and sent no status within {timeout:?}"
                ))
            })
    }

    /// Ends the call after the chunks queued in `sender` and waits at most `timeout` for
    /// its status: what is left to send is at most the queue (a few MiB), so a live
    /// successor answers well within one per-chunk timeout, and one that never answers
    /// fails the round after that wait, not at the call's whole-all-reduce deadline.
    pub async fn finish(mut self, sender: ChunkSender, timeout: Duration) -> Result<(), Status> {
        drop(sender);
        match tokio::time::timeout(timeout, &mut self.0).await {
            Ok(Ok(result)) => result,
            Ok(Err(e)) => Err(Status::internal(format!("PushChunks task: {e}"))),
            Err(_) => Err(Status::deadline_exceeded(format!(
                "the successor did not end the PushChunks call within {timeout:?} of its last chunk"
            ))),
        }
    }
}

impl Drop for ChunkCall {
    fn drop(&mut self) {
        // An all-reduce that failed elsewhere abandons its call.
        self.0.abort();
    }
}

/// Sends `request` on `channel` and reads the gRPC status of its response.
async fn call(mut channel: Channel, request: http::Request<Body>) -> Result<(), Status> {
    let transport = |e: tonic::transport::Error| Status::from_error(Box::new(e));
    futures::future::poll_fn(|cx| channel.poll_ready(cx))
        .await
        .map_err(transport)?;
    let response = channel.call(request).await.map_err(transport)?;
    if response.status() != http::StatusCode::OK {
        return Err(Status::unknown(format!(
            "chunk call answered HTTP {}",
            response.status()
        )));
    }
    // A trailers-only response carries the status in its headers.
    if let Some(status) = Status::from_header_map(response.headers()) {
        return result_of(status);
    }
    let collected = response.into_body().collect().await?;
    match collected.trailers().and_then(Status::from_header_map) {
        Some(status) => result_of(status),
        None => Err(Status::internal("chunk call response without grpc-status")),
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
mod tests;
