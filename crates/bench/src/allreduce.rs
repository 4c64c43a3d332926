//! `osrt bench allreduce`: ring all-reduce throughput of 2 ranks over gRPC on loopback,
//! beside raw TCP moving the same bytes between sockets of the same machine.
//!
//! Two baselines, both on sockets connected before the first repeat (as the all-reduce
//! reuses its connections):
//! - the **TCP ring** (the target's): the all-reduce's own traffic over bare sockets. A
//!   ring all-reduce of `N` floats on `W` ranks has every rank send `2·(W−1)/W·N` floats
//!   to its successor while receiving as many from its predecessor, all ranks at once;
//!   the baseline does that with `write_all`/`read`, each rank reading into a buffer of
//!   the message's size, front to back: a copy of the same bytes from one process's
//!   memory into another's, which is the least an all-reduce has to do with them. The
//!   ratio to it is the share of the transport's speed that gRPC framing, the chunk
//!   protocol and the reduction keep.
//! - the same ring **discarding** what it receives (every read into one reused 1 MiB
//!   buffer that stays in cache): the sockets' own speed, a bound no real receiver
//!   reaches; reported for comparison with the figures of 2026-11-25.

use crate::median;
use osrt_collective::{Mailbox, Ring, RingConfig, serve};
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
    /// The ring's traffic over bare sockets, received into message-sized buffers (see the
    /// module docs).
    pub median_tcp_ring_s: f64,
    /// all-reduce throughput / TCP ring throughput (the target's ratio), as the ratio of
    /// the two medians.
    pub ratio: f64,
    /// The same ratio as the median of each repeat's own ratio (its all-reduce against
    /// the TCP ring measured right after it): a noisy spell of a shared machine hits
    /// both members of a pair alike.
    pub ratio_paired: f64,
    /// The ring's traffic over bare sockets, every read into one reused 1 MiB buffer.
    pub median_tcp_ring_discard_s: f64,
    pub ratio_discard: f64,
    pub ratio_discard_paired: f64,
    /// Timed repeats behind the medians.
    pub repeats: usize,
    /// Busy cores during the timed all-reduces: this process's CPU time (user + system,
    /// all threads) over their wall time. Near the machine's core count, the all-reduce is
    /// bound by work (copies, reduction, framing); well below it, by waiting.
    pub allreduce_busy_cores: f64,
    /// The user-space part of `allreduce_busy_cores` (the rest is the kernel's: socket
    /// copies, TCP, wake-ups). The TCP ring's is ~0: its work is all in the kernel.
    pub allreduce_user_cores: f64,
    /// The same as `allreduce_busy_cores` for the copying TCP ring.
    pub tcp_ring_busy_cores: f64,
}

/// This process's CPU time so far, all threads, in seconds: `(user, system)`, from
/// `/proc/self/stat` (clock ticks: 10 ms, so only sums over many repeats mean much);
/// `None` where there is no procfs.
fn process_cpu_s() -> Option<(f64, f64)> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (which may hold spaces, inside parentheses).
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name.
    let ticks = |i: usize| f.get(i)?.parse::<f64>().ok();
    Some((ticks(11)? / 100.0, ticks(12)? / 100.0))
}

/// One rank's sockets of a bare-TCP ring, with the bytes it sends and a receive buffer.
struct Link {
    to_successor: tokio::net::TcpStream,
    from_predecessor: tokio::net::TcpStream,
    data: Vec<u8>,
    /// Where received bytes land: a buffer as large as `data`, filled front to back, or
    /// (`discard`) one reused 1 MiB buffer.
    buf: Vec<u8>,
}

/// A ring of `world` ranks over loopback sockets, connected once and reused for every
/// repeat, as the all-reduce reuses its connections (no connection set-up or TCP slow
/// start in either figure).
struct TcpRing {
    links: Vec<Link>,
    discard: bool,
}

impl TcpRing {
    async fn connect(world: usize, bytes: usize, discard: bool) -> Self {
        let mut listeners = Vec::new();
        for _ in 0..world {
            let l = tokio::net::TcpListener::bind("127.0.0.1:0").await;
            listeners.push(l.expect("bind"));
        }
        let mut links = Vec::new();
        for r in 0..world {
            let addr = listeners[(r + 1) % world].local_addr().expect("addr");
            let s = tokio::net::TcpStream::connect(addr).await.expect("connect");
            s.set_nodelay(true).expect("nodelay");
            // Rank r's predecessor connects to listener r: accept r's incoming below.
            links.push(s);
        }
        let mut incoming = Vec::new();
        for l in &listeners {
            incoming.push(l.accept().await.expect("accept").0);
        }
        // Buffers are touched before any clock starts: page faults are not the transport's.
        let links = links
            .into_iter()
            .zip(incoming)
            .map(|(to_successor, from_predecessor)| Link {
                to_successor,
                from_predecessor,
                data: vec![7u8; bytes],
                buf: vec![0u8; if discard { 1 << 20 } else { bytes }],
            })
            .collect();
        Self { links, discard }
    }

