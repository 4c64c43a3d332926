//! Ring all-reduce over real gRPC on loopback: sums, bit-identical replicas, stale and
//! malformed traffic, dead peers, and the hand-framed chunk calls against tonic's own
//! generated client and server.

use bytes::Bytes;
use osrt_collective::{
    CollectiveError, Layout, Mailbox, Ring, RingConfig, Stage, chunk_wire, serve,
};
use osrt_proto::auth::{AttachToken, Token};
use osrt_proto::credentials::Credentials;
use osrt_proto::v1::collective_client::CollectiveClient;
use osrt_proto::v1::collective_server::{Collective, CollectiveServer};
use osrt_proto::v1::{Chunk, ChunkAck, ChunkTag, Phase};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::ops::Range;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::oneshot;

struct Node {
    addr: String,
    mailbox: Arc<Mailbox>,
    server: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
    _stop: oneshot::Sender<()>,
}

async fn start(n: usize, job: &str) -> Vec<Node> {
    let mut nodes = Vec::new();
    for _ in 0..n {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = format!("http://{}", listener.local_addr().unwrap());
        let mailbox = Mailbox::new(job);
        let (tx, rx) = oneshot::channel::<()>();
        let server = tokio::spawn(serve(
            listener,
            mailbox.clone(),
            credentials(),
            async move {
                let _ = rx.await;
            },
        ));
        nodes.push(Node {
            addr,
            mailbox,
            server,
            _stop: tx,
        });
    }
    nodes
}

fn config(
    nodes: &[Node],
    rank: usize,
    bucket: usize,
    chunk: usize,
    timeout: Duration,
) -> RingConfig {
    RingConfig {
        job: "test-job".into(),
        generation: 1,
        first_step: 0,
        rank,
        peers: nodes.iter().map(|n| n.addr.clone()).collect(),
        bucket_floats: bucket,
        chunk_floats: chunk,
        timeout,
        credentials: credentials(),
    }
}

/// tonic's generated client of `node`'s collective server, with the job's token.
async fn client_of(
    node: &Node,
) -> CollectiveClient<
    tonic::service::interceptor::InterceptedService<tonic::transport::Channel, AttachToken>,
> {
    let channel = tonic::transport::Endpoint::from_shared(node.addr.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    CollectiveClient::with_interceptor(channel, AttachToken(token()))
}

/// One token for every node of a test process.
fn token() -> Token {
    static T: std::sync::OnceLock<Token> = std::sync::OnceLock::new();
    T.get_or_init(Token::generate).clone()
}

/// [`token`], without TLS.
fn credentials() -> Credentials {
    Credentials::new(token(), None)
}

fn random(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| rng.random_range(-1.0..1.0)).collect()
}

#[test]
fn layout_covers_the_buffer_exactly_once() {
    for (len, world, bucket, chunk) in [
        (10, 3, 4, 1),
        (1000, 2, 300, 7),
        (5, 4, 100, 2),
        (1, 3, 1, 1),
    ] {
        let l = Layout::new(len, world, bucket, chunk);
        let mut seen = vec![0; len];
        for b in 0..l.buckets.len() {
            for s in 0..world {
                for c in l.chunks(l.segment(b, s)) {
                    assert!(c.len() <= chunk);
                    for i in c {
                        seen[i] += 1;
                    }
                }
            }
        }
        assert!(
            seen.iter().all(|&x| x == 1),
            "{len} {world} {bucket} {chunk}"
        );
        // Reverse parameter order: the first bucket ends at the buffer's end.
        assert_eq!(l.buckets[0].end, len);
    }
}

/// Rings of 2–4 ranks. With 256-float chunks more chunks are ready to send at once
/// (~120–160) than a rank's send queue holds (64): sends must go on as the queue drains,
/// while receives are still pending.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ring_all_reduce_sums_and_replicas_are_bit_identical() {
    for (world, chunk) in [(2usize, 4096), (3, 4096), (3, 256), (4, 256)] {
        let nodes = start(world, "test-job").await;
        let len = 100_003;
        let inputs: Vec<Vec<f32>> = (0..world).map(|r| random(len, r as u64)).collect();
        let mut tasks = Vec::new();
        for rank in 0..world {
            let cfg = config(&nodes, rank, 30_000, chunk, Duration::from_secs(10));
            let mut ring = Ring::new(cfg, nodes[rank].mailbox.clone()).unwrap();
            let mut buf = inputs[rank].clone();
            tasks.push(tokio::spawn(async move {
                for step in 0..2u64 {
                    ring.all_reduce(step, &mut buf).await.unwrap();
                }
                buf
            }));
        }
        let mut outs = Vec::new();
        for t in tasks {
            outs.push(t.await.unwrap());
        }
        for o in &outs[1..] {
            assert!(
                o.iter()
                    .zip(&outs[0])
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "replicas differ"
            );
        }
        // Two steps: the second all-reduce sums the sums → world × Σ inputs.
        for i in (0..len).step_by(997) {
            let want: f32 = inputs.iter().map(|v| v[i]).sum::<f32>() * world as f32;
            assert!(
                (outs[0][i] - want).abs() < 1e-4,
                "index {i}: {} vs {want}",
                outs[0][i]
            );
        }
    }
}

