//! The operands' view every CPU product reads ([`MatRef`]: a checked strided matrix inside
//! a slice) and how many threads a product may take ([`Threads`]).

use candle_core::{CpuStorage, Layout, Result};

/// A strided `[rows, cols]` view of f32 values inside a slice: element `(i, j)` is
/// `data[off + i·rs + j·cs]`. Constructed only through [`MatRef::new`], which checks
/// that every element is inside `data`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct MatRef<'a> {
    data: &'a [f32],
    off: usize,
    rows: usize,
    cols: usize,
    rs: usize,
    cs: usize,
}

impl<'a> MatRef<'a> {
    pub(crate) fn new(
        data: &'a [f32],
        off: usize,
        (rows, cols): (usize, usize),
        (rs, cs): (usize, usize),
    ) -> Result<Self> {
        if rows > 0 && cols > 0 {
            let last = (rows - 1)
                .checked_mul(rs)
                .and_then(|r| (cols - 1).checked_mul(cs).and_then(|c| r.checked_add(c)))
                .and_then(|rc| rc.checked_add(off));
            if last.is_none_or(|l| l >= data.len()) {
                candle_core::bail!(
                    "matmul: a [{rows}, {cols}] view (offset {off}, strides [{rs}, {cs}]) \
                     outside {} values",
                    data.len()
                );
            }
        }
        Ok(Self {
            data,
            off,
            rows,
            cols,
            rs,
            cs,
        })
    }

    /// A 2-D layout of an f32 storage (any strides, offset included).
    pub(crate) fn of(s: &'a CpuStorage, l: &Layout) -> Result<Self> {
        let CpuStorage::F32(v) = s else {
            candle_core::bail!("matmul: fused ops take f32");
        };
        let (rows, cols) = l.shape().dims2()?;
        let st = l.stride();
        Self::new(v, l.start_offset(), (rows, cols), (st[0], st[1]))
    }

    pub(crate) fn t(self) -> Self {
        Self {
            rows: self.cols,
            cols: self.rows,
            rs: self.cs,
            cs: self.rs,
            ..self
        }
    }

    /// Rows `r0 .. r0 + len`.
    pub(crate) fn rows(self, r0: usize, len: usize) -> Result<Self> {
        if r0 + len > self.rows {
            candle_core::bail!("matmul: rows {r0}..{} of {}", r0 + len, self.rows);
        }
        Self::new(
            self.data,
            self.off + r0 * self.rs,
            (len, self.cols),
            (self.rs, self.cs),
        )
    }

    /// Columns `c0 .. c0 + len`.
    pub(crate) fn cols(self, c0: usize, len: usize) -> Result<Self> {
        self.t().rows(c0, len).map(Self::t)
    }

    pub(crate) fn dims(&self) -> (usize, usize) {
        (self.rows, self.cols)
    }

    /// The slice, the offset of element `(0, 0)` and the strides `(rs, cs)`: every
    /// element `(i, j)` inside [`Self::dims`] is at `off + i·rs + j·cs < data.len()`.
    pub(crate) fn raw(&self) -> (&'a [f32], usize, (usize, usize)) {
        (self.data, self.off, (self.rs, self.cs))
    }

    /// Element `(i, j)` (inside [`Self::dims`]).
    pub(crate) fn get(&self, i: usize, j: usize) -> f32 {
        self.data[self.off + i * self.rs + j * self.cs]
    }
}

/// How many threads one product may use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Threads {
    /// The current rayon pool (candle's device pool inside a step).
    Pool,
    /// The calling thread only: for products that are themselves parallel tasks.
    One,
}
