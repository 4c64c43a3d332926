//! The ledger of `osrt bench model --ledger` for people: per op kind the products' FLOPs
//! by type, the bytes cast, copied and moved by other ops, and the time at the rates;
//! then any f32 product of a bf16 step, and the costliest products.

use osrt_bench::model::LedgerFigures;
use osrt_kernels::ledger::{Moved, Product};

fn gflop(x: f64) -> f64 {
    x / 1e9
}

fn mb(b: u64) -> f64 {
    b as f64 / 1e6
}

fn shape(p: &Product) -> String {
    let t = |i: usize| match (p.transposed[i], p.copied[i]) {
        (true, _) => "ᵀ",
        (false, true) => "(copied)",
        (false, false) => "",
    };
    format!(
        "{}·[{}×{}]{}·[{}×{}]{} {}×{}→{}",
        p.batch,
        p.m,
        p.k,
        t(0),
        p.k,
        p.n,
        t(1),
        p.a,
        p.b,
        p.out
    )
}

pub(super) fn print_ledger(l: &LedgerFigures) {
    println!(
        "  ledger of {} (batch {}, {} view(s), {} rays, {} px, {} parameters) on {}, {}, {} \
         kernels{}; time at {}",
        l.preset,
        l.batch_size,
        l.input_views,
        l.rays_per_scene,
        l.image_size,
        l.parameters,
        l.device,
        l.precision,
        l.kernels,
        if l.recompute { ", recomputed" } else { "" },
        l.rates.name,
    );
    println!(
        "    {:<12} {:>8} {:>10} {:>10} {:>10} {:>10} {:>10} {:>11} {:>11}",
        "op",
        "products",
        "bf16 GFLOP",
        "f32 GFLOP",
        "cast MB",
        "copy MB",
        "other MB",
        "products ms",
        "moves ms"
    );
    for t in &l.totals {
        let f = |k: &str| t.flops.get(k).copied().unwrap_or(0.0);
        let b = |k: Moved| t.bytes.get(&k).copied().unwrap_or(0);
        println!(
            "    {:<12} {:>8} {:>10.2} {:>10.2} {:>10.1} {:>10.1} {:>10.1} {:>11.3} {:>11.3}",
            t.kind,
            t.products,
            gflop(f("bf16")),
            gflop(f("f32") + f("mixed")),
            mb(b(Moved::Cast)),
            mb(b(Moved::Copy)),
            mb(b(Moved::Op)),
            t.product_s * 1e3,
            t.movement_s * 1e3,
        );
        if t.recompute_flops > 0.0 {
            println!(
                "    {:<12} {:>8} of which made again in the backward pass: {:.2} GFLOP",
                "",
                "",
                gflop(t.recompute_flops)
            );
        }
    }
    if l.precision == "bf16" {
        let f32s: Vec<_> = l
            .entries
            .products
            .iter()
            .filter(|(p, _)| p.precision() != "bf16")
            .collect();
        match f32s.is_empty() {
            true => println!("    every product on bf16 operands"),
            false => println!("    products not on bf16 operands:"),
        }
        for (p, n) in f32s {
            println!("      {n:>4} × {} {:?} {}", p.kind, p.phase, shape(p));
        }
    }
    let mut costly: Vec<_> = l.entries.products.iter().collect();
    let at = |(p, n): &&(Product, usize)| *n as f64 * l.rates.product_s(p);
    costly.sort_by(|a, b| at(b).total_cmp(&at(a)));
    println!("    costliest products (calls × time at the rates):");
    for e in costly.iter().take(10) {
        let (p, n) = e;
        println!(
            "      {:>8.3} ms  {n:>4} × {} {:?} {}",
            at(e) * 1e3,
            p.kind,
            p.phase,
            shape(p)
        );
    }
}