/// A stage fed bucket by bucket by a producer task at its own pace (as a GPU's copies to
/// the host arrive), recording every bucket's sums as the ring reports them.
struct Feed {
    rx: tokio::sync::mpsc::Receiver<(usize, Vec<f32>)>,
    /// A bucket received but not yet written (kept across a cancelled `staged`).
    pending: Option<(usize, Vec<f32>)>,
    reduced: Vec<(usize, Vec<f32>)>,
    fail_at: Option<usize>,
}

impl Feed {
    /// Feeds `input`'s buckets (of `layout`) in order, each after a random pause of up to
    /// `pause_us` microseconds.
    fn of(input: &[f32], layout: &Layout, seed: u64, pause_us: u64) -> Self {
        let (tx, rx) = tokio::sync::mpsc::channel(1);
        let pieces: Vec<(usize, Vec<f32>)> = (layout.buckets.iter().cloned())
            .map(|r: Range<usize>| input[r].to_vec())
            .enumerate()
            .collect();
        tokio::spawn(async move {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            for p in pieces {
                tokio::time::sleep(Duration::from_micros(rng.random_range(0..=pause_us))).await;
                if tx.send(p).await.is_err() {
                    return;
                }
            }
        });
        Self {
            rx,
            pending: None,
            reduced: Vec::new(),
            fail_at: None,
        }
    }
}

impl Stage for Feed {
    async fn staged(&mut self, bucket: usize) -> Result<(), String> {
        if self.fail_at == Some(bucket) {
            return Err("injected staging failure".into());
        }
        if self.pending.is_none() {
            self.pending = Some(self.rx.recv().await.ok_or("the producer is gone")?);
        }
        let got = self.pending.as_ref().map(|p| p.0);
        assert_eq!(got, Some(bucket), "buckets staged out of order");
        Ok(())
    }

    fn fill(&mut self, bucket: usize, dst: &mut [f32]) -> Result<(), String> {
        let (b, v) = self.pending.take().expect("fill after staged");
        assert_eq!(b, bucket);
        dst.copy_from_slice(&v);
        Ok(())
    }

    fn reduced(&mut self, bucket: usize, sums: &[f32]) -> Result<(), String> {
        self.reduced.push((bucket, sums.to_vec()));
        Ok(())
    }
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// A buffer filled bucket by bucket while the ring runs gives the bits of the plain
/// all-reduce of the whole buffer on every rank, and the stage hears of every bucket's
/// sums once, in order, with the bucket's final floats; on rings of 1 to 3 ranks, with
/// pieces arriving at random times (and, for one run, all at once).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_staged_all_reduce_gives_the_bits_of_the_plain_one() {
    for (world, chunk, pause_us) in [
        (1usize, 4096, 500),
        (2, 4096, 3000),
        (2, 1000, 0),
        (3, 256, 2000),
    ] {
        let nodes = start(world, "test-job").await;
        let len = 100_003;
        let inputs: Vec<Vec<f32>> = (0..world).map(|r| random(len, 10 + r as u64)).collect();
        let mut tasks = Vec::new();
        for rank in 0..world {
            let cfg = config(&nodes, rank, 30_000, chunk, Duration::from_secs(10));
            let mut ring = Ring::new(cfg, nodes[rank].mailbox.clone()).unwrap();
            let input = inputs[rank].clone();
            tasks.push(tokio::spawn(async move {
                let mut plain = input.clone();
                ring.all_reduce(0, &mut plain).await.unwrap();
                let layout = ring.layout(len);
                let mut feed = Feed::of(&input, &layout, rank as u64, pause_us);
                // Whatever is in the buffer beforehand does not count.
                let mut staged = vec![f32::NAN; len];
                ring.all_reduce_staged(1, &mut staged, &mut feed)
                    .await
                    .unwrap();
                (plain, staged, feed.reduced, layout)
            }));
        }
        for t in tasks {
            let (plain, staged, reduced, layout) = t.await.unwrap();
            assert_eq!(bits(&staged), bits(&plain), "world {world}: staged differs");
            let order: Vec<usize> = reduced.iter().map(|r| r.0).collect();
            assert_eq!(order, (0..layout.buckets.len()).collect::<Vec<_>>());
            for (b, sums) in reduced {
                let r = layout.buckets[b].clone();
                assert_eq!(bits(&sums), bits(&plain[r]), "world {world}: bucket {b}");
            }
        }
    }
}

