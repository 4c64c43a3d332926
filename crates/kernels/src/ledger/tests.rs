use super::*;
use crate::testing::randn;
use crate::{Kernels, MlpAct, Precision, on_device_pool, with_kernels, with_precision};
use candle_core::{Device, Var};

/// Runs `f` with `k` and `p`, the forward pass's entries in one ledger and the backward
/// pass's (of the sum of `f`'s output) in another.
fn passes(k: Kernels, p: Precision, f: impl Fn() -> Tensor + Send + Sync) -> (Entries, Entries) {
    let (fwd, bwd) = (Ledger::default(), Ledger::default());
    with_kernels(k, || {
        with_precision(p, || {
            let y = recording(Some(fwd.clone()), || on_device_pool(&Device::Cpu, &f));
            recording(Some(bwd.clone()), || {
                on_device_pool(&Device::Cpu, || y.sum_all().unwrap().backward().unwrap())
            });
        })
    });
    (fwd.take(), bwd.take())
}

fn flops(e: &Entries, phase: Phase) -> f64 {
    let of = |p: &Product, n: &usize| (p.phase == phase) as usize as f64 * p.flops() * *n as f64;
    e.products.iter().map(|(p, n)| of(p, n)).sum()
}

fn precisions(e: &Entries) -> Vec<String> {
    let mut v: Vec<String> = e
        .products
        .iter()
        .map(|(p, _)| p.precision().into())
        .collect();
    v.dedup();
    v
}

/// An MLP `8 → 16 → 4` over 15 rows, its input a constant: forward `2·15·(8·16 + 16·4)`
/// FLOPs, backward both weights' gradients and the hidden layer's input gradient (not
/// the input's). The device graph's node and the fused CPU node, entered at different
/// places (the node's tensor products; the gemm calls), agree; every product is under the
/// op's kind, in the pass that made it, in the precision asked for; candle's composed
/// backward pass (entered from the forward pass's shapes) computes the input's gradient
/// too, as candle does.
#[test]
fn an_mlps_products_are_entered_once_each_in_their_pass() {
    let x = randn(&[3, 5, 8], 1.0, 1);
    let w: Vec<Var> = [(&[16usize, 8][..], 2), (&[16], 3), (&[4, 16], 4), (&[4], 5)]
        .iter()
        .map(|&(s, seed)| Var::from_tensor(&randn(s, 0.3, seed)).unwrap())
        .collect();
    let f = || {
        let layers = [
            (w[0].as_tensor(), Some(w[1].as_tensor())),
            (w[2].as_tensor(), Some(w[3].as_tensor())),
        ];
        crate::mlp(&x, &layers, MlpAct::Gelu).unwrap()
    };
    let rows = 15.0;
    let forward = 2.0 * rows * (8.0 * 16.0 + 16.0 * 4.0);
    let backward = 2.0 * rows * (8.0 * 16.0 + 16.0 * 4.0 + 16.0 * 4.0);
    for (k, p, want) in [
        (Kernels::Device, Precision::Bf16, "bf16"),
        (Kernels::Device, Precision::F32, "f32"),
        (Kernels::Fused, Precision::F32, "f32"),
    ] {
        let (fw, bw) = passes(k, p, f);
        let case = format!("{k} {p}");
        assert_eq!(flops(&fw, Phase::Forward), forward, "{case}");
        assert_eq!(flops(&fw, Phase::Backward), 0.0, "{case}");
        assert_eq!(flops(&bw, Phase::Backward), backward, "{case}");
        assert_eq!(flops(&bw, Phase::Forward), 0.0, "{case}");
        assert_eq!(fw.products.len() + bw.products.len(), 5, "{case}");
        for e in [&fw, &bw] {
            assert!(e.products.iter().all(|(p, _)| p.kind == "mlp"), "{case}");
            assert_eq!(precisions(e), [want], "{case}");
        }
        // Casts only where the products are bf16.
        let casts = |e: &Entries| e.movements.iter().any(|(m, _)| m.moved == Moved::Cast);
        assert_eq!(casts(&fw) && casts(&bw), p == Precision::Bf16, "{case}");
    }
    for p in [Precision::F32, Precision::Bf16] {
        let (fw, bw) = passes(Kernels::Composed, p, f);
        assert_eq!(flops(&fw, Phase::Forward), forward, "composed {p}");
        let both = 2.0 * rows * (8.0 * 16.0 + 16.0 * 4.0) * 2.0;
        assert_eq!(flops(&fw, Phase::Backward), both, "composed {p}");
        assert!(
            bw.products.is_empty(),
            "composed {p}: candle's own backward pass"
        );
        assert_eq!(precisions(&fw), [p.to_string()], "composed {p}");
    }
}

