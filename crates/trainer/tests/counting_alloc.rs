//! The counting allocator as the `osrt` binary installs it: live bytes and their peak
//! follow allocations, frees and reallocations.

use osrt_trainer::memory::{CountingAlloc, live_heap_bytes, peak_heap_bytes, reset_peak_heap};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

#[test]
fn the_peak_follows_allocations_and_frees() {
    const MB: usize = 1 << 20;
    // Other test threads may allocate meanwhile: the bounds allow them a little.
    let slack = 4 * MB;
    let base = live_heap_bytes().expect("installed");
    reset_peak_heap();
    let a = vec![1u8; 64 * MB];
    let live = live_heap_bytes().unwrap();
    assert!(
        live >= base + 64 * MB && live <= base + 64 * MB + slack,
        "{live} vs {base}"
    );
    drop(a);
    let b = vec![1u8; 16 * MB];
    let peak = peak_heap_bytes().unwrap();
    assert!(
        peak >= base + 64 * MB && peak <= base + 64 * MB + slack,
        "{peak}"
    );
    drop(b);
    let after = live_heap_bytes().unwrap();
    assert!(
        after <= base + slack,
        "{after} vs {base}: frees are counted"
    );

    // A growing Vec reallocates: the old and the new block are counted together.
    reset_peak_heap();
    let mut v: Vec<u8> = Vec::with_capacity(32 * MB);
    v.resize(32 * MB, 1);
    v.push(0);
    let peak = peak_heap_bytes().unwrap();
    assert!(
        peak >= base + 96 * MB,
        "{peak}: a moving realloc holds both blocks"
    );
    drop(v);
}