/// A stage that fails ends its rank's all-reduce with the stage's reason and bucket; the
/// other rank's fails at its deadline instead of hanging.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failing_stage_fails_the_all_reduce() {
    let nodes = start(2, "test-job").await;
    let len = 100_003;
    let mut tasks = Vec::new();
    for rank in 0..2 {
        let cfg = config(&nodes, rank, 30_000, 4096, Duration::from_millis(500));
        let mut ring = Ring::new(cfg, nodes[rank].mailbox.clone()).unwrap();
        let input = random(len, rank as u64);
        tasks.push(tokio::spawn(async move {
            let mut feed = Feed::of(&input, &ring.layout(len), 0, 0);
            feed.fail_at = (rank == 1).then_some(2);
            let mut buf = vec![0.0; len];
            ring.all_reduce_staged(0, &mut buf, &mut feed).await
        }));
    }
    let r0 = tasks.remove(0).await.unwrap();
    let r1 = tasks.remove(0).await.unwrap();
    assert!(
        matches!(&r1, Err(CollectiveError::Stage { rank: 1, bucket: 2, reason }) if reason.contains("injected")),
        "{r1:?}"
    );
    assert!(r0.is_err(), "rank 0 finished an all-reduce rank 1 left");
}

fn chunk(job: &str, generation: u64, step: u64, from: u32, data: Vec<f32>) -> Chunk {
    Chunk {
        tag: Some(ChunkTag {
            job: job.into(),
            generation,
            step,
            bucket: 0,
            phase: Phase::ReduceScatter as i32,
            round: 0,
            chunk: 0,
            from_rank: from,
        }),
        data: Bytes::from(
            data.iter()
                .flat_map(|x| x.to_le_bytes())
                .collect::<Vec<u8>>(),
        ),
    }
}

/// Rank 0's chunk `c` of all-reduce 3 in `phase`, of 2 floats `v` (chunks of 2, 8 floats).
fn tagged(phase: Phase, c: u32, v: f32) -> Chunk {
    let mut ch = chunk("test-job", 1, 3, 0, vec![v; 2]);
    let t = ch.tag.as_mut().unwrap();
    t.phase = phase as i32;
    t.chunk = c;
    ch
}

/// Everything rank 1 receives from rank 0 in all-reduce 3 of 8 ones in chunks of 2: it
/// sums segment 0 in the reduce-scatter and copies segment 1 in the all-gather (rank 0
/// would send 2.0 + 1.0 for both).
fn rank_0s_chunks() -> Vec<Chunk> {
    vec![
        tagged(Phase::ReduceScatter, 0, 1.0),
        tagged(Phase::ReduceScatter, 1, 1.0),
        tagged(Phase::AllGather, 0, 5.0),
        tagged(Phase::AllGather, 1, 5.0),
    ]
}

/// What a rank's all-reduce task hands back: its result, its buffer and its ring.
type Waiting = tokio::task::JoinHandle<(Result<(), CollectiveError>, Vec<f32>, Ring)>;

/// Runs `ring`'s all-reduce `step` of 8 ones on a task of its own.
fn all_reduce_in_background(mut ring: Ring, step: u64) -> Waiting {
    tokio::spawn(async move {
        let mut buf = vec![1.0f32; 8];
        let r = ring.all_reduce(step, &mut buf).await;
        (r, buf, ring)
    })
}

/// Two nodes; rank 1 waits in all-reduce 3 of 8 ones (segments of 4, chunks of
/// `chunk_floats`); rank 0 is in generation 1 but never joins: the test speaks for it.
async fn rank_1_waiting(chunk_floats: usize) -> (Vec<Node>, Waiting) {
    let nodes = start(2, "test-job").await;
    nodes[0].mailbox.set_generation(1, 0, 3);
    let cfg = config(&nodes, 1, 1000, chunk_floats, Duration::from_secs(5));
    let ring = Ring::new(cfg, nodes[1].mailbox.clone()).unwrap();
    let waiting = all_reduce_in_background(ring, 3);
    tokio::time::sleep(Duration::from_millis(200)).await;
    (nodes, waiting)
}

