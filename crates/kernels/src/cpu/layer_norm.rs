//! LayerNorm over the last dimension on the CPU as one node, forward and backward in one
//! pass each (both with CUDA kernels too).

use super::{ROWS_PER_TASK, buffer, f32_slice};
use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor};
use std::sync::Mutex;

pub(crate) struct LayerNormOp {
    pub(crate) eps: f32,
}

/// Mean and 1/σ of one row.
fn row_stats(x: &[f32], eps: f32) -> (f32, f32) {
    let d = x.len() as f32;
    let mean = x.iter().sum::<f32>() / d;
    let var = x.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d;
    (mean, 1.0 / (var + eps).sqrt())
}

impl CustomOp3 for LayerNormOp {
    fn name(&self) -> &'static str {
        "osrt-layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "layer_norm x")?;
        let g = f32_slice(s2, l2, "layer_norm weight")?;
        let b = f32_slice(s3, l3, "layer_norm bias")?;
        let d = g.len();
        let per = d * ROWS_PER_TASK;
        let out = buffer::par_filled(x.len(), per, |t, o| {
            let x = &x[t * per..][..o.len()];
            for (o, x) in o.chunks_mut(d).zip(x.chunks(d)) {
                let (mean, rstd) = row_stats(x, self.eps);
                for i in 0..d {
                    o[i] = (x[i] - mean) * rstd * g[i] + b[i];
                }
            }
        });
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        crate::cuda::layer_norm_fwd(s1, l1, s2, l2, s3, l3, self.eps)
    }

    fn bwd(
        &self,
        x: &Tensor,
        g: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let d = g.elem_count();
        let rows = x.elem_count() / d;
        let packed = x.apply_op3_no_bwd(g, &grad.contiguous()?, &LayerNormBwd { eps: self.eps })?;
        let dx = packed.narrow(0, 0, rows)?.reshape(x.shape())?;
        let dg = packed.get(rows)?.reshape(g.shape())?;
        let db = packed.get(rows + 1)?.reshape(g.shape())?;
        Ok((Some(dx), Some(dg), Some(db)))
    }
}

/// LayerNorm's backward in one pass: `[rows + 2, d]` = dx rows, then dγ, then dβ.
pub(crate) struct LayerNormBwd {
    pub(crate) eps: f32,
}

impl CustomOp3 for LayerNormBwd {
    fn name(&self) -> &'static str {
        "osrt-layer-norm-bwd"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "layer_norm backward x")?;
        let g = f32_slice(s2, l2, "layer_norm backward weight")?;
        let dy = f32_slice(s3, l3, "layer_norm backward gradient")?;
        let d = g.len();
        let rows = x.len() / d;
        let per = d * ROWS_PER_TASK;
        // Per task: dx rows, and partial dγ / dβ sums reduced afterwards in task order
        // (a fixed order: the result does not depend on the thread count's scheduling).
        // The last 2·d values (dγ, dβ) are left zero by the tasks.
        let partials = Mutex::new(vec![None; rows.div_ceil(ROWS_PER_TASK)]);
        let mut out = buffer::par_filled((rows + 2) * d, per, |t, o| {
            let start = t * per;
            let n = (rows * d).saturating_sub(start).min(o.len());
            if n == 0 {
                return;
            }
            let (x, dy) = (&x[start..start + n], &dy[start..start + n]);
            let mut acc = vec![0f32; 2 * d];
            let mut xhat = vec![0f32; d];
            for ((dx, x), dy) in o[..n].chunks_mut(d).zip(x.chunks(d)).zip(dy.chunks(d)) {
                let (mean, rstd) = row_stats(x, self.eps);
                let (mut m1, mut m2) = (0f32, 0f32);
                for i in 0..d {
                    xhat[i] = (x[i] - mean) * rstd;
                    let gy = dy[i] * g[i];
                    m1 += gy;
                    m2 += gy * xhat[i];
                    acc[i] += dy[i] * xhat[i];
                    acc[d + i] += dy[i];
                }
                let (m1, m2) = (m1 / d as f32, m2 / d as f32);
                for i in 0..d {
                    dx[i] = rstd * (dy[i] * g[i] - m1 - xhat[i] * m2);
                }
            }
            partials.lock().unwrap_or_else(|e| e.into_inner())[t] = Some(acc);
        });
        let dgb = &mut out[rows * d..];
        let partials = partials.into_inner().unwrap_or_else(|e| e.into_inner());
        for p in partials.into_iter().flatten() {
            for (o, v) in dgb.iter_mut().zip(p) {
                *o += v;
            }
        }
        Ok((CpuStorage::F32(out), Shape::from((rows + 2, d))))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        crate::cuda::layer_norm_bwd(s1, l1, s2, l2, s3, l3, self.eps)
    }
}

/// LayerNorm over the last dimension as one node (f32 on the CPU or a CUDA device).
pub(crate) fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f32) -> Result<Tensor> {
    x.contiguous()?.apply_op3(
        &weight.contiguous()?,
        &bias.contiguous()?,
        LayerNormOp { eps },
    )
}
