//! The CUDA C source of osrt's device kernels (`device_kernels.cu`) and the geometry each
//! is launched with. `cuda::launch` compiles the source with NVRTC and launches it on a GPU;
//! this module is outside the `cuda` feature so that the CPU build can run the same source
//! on the host (`cuda::emulated`, a test-only CUDA emulator) and check every kernel against
//! the CPU ops without a GPU.

/// The kernels, compiled by NVRTC in a `cuda` build (`cuda::compile`).
pub const SOURCE: &str = include_str!("device_kernels.cu");

/// Rows (warps) per block of the row kernels.
pub const ROWS_PER_BLOCK: u32 = 8;
/// Rows per chunk of the column sums (LayerNorm's parameter gradients, a bias's gradient).
pub const PARAM_CHUNK: usize = 64;
/// Threads per block of the element-wise kernels.
const ELEMENTWISE_BLOCK: u32 = 256;
/// Most blocks an element-wise launch takes; its kernels loop over the rest (grid stride).
const MAX_ELEMENTWISE_BLOCKS: usize = 65_535 * 16;
/// CUDA's limit on a grid's y and z sizes (x: 2³¹ − 1).
pub const MAX_GRID_YZ: u32 = 65_535;

/// A launch's grid and block sizes, `(x, y, z)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Launch {
    pub grid: (u32, u32, u32),
    pub block: (u32, u32, u32),
}

/// A warp per row (`threadIdx.x` the lane), `ROWS_PER_BLOCK` rows per block: LayerNorm
/// and softmax, forward and backward.
pub fn rows(rows: i32) -> Launch {
    Launch {
        grid: ((rows.max(0) as u32).div_ceil(ROWS_PER_BLOCK).max(1), 1, 1),
        block: (32, ROWS_PER_BLOCK, 1),
    }
}

/// A thread per column of `width`, a block row per chunk of rows (`blockIdx.y`), at most
/// [`MAX_GRID_YZ`] of them (the kernels loop over the chunks past it): the column sums
/// (`osrt_column_partials`, `osrt_layer_norm_bwd_params`, `osrt_sum_chunks`).
pub fn columns(width: i32, chunks: usize) -> Launch {
    Launch {
        grid: (
            (width.max(0) as u32).div_ceil(128).max(1),
            chunks.clamp(1, MAX_GRID_YZ as usize) as u32,
            1,
        ),
        block: (128, 1, 1),
    }
}

/// Grid-stride loops over `n` elements: bias with activation, im2col, col2im.
pub fn elementwise(n: usize) -> Launch {
    Launch {
        grid: (
            n.div_ceil(ELEMENTWISE_BLOCK as usize)
                .clamp(1, MAX_ELEMENTWISE_BLOCKS) as u32,
            1,
            1,
        ),
        block: (ELEMENTWISE_BLOCK, 1, 1),
    }
}

/// The chunks of `rows` rows the column sums split them into.
pub fn chunks(rows: usize) -> usize {
    rows.div_ceil(PARAM_CHUNK).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn launches_cover_their_work() {
        for n in [0usize, 1, 255, 256, 257, 10_000] {
            let l = elementwise(n);
            assert!(l.grid.0 as usize * l.block.0 as usize >= n.max(1));
        }
        // Past the cap the grid stops growing and the kernels' loops take the rest.
        assert_eq!(
            elementwise(usize::MAX / 2).grid.0 as usize,
            MAX_ELEMENTWISE_BLOCKS
        );
        for r in [0, 1, 7, 8, 9, 1000] {
            let l = rows(r);
            assert!(l.grid.0 * l.block.1 >= r as u32 && l.grid.0 >= 1);
        }
        assert_eq!(columns(129, 3).grid, (2, 3, 1));
        // 5 M rows: more chunks than a grid's y holds.
        assert_eq!(columns(7, chunks(5_000_000)).grid, (1, MAX_GRID_YZ, 1));
        assert_eq!((chunks(0), chunks(64), chunks(65)), (1, 1, 2));
    }
}