/// Rank 1's waiting round fails with the malformed chunk's reason, well before its
/// deadline (the chunk was sent at `sent`).
async fn the_round_fails_at_once_on_the_malformed_chunk(waiting: Waiting, sent: Instant) {
    let err = waiting.await.unwrap().0.unwrap_err();
    assert!(
        matches!(err, CollectiveError::Peer(ref m, 1) if m.contains("malformed chunk")),
        "{err}"
    );
    assert!(sent.elapsed() < Duration::from_secs(2));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stale_foreign_and_malformed_chunks_are_rejected() {
    let (nodes, waiting) = rank_1_waiting(1000).await;
    // Without the job's token, or with another job's: refused before anything is parsed.
    let mut bare = CollectiveClient::connect(nodes[1].addr.clone())
        .await
        .unwrap();
    let e = push_one(&mut bare, chunk("test-job", 1, 3, 0, vec![0.0; 4]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e}");
    let channel = tonic::transport::Endpoint::from_shared(nodes[1].addr.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut foreign =
        CollectiveClient::with_interceptor(channel.clone(), AttachToken(Token::generate()));
    let e = push_one(&mut foreign, chunk("test-job", 1, 3, 0, vec![0.0; 4]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e}");
    let mut client = CollectiveClient::with_interceptor(channel, AttachToken(token()));
    let e = push_one(&mut client, chunk("other-job", 1, 3, 0, vec![0.0; 4]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::PermissionDenied, "{e}");
    let e = push_one(&mut client, chunk("test-job", 0, 3, 0, vec![0.0; 4]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::FailedPrecondition);
    assert!(e.message().contains("stale chunk: generation 0"), "{e}");
    let e = push_one(&mut client, chunk("test-job", 1, 2, 0, vec![0.0; 4]))
        .await
        .unwrap_err();
    assert!(e.message().contains("stale chunk: step 2"), "{e}");
    // A chunk of a *newer* generation (a peer that joined it first) is kept, not refused.
    push_one(&mut client, chunk("test-job", 2, 0, 0, vec![0.0; 4]))
        .await
        .unwrap();
    let e = push_one(
        &mut client,
        Chunk {
            tag: None,
            data: Bytes::new(),
        },
    )
    .await
    .unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    // Wrong length: refused, and the waiting round fails at once with the reason.
    let t = Instant::now();
    let e = push_one(&mut client, chunk("test-job", 1, 3, 0, vec![0.0; 3]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(e.message().contains("malformed chunk"), "{e}");
    the_round_fails_at_once_on_the_malformed_chunk(waiting, t).await;
}

/// Two ranks that reduced a gradient of the test's size (so the mailbox's bound on early
/// chunks follows it), rank 1 then in generation 2.
async fn two_ranks_past_a_small_all_reduce() -> Vec<Node> {
    let nodes = start(2, "test-job").await;
    let rings: Vec<Ring> = (0..2)
        .map(|r| {
            let cfg = config(&nodes, r, 1000, 1000, Duration::from_secs(5));
            Ring::new(cfg, nodes[r].mailbox.clone()).unwrap()
        })
        .collect();
    let tasks: Vec<Waiting> = rings
        .into_iter()
        .map(|r| all_reduce_in_background(r, 0))
        .collect();
    for t in tasks {
        t.await.unwrap().0.unwrap();
    }
    nodes[1].mailbox.set_generation(2, 1, 0);
    nodes
}

/// What a rank keeps for later is bounded: chunks at most one step ahead (checked like
/// the current step's), at most one generation ahead, and no more bytes of them than a
/// gradient.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn chunks_kept_for_later_are_bounded() {
    let (nodes, waiting) = rank_1_waiting(1000).await;
    let mut client = client_of(&nodes[1]).await;
    // Rank 1 is in step 3: step 4 is kept (from the ring predecessor only), step 5
    // refused.
    push_one(&mut client, chunk("test-job", 1, 4, 0, vec![0.0; 4]))
        .await
        .unwrap();
    let e = push_one(&mut client, chunk("test-job", 1, 4, 1, vec![0.0; 4]))
        .await
        .unwrap_err();
    assert!(
        e.message().contains("expected the ring predecessor 0"),
        "{e}"
    );
    let e = push_one(&mut client, chunk("test-job", 1, 5, 0, vec![0.0; 4]))
        .await
        .unwrap_err();
    assert!(e.message().contains("at most one step ahead"), "{e}");
    let e = push_one(&mut client, chunk("test-job", 3, 0, 0, vec![0.0; 4]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::FailedPrecondition);
    assert!(e.message().contains("at most one ahead"), "{e}");
    // Generation 2's steps cannot be checked before rank 1 gets there: steps 1 and 0 of
    // it are both kept (within the bytes bound below).
    for step in [1, 0] {
        push_one(&mut client, chunk("test-job", 2, step, 0, vec![0.0; 4]))
            .await
            .unwrap();
    }
    drop(waiting);
    // After a gradient of 8 floats was reduced, early chunks may total 32 bytes + 1 MiB.
    let nodes = two_ranks_past_a_small_all_reduce().await;
    let channel = tonic::transport::Endpoint::from_shared(nodes[1].addr.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut client = CollectiveClient::with_interceptor(channel, AttachToken(token()))
        .max_encoding_message_size(8 << 20);
    let mut big = chunk("test-job", 2, 0, 0, vec![0.0; 1 << 18]);
    push_one(&mut client, big.clone()).await.unwrap();
    big.tag.as_mut().unwrap().chunk = 1;
    let e = push_one(&mut client, big).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e}");
}

/// Sends one chunk of all-reduce `step` from "rank 0" of `generation` to `node`, as a
/// peer holding the job's token but sending nonsense would.
async fn push_bogus(node: &Node, generation: u64, step: u64) -> Result<(), tonic::Status> {
    let mut client = client_of(node).await;
    push_one(
        &mut client,
        chunk("test-job", generation, step, 0, vec![0.0; 4]),
    )
    .await
    .map(|_| ())
}

/// The two ranks of `nodes` run all-reduce `step` of 8 ones in `generation`; both must
/// end with eights.
async fn both_ranks_reduce(nodes: &[Node], generation: u64, step: u64) {
    let tasks: Vec<Waiting> = (0..2)
        .map(|r| {
            let mut cfg = config(nodes, r, 1000, 1000, Duration::from_secs(5));
            cfg.generation = generation;
            cfg.first_step = step;
            all_reduce_in_background(Ring::new(cfg, nodes[r].mailbox.clone()).unwrap(), step)
        })
        .collect();
    for t in tasks {
        let (r, buf, _) = t.await.unwrap();
        r.unwrap();
        assert_eq!(buf, vec![2.0; 8]);
    }
}

/// A chunk from far ahead (step `u64::MAX`) that reaches a rank before its first
/// all-reduce of a generation, or while it is still in the previous generation, does not
/// shut out the real chunks: the generation's all-reduce goes through.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_chunk_from_far_ahead_does_not_fail_the_generation() {
    let nodes = start(2, "test-job").await;
    // Rank 1 is in generation 1, whose first all-reduce is number 5; it has not got there.
    nodes[1].mailbox.set_generation(1, 1, 5);
    let e = push_bogus(&nodes[1], 1, u64::MAX).await.unwrap_err();
    assert!(e.message().contains("at most one step ahead"), "{e}");
    both_ranks_reduce(&nodes, 1, 5).await;
    // Rank 1 is at all-reduce 5 of generation 1; a chunk of generation 2 names a step
    // nobody can check yet, so it is kept; entering generation 2 (first all-reduce 9)
    // drops it.
    push_bogus(&nodes[1], 2, u64::MAX).await.unwrap();
    both_ranks_reduce(&nodes, 2, 9).await;
}

/// Early chunks are bounded in number as well as bytes: a stream of empty chunks under
/// distinct keys is refused once their bookkeeping reaches the bound.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn empty_early_chunks_cannot_pile_up() {
    let nodes = two_ranks_past_a_small_all_reduce().await;
    let mut client = client_of(&nodes[1]).await;
    // After an 8-float gradient the bound is about 1 MiB: some 8,200 entries.
    for i in 0..20_000 {
        let mut c = chunk("test-job", 2, 0, 0, vec![]);
        c.tag.as_mut().unwrap().chunk = i;
        if let Err(e) = push_one(&mut client, c).await {
            assert_eq!(e.code(), tonic::Code::ResourceExhausted, "chunk {i}: {e}");
            assert!(i > 1000, "refused after {i}");
            return;
        }
    }
    panic!("20,000 empty early chunks were all kept");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_peer_fails_the_round_within_the_deadline() {
    let nodes = start(2, "test-job").await;
    // Rank 1's process dies: its server and listener are gone.
    nodes[1].server.abort();
    tokio::time::sleep(Duration::from_millis(100)).await;
    let cfg = config(&nodes, 0, 1000, 1000, Duration::from_secs(2));
    let mut ring = Ring::new(cfg, nodes[0].mailbox.clone()).unwrap();
    let t = Instant::now();
    let err = ring.all_reduce(0, &mut vec![1.0f32; 16]).await.unwrap_err();
    assert!(
        t.elapsed() < Duration::from_secs(5),
        "took {:?}",
        t.elapsed()
    );
    assert!(matches!(err, CollectiveError::Send { to: 1, .. }), "{err}");
    // A live peer that never sends: the wait times out.
    let nodes2 = start(2, "test-job").await;
    nodes2[1].mailbox.set_generation(1, 1, 0);
    let mut ring = Ring::new(
        config(&nodes2, 0, 1000, 1000, Duration::from_secs(1)),
        nodes2[0].mailbox.clone(),
    )
    .unwrap();
    let t = Instant::now();
    let err = ring.all_reduce(0, &mut vec![1.0f32; 16]).await.unwrap_err();
    assert!(
        matches!(err, CollectiveError::Timeout { from: 1, .. }),
        "{err}"
    );
    assert!(t.elapsed() < Duration::from_secs(3));
}

/// A peer that opens an HTTP/2 connection and then answers nothing (a host gone without
/// closing its sockets) is dropped by the ring's server: its pings go unanswered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_peer_that_answers_no_ping_is_dropped() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let nodes = start(1, "test-job").await;
    let addr = nodes[0].addr.trim_start_matches("http://").to_string();
    let mut tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    // The client preface and an empty SETTINGS frame; then silence.
    tcp.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n")
        .await
        .unwrap();
    tcp.write_all(&[0, 0, 0, 4, 0, 0, 0, 0, 0]).await.unwrap();
    let t = Instant::now();
    let mut buf = [0u8; 4096];
    let limit =
        osrt_proto::KEEP_ALIVE_INTERVAL + osrt_proto::KEEP_ALIVE_TIMEOUT + Duration::from_secs(5);
    loop {
        match tokio::time::timeout_at((t + limit).into(), tcp.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => break,
            Ok(Ok(_)) => continue,
            Err(_) => panic!("the silent peer was still connected after {limit:?}"),
        }
    }
    assert!(t.elapsed() >= osrt_proto::KEEP_ALIVE_TIMEOUT);
}

/// tonic's generated `Collective` server, recording what it is sent.
#[derive(Default, Clone)]
struct Recorder(Arc<std::sync::Mutex<Vec<Chunk>>>);

impl Recorder {
    fn record(&self, chunk: Chunk) -> Result<(), tonic::Status> {
        if chunk.tag.as_ref().is_some_and(|t| t.job == "refuse-me") {
            return Err(tonic::Status::failed_precondition("refused as asked"));
        }
        self.0.lock().unwrap().push(chunk);
        Ok(())
    }
}

#[tonic::async_trait]
impl Collective for Recorder {
    async fn push_chunks(
        &self,
        request: tonic::Request<tonic::Streaming<Chunk>>,
    ) -> Result<tonic::Response<ChunkAck>, tonic::Status> {
        let mut chunks = request.into_inner();
        while let Some(chunk) = chunks.message().await? {
            self.record(chunk)?;
        }
        Ok(tonic::Response::new(ChunkAck {}))
    }
}

/// Sends one chunk on its own `PushChunks` call (tonic's generated client), returning the
/// server's answer.
async fn push_one<T>(
    client: &mut CollectiveClient<T>,
    c: Chunk,
) -> Result<tonic::Response<ChunkAck>, tonic::Status>
where
    T: tonic::client::GrpcService<tonic::body::Body>,
    T::Error: Into<tonic::codegen::StdError>,
    T::ResponseBody: tonic::codegen::Body<Data = bytes::Bytes> + Send + 'static,
    <T::ResponseBody as tonic::codegen::Body>::Error: Into<tonic::codegen::StdError> + Send,
{
    client.push_chunks(futures::stream::iter([c])).await
}

/// Sends `chunks` on one hand-framed `PushChunks` call and returns its status.
async fn stream_chunks(
    channel: tonic::transport::Channel,
    token: &Token,
    chunks: &[Chunk],
) -> Result<(), tonic::Status> {
    let (sender, mut call) =
        chunk_wire::open_stream(channel, &token.header(), Duration::from_secs(5), 2)?;
    for c in chunks {
        let permit = tokio::select! {
            status = call.ended() => return Err(status),
            permit = sender.reserve() => permit,
        };
        match permit {
            Ok(p) => p.send(c.tag.as_ref().unwrap(), c.data.clone()),
            Err(_) => return Err(call.status_within(Duration::from_secs(5)).await),
        }
    }
    call.finish(sender, Duration::from_secs(5)).await
}

/// A successor that takes every chunk but never answers the call.
struct Silent;

#[tonic::async_trait]
impl Collective for Silent {
    async fn push_chunks(
        &self,
        request: tonic::Request<tonic::Streaming<Chunk>>,
    ) -> Result<tonic::Response<ChunkAck>, tonic::Status> {
        let mut chunks = request.into_inner();
        while chunks.message().await?.is_some() {}
        std::future::pending().await
    }
}

/// The end of a call waits one per-chunk timeout for the successor's answer, not the
/// call's deadline (which allows every chunk of an all-reduce its timeout).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_end_of_a_call_is_bounded_by_one_wait() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(CollectiveServer::new(Silent))
            .serve_with_incoming(tonic::transport::server::TcpIncoming::from(listener)),
    );
    let channel = tonic::transport::Endpoint::from_shared(addr)
        .unwrap()
        .connect_lazy();
    let (sender, call) =
        chunk_wire::open_stream(channel, &token().header(), Duration::from_secs(60), 2).unwrap();
    let c = chunk("test-job", 1, 0, 0, vec![1.0; 8]);
    sender
        .reserve()
        .await
        .unwrap()
        .send(c.tag.as_ref().unwrap(), c.data.clone());
    let t = Instant::now();
    let e = call
        .finish(sender, Duration::from_millis(500))
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::DeadlineExceeded, "{e}");
    assert!(
        t.elapsed() < Duration::from_secs(5),
        "took {:?}",
        t.elapsed()
    );
}

/// The ring's hand-framed `PushChunks` (chunk_wire) is ordinary gRPC: tonic's generated
/// server decodes every message into the same `Chunk`, in order, and its refusal comes
/// back as the status it sent.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_hand_framed_stream_talks_to_tonics_generated_server() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = format!("http://{}", listener.local_addr().unwrap());
    let recorder = Recorder::default();
    let service = tonic::service::interceptor::InterceptedService::new(
        CollectiveServer::new(recorder.clone()).max_decoding_message_size(2 << 20),
        osrt_proto::auth::CheckToken::new(token(), "test"),
    );
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(service)
            .serve_with_incoming(tonic::transport::server::TcpIncoming::from(listener)),
    );
    let channel = tonic::transport::Endpoint::from_shared(addr)
        .unwrap()
        .connect_lazy();
    let sent: Vec<Chunk> = [1usize, 1000, 1 << 18, 0, 3]
        .into_iter()
        .enumerate()
        .map(|(i, n)| chunk("test-job", 4, 7, i as u32, random(n, i as u64)))
        .collect();
    stream_chunks(channel.clone(), &token(), &sent)
        .await
        .unwrap();
    assert_eq!(*recorder.0.lock().unwrap(), sent);
    // A call with no chunk at all is a valid, empty stream.
    stream_chunks(channel.clone(), &token(), &[]).await.unwrap();
    // Refused halfway: the call ends with the server's status; what came before was taken.
    recorder.0.lock().unwrap().clear();
    let refused = chunk("refuse-me", 4, 7, 0, vec![1.0; 4]);
    let e = stream_chunks(
        channel.clone(),
        &token(),
        &[sent[0].clone(), refused, sent[1].clone()],
    )
    .await
    .unwrap_err();
    assert_eq!(e.code(), tonic::Code::FailedPrecondition, "{e}");
    assert_eq!(e.message(), "refused as asked");
    assert_eq!(*recorder.0.lock().unwrap(), vec![sent[0].clone()]);
    let e = stream_chunks(channel, &Token::generate(), &sent[..1])
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e}");
}

