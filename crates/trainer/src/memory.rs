//! This process's memory: its resident high-water mark (for run records and sweep
//! tables), and the heap bytes live at once, counted by [`CountingAlloc`] where a binary
//! installs it as its global allocator (the `osrt` binary does), so that `osrt bench
//! model` can state a train step's peak allocation on the CPU.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// Peak resident set size of this process in MiB (`VmHWM` of `/proc/self/status`);
/// `None` where the platform does not report it.
pub fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Resets the resident high-water mark to the current resident size (Linux: writing 5
/// to `/proc/self/clear_refs`); false where that is not possible.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
static INSTALLED: AtomicBool = AtomicBool::new(false);

/// The system allocator, counting the bytes live and their peak. Two relaxed atomic
/// operations per allocation: nothing a train step, whose allocations are tensors, can
/// measure.
pub struct CountingAlloc;

#[allow(unsafe_code)]
// SAFETY: every call is forwarded to `System` with the caller's own arguments, so this
// allocator upholds exactly the guarantees `System` does; the counters are side effects.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded unchanged (see the impl).
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded unchanged (see the impl).
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged (see the impl).
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: forwarded unchanged (see the impl).
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            // Counted as the new block arriving before the old one leaves, which is
            // what a moving realloc costs at its peak.
            grew(new_size);
            LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        }
        p
    }
}

fn grew(bytes: usize) {
    INSTALLED.store(true, Ordering::Relaxed);
    let live = LIVE.fetch_add(bytes, Ordering::Relaxed) + bytes;
    PEAK.fetch_max(live, Ordering::Relaxed);
}

/// Heap bytes allocated and not yet freed; `None` where [`CountingAlloc`] is not this
/// process's global allocator.
pub fn live_heap_bytes() -> Option<usize> {
    INSTALLED
        .load(Ordering::Relaxed)
        .then(|| LIVE.load(Ordering::Relaxed))
}

/// The most heap bytes live at once since the last [`reset_peak_heap`] (or the start).
pub fn peak_heap_bytes() -> Option<usize> {
    INSTALLED
        .load(Ordering::Relaxed)
        .then(|| PEAK.load(Ordering::Relaxed))
}

/// Starts a new peak from the bytes live now.
pub fn reset_peak_heap() {
    PEAK.store(LIVE.load(Ordering::Relaxed), Ordering::Relaxed);
}

#[cfg(test)]
mod tests {
    #[test]
    #[cfg(target_os = "linux")]
    fn peak_rss_grows_with_a_touched_allocation() {
        // From the resident size now: other tests of this process may have raised the
        // high-water mark above it (and freed their memory since).
        super::reset_peak_rss();
        let before = super::peak_rss_mb().expect("linux reports VmHWM");
        let big = vec![1u8; 64 << 20];
        let after = super::peak_rss_mb().expect("linux reports VmHWM");
        assert!(big.iter().map(|&b| b as usize).sum::<usize>() == 64 << 20);
        assert!(after >= before + 60.0, "{before} MiB → {after} MiB");
    }

    /// A test binary does not install the counter: the figures say so rather than 0.
    #[test]
    fn without_the_counting_allocator_there_is_no_heap_figure() {
        let _v = vec![0u8; 1 << 20];
        assert_eq!(super::live_heap_bytes(), None);
        assert_eq!(super::peak_heap_bytes(), None);
    }
}
