//! What a bf16 matrix product keeps for the backward pass, counted by this test binary's
//! allocator (one test in the binary, so no other test allocates meanwhile).

use candle_core::{DType, Device, Tensor, Var};
use osrt_kernels::{Kernels, Precision, matmul, with_kernels, with_precision};
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

static LIVE: AtomicUsize = AtomicUsize::new(0);

struct Counting;

#[allow(unsafe_code)]
// SAFETY: every call is forwarded to `System` unchanged; the counter is a side effect.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded unchanged.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            LIVE.fetch_add(layout.size(), Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged.
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// The counter sees every thread: the tests of this file take turns.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn var(dims: &[usize], seed: u64) -> Var {
    let n: usize = dims.iter().product();
    let v: Vec<f32> = (0..n)
        .map(|i| ((i as u64 * 2654435761 + seed) % 1000) as f32 / 500.0 - 1.0)
        .collect();
    Var::from_tensor(&Tensor::from_vec(v, dims, &Device::Cpu).unwrap()).unwrap()
}

/// Bytes held after `x · w` while its graph is alive, less the operands (which the step
/// holds anyway), and the gradient of `w` for comparison.
fn kept(kernels: Kernels, x: &Var, w: &Var) -> (usize, Tensor) {
    with_kernels(kernels, || {
        with_precision(Precision::Bf16, || {
            let before = LIVE.load(Ordering::Relaxed);
            let y = matmul(x.as_tensor(), w.as_tensor()).unwrap();
            let kept = LIVE.load(Ordering::Relaxed) - before;
            let g = y.sum_all().unwrap().backward().unwrap();
            (kept, g.get(w.as_tensor()).unwrap().clone())
        })
    })
}

/// The one-node bf16 product keeps its f32 output and nothing else; candle's composed
/// version also keeps the bf16 copies of both operands and of the product. The two
/// compute the same gradient. (The device graph's node: the fused CPU kernels' bf16
/// product, which keeps nothing either, rounds differently; `a_fused_bf16_product_keeps_its_output_only`.)
#[test]
fn a_bf16_product_keeps_no_bf16_copies() {
    let _turn = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let (m, k, n) = (512, 256, 128);
    let (x, w) = (var(&[m, k], 1), var(&[k, n], 2));
    let out = m * n * 4;
    // Once each first: thread pools and the products' packing buffers are allocated at
    // first use and stay. Then the median of five: the counter sees every thread, and a
    // pool thread that takes its first task in a counted call (or frees a buffer late) moves
    // one count by its buffer's size.
    kept(Kernels::Device, &x, &w);
    kept(Kernels::Composed, &x, &w);
    let median = |kernels: Kernels| {
        let mut runs: Vec<(usize, Tensor)> = (0..5).map(|_| kept(kernels, &x, &w)).collect();
        runs.sort_by_key(|r| r.0);
        runs.swap_remove(2)
    };
    let (node, g_node) = median(Kernels::Device);
    let (composed, g_composed) = median(Kernels::Composed);
    // A few hundred bytes of graph bookkeeping besides the tensors.
    assert!(
        node >= out && node < out + 4096,
        "node kept {node}, output {out}"
    );
    let copies = (m * k + k * n + m * n) * 2;
    assert!(
        composed >= out + copies,
        "composed kept {composed}, output {out} + bf16 copies {copies}"
    );
    assert_eq!(g_node.dtype(), DType::F32);
    let d = (g_node - g_composed)
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap();
    assert_eq!(d.to_scalar::<f32>().unwrap(), 0.0);
}

/// The fused CPU kernels' bf16 product (where the CPU has one) keeps its f32 output and
/// nothing else either: its operands' bf16 packing is per call.
#[test]
fn a_fused_bf16_product_keeps_its_output_only() {
    let _turn = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let (m, k, n) = (512, 256, 128);
    let (x, w) = (var(&[m, k], 1), var(&[k, n], 2));
    let out = m * n * 4;
    kept(Kernels::Fused, &x, &w);
    let mut runs: Vec<usize> = (0..5).map(|_| kept(Kernels::Fused, &x, &w).0).collect();
    runs.sort();
    assert!(
        runs[2] >= out && runs[2] < out + 4096,
        "kept {}, output {out}",
        runs[2]
    );
}
