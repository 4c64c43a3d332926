//! A linear layer's bias and the activation after it as one node: `y = act(x + b)`.
//!
//! Why: on a GPU the layers are candle's matrix product followed by this op. Composed,
//! the bias add and a leaky ReLU keep three full-size tensors for the backward pass
//! (`x + b`, `s·(x + b)`, the maximum); this node keeps none of its own (its input is the
//! product, which the graph holds anyway, and the backward pass recomputes `x + b`). On
//! the CPU the whole-MLP op covers these layers; the CPU version here is the reference the
//! CUDA kernels are checked against.

use crate::mlp::MlpAct;
use crate::*;
use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};

/// The activation as the CUDA kernels spell it: `(kind, slope)` with kind 0 = none,
/// 1 = (leaky) ReLU, 2 = erf-GELU.
#[cfg(any(feature = "cuda", test))]
pub(crate) fn act_code(act: Option<MlpAct>) -> (i32, f32) {
    match act {
        None => (0, 0.0),
        Some(MlpAct::Relu) => (1, 0.0),
        Some(MlpAct::LeakyRelu(s)) => (1, s),
        Some(MlpAct::Gelu) => (2, 0.0),
    }
}

/// `x + b` per row of `[rows, d]`.
fn biased(x: &[f32], b: &[f32]) -> Vec<f32> {
    let mut z = x.to_vec();
    add_bias_rows(&mut z, b);
    z
}

pub(crate) struct BiasActOp {
    pub(crate) act: Option<MlpAct>,
}

impl CustomOp2 for BiasActOp {
    fn name(&self) -> &'static str {
        "osrt-bias-act"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "bias+activation x")?;
        let b = f32_slice(s2, l2, "bias+activation bias")?;
        let z = biased(x, b);
        let out = match self.act {
            None => z,
            Some(a) => a.forward(&z),
        };
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        crate::cuda::bias_act_fwd(s1, l1, s2, l2, act_code(self.act))
    }

    fn bwd(
        &self,
        x: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let dz = match self.act {
            None => grad.clone(),
            Some(act) => x.apply_op3_no_bwd(b, &grad.contiguous()?, &BiasActBwd { act })?,
        };
        let db = dz
            .contiguous()?
            .apply_op1_no_bwd(&ColumnSum { d: b.elem_count() })?
            .reshape(b.shape())?;
        Ok((Some(dz), Some(db)))
    }
}

/// `dz = dy · act'(x + b)`.
pub(crate) struct BiasActBwd {
    pub(crate) act: MlpAct,
}

impl CustomOp3 for BiasActBwd {
    fn name(&self) -> &'static str {
        "osrt-bias-act-bwd"
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
        let x = f32_slice(s1, l1, "bias+activation backward x")?;
        let b = f32_slice(s2, l2, "bias+activation backward bias")?;
        let dy = f32_slice(s3, l3, "bias+activation backward gradient")?;
        let out = self.act.backward(&biased(x, b), dy);
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
        crate::cuda::bias_act_bwd(s1, l1, s2, l2, s3, l3, act_code(Some(self.act)))
    }
}

/// `act(x + b)` for `x: [.., d]`, `b: [d]`, `act` none (a bias add) or an MLP activation.
/// One node where the one-node ops apply (f32 on the CPU or a CUDA device); the composed
/// ops otherwise.
pub fn bias_act(x: &Tensor, b: &Tensor, act: Option<MlpAct>) -> Result<Tensor> {
    crate::profile::op("bias_act", &[x, b], move |t| {
        bias_act_here(&t[0], &t[1], act)
    })
}

fn bias_act_here(x: &Tensor, b: &Tensor, act: Option<MlpAct>) -> Result<Tensor> {
    if usable_with_cuda(&[x, b])
        && b.rank() == 1
        && x.dim(candle_core::D::Minus1)? == b.elem_count()
    {
        return x
            .contiguous()?
            .apply_op2(&b.contiguous()?, BiasActOp { act });
    }
    let z = x.broadcast_add(b)?;
    match act {
        None => Ok(z),
        Some(a) => a.apply(&z),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::*;
    use candle_core::Device;

    const ACTS: [Option<MlpAct>; 4] = [
        None,
        Some(MlpAct::Relu),
        Some(MlpAct::LeakyRelu(0.01)),
        Some(MlpAct::Gelu),
    ];

    #[test]
    fn bias_act_matches_the_composed_ops_and_finite_differences() {
        for act in ACTS {
            let args = [randn(&[3, 7, 24], 1.0, 61), randn(&[24], 1.0, 62)];
            assert_matches_composed(&args, |t| bias_act(&t[0], &t[1], act), 1e-5);
            let small = [randn(&[2, 3, 5], 1.0, 63), randn(&[5], 1.0, 64)];
            finite_difference_check(&small, |t| bias_act(&t[0], &t[1], act));
        }
    }

    #[test]
    fn bias_act_is_finite_on_extreme_inputs() {
        let x = Tensor::new(
            &[[1e30f32, -1e30, 0.0, 3e38], [-3e38, 1e-30, -1e-30, 7.0]],
            &Device::Cpu,
        )
        .unwrap();
        let b = Tensor::new(&[0.5f32, -0.5, 0.0, 1.0], &Device::Cpu).unwrap();
        for act in ACTS {
            let [(y, grads), _] = both(&[x.clone(), b.clone()], |t| bias_act(&t[0], &t[1], act));
            for t in std::iter::once(&y).chain(&grads) {
                let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
                assert!(v.iter().all(|x| x.is_finite()), "{act:?}: {v:?}");
            }
        }
    }
}
