//! What the operations that compute on the host share (fusion's fused pass in mvmp-fusion, the
//! convolution columns here): reading a backend tensor's values, its dimensions, and transposing planes.
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Flex, TensorMetadata};
use burn::tensor::TensorData;
use rayon::prelude::*;
use std::any::Any;

/// A float tensor's values on the host, as float32, in a `Vec` of their own (a copy on flex, whose
/// buffers are aligned for any element type and so cannot become a `Vec<f32>`).
pub fn read_f32<B: Backend>(t: FloatTensor<B>) -> Vec<f32> {
    HostF32::read::<B>(t).to_vec()
}

/// A float tensor's values on the host, as float32, read in place: a contiguous float32 flex tensor is
/// borrowed as it is, shared or not. Reading a tensor only to compute from it, this saves one to three
/// passes over memory on one core: flex's `into_data` copies a shared buffer twice, and its buffers,
/// aligned for any element type, cannot become a `Vec<f32>` without a third copy ([`read_f32`] copied
/// every column gradient of a convolution).
pub enum HostF32 {
    Flex(FloatTensor<Flex>),
    Data(TensorData),
}

impl HostF32 {
    pub fn read<B: Backend>(t: FloatTensor<B>) -> Self {
        let any: Box<dyn Any> = Box::new(t);
        match any.downcast::<FloatTensor<Flex>>() {
            Ok(f) if f.as_slice::<f32>().is_some() => HostF32::Flex(*f),
            Ok(f) => HostF32::data::<Flex>(*f),
            Err(any) => HostF32::data::<B>(*any.downcast().expect("the tensor boxed above")),
        }
    }

    fn data<B: Backend>(t: FloatTensor<B>) -> Self {
        HostF32::Data(read_data::<B>(t))
    }
}

/// A float tensor's values on the host as float32 data (through the backend's `into_data`).
pub fn read_data<B: Backend>(t: FloatTensor<B>) -> TensorData {
    burn::tensor::try_read_sync(B::float_into_data(t))
        .expect("flex reads synchronously")
        .expect("a readable tensor")
        .convert::<f32>()
}

impl std::ops::Deref for HostF32 {
    type Target = [f32];

    fn deref(&self) -> &[f32] {
        match self {
            HostF32::Flex(t) => t.as_slice::<f32>().expect("checked when read"),
            HostF32::Data(d) => d.as_slice::<f32>().expect("float32 after conversion"),
        }
    }
}

/// A tensor's dimensions, `D` of them.
pub fn dims<const D: usize>(t: &impl TensorMetadata) -> [usize; D] {
    let shape = t.shape();
    std::array::from_fn(|i| shape[i])
}

/// `[N][A][B]` -> `[N][B][A]`: each of `n` planes transposed (channels-first to channels-last and back),
/// rows of the result in parallel (so one plane, a batch of one, runs on every thread too).
pub fn transpose_planes(src: &[f32], n: usize, a: usize, b: usize) -> Vec<f32> {
    let mut dst = vec![0f32; n * a * b];
    if a == 0 || b == 0 {
        return dst;
    }
    // Neighbouring rows read neighbouring values of each source row: a run of them shares cache lines.
    dst.par_chunks_mut(a)
        .with_min_len(16)
        .enumerate()
        .for_each(|(r, row)| {
            let (plane, j) = (r / b, r % b);
            let src = &src[plane * a * b..(plane + 1) * a * b];
            for (i, x) in row.iter_mut().enumerate() {
                *x = src[i * b + j];
            }
        });
    dst
}

#[cfg(test)]
mod tests {
    /// Every value lands at its transposed place, for one plane and several, and empty axes.
    #[test]
    fn planes_are_transposed() {
        for (n, a, b) in [(1, 3, 5), (3, 7, 2), (2, 0, 4), (1, 40, 33)] {
            let src: Vec<f32> = (0..n * a * b).map(|i| i as f32).collect();
            let dst = super::transpose_planes(&src, n, a, b);
            for p in 0..n {
                for i in 0..a {
                    for j in 0..b {
                        assert_eq!(dst[(p * b + j) * a + i], src[(p * a + i) * b + j]);
                    }
                }
            }
        }
    }
}
