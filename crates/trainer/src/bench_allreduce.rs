//! `osrt bench allreduce`: ring all-reduce throughput of 2 ranks over gRPC on loopback,
//! beside raw TCP moving the same bytes between sockets of the same machine.
//!
//! Two baselines. The *ring* baseline is the all-reduce's own traffic over bare sockets:
//! a ring all-reduce of `N` floats on `W` ranks has every rank send `2·(W−1)/W·N` floats
//! to its successor while receiving as many from its predecessor, all ranks at once;
//! the baseline does exactly that with `write_all`/`read` on already-connected sockets.
//! The ratio to it is the share of the transport's speed that gRPC framing, the chunk
//! protocol and the reduction keep. The *one-way* baseline (one socket copying `N·4`
//! bytes, connect included) is reported beside it for comparison with older figures.

use crate::collective::{Mailbox, Ring, RingConfig, serve};
use osrt_dataset::bench::median;
use serde::Serialize;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[derive(Debug, Clone, Serialize)]
pub struct AllReduceFigures {
    pub floats: usize,
    pub chunk_floats: usize,
    pub bytes: usize,
    pub median_allreduce_s: f64,
    /// Buffer bytes / all-reduce time.
    pub allreduce_gb_per_s: f64,
    /// The ring's traffic over bare sockets (see the module docs).
    pub median_tcp_ring_s: f64,
    /// all-reduce throughput / ring-traffic TCP throughput (the target's ratio).
    pub ratio: f64,
    /// One socket copying the buffer's bytes once, one way.
    pub median_tcp_copy_s: f64,
    pub tcp_gb_per_s: f64,
    /// all-reduce throughput / one-way copy throughput.
    pub ratio_one_way: f64,
}

/// Connected ring of `world` loopback sockets: `(to successor, from predecessor)` per rank.
async fn tcp_ring_sockets(world: usize) -> Vec<(tokio::net::TcpStream, tokio::net::TcpStream)> {
    let mut listeners = Vec::new();
    for _ in 0..world {
        listeners.push(
            tokio::net::TcpListener::bind("127.0.0.1:0")
                .await
                .expect("bind"),
        );
    }
    let mut outgoing = Vec::new();
    for r in 0..world {
        let addr = listeners[(r + 1) % world].local_addr().expect("addr");
        let s = tokio::net::TcpStream::connect(addr).await.expect("connect");
        s.set_nodelay(true).expect("nodelay");
        outgoing.push(s);
    }
    let mut incoming = Vec::new();
    for l in &listeners {
        incoming.push(l.accept().await.expect("accept").0);
    }
    // Rank r's predecessor connected to listener r.
    outgoing.into_iter().zip(incoming).collect()
}

/// Every rank of a `world` ring sends `bytes` to its successor while receiving `bytes`
/// from its predecessor, as a ring all-reduce does; seconds until all are done.
async fn tcp_ring(world: usize, bytes: usize) -> f64 {
    let sockets = tcp_ring_sockets(world).await;
    // Buffers are touched before the clock starts: page faults are not the transport's.
    let buffers: Vec<_> = (0..world)
        .map(|_| (vec![7u8; bytes], vec![0u8; 1 << 20]))
        .collect();
    let t = Instant::now();
    let tasks: Vec<_> = sockets
        .into_iter()
        .zip(buffers)
        .map(|((mut out, mut inc), (data, mut buf))| {
            tokio::spawn(async move {
                let send = async {
                    out.write_all(&data).await.expect("write");
                };
                let recv = async {
                    let mut got = 0;
                    while got < bytes {
                        let n = inc.read(&mut buf).await.expect("read");
                        assert!(n > 0, "peer closed early");
                        got += n;
                    }
                };
                tokio::join!(send, recv);
            })
        })
        .collect();
    for task in tasks {
        task.await.expect("ring rank");
    }
    t.elapsed().as_secs_f64()
}

