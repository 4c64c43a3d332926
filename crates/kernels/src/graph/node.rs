//! The candle custom-op plumbing shared by the nodes built from tensor ops (attention,
//! convolution, MLP): each computes its forward pass on detached tensors before it is
//! applied and hands the result over ([`Handover`]); [`Node`] is the custom op of two or
//! three operands whose forward pass returns that result on either backend and whose
//! backward pass is the node's own ([`TensorNode::backward`]).

use crate::graph::handover::Handover;
use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};

/// A node built from tensor ops.
pub(crate) trait TensorNode: Send + Sync {
    /// The op's name in candle's graph.
    fn name(&self) -> &'static str;

    /// What errors call the node.
    fn what(&self) -> &'static str;

    /// The finished forward pass.
    fn out(&self) -> &Handover;

    /// The gradient of each operand (in the order the node was applied to them, `None`
    /// where it has none) from the output's gradient `grad`.
    fn backward(&self, operands: &[&Tensor], grad: &Tensor) -> Result<Vec<Option<Tensor>>>;
}

/// A [`TensorNode`] as candle's custom op (`apply_op2`, `apply_op3`), with the ledger's
/// op kind where it was made (its backward pass's).
pub(crate) struct Node<T>(T, &'static str);

impl<T: TensorNode> Node<T> {
    pub(crate) fn new(node: T) -> Self {
        Self(node, crate::ledger::context().0)
    }

    fn gradients<const N: usize>(
        &self,
        operands: [&Tensor; N],
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; N]> {
        let d =
            crate::ledger::backward(self.1, self.0.what(), || self.0.backward(&operands, grad))?;
        let mut d = d.into_iter();
        Ok(std::array::from_fn(|_| d.next().flatten()))
    }
}

impl<T: TensorNode> CustomOp2 for Node<T> {
    fn name(&self) -> &'static str {
        self.0.name()
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        self.0.out().cpu(self.0.what())
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        self.0.out().cuda(self.0.what())
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let [da, db] = self.gradients([a, b], grad)?;
        Ok((da, db))
    }
}

impl<T: TensorNode> CustomOp3 for Node<T> {
    fn name(&self) -> &'static str {
        self.0.name()
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        self.0.out().cpu(self.0.what())
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        self.0.out().cuda(self.0.what())
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        c: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let [da, db, dc] = self.gradients([a, b, c], grad)?;
        Ok((da, db, dc))
    }
}