/// tonic's generated streaming client against the ring's server: the chunks of a whole
/// all-reduce arrive as messages of one call and the waiting rank completes; a malformed
/// chunk in the middle of a call fails the call and the round at once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tonics_generated_stream_client_talks_to_the_ring_server() {
    // Chunks of 2: rank 1 receives 2 reduce-scatter and 2 all-gather chunks from rank 0.
    let (nodes, waiting) = rank_1_waiting(2).await;
    let mut client = client_of(&nodes[1]).await;
    let messages = rank_0s_chunks();
    client
        .push_chunks(futures::stream::iter(messages))
        .await
        .unwrap();
    let (result, buf, ring) = waiting.await.unwrap();
    // Rank 1's own sends go to rank 0's server, which takes them without a local
    // all-reduce waiting: the round completes.
    result.unwrap();
    assert_eq!(buf, [2.0, 2.0, 2.0, 2.0, 5.0, 5.0, 5.0, 5.0]);

    // Step 4: a chunk one float short, second in the call.
    let waiting = all_reduce_in_background(ring, 4);
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut short = tagged(Phase::ReduceScatter, 1, 1.0);
    short.tag.as_mut().unwrap().step = 4;
    short.data.truncate(4);
    let mut first = tagged(Phase::ReduceScatter, 0, 1.0);
    first.tag.as_mut().unwrap().step = 4;
    let t = Instant::now();
    let e = client
        .push_chunks(futures::stream::iter(vec![first, short]))
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e}");
    assert!(e.message().contains("malformed chunk"), "{e}");
    the_round_fails_at_once_on_the_malformed_chunk(waiting, t).await;
}

