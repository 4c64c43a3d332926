// A CUDA emulator on the host, for the tests of osrt's kernels in a build without a GPU
// (`emulated.rs`): the kernels' source compiles as C++20 after this header, and
// `emu_launch` runs a kernel over its grid.
//
// Every CUDA thread of a block is a host thread, all of a block's threads run at once
// (blocks one after another), and the lanes of a warp meet at a barrier on each shuffle,
// so a kernel whose lanes exchange values or wait for each other runs as it would on a
// GPU. What it does not model: timing, memory spaces (`__shared__` is one static
// variable, right only because blocks run one at a time), fused multiply-adds (NVRTC
// contracts `a * b + c`, the host compiler here does not) and the device's math library
// (`expf`, `erff` are the host's; both are within a few ulp of the exact value).
#include <barrier>
#include <cmath>
#include <cstring>
#include <exception>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

struct uint3 { unsigned x, y, z; };
struct dim3 { unsigned x, y, z; };

#define __global__
#define __device__
#define __forceinline__ inline
#define __shared__ static

using std::max;
using std::min;

// Set for a block before its threads start: read-only while they run.
static uint3 blockIdx;
static dim3 blockDim, gridDim;

struct EmuWarp {
    explicit EmuWarp(int lanes) : arrive(lanes) {}
    std::barrier<> arrive;
    unsigned bits[32];
};

thread_local uint3 threadIdx;
thread_local EmuWarp* emu_warp;
thread_local unsigned emu_lane;
static std::barrier<>* emu_block_barrier;

inline float __int_as_float(int v) { float f; std::memcpy(&f, &v, 4); return f; }
inline float __uint_as_float(unsigned v) { float f; std::memcpy(&f, &v, 4); return f; }
inline int __float_as_int(float f) { int v; std::memcpy(&v, &f, 4); return v; }
inline unsigned __float_as_uint(float f) { unsigned v; std::memcpy(&v, &f, 4); return v; }

// Every lane of the warp must call it (as `0xffffffff` promises on a GPU).
template <typename T>
inline T __shfl_xor_sync(unsigned, T v, int lane_mask) {
    static_assert(sizeof(T) == 4, "the emulator shuffles 32-bit values");
    std::memcpy(&emu_warp->bits[emu_lane], &v, 4);
    emu_warp->arrive.arrive_and_wait();
    T out;
    std::memcpy(&out, &emu_warp->bits[(emu_lane ^ lane_mask) & 31], 4);
    emu_warp->arrive.arrive_and_wait();
    return out;
}

inline void __syncthreads() { emu_block_barrier->arrive_and_wait(); }

extern "C" int emu_launch(unsigned gx, unsigned gy, unsigned gz, unsigned bx, unsigned by,
                          unsigned bz, void (*body)(void*), void* ctx) {
    // CUDA's limits on a launch: a kernel launched past them fails on a GPU.
    unsigned threads = bx * by * bz;
    if (threads == 0 || threads > 1024 || bz > 64) return 1;
    if (gx == 0 || gy == 0 || gz == 0 || gx > 2147483647u || gy > 65535 || gz > 65535) return 3;
    // The grid's sizes and the block's index are globals: one launch at a time, as on
    // one stream (tests call from several threads).
    static std::mutex one_at_a_time;
    std::lock_guard<std::mutex> hold(one_at_a_time);
    gridDim = dim3{gx, gy, gz};
    blockDim = dim3{bx, by, bz};
    unsigned warps = (threads + 31) / 32;
    try {
        for (unsigned z = 0; z < gz; ++z)
            for (unsigned y = 0; y < gy; ++y)
                for (unsigned x = 0; x < gx; ++x) {
                    blockIdx = uint3{x, y, z};
                    std::vector<std::unique_ptr<EmuWarp>> ws;
                    for (unsigned w = 0; w < warps; ++w)
                        ws.push_back(std::make_unique<EmuWarp>(
                            (int)std::min(32u, threads - 32 * w)));
                    std::barrier<> block(threads);
                    emu_block_barrier = &block;
                    std::vector<std::thread> ts;
                    ts.reserve(threads);
                    for (unsigned t = 0; t < threads; ++t)
                        ts.emplace_back([&, t] {
                            // The linear thread number: x fastest, as on a GPU.
                            threadIdx = uint3{t % bx, (t / bx) % by, t / (bx * by)};
                            emu_warp = ws[t / 32].get();
                            emu_lane = t % 32;
                            body(ctx);
                        });
                    for (auto& th : ts) th.join();
                }
    } catch (const std::exception&) {
        return 2;
    }
    return 0;
}
