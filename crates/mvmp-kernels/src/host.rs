//! What the operations that compute on the host share (fusion's fused pass in mvmp-fusion, the
//! convolution columns here): reading a backend tensor's values, its dimensions, and transposing planes.
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Flex, TensorMetadata};
use burn::tensor::TensorData;
use rayon::prelude::*;
use std::any::Any;
use std::mem::MaybeUninit;

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

/// A buffer of `n` floats made in parallel: `fill(i, piece)` gets the `i`-th piece of `chunk` values
/// (the last may be shorter), zeroed by the task that fills it while it is in cache. A buffer made by
/// `vec![0.0; n]` is zeroed on the calling thread alone, a pass over megabytes that the other threads
/// wait for.
pub fn par_filled(
    n: usize,
    chunk: usize,
    fill: impl Fn(usize, &mut [f32]) + Sync + Send,
) -> Vec<f32> {
    let mut v: Vec<f32> = Vec::with_capacity(n);
    v.spare_capacity_mut()[..n]
        .par_chunks_mut(chunk.max(1))
        .enumerate()
        .for_each(|(i, piece)| {
            piece.fill(MaybeUninit::new(0.0));
            // SAFETY: every value of the piece was just written.
            let piece = unsafe { &mut *(piece as *mut [MaybeUninit<f32>] as *mut [f32]) };
            fill(i, piece)
        });
    // SAFETY: the pieces cover all `n` values and each was zeroed.
    unsafe { v.set_len(n) };
    v
}

/// `n` zeros, written in parallel (see [`par_filled`]).
pub fn par_zeroed(n: usize) -> Vec<f32> {
    par_filled(n, ZEROED_CHUNK, |_, _| ())
}

/// Values per task of [`par_zeroed`]: 256 KiB.
const ZEROED_CHUNK: usize = 1 << 16;

/// `[N][A][B]` -> `[N][B][A]`: each of `n` planes transposed (channels-first to channels-last and back),
/// rows of the result in parallel (so one plane, a batch of one, runs on every thread too).
pub fn transpose_planes(src: &[f32], n: usize, a: usize, b: usize) -> Vec<f32> {
    if a == 0 || b == 0 {
        return vec![0f32; n * a * b];
    }
    // Neighbouring rows read neighbouring values of each source row: a run of them shares cache lines.
    par_filled(n * a * b, a * 16, |chunk, rows| {
        for (k, row) in rows.chunks_exact_mut(a).enumerate() {
            let r = chunk * 16 + k;
            let (plane, j) = (r / b, r % b);
            let src = &src[plane * a * b..(plane + 1) * a * b];
            for (i, x) in row.iter_mut().enumerate() {
                *x = src[i * b + j];
            }
        }
    })
}

#[cfg(test)]
mod tests {
    /// Each piece comes zeroed with its own index, the last one shorter, and the pieces cover the
    /// buffer in order; an empty buffer calls nothing.
    #[test]
    fn pieces_are_zeroed_indexed_and_cover_the_buffer() {
        for (n, chunk) in [(10, 3), (9, 3), (1, 4), (0, 2), (5, 0)] {
            let v = super::par_filled(n, chunk, |i, piece| {
                assert!(piece.iter().all(|&x| x == 0.0));
                for (k, x) in piece.iter_mut().enumerate() {
                    *x = (i * chunk.max(1) + k) as f32;
                }
            });
            assert_eq!(v, (0..n).map(|i| i as f32).collect::<Vec<_>>());
        }
        assert!(super::par_zeroed(70_000).iter().all(|&x| x == 0.0));
    }

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