/// A predecessor that sends each chunk just inside the per-chunk timeout (a straggler)
/// fails the all-reduce once the transfer's budget is spent, instead of holding the
/// ring for a timeout per chunk.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_peer_that_drips_its_chunks_fails_the_round_as_a_straggler() {
    let nodes = start(2, "test-job").await;
    nodes[0].mailbox.set_generation(1, 0, 3);
    let timeout = Duration::from_secs(2);
    // Chunks of 1 float: rank 1 receives 4 reduce-scatter and 4 all-gather chunks.
    let ring = Ring::new(
        config(&nodes, 1, 1000, 1, timeout),
        nodes[1].mailbox.clone(),
    )
    .unwrap();
    let t = Instant::now();
    let waiting = all_reduce_in_background(ring, 3);
    let mut client = client_of(&nodes[1]).await;
    let gap = timeout.mul_f64(0.6);
    for (phase, c) in [Phase::ReduceScatter, Phase::AllGather]
        .into_iter()
        .flat_map(|p| (0..4).map(move |c| (p, c)))
    {
        tokio::time::sleep(gap).await;
        if waiting.is_finished() {
            break;
        }
        let mut ch = chunk("test-job", 1, 3, 0, vec![1.0]);
        let tag = ch.tag.as_mut().unwrap();
        tag.phase = phase as i32;
        tag.chunk = c;
        if push_one(&mut client, ch).await.is_err() {
            break;
        }
    }
    let err = waiting.await.unwrap().0.unwrap_err();
    let budget = osrt_collective::all_reduce_budget(timeout, 8 * 4);
    assert!(
        matches!(err, CollectiveError::Straggler { from: 0, expected: 8, received, .. } if received < 8),
        "{err}"
    );
    // The budget counts from the first chunk (one gap in).
    assert!(
        t.elapsed() < budget + timeout * 2,
        "failed after {:?}, budget {budget:?}",
        t.elapsed()
    );
}

