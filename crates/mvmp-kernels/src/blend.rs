//! The weight average's update, `avg * keep + w * take`, on flex as one pass over both cores.
//!
//! Burn computes it as two scalings and a sum: the average is shared with the copy the last step kept
//! and the weights with the model, so each scaling writes a new buffer, and the three passes run on the
//! thread that carries a step's serial work. Here the weights are read where they lie, the average is
//! updated in its own buffer where no one else holds it (else in a new one), in parallel. The values
//! are burn-flex's bit for bit: the same float32 products and sum in the same order.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use crate::host::HostF32;

/// Elements per parallel chunk.
const CHUNK: usize = 1 << 15;

static HOST_BLEND: AtomicBool = AtomicBool::new(true);

/// Whether flex takes this pass (the default) or burn's operations; process-wide, so that a benchmark
/// can time both.
pub fn set_host_blend(on: bool) {
    HOST_BLEND.store(on, Ordering::Relaxed);
}

/// `avg * keep + w * take` for two float32 vectors of one length (the scalars as burn's tensor scalars
/// reach float32: `f64 as f32`): on flex one pass, otherwise burn's own operations.
pub fn blend(avg: Tensor<1>, w: Tensor<1>, keep: f64, take: f64) -> Tensor<1> {
    let host = HOST_BLEND.load(Ordering::Relaxed)
        && avg.device() == Device::flex()
        && w.device() == Device::flex()
        && avg.dims() == w.dims()
        && avg.dtype() == burn::tensor::DType::F32
        && w.dtype() == burn::tensor::DType::F32;
    if !host {
        return avg.mul_scalar(keep) + w.mul_scalar(take);
    }
    Tensor::from_dispatch(<Dispatch as BlendBackend>::blend(
        avg.into_dispatch(),
        w.into_dispatch(),
        keep as f32,
        take as f32,
    ))
}

fn mix(avg: &mut [f32], w: &[f32], keep: f32, take: f32) {
    (avg.par_chunks_mut(CHUNK).zip(w.par_chunks(CHUNK))).for_each(|(a, w)| {
        for (a, &w) in a.iter_mut().zip(w) {
            *a = *a * keep + w * take;
        }
    });
}

/// The backend side: a host pass into a new buffer; flex updates the average's own buffer in place.
#[backend_extension(Flex)]
pub trait BlendBackend: Backend {
    fn blend(
        avg: FloatTensor<Self>,
        w: FloatTensor<Self>,
        keep: f32,
        take: f32,
    ) -> FloatTensor<Self> {
        into_new::<Self>(avg, &HostF32::read::<Self>(w), keep, take)
    }
}

/// The blend written to a new buffer (the average's own is shared or not whole).
fn into_new<B: Backend>(avg: FloatTensor<B>, w: &[f32], keep: f32, take: f32) -> FloatTensor<B> {
    let device = avg.device();
    let shape = avg.shape().to_vec();
    let mut a = HostF32::read::<B>(avg).to_vec();
    mix(&mut a, w, keep, take);
    B::float_from_data(TensorData::new(a, shape), &device)
}

impl BlendBackend for Flex {
    fn blend(
        mut avg: FloatTensor<Flex>,
        w: FloatTensor<Flex>,
        keep: f32,
        take: f32,
    ) -> FloatTensor<Flex> {
        let n = avg.shape().num_elements();
        let whole = avg.layout().contiguous_offsets() == Some((0, n));
        let w = HostF32::read::<Flex>(w);
        match avg.try_storage_mut::<f32>() {
            Some(a) if whole && a.len() == n => {
                mix(a, &w, keep, take);
                avg
            }
            _ => into_new::<Flex>(avg, &w, keep, take),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Distribution;

    fn bits(t: Tensor<1>) -> Vec<u32> {
        let v = t.into_data().try_to_vec::<f32>().unwrap();
        v.into_iter().map(f32::to_bits).collect()
    }

    /// Over several parallel chunks and rates, with the average's buffer its own and shared, the pass
    /// gives burn's two scalings and sum bit for bit and leaves the weights and a shared average as
    /// they were.
    #[test]
    fn the_pass_is_burns_scalings_and_sum_bit_for_bit() {
        let d = Device::flex();
        let n = 3 * CHUNK + 17;
        for r in [0.1, 2.0 / 11.0, 0.99] {
            let avg = Tensor::<1>::random([n], Distribution::Normal(0.0, 1.0), &d);
            let w = Tensor::<1>::random([n], Distribution::Normal(0.0, 3.0), &d);
            let want = bits(avg.clone().mul_scalar(r) + w.clone().mul_scalar(1.0 - r));
            let (avg_before, w_before) = (bits(avg.clone()), bits(w.clone()));
            let shared = avg.clone();
            assert_eq!(
                bits(blend(shared, w.clone(), r, 1.0 - r)),
                want,
                "shared, {r}"
            );
            assert_eq!(bits(avg.clone()), avg_before);
            let own = Tensor::<1>::from_data(avg.into_data(), &d);
            assert_eq!(bits(blend(own, w.clone(), r, 1.0 - r)), want, "own, {r}");
            assert_eq!(bits(w), w_before);
        }
    }
}
