//! osrt's CUDA kernels (`device_kernels.cu`) run on the host, for a build without a GPU:
//! the source is compiled by the host's C++ compiler after a CUDA emulator
//! (`emulated/cuda_host.hpp`: a host thread per CUDA thread, warps meeting at a barrier
//! on each shuffle), loaded, and launched with the geometry `cuda::launch` uses
//! (`device_kernels`). The tests hold each kernel to the CPU op or an f64 reference on
//! the same inputs, ordinary and extreme: an indexing or reduction error in the source
//! shows here, before any GPU runs it. What remains for a GPU (`osrt check-device`):
//! NVRTC's code, fused multiply-adds, the device's math library and speed.

// The kernels are foreign functions over raw pointers; each call below passes buffers of
// the sizes the kernel's launch reads and writes (checked by the assertions beside it).
#![allow(unsafe_code)]

use super::device_kernels::{self as geometry, Launch, PARAM_CHUNK, SOURCE};
use std::ffi::c_void;
use std::sync::OnceLock;

/// The host runtime the kernels compile against (threads for CUDA threads, barriers for
/// warps and blocks).
const HEADER: &str = include_str!("emulated/cuda_host.hpp");

type LaunchFn = unsafe extern "C" fn(
    u32,
    u32,
    u32,
    u32,
    u32,
    u32,
    extern "C" fn(*mut c_void),
    *mut c_void,
) -> i32;

/// The host build of the kernels, loaded once per test process.
pub(crate) struct Emulator {
    lib: libloading::Library,
}

/// A raw pointer shared by the emulated threads (each writes its own elements).
pub(crate) struct Ptr<T>(*mut T);
impl<T> Clone for Ptr<T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for Ptr<T> {}
// SAFETY: the kernels' threads write disjoint elements; the buffers outlive the launch.
unsafe impl<T> Sync for Ptr<T> {}
unsafe impl<T> Send for Ptr<T> {}

impl<T> Ptr<T> {
    pub(crate) fn of(v: &mut [T]) -> Self {
        Self(v.as_mut_ptr())
    }
    /// The pointer (a method, so that a closure captures the `Sync` wrapper, not the field).
    pub(crate) fn get(&self) -> *mut T {
        self.0
    }
}

impl Emulator {
    /// Compiles and loads the kernels with the host's C++ compiler (`$CXX`, else `c++`).
    pub(crate) fn get() -> &'static Emulator {
        static EMU: OnceLock<Emulator> = OnceLock::new();
        EMU.get_or_init(|| Self::build().unwrap_or_else(|e| panic!("CUDA emulator: {e}")))
    }

    fn build() -> std::result::Result<Emulator, String> {
        let dir = std::env::temp_dir().join(format!("osrt-emulated-{}", std::process::id()));
        std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        // The header goes beside the source, from the text compiled into this binary: a
        // path into the checkout would be the one this crate was compiled at, and a build
        // folder shared by checkouts at other paths (CI's) keeps binaries whose checkout
        // has moved.
        let header = dir.join("cuda_host.hpp");
        std::fs::write(&header, HEADER).map_err(|e| format!("{}: {e}", header.display()))?;
        let src = dir.join("kernels.cpp");
        std::fs::write(
            &src,
            format!("#include \"cuda_host.hpp\"\n#line 1 \"device_kernels.cu\"\n{SOURCE}"),
        )
        .map_err(|e| format!("{}: {e}", src.display()))?;
        let lib = dir.join("libkernels.so");
        let cxx = std::env::var("CXX").unwrap_or_else(|_| "c++".into());
        let out = std::process::Command::new(&cxx)
            .args([
                "-std=c++20",
                "-O1",
                "-shared",
                "-fPIC",
                "-pthread",
                "-Wall",
                "-Werror",
            ])
            .arg("-Wno-unused-function")
            .arg(&src)
            .arg("-o")
            .arg(&lib)
            .output()
            .map_err(|e| format!("running {cxx} (a C++20 compiler, gcc's g++ on Debian): {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "{cxx} failed on the kernels:\n{}",
                String::from_utf8_lossy(&out.stderr)
            ));
        }
        // SAFETY: the library is the file just built from the header above and the
        // kernels; loading it runs no initialisers beyond the C++ runtime's.
        let lib = unsafe { libloading::Library::new(&lib) }.map_err(|e| e.to_string())?;
        let _ = std::fs::remove_dir_all(&dir);
        Ok(Emulator { lib })
    }

    /// Kernel `name` as a function pointer of type `F` (its signature, written by the caller).
    ///
    /// # Safety
    /// `F` must be the kernel's C signature.
    pub(crate) unsafe fn kernel<F: Copy>(&self, name: &str) -> F {
        // SAFETY: the caller names the kernel's signature.
        let sym = unsafe { self.lib.get::<F>(name.as_bytes()) }
            .unwrap_or_else(|e| panic!("kernel {name}: {e}"));
        *sym
    }

    /// Runs `body` (a kernel call) once per thread of the launch, as a GPU would.
    pub(crate) fn launch(&self, l: Launch, body: &(dyn Fn() + Sync)) {
        extern "C" fn trampoline(ctx: *mut c_void) {
            // SAFETY: `ctx` is the `&&dyn Fn` below, alive until the launch returns.
            let f = unsafe { &*(ctx as *const &(dyn Fn() + Sync)) };
            if std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).is_err() {
                std::process::abort();
            }
        }
        // SAFETY: `emu_launch` is the header's launcher; it joins every thread before
        // returning, so `body` outlives all calls.
        let launch: LaunchFn = unsafe { self.kernel("emu_launch") };
        let ctx = &body as *const &(dyn Fn() + Sync) as *mut c_void;
        let (g, b) = (l.grid, l.block);
        let rc = unsafe { launch(g.0, g.1, g.2, b.0, b.1, b.2, trampoline, ctx) };
        assert_eq!(rc, 0, "emulated launch {l:?} failed");
    }
}

