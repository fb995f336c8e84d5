//! HRNet: output shapes and stride, parameter counts of the reference configurations.
use burn::module::Module;
use burn::tensor::{Device, Tensor};
use mvmp_backbone::HRNetConfig;

#[test]
fn heatmaps_at_stride_four() {
    let d = Device::flex();
    for name in ["tiny", "small"] {
        let net = HRNetConfig::by_name(name, 15).unwrap().init(&d);
        let y = net.forward(Tensor::<4>::zeros([2, 3, 64, 96], &d));
        assert_eq!(y.dims(), [2, 15, 16, 24], "{name}");
        // Sizes that are not multiples of 32 (the paper's 1288 is not): branches round up, fusion resizes.
        let y = net.forward(Tensor::<4>::zeros([1, 3, 100, 92], &d));
        assert_eq!(y.dims(), [1, 15, 25, 23], "{name}");
    }
    assert!(HRNetConfig::by_name("w16", 15).is_none());
}

#[test]
fn reference_parameter_counts() {
    // On an autodiff device trainable parameters require gradients and running statistics do not.
    let d = Device::flex().autodiff();
    // The published sizes of the COCO pose nets (17 joints): 28.5 M (W32) and 63.6 M (W48). Batch-norm
    // running statistics are state, not parameters, in both counts.
    let count = |cfg: HRNetConfig| {
        struct Trainable(usize);
        impl burn::module::ModuleVisitor for Trainable {
            fn visit_float<const D: usize>(&mut self, p: &burn::module::Param<Tensor<D>>) {
                if p.is_require_grad() {
                    self.0 += p.val().shape().num_elements();
                }
            }
        }
        let net = cfg.init(&d);
        let mut v = Trainable(0);
        net.visit(&mut v);
        v.0
    };
    let w32 = count(HRNetConfig::hrnet_w32(17));
    let w48 = count(HRNetConfig::hrnet_w48(17));
    assert!((28_400_000..28_600_000).contains(&w32), "W32: {w32}");
    assert!((63_500_000..63_700_000).contains(&w48), "W48: {w48}");
}
