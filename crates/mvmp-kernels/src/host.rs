//! What the operations that compute on the host share (fusion's fused pass in mvmp-fusion, the
//! convolution columns here): reading a backend tensor's values, its dimensions, and transposing planes.
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, TensorMetadata};
use rayon::prelude::*;

/// A float tensor's values on the host, as float32.
pub fn read_f32<B: Backend>(t: FloatTensor<B>) -> Vec<f32> {
    burn::tensor::try_read_sync(B::float_into_data(t))
        .expect("flex reads synchronously")
        .expect("a readable tensor")
        .convert::<f32>()
        .try_into_vec::<f32>()
        .expect("float32 after conversion")
}

/// A tensor's dimensions, `D` of them.
pub fn dims<const D: usize>(t: &impl TensorMetadata) -> [usize; D] {
    let shape = t.shape();
    std::array::from_fn(|i| shape[i])
}

/// `[N][A][B]` -> `[N][B][A]`: each of `n` planes transposed (channels-first to channels-last and back),
/// planes in parallel.
pub fn transpose_planes(src: &[f32], n: usize, a: usize, b: usize) -> Vec<f32> {
    let mut dst = vec![0f32; n * a * b];
    dst.par_chunks_mut(a * b)
        .zip(src.par_chunks(a * b))
        .for_each(|(dst, src)| {
            for (i, row) in src.chunks_exact(b).enumerate() {
                for (j, &x) in row.iter().enumerate() {
                    dst[j * a + i] = x;
                }
            }
        });
    dst
}
