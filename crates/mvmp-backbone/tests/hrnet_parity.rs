//! One HRNet module (2 branches, one basic block each, fuse layers up and down) against an independent numpy
//! computation (scripts/hrnet_module_fixture.py), batch norm in inference mode.
use burn::module::{Param, RunningState};
use burn::nn::BatchNorm;
use burn::nn::conv::Conv2d;
use burn::tensor::{Device, Tensor, TensorData};
use mvmp_backbone::HRNetConfig;

fn formula(n: usize, a: f64, b: f64, scale: f64) -> Vec<f32> {
    (0..n)
        .map(|i| ((i as f64 * a + b).sin() * scale) as f32)
        .collect()
}

fn set_conv(c: &mut Conv2d, name: &str, co: usize, ci: usize, k: usize, d: &Device) {
    let v = formula(
        co * ci * k * k,
        0.37 + name.len() as f64 * 0.01,
        name.len() as f64 * 0.05,
        0.2,
    );
    c.weight = Param::from_tensor(Tensor::from_data(TensorData::new(v, [co, ci, k, k]), d));
}

fn set_bn(bn: &mut BatchNorm, name: &str, c: usize, d: &Device) {
    let l = name.len() as f64;
    let t = |v: Vec<f32>| Tensor::<1>::from_data(TensorData::new(v, [c]), d);
    bn.gamma = Param::from_tensor(t(formula(c, 0.3, l * 0.1, 0.1)
        .iter()
        .map(|x| x + 1.0)
        .collect()));
    bn.beta = Param::from_tensor(t(formula(c, 0.7, l * 0.2, 0.1)));
    bn.running_mean = RunningState::new(t(formula(c, 1.1, l * 0.3, 0.1)));
    bn.running_var = RunningState::new(t(formula(c, 1.3, l * 0.4, 0.5)
        .iter()
        .map(|x| 1.0 + x.abs())
        .collect()));
}

fn flat(v: &serde_json::Value) -> Vec<f32> {
    match v {
        serde_json::Value::Array(a) => a.iter().flat_map(flat).collect(),
        x => vec![x.as_f64().unwrap() as f32],
    }
}

#[test]
fn one_module_matches_the_numpy_reference() {
    let fx: serde_json::Value =
        serde_json::from_str(include_str!("fixtures/hrnet_module.json")).unwrap();
    let d = Device::flex();
    let (c0, c1, h, w) = (8usize, 16usize, 8usize, 12usize);
    let mut net = HRNetConfig::tiny(17).init(&d);
    let m = &mut net.stage2[0];
    for (b, c) in [(0usize, c0), (1, c1)] {
        let blk = &mut m.branches[b][0];
        let p = format!("branches.{b}.0");
        set_conv(&mut blk.conv1, &format!("{p}.conv1"), c, c, 3, &d);
        set_bn(&mut blk.bn1, &format!("{p}.bn1"), c, &d);
        set_conv(&mut blk.conv2, &format!("{p}.conv2"), c, c, 3, &d);
        set_bn(&mut blk.bn2, &format!("{p}.bn2"), c, &d);
    }
    let up = m.fuse_layers[0][1].as_mut().unwrap().up.as_mut().unwrap();
    set_conv(&mut up.conv, "fuse_layers.0.1.0", c0, c1, 1, &d);
    set_bn(&mut up.bn, "fuse_layers.0.1.1", c0, &d);
    let down = &mut m.fuse_layers[1][0].as_mut().unwrap().down[0];
    set_conv(&mut down.cb.conv, "fuse_layers.1.0.0.0", c1, c0, 3, &d);
    set_bn(&mut down.cb.bn, "fuse_layers.1.0.0.1", c1, &d);
    let x0 = Tensor::<4>::from_data(TensorData::new(flat(&fx["x0"]), [1, c0, h, w]), &d);
    let x1 = Tensor::<4>::from_data(TensorData::new(flat(&fx["x1"]), [1, c1, h / 2, w / 2]), &d);
    let out = net.stage2[0].forward(vec![x0, x1]);
    for (o, key) in out.into_iter().zip(["y0", "y1"]) {
        let got: Vec<f32> = o.into_data().try_into_vec().unwrap();
        let want = flat(&fx[key]);
        assert_eq!(got.len(), want.len());
        let worst = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        // float32 against float64 through two convolutions and batch norms.
        assert!(worst < 1e-4, "{key}: max abs difference {worst}");
    }
}