type RowFwd = unsafe extern "C" fn(*const f32, *const f32, *const f32, *mut f32, i32, i32, f32);
type RowBwd =
    unsafe extern "C" fn(*const f32, *const f32, *const f32, *mut f32, *mut f32, i32, i32, f32);
type Partials = unsafe extern "C" fn(*const f32, *const f32, *const f32, *mut f32, i32, i32, i32);
type SumChunks = unsafe extern "C" fn(*const f32, *mut f32, i32, i32);
type ColumnPartials = unsafe extern "C" fn(*const f32, *mut f32, i32, i32, i32);
type SoftmaxFwd = unsafe extern "C" fn(*const f32, *mut f32, i32, i32);
type SoftmaxBwd = unsafe extern "C" fn(*const f32, *const f32, *mut f32, i32, i32);
type SoftmaxBwdScaled = unsafe extern "C" fn(*const f32, *mut f32, i32, i32, f32);
type BiasActFwd = unsafe extern "C" fn(*const f32, *const f32, *mut f32, i64, i32, i32, f32);
type BiasActBwd =
    unsafe extern "C" fn(*const f32, *const f32, *const f32, *mut f32, i64, i32, i32, f32);
type BiasActLow = unsafe extern "C" fn(*const u16, *const f32, *mut u16, i64, i32, i32, f32);
type BiasActFwdInPlace = unsafe extern "C" fn(*mut f32, *const f32, i64, i32, i32, f32);
type BiasActBwdInPlace = unsafe extern "C" fn(*mut f32, *const f32, *const f32, i64, i32, i32, f32);
type BiasActBwdLow =
    unsafe extern "C" fn(*const u16, *const f32, *const u16, *mut f32, i64, i32, i32, f32);
type Fold<I, O> =
    unsafe extern "C" fn(*const I, *mut O, i64, i32, i32, i32, i32, i32, i32, i32, i32);

/// The host sequences of `cuda::rows` and `cuda::elementwise`, on host buffers.
impl Emulator {
    /// `cuda::layer_norm_fwd`: rows of `d`.
    pub(crate) fn layer_norm_fwd(&self, x: &[f32], g: &[f32], b: &[f32], eps: f32) -> Vec<f32> {
        let d = g.len();
        assert!(b.len() == d && x.len().is_multiple_of(d));
        let rows = (x.len() / d) as i32;
        let mut y = vec![f32::NAN; x.len()];
        // SAFETY: the signature of `osrt_layer_norm_fwd`.
        let k: RowFwd = unsafe { self.kernel("osrt_layer_norm_fwd") };
        let (xp, gp, bp, yp) = (ptr(x), ptr(g), ptr(b), Ptr::of(&mut y));
        self.launch(geometry::rows(rows), &|| unsafe {
            k(xp.get(), gp.get(), bp.get(), yp.get(), rows, d as i32, eps)
        });
        y
    }

