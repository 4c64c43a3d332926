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

/// A small payload padded with an unknown field in one frame is handed on as a copy of
/// its own: kept as an early chunk, it must not hold the frame (a megabyte counted as 4
/// bytes). A payload that fills its frame stays a slice of it (no copy).
#[test]
fn a_payload_small_beside_its_frame_does_not_keep_the_frame() {
    let message = |data: &[u8], padding: usize| {
        let mut msg = Chunk {
            tag: Some(tag()),
            data: Bytes::copy_from_slice(data),
        }
        .encode_to_vec();
        if padding > 0 {
            msg.push((11 << 3) | 2);
            prost::encode_length_delimiter(padding, &mut msg).unwrap();
            msg.extend(std::iter::repeat_n(0u8, padding));
        }
        let mut body = vec![0u8];
        body.extend((msg.len() as u32).to_be_bytes());
        body.extend(msg);
        Bytes::from(body)
    };
    let inside = |c: &Chunk, frame: &Bytes| {
        let (p, f) = (c.data.as_ptr() as usize, frame.as_ptr() as usize);
        p >= f && p < f + frame.len()
    };
    let padded = message(b"abcd", 1 << 20);
    let (chunks, result) = accept_all(vec![padded.clone()], 4 << 20);
    result.unwrap();
    assert_eq!(chunks[0].data, Bytes::from_static(b"abcd"));
    assert!(
        !inside(&chunks[0], &padded),
        "the payload still points into its frame"
    );
    let full = message(&[7u8; 4096], 0);
    let (chunks, result) = accept_all(vec![full.clone()], 4 << 20);
    result.unwrap();
    assert!(
        inside(&chunks[0], &full),
        "a payload filling its frame was copied"
    );
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

/// `bytes` cut into frames at `cuts` (positions taken modulo the length).
fn framed(bytes: &[u8], cuts: &[usize]) -> Frames {
    let mut at: Vec<usize> = cuts.iter().map(|c| c % (bytes.len() + 1)).collect();
    at.extend([0, bytes.len()]);
    at.sort_unstable();
    at.dedup();
    let mut f = Frames::default();
    for w in at.windows(2) {
        f.push(Bytes::copy_from_slice(&bytes[w[0]..w[1]]));
    }
    f
}

fn any_tag() -> impl proptest::strategy::Strategy<Value = ChunkTag> {
    use proptest::prelude::*;
    (
        ".{0,12}",
        any::<u64>(),
        any::<u64>(),
        any::<u32>(),
        any::<i32>(),
        (any::<u32>(), any::<u32>(), any::<u32>()),
    )
        .prop_map(
            |(job, generation, step, bucket, phase, (round, chunk, from_rank))| ChunkTag {
                job,
                generation,
                step,
                bucket,
                phase,
                round,
                chunk,
                from_rank,
            },
        )
}

/// A protobuf body: a chunk's encoding with bytes flipped or cut, or any bytes.
fn message_body() -> impl proptest::strategy::Strategy<Value = Vec<u8>> {
    use proptest::prelude::*;
    let flipped = (
        any_tag(),
        proptest::collection::vec(any::<u8>(), 0..40),
        proptest::collection::vec((any::<proptest::sample::Index>(), 1u8..=255), 0..4),
        proptest::option::of(any::<proptest::sample::Index>()),
    )
        .prop_map(|(tag, data, flips, cut)| {
            let mut body = Chunk {
                tag: Some(tag),
                data: data.into(),
            }
            .encode_to_vec();
            for (at, x) in flips {
                let i = at.index(body.len());
                body[i] ^= x;
            }
            if let Some(c) = cut {
                body.truncate(c.index(body.len() + 1));
            }
            body
        });
    prop_oneof![3 => flipped, 1 => proptest::collection::vec(any::<u8>(), 0..200)]
}

/// The properties' settings: `PROPTEST_CASES` cases (256 by default), nothing written to
/// disk on failure (the failing case is printed).
fn fuzz_config() -> proptest::test_runner::Config {
    proptest::test_runner::Config {
        failure_persistence: None,
        ..Default::default()
    }
}

proptest::proptest! {
    #![proptest_config(fuzz_config())]

    /// Any bytes arriving in any frames: every whole message decodes or is refused with
    /// a status, never a panic, and whatever decodes is what prost decodes from the same
    /// message (a differential check against protobuf's reference implementation here).
    #[test]
    fn any_bytes_in_any_frames_decode_as_prost_does(
        bodies in proptest::collection::vec(message_body(), 1..4),
        raw in proptest::prelude::any::<bool>(),
        cuts in proptest::collection::vec(proptest::prelude::any::<usize>(), 0..8),
        limit in 0usize..700,
    ) {
        // Mostly well-prefixed gRPC messages (so the bodies reach the protobuf decoder),
        // sometimes the bytes alone.
        let bytes: Vec<u8> = if raw {
            bodies.concat()
        } else {
            bodies
                .iter()
                .flat_map(|b| [&[0u8][..], &(b.len() as u32).to_be_bytes(), b].concat())
                .collect()
        };
        let mut f = framed(&bytes, &cuts);
        let mut at = 0usize;
        while let Ok(Some(message)) = f.next_message(limit) {
            let len = message.remaining;
            let body = &bytes[at + 5..at + 5 + len];
            at += 5 + len;
            if let Ok(ours) = decode_chunk(message) {
                let reference = Chunk::decode(body);
                proptest::prop_assert!(reference.is_ok(), "prost refuses what we decode: {body:?}");
                proptest::prop_assert_eq!(ours, reference.unwrap());
            }
        }
    }

    /// Any chunk, encoded and cut into any frames, decodes to itself.
    #[test]
    fn encoded_chunks_decode_across_any_frames(
        tag in any_tag(),
        data in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..300),
        cuts in proptest::collection::vec(proptest::prelude::any::<usize>(), 0..8),
    ) {
        let [head, payload] = encode_request(&tag, Bytes::from(data.clone()));
        let bytes = [head.as_ref(), payload.as_ref()].concat();
        let mut f = framed(&bytes, &cuts);
        let message = f.next_message(usize::MAX).unwrap().expect("one whole message");
        proptest::prop_assert_eq!(f.remaining, 0);
        let chunk = decode_chunk(message).unwrap();
        proptest::prop_assert_eq!(chunk.tag, Some(tag));
        proptest::prop_assert_eq!(chunk.data.as_ref(), &data[..]);
    }
}
