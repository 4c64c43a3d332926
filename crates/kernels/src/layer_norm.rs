use crate::*;
use candle_core::{CpuStorage, CustomOp3, D, Layout, Result, Shape, Tensor};

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

/// LayerNorm over the last dimension: `x: [.., d]`, `weight`, `bias: [d]` → `[.., d]`.
pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    crate::profile::op("layer_norm", &[x, weight, bias], move |t| {
        layer_norm_here(&t[0], &t[1], &t[2], eps)
    })
}

fn layer_norm_here(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    if usable_with_cuda(&[x, weight, bias]) {
        return x.contiguous()?.apply_op3(
            &weight.contiguous()?,
            &bias.contiguous()?,
            LayerNormOp { eps: eps as f32 },
        );
    }
    let mean = x.mean_keepdim(D::Minus1)?;
    let centred = x.broadcast_sub(&mean)?;
    let var = centred.sqr()?.mean_keepdim(D::Minus1)?;
    let normed = centred.broadcast_div(&(var + eps)?.sqrt()?)?;
    normed.broadcast_mul(weight)?.broadcast_add(bias)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::*;
    use candle_core::Device;

    fn ln(ts: &[Tensor]) -> Result<Tensor> {
        layer_norm(&ts[0], &ts[1], &ts[2], 1e-5)
    }

    #[test]
    fn layer_norm_matches_the_composed_version_and_finite_differences() {
        let args = [
            randn(&[3, 70, 16], 1.0, 1),
            randn(&[16], 1.0, 2),
            randn(&[16], 1.0, 3),
        ];
        assert_matches_composed(&args, ln, 2e-5);
        let small = [
            randn(&[2, 3, 8], 1.0, 4),
            randn(&[8], 1.0, 5),
            randn(&[8], 1.0, 6),
        ];
        finite_difference_check(&small, ln);
    }

    #[test]
    fn layer_norm_is_finite_on_extreme_and_constant_rows() {
        // Large magnitudes, a constant row (zero variance) and tiny values.
        let mut v = vec![1e6f32, -3e6, 2e6, 5e5];
        v.extend([7.0f32; 4]);
        v.extend([1e-20f32, -1e-20, 0.0, 2e-20]);
        let x = Tensor::from_vec(v, (3, 4), &Device::Cpu).unwrap();
        let args = [x, randn(&[4], 1.0, 7), randn(&[4], 1.0, 8)];
        let [(y, grads), _] = both(&args, ln);
        for t in std::iter::once(&y).chain(&grads) {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            assert!(v.iter().all(|x| x.is_finite()), "{v:?}");
        }
        // The constant row normalises to exactly the bias.
        let row: Vec<f32> = y.get(1).unwrap().to_vec1().unwrap();
        let bias: Vec<f32> = args[2].to_vec1().unwrap();
        assert_eq!(row, bias);
        assert_matches_composed(&args, ln, 1e-3);
    }
    #[test]
    fn non_contiguous_inputs_take_the_same_values() {
        let x = randn(&[6, 8], 1.0, 31).t().unwrap(); // [8, 6], strided
        let g = randn(&[6], 1.0, 32);
        let b = randn(&[6], 1.0, 33);
        let a = with_fused(true, || layer_norm(&x, &g, &b, 1e-5)).unwrap();
        let c = with_fused(false, || layer_norm(&x, &g, &b, 1e-5)).unwrap();
        assert!(max_diff(&a, &c) < 1e-5);
    }
}