    /// `cuda::layer_norm_bwd`: `(dx, dγ, dβ)`; the parameter sums over at most `y_cap`
    /// block rows (`u32::MAX`: `cuda::rows`'s launch).
    pub(crate) fn layer_norm_bwd(
        &self,
        x: &[f32],
        g: &[f32],
        dy: &[f32],
        eps: f32,
        y_cap: u32,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let d = g.len();
        assert!(dy.len() == x.len() && x.len().is_multiple_of(d));
        let rows = x.len() / d;
        let chunks = geometry::chunks(rows);
        let mut dx = vec![f32::NAN; x.len()];
        let mut stats = vec![f32::NAN; 2 * rows];
        let mut partial = vec![f32::NAN; chunks * 2 * d];
        let mut sums = vec![f32::NAN; 2 * d];
        // SAFETY: the kernels' signatures; the buffers have the sizes the launches of
        // `cuda::rows` and `cuda::elementwise` allocate.
        unsafe {
            let bwd: RowBwd = self.kernel("osrt_layer_norm_bwd");
            let params: Partials = self.kernel("osrt_layer_norm_bwd_params");
            let sum: SumChunks = self.kernel("osrt_sum_chunks");
            let (xp, gp, dyp) = (ptr(x), ptr(g), ptr(dy));
            let (dxp, sp, pp, op) = (
                Ptr::of(&mut dx),
                Ptr::of(&mut stats),
                Ptr::of(&mut partial),
                Ptr::of(&mut sums),
            );
            let (r, dd) = (rows as i32, d as i32);
            self.launch(geometry::rows(r), &|| {
                bwd(
                    xp.get(),
                    gp.get(),
                    dyp.get(),
                    dxp.get(),
                    sp.get(),
                    r,
                    dd,
                    eps,
                )
            });
            self.launch(capped(geometry::columns(dd, chunks), y_cap), &|| {
                params(
                    xp.get(),
                    dyp.get(),
                    sp.get(),
                    pp.get(),
                    r,
                    dd,
                    PARAM_CHUNK as i32,
                )
            });
            self.launch(geometry::columns(2 * dd, 1), &|| {
                sum(pp.get(), op.get(), chunks as i32, 2 * dd)
            });
        }
        let db = sums.split_off(d);
        (dx, sums, db)
    }

    /// `cuda::softmax_fwd` over rows of `d`.
    pub(crate) fn softmax_fwd(&self, x: &[f32], d: usize) -> Vec<f32> {
        let rows = (x.len() / d) as i32;
        let mut y = vec![f32::NAN; x.len()];
        // SAFETY: the signature of `osrt_softmax_fwd`.
        let k: SoftmaxFwd = unsafe { self.kernel("osrt_softmax_fwd") };
        let (xp, yp) = (ptr(x), Ptr::of(&mut y));
        self.launch(geometry::rows(rows), &|| unsafe {
            k(xp.get(), yp.get(), rows, d as i32)
        });
        y
    }

    /// `cuda::softmax_bwd` from the output `y`.
    pub(crate) fn softmax_bwd(&self, y: &[f32], dy: &[f32], d: usize) -> Vec<f32> {
        let rows = (y.len() / d) as i32;
        let mut dx = vec![f32::NAN; y.len()];
        // SAFETY: the signature of `osrt_softmax_bwd`.
        let k: SoftmaxBwd = unsafe { self.kernel("osrt_softmax_bwd") };
        let (yp, dyp, dxp) = (ptr(y), ptr(dy), Ptr::of(&mut dx));
        self.launch(geometry::rows(rows), &|| unsafe {
            k(yp.get(), dyp.get(), dxp.get(), rows, d as i32)
        });
        dx
    }

