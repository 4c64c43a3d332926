//! The AMX unit: one 32 × 32 output block from packed blocks with `TDPBF16PS`, four
//! accumulator tiles (`tmm0`–`tmm3`: the block's 16 × 16 quarters), two `A` tiles
//! (`tmm4`, `tmm5`) and two `B` tiles (`tmm6`, `tmm7`).
//!
//! The tile instructions are `asm!`: Rust's AMX intrinsics are unstable. No code the
//! compiler generates touches the tile registers, so their state between the `asm!`
//! blocks of one [`block`] call is ours. Linux starts a process without the right to use
//! the tiles' 8 KiB of register state: [`available`] asks for it once
//! (`arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`), which covers every thread.

use super::layout::BLOCK;
use std::arch::asm;

/// Whether the CPU has AMX-BF16 tiles, the OS saves their state, and this process may use
/// them (asked once).
pub(crate) fn available() -> bool {
    static OK: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *OK.get_or_init(|| {
        let has = std::arch::is_x86_feature_detected!("avx512f") && cpu_has_amx_bf16();
        has && super::dot::available() && permitted()
    })
}

/// CPUID leaf 7: EDX bit 22 (AMX-BF16) and bit 24 (AMX-TILE); the OS's XCR0 with the
/// tile configuration and data states (bits 17, 18).
fn cpu_has_amx_bf16() -> bool {
    use std::arch::x86_64::{__cpuid, __cpuid_count};
    // CPUID exists on every x86-64 CPU; leaf 7 is read only if the CPU reports it.
    if __cpuid(0).eax < 7 {
        return false;
    }
    let leaf7 = __cpuid_count(7, 0);
    let cpu = leaf7.edx & (1 << 22) != 0 && leaf7.edx & (1 << 24) != 0;
    // CPUID leaf 1, ECX bit 27 (OSXSAVE): XGETBV may run.
    let osxsave = __cpuid(1).ecx & (1 << 27) != 0;
    cpu && osxsave && {
        let xcr0: u64;
        // SAFETY: XGETBV with ECX = 0 reads XCR0; OSXSAVE is set (checked above).
        unsafe {
            let (lo, hi): (u32, u32);
            asm!("xgetbv", in("ecx") 0u32, out("eax") lo, out("edx") hi, options(nomem, nostack));
            xcr0 = (lo as u64) | ((hi as u64) << 32);
        }
        xcr0 & (0b11 << 17) == 0b11 << 17
    }
}

/// Asks Linux for the tile data state (`ARCH_REQ_XCOMP_PERM`); `false` where refused or
/// not Linux.
fn permitted() -> bool {
    #[cfg(target_os = "linux")]
    {
        const SYS_ARCH_PRCTL: i64 = 158;
        const ARCH_REQ_XCOMP_PERM: i64 = 0x1023;
        const XFEATURE_XTILEDATA: i64 = 18;
        let ret: i64;
        // SAFETY: the arch_prctl system call with two integer arguments; it touches no
        // memory of ours. The kernel clobbers rcx and r11.
        unsafe {
            asm!(
                "syscall",
                inlateout("rax") SYS_ARCH_PRCTL => ret,
                in("rdi") ARCH_REQ_XCOMP_PERM,
                in("rsi") XFEATURE_XTILEDATA,
                lateout("rcx") _,
                lateout("r11") _,
                options(nostack),
            );
        }
        ret == 0
    }
    #[cfg(not(target_os = "linux"))]
    false
}

/// The tile configuration: palette 1, eight tiles of 16 rows × 64 bytes.
#[repr(C, align(64))]
struct Config([u8; 64]);

const CONFIG: Config = {
    let mut c = [0u8; 64];
    c[0] = 1;
    let mut t = 0;
    while t < 8 {
        c[16 + 2 * t] = 64;
        c[48 + t] = 16;
        t += 1;
    }
    Config(c)
};

/// Loads the tile configuration on this thread (before a task's first [`block`]).
///
/// # Safety
/// AMX must run here and be permitted ([`available`]).
pub(crate) unsafe fn configure() {
    // SAFETY: the caller's contract; `CONFIG` is a valid 64-byte palette-1 configuration.
    unsafe { asm!("ldtilecfg [{}]", in(reg) &CONFIG.0, options(nostack, readonly)) };
}

/// Releases this thread's tiles (after a task's last [`block`]).
///
/// # Safety
/// AMX must run here ([`available`]).
pub(crate) unsafe fn release() {
    // SAFETY: the caller's contract.
    unsafe { asm!("tilerelease", options(nostack, nomem)) };
}

/// The 32 × 32 output block at `dst` (rows `ld` values apart) = the 32-row group `a`
/// (`kb` pairs of x-major blocks, `[kb][2][16 × 16]`) times the column blocks `b0`, `b1`
/// (`kb` p-major blocks each).
///
/// # Safety
/// AMX must run here and the tiles be configured on this thread ([`configure`]); `a`
/// must hold `2·kb` blocks, `b0` and `b1` `kb` each; `dst` must be valid for writes of 32
/// rows of 32 f32 values, `ld` apart.
pub(crate) unsafe fn block(
    a: &[u32],
    b0: &[u32],
    b1: &[u32],
    kb: usize,
    (dst, ld): (*mut f32, usize),
) {
    const L: usize = BLOCK * BLOCK;
    assert!(a.len() >= 2 * kb * L && b0.len() >= kb * L && b1.len() >= kb * L);
    // Rows of every packed block are 64 bytes apart; of the output, `ld` values.
    let (stride, c_stride) = (64usize, ld * 4);
    // SAFETY: the caller's contract (tiles configured as `CONFIG`, `dst` writable); each
    // load reads one 1 KiB block inside the slices (asserted above).
    unsafe {
        asm!(
            "tilezero tmm0",
            "tilezero tmm1",
            "tilezero tmm2",
            "tilezero tmm3",
            options(nostack, nomem)
        );
        for q in 0..kb {
            asm!(
                "tileloadd tmm4, [{a0} + {s}*1]",
                "tileloadd tmm5, [{a1} + {s}*1]",
                "tileloadd tmm6, [{b0} + {s}*1]",
                "tileloadd tmm7, [{b1} + {s}*1]",
                "tdpbf16ps tmm0, tmm4, tmm6",
                "tdpbf16ps tmm1, tmm4, tmm7",
                "tdpbf16ps tmm2, tmm5, tmm6",
                "tdpbf16ps tmm3, tmm5, tmm7",
                a0 = in(reg) a.as_ptr().add(2 * q * L),
                a1 = in(reg) a.as_ptr().add((2 * q + 1) * L),
                b0 = in(reg) b0.as_ptr().add(q * L),
                b1 = in(reg) b1.as_ptr().add(q * L),
                s = in(reg) stride,
                options(nostack, readonly),
            );
        }
        asm!(
            "tilestored [{c0} + {s}*1], tmm0",
            "tilestored [{c1} + {s}*1], tmm1",
            "tilestored [{c2} + {s}*1], tmm2",
            "tilestored [{c3} + {s}*1], tmm3",
            c0 = in(reg) dst,
            c1 = in(reg) dst.add(BLOCK),
            c2 = in(reg) dst.add(BLOCK * ld),
            c3 = in(reg) dst.add(BLOCK * ld + BLOCK),
            s = in(reg) c_stride,
            options(nostack),
        );
    }
}