/// A predecessor still computing its share when this rank starts the all-reduce (a long
/// step, micro-batches) is waited for within the grace the worker sets, past the
/// per-chunk timeout; without the grace the same wait times out.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_predecessor_still_computing_is_waited_for_within_its_grace() {
    for (grace, finishes) in [(Duration::from_secs(5), true), (Duration::ZERO, false)] {
        let nodes = start(2, "test-job").await;
        nodes[0].mailbox.set_generation(1, 0, 3);
        let cfg = config(&nodes, 1, 1000, 2, Duration::from_secs(1));
        let mut ring = Ring::new(cfg, nodes[1].mailbox.clone()).unwrap();
        ring.set_peer_grace(grace);
        let waiting = all_reduce_in_background(ring, 3);
        // Rank 0 sends its first chunk 2 s in: twice the per-chunk timeout.
        tokio::time::sleep(Duration::from_secs(2)).await;
        let mut client = client_of(&nodes[1]).await;
        let messages = rank_0s_chunks();
        let _ = client.push_chunks(futures::stream::iter(messages)).await;
        let (result, buf, _) = waiting.await.unwrap();
        if finishes {
            result.unwrap();
            assert_eq!(buf, [2.0, 2.0, 2.0, 2.0, 5.0, 5.0, 5.0, 5.0]);
        } else {
            let err = result.unwrap_err();
            assert!(
                matches!(err, CollectiveError::Timeout { from: 0, .. }),
                "{err}"
            );
        }
    }
}
