//! A linear layer's bias and the activation after it as one node: `y = act(x + b)`.
//!
//! Why: on a GPU the layers are candle's matrix product followed by this op. Composed,
//! the bias add and a leaky ReLU keep three full-size tensors for the backward pass
//! (`x + b`, `s·(x + b)`, the maximum); this node keeps none of its own (its input is the
//! product, which the graph holds anyway, and the backward pass recomputes `x + b`). On
//! the CPU the whole-MLP op covers these layers; the CPU version here is the reference the
//! CUDA kernels are checked against.

use super::activation::MlpAct;
use super::linear::{ColumnSum, add_bias_rows};
use super::{f32_slice, f32_slice_mut};
use candle_core::{
    CpuStorage, CustomOp2, CustomOp3, InplaceOp2, InplaceOp3, Layout, Result, Shape, Tensor,
};

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

/// [`BiasActOp`] written over `x`: the same values, no second buffer of `x`'s size.
impl InplaceOp2 for BiasActOp {
    fn name(&self) -> &'static str {
        "osrt-bias-act-in-place"
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<()> {
        let b = f32_slice(s2, l2, "bias+activation in place bias")?;
        let x = f32_slice_mut(s1, l1, "bias+activation in place x")?;
        if x.len() % b.len().max(1) != 0 {
            candle_core::bail!(
                "bias+activation in place: {} elements for a bias of {}",
                x.len(),
                b.len()
            )
        }
        add_bias_rows(x, b);
        if let Some(a) = self.act {
            a.forward_in_place(x);
        }
        Ok(())
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &mut candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> Result<()> {
        crate::cuda::bias_act_fwd_in_place(s1, l1, s2, l2, act_code(self.act))
    }
}

/// [`BiasActBwd`] written over `x`.
impl InplaceOp3 for BiasActBwd {
    fn name(&self) -> &'static str {
        "osrt-bias-act-bwd-in-place"
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<()> {
        let b = f32_slice(s2, l2, "bias+activation backward in place bias")?;
        let dy = f32_slice(s3, l3, "bias+activation backward in place gradient")?;
        let x = f32_slice_mut(s1, l1, "bias+activation backward in place x")?;
        if x.len() != dy.len() || x.len() % b.len().max(1) != 0 {
            candle_core::bail!(
                "bias+activation backward in place: {} elements, a gradient of {}, a bias of {}",
                x.len(),
                dy.len(),
                b.len()
            )
        }
        add_bias_rows(x, b);
        self.act.backward_in_place(x, dy);
        Ok(())
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &mut candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> Result<()> {
        crate::cuda::bias_act_bwd_in_place(s1, l1, s2, l2, s3, l3, act_code(Some(self.act)))
    }
}

/// `bf16(act(f32(z) + b))`: a bf16 product's bias and activation rounded back to bf16 for
/// the next product, without the f32 tensor of the layer's size that widening,
/// [`BiasActOp`] and rounding make (the bits of those three ops).
struct BiasActLow {
    act: Option<MlpAct>,
}

impl CustomOp2 for BiasActLow {
    fn name(&self) -> &'static str {
        "osrt-bias-act-low"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let CpuStorage::BF16(z) = s1 else {
            candle_core::bail!("bias+activation to bf16: a bf16 input only");
        };
        let Some((a, e)) = l1.contiguous_offsets() else {
            candle_core::bail!("bias+activation to bf16: a contiguous input only");
        };
        let z = &z[a..e];
        let b = f32_slice(s2, l2, "bias+activation to bf16 bias")?;
        let d = b.len().max(1);
        let mut out = vec![half::bf16::ZERO; z.len()];
        MlpAct::forward_with(
            self.act,
            &mut out,
            |start, x| {
                for (j, v) in x.iter_mut().enumerate() {
                    // `add_bias_rows`'s sum on the widened value.
                    *v = z[start + j].to_f32() + b[(start + j) % d];
                }
            },
            |y, o| {
                for (o, y) in o.iter_mut().zip(y) {
                    *o = half::bf16::from_f32(*y);
                }
            },
        );
        Ok((CpuStorage::BF16(out), l1.shape().clone()))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        crate::cuda::bias_act_low(s1, l1, s2, l2, act_code(self.act))
    }
}

/// `bf16(act(f32(z) + b))` for a bf16 `z: [.., d]` and an f32 `b: [d]`, outside the graph.
pub(crate) fn bias_act_low(z: &Tensor, b: &Tensor, act: Option<MlpAct>) -> Result<Tensor> {
    check_rows(z, b, None)?;
    if z.dtype() != candle_core::DType::BF16 || b.dtype() != candle_core::DType::F32 {
        candle_core::bail!(
            "bias+activation to bf16: z {:?}, bias {:?}; expected bf16 and f32",
            z.dtype(),
            b.dtype()
        )
    }
    z.contiguous()?
        .apply_op2_no_bwd(&b.contiguous()?, &BiasActLow { act })
}

/// `dy · act'(f32(z) + b)` in f32 for a bf16 product `z` and a bf16 gradient `dy`: the
/// bits of widening both and [`BiasActBwd`], without their two f32 copies of the layer's
/// size (a bf16 MLP node's hidden layer, whose incoming gradient is the layer after's
/// bf16 product).
struct BiasActBwdLow {
    act: MlpAct,
}

impl CustomOp3 for BiasActBwdLow {
    fn name(&self) -> &'static str {
        "osrt-bias-act-bwd-low"
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
        let (CpuStorage::BF16(z), CpuStorage::BF16(dy)) = (s1, s3) else {
            candle_core::bail!("bias+activation backward from bf16: bf16 z and gradient only");
        };
        let (Some((a, e)), Some((c, f))) = (l1.contiguous_offsets(), l3.contiguous_offsets())
        else {
            candle_core::bail!("bias+activation backward from bf16: contiguous operands only");
        };
        let (z, dy) = (&z[a..e], &dy[c..f]);
        let b = f32_slice(s2, l2, "bias+activation backward from bf16 bias")?;
        let d = b.len().max(1);
        if z.len() != dy.len() || z.len() % d != 0 {
            candle_core::bail!(
                "bias+activation backward from bf16: {} elements, a gradient of {}, a bias of {}",
                z.len(),
                dy.len(),
                b.len()
            )
        }
        let mut out = vec![0f32; z.len()];
        self.act.backward_with(&mut out, |start, x, g| {
            for (j, (x, g)) in x.iter_mut().zip(g).enumerate() {
                // `add_bias_rows`'s sum on the widened value.
                *x = z[start + j].to_f32() + b[(start + j) % d];
                *g = dy[start + j].to_f32();
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
        crate::cuda::bias_act_bwd_low(s1, l1, s2, l2, s3, l3, act_code(Some(self.act)))
    }
}

/// `dy · act'(f32(z) + b)` in f32 for a bf16 `z: [.., d]`, an f32 `b: [d]` and a bf16 `dy`
/// of `z`'s shape, outside the graph.
pub(crate) fn bias_act_bwd_low(z: &Tensor, b: &Tensor, dy: &Tensor, act: MlpAct) -> Result<Tensor> {
    check_rows(z, b, Some(dy))?;
    let bf16 = candle_core::DType::BF16;
    if z.dtype() != bf16 || dy.dtype() != bf16 || b.dtype() != candle_core::DType::F32 {
        candle_core::bail!(
            "bias+activation backward from bf16: z {:?}, bias {:?}, gradient {:?}; expected \
             bf16, f32, bf16",
            z.dtype(),
            b.dtype(),
            dy.dtype()
        )
    }
    z.contiguous()?
        .apply_op3_no_bwd(&b.contiguous()?, &dy.contiguous()?, &BiasActBwdLow { act })
}

/// `x ← act(x + b)` for `x: [.., d]` (f32, contiguous), `b: [d]`, outside the graph. `x`
/// must be the caller's own: every tensor sharing its storage sees the change.
pub(crate) fn bias_act_in_place(x: &Tensor, b: &Tensor, act: Option<MlpAct>) -> Result<()> {
    check_rows(x, b, None)?;
    x.inplace_op2(b, &BiasActOp { act })
}

/// `x: [.., d]` with `b: [d]` (and `dy` of `x`'s shape), or an error naming them.
fn check_rows(x: &Tensor, b: &Tensor, dy: Option<&Tensor>) -> Result<()> {
    let fits = b.rank() == 1
        && x.rank() > 0
        && x.dim(candle_core::D::Minus1)? == b.elem_count()
        && dy.is_none_or(|dy| dy.shape() == x.shape());
    match fits {
        true => Ok(()),
        false => candle_core::bail!(
            "bias+activation in place: x {:?}, bias {:?}, gradient {:?}",
            x.shape(),
            b.shape(),
            dy.map(Tensor::shape)
        ),
    }
}

/// `x ← dy · act'(x + b)` (the input gradient of [`crate::bias_act`] at `x`), outside the graph,
/// over the caller's own `x`.
pub(crate) fn bias_act_bwd_in_place(
    x: &Tensor,
    b: &Tensor,
    dy: &Tensor,
    act: MlpAct,
) -> Result<()> {
    check_rows(x, b, Some(dy))?;
    x.inplace_op3(b, dy, &BiasActBwd { act })
}

/// `act(x + b)` for `x: [.., d]`, `b: [d]` as one node (f32 on the CPU or a CUDA device).
pub(crate) fn bias_act(x: &Tensor, b: &Tensor, act: Option<MlpAct>) -> Result<Tensor> {
    x.contiguous()?
        .apply_op2(&b.contiguous()?, BiasActOp { act })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::randn;
    use candle_core::Device;

    const ACTS: [Option<MlpAct>; 4] = [
        None,
        Some(MlpAct::Relu),
        Some(MlpAct::LeakyRelu(0.01)),
        Some(MlpAct::Gelu),
    ];

    /// The in-place forward and backward ops give the node's bits, over sizes that end
    /// mid-chunk of the parallel loops, with extreme values and exact zeros of `x + b`.
    #[test]
    fn the_in_place_ops_give_the_node_bits() {
        let (rows, d) = (700, 37);
        let mut x = randn(&[rows * d], 2.0, 90).to_vec1::<f32>().unwrap();
        for (j, v) in [1e30f32, -1e30, 1e-30, -1e-30, 0.0, -0.0, 3e38, -3e38]
            .into_iter()
            .enumerate()
        {
            x[j * 1001] = v;
        }
        let b = randn(&[d], 0.5, 91);
        let bv = b.to_vec1::<f32>().unwrap();
        x[9 * d + 3] = -bv[3];
        let x = Tensor::from_vec(x, (rows, d), &Device::Cpu).unwrap();
        let dy = randn(&[rows, d], 1.0, 92);
        let bits = |t: &Tensor| -> Vec<u32> {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            v.iter().map(|x| x.to_bits()).collect()
        };
        for act in ACTS {
            let y = x.apply_op2_no_bwd(&b, &BiasActOp { act }).unwrap();
            let h = x.copy().unwrap();
            bias_act_in_place(&h, &b, act).unwrap();
            assert_eq!(bits(&h), bits(&y), "{act:?}");
            if let Some(a) = act {
                let dz = x.apply_op3_no_bwd(&b, &dy, &BiasActBwd { act: a }).unwrap();
                let g = x.copy().unwrap();
                bias_act_bwd_in_place(&g, &b, &dy, a).unwrap();
                assert_eq!(bits(&g), bits(&dz), "{a:?} gradient");
            }
        }
        // A bias that does not divide the rows, a gradient of another size: errors.
        let odd = randn(&[5], 1.0, 93);
        assert!(bias_act_in_place(&x.copy().unwrap(), &odd, None).is_err());
        let short = randn(&[rows - 1, d], 1.0, 94);
        assert!(bias_act_bwd_in_place(&x.copy().unwrap(), &b, &short, MlpAct::Gelu).is_err());
    }

    /// The bf16-to-bf16 op gives the bits of widening, [`BiasActOp`] and rounding, over
    /// sizes that end mid-chunk, with values whose sums overflow bf16, tiny values and
    /// exact zeros of `z + b`; it refuses an f32 input.
    #[test]
    fn the_bf16_op_gives_the_three_ops_bits() {
        use candle_core::DType;
        let (rows, d) = (700, 37);
        let mut x = randn(&[rows * d], 2.0, 95).to_vec1::<f32>().unwrap();
        for (j, v) in [
            3.3e38f32,
            -3.3e38,
            1e-30,
            -1e-30,
            0.0,
            -0.0,
            1.0 + 1.0 / 256.0,
        ]
        .into_iter()
        .enumerate()
        {
            x[j * 1001] = v;
        }
        let b = randn(&[d], 0.5, 96);
        let z = Tensor::from_vec(x, (rows, d), &Device::Cpu)
            .unwrap()
            .to_dtype(DType::BF16)
            .unwrap();
        let bits = |t: &Tensor| -> Vec<u16> {
            let v: Vec<half::bf16> = t.flatten_all().unwrap().to_vec1().unwrap();
            v.iter().map(|x| x.to_bits()).collect()
        };
        for act in ACTS {
            let want = z
                .to_dtype(DType::F32)
                .unwrap()
                .apply_op2_no_bwd(&b, &BiasActOp { act })
                .unwrap()
                .to_dtype(DType::BF16)
                .unwrap();
            let got = bias_act_low(&z, &b, act).unwrap();
            assert_eq!(got.dtype(), DType::BF16);
            assert_eq!(bits(&got), bits(&want), "{act:?}");
        }
        assert!(bias_act_low(&z.to_dtype(DType::F32).unwrap(), &b, None).is_err());
    }

    /// The backward op from bf16 gives the bits of widening `z` and `dy` and
    /// [`BiasActBwd`], over sizes that end mid-chunk, with products whose sums overflow,
    /// tiny values, exact zeros of `z + b` and gradients at bf16's extremes; it refuses f32
    /// operands and a gradient of another shape.
    #[test]
    fn the_backward_from_bf16_gives_the_widened_ops_bits() {
        use candle_core::DType;
        let (rows, d) = (700, 37);
        let mut x = randn(&[rows * d], 2.0, 97).to_vec1::<f32>().unwrap();
        let mut g = randn(&[rows * d], 1.0, 98).to_vec1::<f32>().unwrap();
        for (j, v) in [
            3.3e38f32,
            -3.3e38,
            1e-30,
            -1e-30,
            0.0,
            -0.0,
            1.0 + 1.0 / 128.0,
        ]
        .into_iter()
        .enumerate()
        {
            x[j * 1001] = v;
            g[j * 1001 + 7] = v;
        }
        let b = randn(&[d], 0.5, 99);
        x[9 * d + 3] = -b.to_vec1::<f32>().unwrap()[3];
        let low = |v: Vec<f32>| {
            Tensor::from_vec(v, (rows, d), &Device::Cpu)
                .unwrap()
                .to_dtype(DType::BF16)
                .unwrap()
        };
        let (z, dy) = (low(x), low(g));
        let bits = |t: &Tensor| -> Vec<u32> {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            v.iter().map(|x| x.to_bits()).collect()
        };
        let wide = |t: &Tensor| t.to_dtype(DType::F32).unwrap();
        for act in [MlpAct::Relu, MlpAct::LeakyRelu(0.01), MlpAct::Gelu] {
            let want = wide(&z)
                .apply_op3_no_bwd(&b, &wide(&dy), &BiasActBwd { act })
                .unwrap();
            let got = bias_act_bwd_low(&z, &b, &dy, act).unwrap();
            assert_eq!(got.dtype(), DType::F32);
            assert_eq!(bits(&got), bits(&want), "{act:?}");
        }
        assert!(bias_act_bwd_low(&wide(&z), &b, &dy, MlpAct::Gelu).is_err());
        assert!(bias_act_bwd_low(&z, &b, &wide(&dy), MlpAct::Gelu).is_err());
        let short = dy.narrow(0, 0, rows - 1).unwrap();
        assert!(bias_act_bwd_low(&z, &b, &short, MlpAct::Gelu).is_err());
    }
}