async fn tcp_copy(bytes: usize) -> f64 {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("addr");
    let reader = tokio::spawn(async move {
        let (mut s, _) = listener.accept().await.expect("accept");
        let mut buf = vec![0u8; 1 << 20];
        let mut got = 0;
        while got < bytes {
            let n = s.read(&mut buf).await.expect("read");
            assert!(n > 0, "peer closed early");
            got += n;
        }
    });
    let data = vec![7u8; bytes];
    let t = Instant::now();
    let mut s = tokio::net::TcpStream::connect(addr).await.expect("connect");
    s.set_nodelay(true).expect("nodelay");
    s.write_all(&data).await.expect("write");
    reader.await.expect("reader");
    t.elapsed().as_secs_f64()
}

/// Median over `repeats` of a 2-rank all-reduce of `floats` values and of a TCP copy of
/// the same number of bytes.
pub async fn bench_allreduce(
    floats: usize,
    repeats: usize,
    chunk_floats: usize,
) -> AllReduceFigures {
    let mut addrs = Vec::new();
    let mut mailboxes = Vec::new();
    let token = osrt_proto::auth::Token::generate();
    for _ in 0..2 {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind");
        addrs.push(format!("http://{}", listener.local_addr().expect("addr")));
        let m = Mailbox::new("bench");
        tokio::spawn(serve(
            listener,
            m.clone(),
            token.clone(),
            None,
            std::future::pending(),
        ));
        mailboxes.push(m);
    }
    let mut rings: Vec<Option<Ring>> = (0..2)
        .map(|rank| {
            let cfg = RingConfig {
                job: "bench".into(),
                generation: 1,
                rank,
                peers: addrs.clone(),
                bucket_floats: 25 << 20,
                chunk_floats,
                timeout: Duration::from_secs(60),
                token: token.clone(),
                tls: None,
            };
            Some(Ring::new(cfg, mailboxes[rank].clone()).expect("ring"))
        })
        .collect();
    let bytes = floats * 4;
    let (mut times, mut tcp, mut ring) = (Vec::new(), Vec::new(), Vec::new());
    // The three measurements take turns, so a noisy spell of a shared machine hits them
    // alike and the ratios stay meaningful.
    for step in 0..=repeats as u64 {
        // Each rank on its own task, as each is its own process in a job (and as the
        // TCP baseline runs its ranks): both cores work, neither waits on the other's
        // reduction.
        let bufs = [vec![1.0f32; floats], vec![2.0f32; floats]];
        let t = Instant::now();
        let tasks: Vec<_> = bufs
            .into_iter()
            .enumerate()
            .map(|(rank, mut buf)| {
                let mut ring = rings[rank].take().expect("ring");
                tokio::spawn(async move {
                    ring.all_reduce(step, &mut buf).await.expect("all-reduce");
                    (ring, buf)
                })
            })
            .collect();
        for (rank, task) in tasks.into_iter().enumerate() {
            let (ring, buf) = task.await.expect("rank task");
            assert_eq!(buf[floats / 2], 3.0);
            rings[rank] = Some(ring);
        }
        // Step 0 warms up connections and allocator.
        if step > 0 {
            times.push(t.elapsed().as_secs_f64());
            tcp.push(tcp_copy(bytes).await);
            // W = 2: each rank sends 2·(W−1)/W·N = N floats.
            ring.push(tcp_ring(2, bytes).await);
        }
    }
    let (ar, tc, tr) = (median(times), median(tcp), median(ring));
    AllReduceFigures {
        floats,
        chunk_floats,
        bytes,
        median_allreduce_s: ar,
        allreduce_gb_per_s: bytes as f64 / ar / 1e9,
        median_tcp_ring_s: tr,
        ratio: tr / ar,
        median_tcp_copy_s: tc,
        tcp_gb_per_s: bytes as f64 / tc / 1e9,
        ratio_one_way: tc / ar,
    }
}
