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
