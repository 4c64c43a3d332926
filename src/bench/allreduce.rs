//! `osrt bench allreduce`: the ring all-reduce over gRPC on loopback against bare TCP
//! rings moving the same bytes.

use super::save_json;
use anyhow::Result;
use clap::Args;

#[derive(Args)]
pub struct BenchAllReduceArgs {
    /// Buffer sizes in floats.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1000000,10000000,50000000"
    )]
    pub floats: Vec<usize>,
    /// Timed repeats per size (after one warm-up; sizes under 10 M floats get proportionally
    /// more, at most 20×); medians are reported.
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Floats per chunk (1024 to 262144: 4 KiB to 1 MiB).
    #[arg(long, default_value_t = osrt_proto::MAX_CHUNK_FLOATS, value_parser = crate::flags::chunk_floats)]
    pub chunk_floats: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Where the JSON figures are saved.
    #[arg(long, default_value = "target/bench/allreduce.json")]
    pub out: std::path::PathBuf,
}

pub async fn allreduce(a: BenchAllReduceArgs) -> Result<()> {
    crate::cluster::reexec_with_worker_allocator()?;
    let mut rows = Vec::new();
    for &n in &a.floats {
        rows.push(osrt_bench::allreduce::bench_allreduce(n, a.repeats, a.chunk_floats).await);
    }
    let text = save_json(&a.out, &serde_json::to_value(&rows)?)?;
    if a.json {
        println!("{text}");
        return Ok(());
    }
    println!(
        "ring all-reduce, 2 ranks over gRPC on loopback, vs bare TCP sockets copying the same \
         bytes in the same ring into message-sized buffers (the target's baseline) and the same \
         ring discarding what it reads:"
    );
    for r in &rows {
        println!(
            "  {:>10} floats: all-reduce {:>8.2} ms ({:.2} GB/s) | TCP ring {:>8.2} ms, ratio {:.2} (paired {:.2}, {} repeats) | TCP ring discarding {:>8.2} ms, ratio {:.2} (paired {:.2}) | busy cores: all-reduce {:.2} (user {:.2}), TCP ring {:.2}",
            r.floats,
            r.median_allreduce_s * 1e3,
            r.allreduce_gb_per_s,
            r.median_tcp_ring_s * 1e3,
            r.ratio,
            r.ratio_paired,
            r.repeats,
            r.median_tcp_ring_discard_s * 1e3,
            r.ratio_discard,
            r.ratio_discard_paired,
            r.allreduce_busy_cores,
            r.allreduce_user_cores,
            r.tcp_ring_busy_cores
        );
    }
    println!("saved to {}", a.out.display());
    Ok(())
}
