//! A convolution's columns times its weight as one operation on flex: the same columns
//! ([`crate::im2col`]) and the same GEMM calls flex makes for `columns.matmul(weight.transpose())`, so
//! the values are those of the two ops bit for bit, but the products write into buffers of their own.
//!
//! Why: flex allocates every product's output zeroed as bytes and then copies it to realign it, on the
//! calling thread, and the columns' gradient (`dy . w`, `k^3` times the input) was the largest of them;
//! the col2im pass then read it. Here that gradient is computed into a host buffer that col2im reads in
//! place. On a `mvmp bench train` profile the products' backward held about a third of the main thread's
//! serial work, most of it those allocations and copies.
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Tensor, TensorData};
use std::any::Any;

use crate::host::{dims, read_data};
use crate::im2col::{Columns, backward_host, host_columns};

/// `columns(x) . weight^T`: `x [B, C, D, H, W]`, `weight [Co, kd * kh * kw * C]` (taps in the columns'
/// order) -> `[B * Do * Ho * Wo, Co]`.
pub fn columns_product(x: Tensor<5>, weight: Tensor<2>, geometry: Columns) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as ColumnsProductBackend>::columns_product(
        x.into_dispatch(),
        weight.into_dispatch(),
        geometry,
    ))
}

/// The backend side of [`columns_product`]; autodiff adds the backward.
#[backend_extension(Flex, Autodiff)]
pub trait ColumnsProductBackend: Backend {
    fn columns_product(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        geometry: Columns,
    ) -> FloatTensor<Self> {
        let cols = host_columns::<Self>(x, &geometry);
        let device = cols.device();
        let y = product::<Self>(&cols, &Self::float_transpose(weight));
        Self::float_from_data(y, &device)
    }
}

impl ColumnsProductBackend for Flex {}

impl<B: Backend + ColumnsProductBackend, C: CheckpointStrategy> ColumnsProductBackend
    for Autodiff<B, C>
{
    fn columns_product(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        geometry: Columns,
    ) -> FloatTensor<Self> {
        let guards = [x.node(), weight.node()];
        let (x, weight) = (x.into_primitive(), weight.into_primitive());
        let dims = dims(&x);
        let cols = host_columns::<B>(x, &geometry);
        let device = cols.device();
        let y = product::<B>(&cols, &B::float_transpose(weight.clone()));
        let y = B::float_from_data(y, &device);
        match ProductBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(
                Saved {
                    cols,
                    weight,
                    dims,
                    geometry,
                },
                y,
            ),
            OpsKind::UnTracked(prep) => prep.finish(y),
        }
    }
}

/// The backward's state: the columns and the weight (each kept for the other's gradient), the input's
/// dimensions and the geometry.
#[derive(Debug, Clone)]
struct Saved<B: Backend> {
    cols: FloatTensor<B>,
    weight: FloatTensor<B>,
    dims: [usize; 5],
    geometry: Columns,
}

#[derive(Debug)]
struct ProductBackward;

impl<B: Backend> Backward<B, 2> for ProductBackward {
    type State = Saved<B>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = grads.consume::<B>(&ops.node);
        let [node_x, node_w] = ops.parents;
        let s = ops.state;
        let device = dy.device();
        // As autodiff's matmul: the columns' gradient `dy . w`, then the weight's, `cols^T . dy`, as
        // the transposed weight's gradient transposed back.
        if let Some(node) = node_x {
            let dcols = product::<B>(&dy, &s.weight);
            let dx = backward_host(dcols.as_slice::<f32>().expect("f32"), s.dims, &s.geometry);
            let dx = B::float_from_data(TensorData::new(dx, s.dims), &device);
            grads.register::<B>(node.id, dx);
        }
        if let Some(node) = node_w {
            let dwt = product::<B>(&B::float_transpose(s.cols), &dy);
            let dwt = B::float_from_data(dwt, &device);
            grads.register::<B>(node.id, B::float_transpose(dwt));
        }
    }
}

/// `lhs [M, K] . rhs [K, N]` on the host. Flex tensors go to the GEMM flex itself calls, with their
/// strides and flex's choice of threads, so the result is flex's matmul bit for bit; other backends use
/// their own matmul.
fn product<B: Backend>(lhs: &FloatTensor<B>, rhs: &FloatTensor<B>) -> TensorData {
    let pair = (lhs as &dyn Any, rhs as &dyn Any);
    if let (Some(l), Some(r)) = (
        pair.0.downcast_ref::<FloatTensor<Flex>>(),
        pair.1.downcast_ref::<FloatTensor<Flex>>(),
    ) && l.dtype() == burn::tensor::DType::F32
        && r.dtype() == burn::tensor::DType::F32
    {
        return flex_gemm(l, r);
    }
    read_data::<B>(B::float_matmul(lhs.clone(), rhs.clone()))
}

/// Flex's own 2D product (its `matmul_2d_strided`): the same GEMM, strides and parallelism.
fn flex_gemm(lhs: &FloatTensor<Flex>, rhs: &FloatTensor<Flex>) -> TensorData {
    let (ls, rs) = (lhs.layout(), rhs.layout());
    let (m, k, n) = (ls.shape()[0], ls.shape()[1], rs.shape()[1]);
    assert_eq!(rs.shape()[0], k, "inner dimensions");
    let (l_rs, l_cs) = (ls.strides()[0], ls.strides()[1]);
    let (r_rs, r_cs) = (rs.strides()[0], rs.strides()[1]);
    let lhs_data: &[f32] = lhs.storage();
    let rhs_data: &[f32] = rhs.storage();
    // Flex's threshold for running a product on every thread.
    let parallelism = if m.saturating_mul(n).saturating_mul(k) >= 192 * 192 * 192 {
        gemm::Parallelism::Rayon(0)
    } else {
        gemm::Parallelism::None
    };
    let mut out = vec![0f32; m * n];
    // SAFETY: the pointers start at each tensor's offset within its own storage, and the shapes and
    // strides are the tensors' own layouts, so every element the GEMM reads lies in that storage; the
    // output is a fresh contiguous `m x n` buffer.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            out.as_mut_ptr(),
            1,
            n as isize,
            false,
            lhs_data.as_ptr().add(ls.start_offset()),
            l_cs,
            l_rs,
            rhs_data.as_ptr().add(rs.start_offset()),
            r_cs,
            r_rs,
            0.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
    TensorData::new(out, [m, n])
}