    /// Every rank sends its bytes to its successor while receiving as many from its
    /// predecessor, sending and receiving on tasks of their own (as the gRPC side's client
    /// and server connections are); seconds until all are done.
    async fn run(&mut self) -> f64 {
        let t = Instant::now();
        let discard = self.discard;
        let tasks: Vec<_> = self
            .links
            .drain(..)
            .map(|link| {
                let Link {
                    mut to_successor,
                    mut from_predecessor,
                    data,
                    mut buf,
                } = link;
                let bytes = data.len();
                let send = tokio::spawn(async move {
                    to_successor.write_all(&data).await.expect("write");
                    (to_successor, data)
                });
                let recv = tokio::spawn(async move {
                    let mut got = 0;
                    while got < bytes {
                        let to = if discard {
                            &mut buf[..]
                        } else {
                            &mut buf[got..]
                        };
                        let n = from_predecessor.read(to).await.expect("read");
                        assert!(n > 0, "peer closed early");
                        got += n;
                    }
                    (from_predecessor, buf)
                });
                (send, recv)
            })
            .collect();
        for (send, recv) in tasks {
            let (to_successor, data) = send.await.expect("send task");
            let (from_predecessor, buf) = recv.await.expect("receive task");
            self.links.push(Link {
                to_successor,
                from_predecessor,
                data,
                buf,
            });
        }
        t.elapsed().as_secs_f64()
    }
}

/// Two ranks' rings on loopback, each with its own Collective server.
async fn loopback_rings(chunk_floats: usize) -> Vec<Option<Ring>> {
    let mut addrs = Vec::new();
    let mut mailboxes = Vec::new();
    let credentials =
        osrt_proto::credentials::Credentials::new(osrt_proto::auth::Token::generate(), None);
    for _ in 0..2 {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind");
        addrs.push(format!("http://{}", listener.local_addr().expect("addr")));
        let m = Mailbox::new("bench");
        tokio::spawn(serve(
            listener,
            m.clone(),
            credentials.clone(),
            std::future::pending(),
        ));
        mailboxes.push(m);
    }
    (0..2)
        .map(|rank| {
            let cfg = RingConfig {
                job: "bench".into(),
                generation: 1,
                first_step: 0,
                rank,
                peers: addrs.clone(),
                bucket_floats: 25 << 20,
                chunk_floats,
                timeout: Duration::from_secs(60),
                credentials: credentials.clone(),
            };
            Some(Ring::new(cfg, mailboxes[rank].clone()).expect("ring"))
        })
        .collect()
}

/// Median over at least `repeats` of a 2-rank all-reduce of `floats` values and of a
/// TCP copy of the same number of bytes. Buffers under 10 M floats get proportionally
/// more repeats (at most 20×): a 1 M-float all-reduce takes a few milliseconds, and a
/// median of 5 such figures on a shared 2-core machine says little.
pub async fn bench_allreduce(
    floats: usize,
    repeats: usize,
    chunk_floats: usize,
) -> AllReduceFigures {
    let mut rings = loopback_rings(chunk_floats).await;
    let bytes = floats * 4;
    let repeats = repeats.max(1) * (10_000_000 / floats.max(1)).clamp(1, 20);
    let (mut times, mut ring, mut discard) = (Vec::new(), Vec::new(), Vec::new());
    // CPU seconds of the timed all-reduces and TCP rings.
    let (mut allreduce_cpu, mut allreduce_user, mut ring_cpu) = (0.0, 0.0, 0.0);
    // W = 2: each rank sends 2·(W−1)/W·N = N floats, as in the ring baseline.
    let mut tcp_ring = TcpRing::connect(2, bytes, false).await;
    let mut tcp_ring_discard = TcpRing::connect(2, bytes, true).await;
    // The measurements take turns, so a noisy spell of a shared machine hits them
    // alike and the ratios stay meaningful.
    for step in 0..=repeats as u64 {
        // Each rank on its own task, as each is its own process in a job (and as the
        // TCP baseline runs its ranks): both cores work, neither waits on the other's
        // reduction.
        let bufs = [vec![1.0f32; floats], vec![2.0f32; floats]];
        let cpu0 = process_cpu_s();
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
        let elapsed = t.elapsed().as_secs_f64();
        let cpu1 = process_cpu_s();
        let ring_s = tcp_ring.run().await;
        let cpu2 = process_cpu_s();
        let discard_s = tcp_ring_discard.run().await;
        // Step 0 warms up connections and allocator.
        if step > 0 {
            if let (Some(c0), Some(c1), Some(c2)) = (cpu0, cpu1, cpu2) {
                allreduce_cpu += (c1.0 - c0.0) + (c1.1 - c0.1);
                allreduce_user += c1.0 - c0.0;
                ring_cpu += (c2.0 - c1.0) + (c2.1 - c1.1);
            }
            times.push(elapsed);
            ring.push(ring_s);
            discard.push(discard_s);
        }
    }
    let allreduce_wall = times.iter().sum::<f64>();
    let allreduce_busy_cores = allreduce_cpu / allreduce_wall;
    let allreduce_user_cores = allreduce_user / allreduce_wall;
    let tcp_ring_busy_cores = ring_cpu / ring.iter().sum::<f64>();
    let paired = |base: &[f64]| median(times.iter().zip(base).map(|(a, r)| r / a).collect());
    let (paired_ring, paired_discard) = (paired(&ring), paired(&discard));
    let (ar, tr, td) = (median(times), median(ring), median(discard));
    AllReduceFigures {
        floats,
        chunk_floats,
        bytes,
        median_allreduce_s: ar,
        allreduce_gb_per_s: bytes as f64 / ar / 1e9,
        median_tcp_ring_s: tr,
        ratio: tr / ar,
        ratio_paired: paired_ring,
        median_tcp_ring_discard_s: td,
        ratio_discard: td / ar,
        ratio_discard_paired: paired_discard,
        repeats,
        allreduce_busy_cores,
        allreduce_user_cores,
        tcp_ring_busy_cores,
    }
}