    /// `cuda::softmax_bwd_scaled_in_place`: `dy` overwritten.
    pub(crate) fn softmax_bwd_scaled_in_place(
        &self,
        y: &[f32],
        dy: &mut [f32],
        d: usize,
        scale: f32,
    ) {
        assert_eq!(y.len(), dy.len());
        let rows = (y.len() / d) as i32;
        // SAFETY: the signature of `osrt_softmax_bwd_scaled_inplace`.
        let k: SoftmaxBwdScaled = unsafe { self.kernel("osrt_softmax_bwd_scaled_inplace") };
        let (yp, dyp) = (ptr(y), Ptr::of(dy));
        self.launch(geometry::rows(rows), &|| unsafe {
            k(yp.get(), dyp.get(), rows, d as i32, scale)
        });
    }

    /// `cuda::bias_act_fwd` with `(kind, slope)` of `cpu::bias_act::act_code`, over `launch`.
    pub(crate) fn bias_act_fwd(
        &self,
        x: &[f32],
        b: &[f32],
        act: (i32, f32),
        l: Launch,
    ) -> Vec<f32> {
        let mut y = vec![f32::NAN; x.len()];
        // SAFETY: the signature of `osrt_bias_act_fwd`.
        let k: BiasActFwd = unsafe { self.kernel("osrt_bias_act_fwd") };
        let (xp, bp, yp) = (ptr(x), ptr(b), Ptr::of(&mut y));
        let (n, cols) = (x.len() as i64, b.len() as i32);
        self.launch(l, &|| unsafe {
            k(xp.get(), bp.get(), yp.get(), n, cols, act.0, act.1)
        });
        y
    }

    /// `cuda::bias_act_bwd`.
    pub(crate) fn bias_act_bwd(
        &self,
        x: &[f32],
        b: &[f32],
        dy: &[f32],
        act: (i32, f32),
    ) -> Vec<f32> {
        let mut dz = vec![f32::NAN; x.len()];
        // SAFETY: the signature of `osrt_bias_act_bwd`.
        let k: BiasActBwd = unsafe { self.kernel("osrt_bias_act_bwd") };
        let (xp, bp, dyp, dzp) = (ptr(x), ptr(b), ptr(dy), Ptr::of(&mut dz));
        let (n, cols) = (x.len() as i64, b.len() as i32);
        self.launch(geometry::elementwise(x.len()), &|| unsafe {
            k(
                xp.get(),
                bp.get(),
                dyp.get(),
                dzp.get(),
                n,
                cols,
                act.0,
                act.1,
            )
        });
        dz
    }

    /// `cuda::bias_act_low` over `launch`: bf16 bits in and out.
    pub(crate) fn bias_act_low(
        &self,
        z: &[u16],
        b: &[f32],
        act: (i32, f32),
        l: Launch,
    ) -> Vec<u16> {
        let mut y = vec![0xffffu16; z.len()];
        // SAFETY: the signature of `osrt_bias_act_low`.
        let k: BiasActLow = unsafe { self.kernel("osrt_bias_act_low") };
        let (n, cols) = (z.len() as i64, b.len() as i32);
        let (zp, bp, yp) = (Ptr(z.as_ptr() as *mut u16), ptr(b), Ptr::of(&mut y));
        self.launch(l, &|| unsafe {
            k(zp.get(), bp.get(), yp.get(), n, cols, act.0, act.1)
        });
        y
    }

    /// `cuda::bias_act_bwd_low` over `launch`: bf16 bits of `z` and `dy` in, f32 out.
    pub(crate) fn bias_act_bwd_low(
        &self,
        z: &[u16],
        b: &[f32],
        dy: &[u16],
        act: (i32, f32),
        l: Launch,
    ) -> Vec<f32> {
        assert_eq!(z.len(), dy.len());
        let mut dz = vec![f32::NAN; z.len()];
        // SAFETY: the signature of `osrt_bias_act_bwd_low`.
        let k: BiasActBwdLow = unsafe { self.kernel("osrt_bias_act_bwd_low") };
        let (n, cols) = (z.len() as i64, b.len() as i32);
        let (zp, bp) = (Ptr(z.as_ptr() as *mut u16), ptr(b));
        let (dyp, dzp) = (Ptr(dy.as_ptr() as *mut u16), Ptr::of(&mut dz));
        self.launch(l, &|| unsafe {
            k(
                zp.get(),
                bp.get(),
                dyp.get(),
                dzp.get(),
                n,
                cols,
                act.0,
                act.1,
            )
        });
        dz
    }

