//! How a node with more parameters than candle's custom ops take (three operands) gets
//! their gradients into candle's graph without a copy of them.
//!
//! Why: packing the parameters into one operand (`Tensor::cat`) makes a copy of every
//! weight that the graph holds until the backward pass ends (the MLP nodes of the
//! `paper` preset: about 85 MB per step, by count of their 21.4 M parameters), and hands
//! the gradients back as one buffer that candle's backward pass of the concatenation
//! narrows apart again. Instead the
//! parameters enter through a chain of links, two parameters each, whose values are one
//! float: `link₀ = Link(0, p₀, p₁)`, `link₁ = Link(link₀, p₂, p₃)`, …, and the node
//! takes the last link as its operand. In the backward pass candle reaches the node
//! before its links (they lead to nothing else), so the node leaves each parameter's
//! gradient in the shared [`ParamGrads`] and each link hands its two on.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp3, DType, Layout, Result, Shape, Tensor};
use std::sync::{Arc, Mutex};

/// The parameters' gradients, from the node's backward pass to its links'.
#[derive(Clone, Default)]
pub(crate) struct ParamGrads(Arc<Mutex<Vec<Option<Tensor>>>>);

impl ParamGrads {
    /// Leaves the gradient of each parameter (in the order given to [`link`]).
    pub(crate) fn put(&self, grads: Vec<Tensor>) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = grads.into_iter().map(Some).collect();
    }

    fn take(&self, i: usize) -> Result<Tensor> {
        let mut g = self.0.lock().unwrap_or_else(|e| e.into_inner());
        match g.get_mut(i).and_then(Option::take) {
            Some(t) => Ok(t),
            None => candle_core::bail!("links: parameter {i}'s gradient was not left by its node"),
        }
    }
}

/// The chain of links over `params` (an even count: pairs), and where their gradients
/// are to be left. The result is `[1]` f32 on the parameters' device, tracked where any
/// parameter is.
pub(crate) fn link(params: &[&Tensor]) -> Result<(Tensor, ParamGrads)> {
    if params.is_empty() || !params.len().is_multiple_of(2) {
        candle_core::bail!("links: {} parameters, expected pairs", params.len());
    }
    let grads = ParamGrads::default();
    let mut chain = Tensor::zeros(1, DType::F32, params[0].device())?;
    for (i, pair) in params.chunks(2).enumerate() {
        let op = Link {
            first: 2 * i,
            grads: grads.clone(),
        };
        chain = chain.apply_op3(pair[0], pair[1], op)?;
    }
    Ok((chain, grads))
}

/// One link: the value of the link before it (`[1]`), two parameters as operands.
struct Link {
    /// The index of its first parameter in [`ParamGrads`].
    first: usize,
    grads: ParamGrads,
}

impl CustomOp3 for Link {
    fn name(&self) -> &'static str {
        "osrt-param-link"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        Ok((s1.try_clone(l1)?, Shape::from(1)))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        Ok((s1.try_clone(l1)?, Shape::from(1)))
    }

    fn bwd(
        &self,
        prev: &Tensor,
        a: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        _grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let ga = self.grads.take(self.first)?;
        let gb = self.grads.take(self.first + 1)?;
        // The link before carries no value: its gradient is a zero that keeps candle's
        // walk going down the chain.
        let gp = match prev.track_op() {
            true => Some(prev.zeros_like()?),
            false => None,
        };
        Ok((gp, a.track_op().then_some(ga), b.track_op().then_some(gb)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    /// Each parameter receives the gradient its node leaves for it, through a chain of
    /// several links; a parameter that carries no gradient receives none; the chain
    /// holds one float per link, not the parameters.
    #[test]
    fn each_parameter_gets_the_gradient_its_node_leaves() {
        let dev = Device::Cpu;
        let p: Vec<Var> = (0..4)
            .map(|i| Var::from_tensor(&Tensor::full(i as f32, (2, 3), &dev).unwrap()).unwrap())
            .collect();
        let frozen = Tensor::ones(5, DType::F32, &dev).unwrap();
        let params = [
            p[0].as_tensor(),
            p[1].as_tensor(),
            p[2].as_tensor(),
            &frozen,
            p[3].as_tensor(),
            p[0].as_tensor(),
        ];
        let (chain, grads) = link(&params).unwrap();
        assert_eq!(chain.dims(), [1]);
        assert!(chain.track_op());
        let left: Vec<Tensor> = params
            .iter()
            .enumerate()
            .map(|(i, t)| (t.ones_like().unwrap() * (10.0 + i as f64)).unwrap())
            .collect();
        grads.put(left);
        let g = chain.sum_all().unwrap().backward().unwrap();
        let got = |v: &Var| {
            g.get(v.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
        };
        assert_eq!(got(&p[1]), vec![11.0; 6]);
        assert_eq!(got(&p[2]), vec![12.0; 6]);
        assert_eq!(got(&p[3]), vec![14.0; 6]);
        // p₀ twice: both gradients, added.
        assert_eq!(got(&p[0]), vec![25.0; 6]);
        assert!(g.get(&frozen).is_none());
        // A second backward without the node leaving gradients again is an error, not a
        // silent zero.
        assert!(chain.sum_all().unwrap().backward().is_err());
        assert!(link(&params[..3]).is_err());
    }
}
