//! The all-reduce benchmark against its baselines, on loopback.

/// `osrt bench allreduce` end to end on a small buffer: every figure is a positive,
/// finite time or ratio, and its all-reduces summed correctly (the benchmark asserts it).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_allreduce_benchmark_measures_every_baseline() {
    let f = osrt_bench::allreduce::bench_allreduce(20_000, 1, 4096).await;
    assert_eq!(f.bytes, 80_000);
    assert_eq!(f.repeats, 20);
    for x in [
        f.median_allreduce_s,
        f.median_tcp_ring_s,
        f.median_tcp_ring_discard_s,
        f.ratio,
        f.ratio_paired,
        f.ratio_discard,
    ] {
        assert!(x.is_finite() && x > 0.0, "{f:?}");
    }
}
