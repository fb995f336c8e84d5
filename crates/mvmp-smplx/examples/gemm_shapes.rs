//! The SMPL-X layer's two GEMMs and its skinning step in the layouts they could take, timed on flex
//! (median of 60 runs): the numbers behind the layer's layout choices. `ONLY=<substring>` runs one case.
//!
//! `cargo run --release -p mvmp-smplx --example gemm_shapes`
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;
use burn::tensor::{Device, Tensor, TensorData};
use std::time::Instant;

fn t2(r: usize, c: usize, d: &Device) -> Tensor<2> {
    let v: Vec<f32> = (0..r * c)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
        .collect();
    Tensor::from_data(TensorData::new(v, [r, c]), d)
}

fn time(name: &str, f: impl Fn() -> Tensor<2>) {
    if let Ok(only) = std::env::var("ONLY")
        && !name.contains(&only)
    {
        return;
    }
    let _ = f().into_data();
    let mut ts = Vec::new();
    for _ in 0..60 {
        let s = Instant::now();
        let r = f();
        std::hint::black_box(&r);
        ts.push(s.elapsed().as_secs_f64() * 1e3);
    }
    ts.sort_by(f64::total_cmp);
    println!("{name:<50} {:.2} ms", ts[ts.len() / 2]);
}

fn main() {
    let d = Device::flex();
    let n = 30;
    let feat = t2(n, 486, &d);
    let pd = t2(486, 31425, &d);
    let pd_t = t2(31425, 486, &d);
    let feat_t = t2(486, n, &d);
    time("feat[30,486] x posedirs[486,31425]", || {
        feat.clone().matmul(pd.clone())
    });
    time("posedirs_T[31425,486] x feat_T[486,30]", || {
        pd_t.clone().matmul(feat_t.clone())
    });
    time("  ... then transposed back", || {
        pd_t.clone().matmul(feat_t.clone()).transpose()
    });
    let a = t2(12 * n, 55, &d);
    let w_t = t2(55, 10475, &d);
    let w = t2(10475, 55, &d);
    let a_t = t2(55, 12 * n, &d);
    time("a[360,55] x weights_t[55,10475]", || {
        a.clone().matmul(w_t.clone())
    });
    time("a[360,55] x weights_t[55,10475], then drop", || {
        let _ = a.clone().matmul(w_t.clone());
        t2(1, 1, &d)
    });
    let a_host: Vec<f32> = a.clone().into_data().try_to_vec().unwrap();
    let w_host: Vec<f32> = w_t.clone().into_data().try_to_vec().unwrap();
    let a2 = Tensor::<2>::from_data(TensorData::new(a_host, [360, 55]), &d);
    let w2 = Tensor::<2>::from_data(TensorData::new(w_host, [55, 10475]), &d);
    time("same, tensors rebuilt from host data", || {
        a2.clone().matmul(w2.clone())
    });
    time("weights[10475,55] x a_T[55,360]", || {
        w.clone().matmul(a_t.clone())
    });
    let a64 = t2(12 * n, 64, &d);
    let w64 = t2(64, 10475, &d);
    time("a[360,64] x weights_t[64,10475] (K padded)", || {
        a64.clone().matmul(w64.clone())
    });
    let big_a = t2(1024, 1024, &d);
    time("1024^3", || big_a.clone().matmul(big_a.clone()));
    // Elementwise combine of skinning: 12 planes [N, V] with x, y, z.
    let tt = t2(12 * n, 10475, &d).reshape([12, n, 10475]);
    let x = t2(n, 10475, &d);
    let vh = t2(4 * n, 10475, &d).reshape([1, 4, n, 10475]);
    time("combine: broadcast multiply + sum_dim", || {
        (tt.clone().reshape([3, 4, n, 10475]) * vh.clone())
            .sum_dim(1)
            .reshape([3, n, 10475])
            .permute([1, 2, 0])
            .reshape([n, 3 * 10475])
    });
    time("combine: 12 planes, 3 outputs", || {
        let c = |k: usize| tt.clone().narrow(0, k, 1).reshape([n, 10475]);
        let out = |r: usize| {
            c(4 * r) * x.clone()
                + c(4 * r + 1) * x.clone()
                + c(4 * r + 2) * x.clone()
                + c(4 * r + 3)
        };
        Tensor::stack::<3>(vec![out(0), out(1), out(2)], 2).reshape([n, 3 * 10475])
    });
}