    /// `cuda::bias_act_fwd_in_place` over `launch`.
    pub(crate) fn bias_act_fwd_in_place(
        &self,
        x: &mut [f32],
        b: &[f32],
        act: (i32, f32),
        l: Launch,
    ) {
        // SAFETY: the signature of `osrt_bias_act_fwd_inplace`.
        let k: BiasActFwdInPlace = unsafe { self.kernel("osrt_bias_act_fwd_inplace") };
        let (n, cols) = (x.len() as i64, b.len() as i32);
        let (xp, bp) = (Ptr::of(x), ptr(b));
        self.launch(l, &|| unsafe {
            k(xp.get(), bp.get(), n, cols, act.0, act.1)
        });
    }

    /// `cuda::bias_act_bwd_in_place` over `launch`.
    pub(crate) fn bias_act_bwd_in_place(
        &self,
        x: &mut [f32],
        b: &[f32],
        dy: &[f32],
        act: (i32, f32),
        l: Launch,
    ) {
        assert_eq!(x.len(), dy.len());
        // SAFETY: the signature of `osrt_bias_act_bwd_inplace`.
        let k: BiasActBwdInPlace = unsafe { self.kernel("osrt_bias_act_bwd_inplace") };
        let (n, cols) = (x.len() as i64, b.len() as i32);
        let (xp, bp, dyp) = (Ptr::of(x), ptr(b), ptr(dy));
        self.launch(l, &|| unsafe {
            k(xp.get(), bp.get(), dyp.get(), n, cols, act.0, act.1)
        });
    }

    /// `cuda::column_sum`: the sums over the rows of `[rows, d]`, the partial sums over
    /// at most `y_cap` block rows.
    pub(crate) fn column_sum(&self, a: &[f32], d: usize, y_cap: u32) -> Vec<f32> {
        let rows = a.len() / d;
        let chunks = geometry::chunks(rows);
        let mut partial = vec![f32::NAN; chunks * d];
        let mut out = vec![f32::NAN; d];
        // SAFETY: the kernels' signatures; the buffers have the sizes the launches of
        // `cuda::rows` and `cuda::elementwise` allocate.
        unsafe {
            let part: ColumnPartials = self.kernel("osrt_column_partials");
            let sum: SumChunks = self.kernel("osrt_sum_chunks");
            let (ap, pp, op) = (ptr(a), Ptr::of(&mut partial), Ptr::of(&mut out));
            let (r, dd) = (rows as i32, d as i32);
            self.launch(capped(geometry::columns(dd, chunks), y_cap), &|| {
                part(ap.get(), pp.get(), r, dd, PARAM_CHUNK as i32)
            });
            self.launch(geometry::columns(dd, 1), &|| {
                sum(pp.get(), op.get(), chunks as i32, dd)
            });
        }
        out
    }

    /// `cuda::im2col` and `cuda::col2im` (kernel `name`): `dims` = `[n, h, w, c, k, stride,
    /// pad, ho, wo]`, `total` outputs, launched over `l`.
    pub(crate) fn fold<I, O: Copy>(
        &self,
        name: &str,
        input: &[I],
        total: usize,
        fill: O,
        dims: [usize; 9],
        l: Launch,
    ) -> Vec<O> {
        let [_, h, w, c, k, stride, pad, ho, wo] = dims.map(|v| v as i32);
        let mut out = vec![fill; total];
        // SAFETY: the unfolding kernels share this signature (input type `I`, output `O`).
        let f: Fold<I, O> = unsafe { self.kernel(name) };
        let (ip, op) = (Ptr(input.as_ptr() as *mut I), Ptr::of(&mut out));
        self.launch(l, &|| unsafe {
            f(
                ip.get(),
                op.get(),
                total as i64,
                h,
                w,
                c,
                k,
                stride.max(1),
                pad,
                ho,
                wo,
            )
        });
        out
    }
}

/// `l` with at most `y` block rows: fewer than the work's chunks, as on a GPU past
/// [`geometry::MAX_GRID_YZ`].
fn capped(mut l: Launch, y: u32) -> Launch {
    l.grid.1 = l.grid.1.min(y);
    l
}

/// A read-only buffer as the kernels' pointer (they never write through it).
fn ptr(v: &[f32]) -> Ptr<f32> {
    Ptr(v.as_ptr() as *mut f32)
}

#[cfg(test)]
mod tests;
