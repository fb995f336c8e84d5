//! 3D pooling composed from tensor ops (burn has no 3D max-pool): the V2V 2 x 2 x 2 max-pool and the
//! 3 x 3 x 3 stride-1 max filter used for non-maximum suppression.
use burn::tensor::Tensor;

/// Max-pool with kernel 2 and stride 2 over `[B, C, X, Y, Z]` (sizes must be even).
pub fn max_pool3d_2(x: Tensor<5>) -> Tensor<5> {
    let [b, c, nx, ny, nz] = x.dims();
    assert!(
        nx % 2 == 0 && ny % 2 == 0 && nz % 2 == 0,
        "max_pool3d_2 needs even sizes, got {nx} x {ny} x {nz}"
    );
    // Fold each axis into (n/2, 2) and take the max over the pairs, one axis at a time.
    let x = x.reshape([b * c * nx * ny * (nz / 2), 2]).max_dim(1); // z pairs
    let x = x.reshape([b * c * nx * (ny / 2), 2, nz / 2]).max_dim(1); // y pairs
    let x = x
        .reshape([b * c * (nx / 2), 2, (ny / 2) * (nz / 2)])
        .max_dim(1); // x pairs
    x.reshape([b, c, nx / 2, ny / 2, nz / 2])
}

/// 3 x 3 x 3 max filter, stride 1, padding 1 (padding never wins), over `[B, C, X, Y, Z]`. A box max is
/// separable, so it is three 1D max filters.
pub fn max_filter3d_3(x: Tensor<5>) -> Tensor<5> {
    let x = max_filter_axis(x, 2);
    let x = max_filter_axis(x, 3);
    max_filter_axis(x, 4)
}

fn max_filter_axis(x: Tensor<5>, axis: usize) -> Tensor<5> {
    let n = x.dims()[axis];
    if n == 1 {
        return x;
    }
    // Neighbours shifted by one along the axis, edges repeated (an edge value never exceeds itself).
    let prev = Tensor::cat(
        vec![
            x.clone().narrow(axis, 0, 1),
            x.clone().narrow(axis, 0, n - 1),
        ],
        axis,
    );
    let next = Tensor::cat(
        vec![
            x.clone().narrow(axis, 1, n - 1),
            x.clone().narrow(axis, n - 1, 1),
        ],
        axis,
    );
    x.max_pair(prev).max_pair(next)
}

/// Non-maximum suppression: keep voxels equal to their 3 x 3 x 3 neighbourhood maximum, zero the rest.
pub fn nms3d(x: Tensor<5>) -> Tensor<5> {
    let m = max_filter3d_3(x.clone());
    let keep = x.clone().equal(m);
    x.clone().mask_fill(keep.bool_not(), 0.0)
}
