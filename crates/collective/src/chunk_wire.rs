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

/// Bytes received as a list of frames, read front to back across frame boundaries.
#[derive(Default)]
struct Frames {
    parts: VecDeque<Bytes>,
    remaining: usize,
}

impl Frames {
    fn push(&mut self, part: Bytes) {
        self.remaining += part.len();
        if !part.is_empty() {
            self.parts.push_back(part);
        }
    }

    /// The next `n` bytes as frames of their own, without copying.
    fn split(&mut self, mut n: usize) -> Option<Frames> {
        if n > self.remaining {
            return None;
        }
        let mut out = Frames::default();
        while n > 0 {
            let front = self
                .parts
                .front_mut()
                .expect("remaining counts these bytes");
            let k = n.min(front.len());
            out.push(front.split_to(k));
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
            1 => f.parts.pop_front().expect("one part"),
            _ => {
                let mut out = BytesMut::with_capacity(n);
                f.parts.iter().for_each(|p| out.extend_from_slice(p));
                out.freeze()
            }
        })
    }

    /// The first `N` bytes, left in place.
    fn peek<const N: usize>(&self) -> Option<[u8; N]> {
        if self.remaining < N {
            return None;
        }
        let mut out = [0u8; N];
        let bytes = self.parts.iter().flat_map(|p| p.iter());
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
mod tests {
    use super::*;

    /// The one message of a body (the frames of one call) as its `Chunk`: decoding
    /// alone, for the tests of the message format.
    fn decode_request(parts: Vec<Bytes>) -> Result<Chunk, Status> {
        let mut f = Frames::default();
        parts.into_iter().for_each(|p| f.push(p));
        let total = f.remaining;
        let Some(message) = f.next_message(usize::MAX)? else {
            return Err(malformed(format!(
                "a {total}-byte body is not one whole message (its prefix announces more)"
            )));
        };
        if f.remaining > 0 {
            return Err(malformed(format!(
                "{} bytes after the message",
                f.remaining
            )));
        }
        decode_chunk(message)
    }

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

    /// Everything `accept_stream` hands on from a body made of `frames`.
    fn accept_all(frames: Vec<Bytes>, limit: usize) -> (Vec<Chunk>, Result<(), Status>) {
        let got = std::sync::Mutex::new(Vec::new());
        let accept = |c: Chunk| {
            got.lock().unwrap().push(c);
            Ok(())
        };
        let body = body_of(frames.into_iter().map(Frame::data).collect());
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let result = rt.block_on(accept_stream(body, &accept, limit));
        (got.into_inner().unwrap(), result)
    }

    /// A `PushChunks` body of several messages gives every chunk back, in order, however
    /// it is cut into frames; a payload that arrived in one frame is not copied.
    #[test]
    fn a_stream_of_messages_cut_anywhere_gives_every_chunk_back() {
        let chunks: Vec<Chunk> = [0usize, 8, 300, 1000]
            .iter()
            .enumerate()
            .map(|(i, &n)| Chunk {
                tag: Some(ChunkTag {
                    chunk: i as u32,
                    ..tag()
                }),
                data: Bytes::from((0..n).map(|k| (k * 3 + i) as u8).collect::<Vec<u8>>()),
            })
            .collect();
        let whole = Bytes::from(chunks.iter().flat_map(prost_body).collect::<Vec<u8>>());
        for a in (0..whole.len()).step_by(7) {
            for b in [a, a + 1, a + 61, whole.len()] {
                let b = b.clamp(a, whole.len());
                let frames = vec![whole.slice(..a), whole.slice(a..b), whole.slice(b..)];
                let (got, result) = accept_all(frames, 4096);
                result.unwrap();
                assert_eq!(got, chunks, "cut at {a}, {b}");
            }
        }
        let frames: Vec<Bytes> = chunks
            .iter()
            .flat_map(|c| encode_request(c.tag.as_ref().unwrap(), c.data.clone()))
            .collect();
        let (got, result) = accept_all(frames.clone(), 4096);
        result.unwrap();
        assert_eq!(got, chunks);
        assert_eq!(
            got[3].data.as_ptr(),
            frames[7].as_ptr(),
            "payload not copied"
        );
    }

    /// A stream that ends inside a message, an oversized message or a malformed one ends
    /// the call with a clear status after the whole messages before it.
    #[test]
    fn a_broken_stream_fails_after_the_whole_messages() {
        let good = Chunk {
            tag: Some(tag()),
            data: Bytes::from_static(b"abcdefgh"),
        };
        let body = Bytes::from(prost_body(&good));
        let cut = Bytes::from([body.clone(), body.slice(..body.len() - 2)].concat());
        let (got, result) = accept_all(vec![cut], 4096);
        assert_eq!(got, vec![good.clone()]);
        let e = result.unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e}");
        assert!(e.message().contains("ends"), "{e}");

        let (got, result) = accept_all(vec![body.clone(), body.clone()], body.len() - 6);
        assert!(got.is_empty());
        assert_eq!(result.unwrap_err().code(), tonic::Code::ResourceExhausted);

        let garbage = Bytes::from_static(&[0, 0, 0, 0, 4, TAG_KEY, 2, 0xff, 0xff]);
        let (got, result) = accept_all(vec![body.clone(), garbage], 4096);
        assert_eq!(got, vec![good]);
        assert_eq!(result.unwrap_err().code(), tonic::Code::InvalidArgument);
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