/// Attention over 2 heads and 70 keys (enough that the device graph splits the heads):
/// the device graph's node and the fused CPU node enter the same products (Q·Kᵀ and the
/// weights times V forward; four backward), the device graph's in bf16 with the heads'
/// split and merge as copies, the fused node's with none (its heads are strided views).
#[test]
fn attentions_products_agree_between_the_device_graph_and_the_fused_node() {
    let q = Var::from_tensor(&randn(&[2, 7, 8], 1.0, 1)).unwrap();
    let kv = Var::from_tensor(&randn(&[2, 70, 8], 1.0, 2)).unwrap();
    let f = || crate::attention(q.as_tensor(), kv.as_tensor(), kv.as_tensor(), 2, 0.5).unwrap();
    let (b, n, m, dh) = (2.0 * 2.0, 7.0, 70.0, 4.0);
    let forward = 2.0 * b * (n * m * dh + n * dh * m);
    let backward = 4.0 * 2.0 * b * n * m * dh;
    let mut seen = Vec::new();
    for (k, p) in [
        (Kernels::Device, Precision::Bf16),
        (Kernels::Device, Precision::F32),
        (Kernels::Fused, Precision::F32),
    ] {
        let (fw, bw) = passes(k, p, f);
        assert_eq!(flops(&fw, Phase::Forward), forward, "{k} {p}");
        assert_eq!(flops(&bw, Phase::Backward), backward, "{k} {p}");
        assert!(fw.products.iter().all(|(p, _)| p.kind == "attention"));
        let copies = |e: &Entries| {
            e.movements
                .iter()
                .filter(|(m, _)| m.what.starts_with("copy"))
                .count()
        };
        seen.push((copies(&fw) > 0, precisions(&fw)));
    }
    assert_eq!(
        seen,
        [
            (true, vec!["bf16".to_string()]),
            (true, vec!["f32".to_string()]),
            (false, vec!["f32".to_string()])
        ]
    );
}

/// A segment made again in the backward pass (`recompute`) enters its products a second
/// time, as `Recompute`, with the forward pass's FLOPs.
#[test]
fn a_recomputed_segment_enters_its_forward_products_again() {
    let x = randn(&[4, 6], 1.0, 1);
    let w = Var::from_tensor(&randn(&[6, 5], 1.0, 2)).unwrap();
    let ledger = Ledger::default();
    with_kernels(Kernels::Device, || {
        recording(Some(ledger.clone()), || {
            let (y, cuts) = crate::with_cuts(true, || {
                let h = crate::recompute(&[&x, w.as_tensor()], |t| crate::matmul(&t[0], &t[1]))?;
                h.sqr()?.sum_all()
            });
            let mut grads = y.unwrap().backward().unwrap();
            cuts.backward(&mut grads).unwrap();
        })
    });
    let e = ledger.take();
    let product = 2.0 * 4.0 * 6.0 * 5.0;
    assert_eq!(flops(&e, Phase::Forward), product);
    assert_eq!(flops(&e, Phase::Recompute), product);
    assert_eq!(
        flops(&e, Phase::Backward),
        product,
        "only the weight's gradient"
    );
}

/// How a product reads an operand: row-major, transposed by strides, or neither.
#[test]
fn an_operands_layout_says_how_the_product_reads_it() {
    let t = randn(&[2, 3, 4], 1.0, 1);
    assert_eq!(reads_as(t.layout()), Some(false));
    assert_eq!(reads_as(t.t().unwrap().layout()), Some(true));
    // candle's products want each matrix's rows packed (cuBLAS's `lda` = its width).
    let apart = t.permute((1, 0, 2)).unwrap();
    assert_eq!(
        reads_as(apart.layout()),
        None,
        "rows of a permuted batch lie apart"
    );
    let narrow = t.narrow(2, 0, 2).unwrap();
    assert_eq!(
        reads_as(narrow.layout()),
        None,
        "a column slice needs a copy"
    );
}

/// Totals: per kind and for the step, FLOPs by type, bytes by movement, and the time at
/// the rates: a product takes the longer of its FLOPs at its type's rate and its bytes at
/// the bandwidth.
#[test]
fn totals_add_up_per_kind_and_over_the_step() {
    let p = |kind: &str, a: &str, m: usize| Product {
        kind: kind.into(),
        phase: Phase::Forward,
        batch: 1,
        m,
        n: 64,
        k: 64,
        a: a.into(),
        b: a.into(),
        out: "f32".into(),
        transposed: [false; 2],
        copied: [false; 2],
    };
    let cast = Movement {
        kind: "mlp".into(),
        phase: Phase::Backward,
        moved: Moved::Cast,
        what: "cast f32→bf16".into(),
        read: 400,
        written: 200,
    };
    let e = Entries {
        products: vec![(p("mlp", "bf16", 1024), 2), (p("attention", "f32", 8), 3)],
        movements: vec![(cast, 5)],
    };
    let rates = Rates {
        name: "test".into(),
        bf16_flops: 1e12,
        f32_flops: 1e11,
        bandwidth: 1e9,
    };
    let t = e.totals(&rates);
    assert_eq!(
        t.iter().map(|t| t.kind.as_str()).collect::<Vec<_>>(),
        ["mlp", "attention", "step"]
    );
    let mlp_flops = 2.0 * 1024.0 * 64.0 * 64.0;
    assert_eq!(t[0].flops["bf16"], 2.0 * mlp_flops);
    assert_eq!(t[0].bytes[&Moved::Cast], 3000);
    // bf16 at 1e12 FLOP/s: 8.4 µs of products; its bytes (128 + 8 + 256 KiB) take longer.
    let bytes = 1024.0 * 64.0 * 2.0 + 64.0 * 64.0 * 2.0 + 1024.0 * 64.0 * 4.0;
    assert_eq!(t[0].product_s, 2.0 * bytes / 1e9);
    assert_eq!(t[0].movement_s, 3000.0 / 1e9);
    let step = &t[2];
    assert_eq!(step.products, 5);
    assert_eq!(step.all_flops(), t[0].all_flops() + t[1].all_flops());
    assert_eq!(step.product_s, t[0].product_s + t[1].product_s);
}
