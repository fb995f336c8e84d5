//! `mvmp bench attention`: seconds and peak extra memory of one attention forward and backward, the
//! tiled operation (`mvmp_kernels::attention`, what training uses) beside burn's plain ops, over growing
//! token counts. Memory is what the process allocates beyond the inputs while the step runs (counted by
//! the binary's allocator): host memory, so it is reported for the CPU backends only.
use std::time::Instant;

use anyhow::Result;
use burn::tensor::{Device, Distribution, Tensor};

use crate::GLOBAL;

pub struct AttentionArgs<'a> {
    pub tokens: &'a [usize],
    pub heads: usize,
    pub head_dim: usize,
    pub tile: usize,
    /// The plain path runs only up to this many tokens (its scores are `heads x N x N` floats, kept for
    /// the backward).
    pub plain_up_to: usize,
    /// Whether the device computes in host memory (cpu, ndarray), where the allocator sees it.
    pub host: bool,
}

/// One forward and backward: seconds, and peak bytes beyond those live before it.
struct Measured {
    seconds: f64,
    peak: usize,
}

/// Most elements of one `[heads, tokens, head_dim]` tensor (4 GiB of float32): the step holds about eight
/// of them (q, k, v, the weights, the output and three gradients), so a larger request is refused rather
/// than left to abort in the allocator.
const MAX_ELEMENTS: usize = 1 << 30;

pub fn bench_attention(args: &AttentionArgs, device: &Device) -> Result<()> {
    for &n in args.tokens {
        let elements = args.heads.saturating_mul(n).saturating_mul(args.head_dim);
        anyhow::ensure!(
            elements <= MAX_ELEMENTS,
            "--tokens {n} with --heads {} and --head-dim {}: {elements} elements per tensor, more than \
             the {MAX_ELEMENTS} the benchmark allows (about eight such tensors are held at once)",
            args.heads,
            args.head_dim
        );
        // The scores: `heads x tile x tile` per tile of the tiled path, `heads x N x N` on the plain one.
        let tile = args.tile.min(n);
        let tiled = args.heads.saturating_mul(tile).saturating_mul(tile);
        anyhow::ensure!(
            tiled <= MAX_ELEMENTS,
            "--tile {} at --tokens {n} with --heads {}: {tiled} scores per tile, more than the \
             {MAX_ELEMENTS} the benchmark allows",
            args.tile,
            args.heads
        );
        let plain = args.heads.saturating_mul(n).saturating_mul(n);
        anyhow::ensure!(
            n > args.plain_up_to || plain <= MAX_ELEMENTS,
            "--plain-up-to {} runs the plain path at --tokens {n} with --heads {}: {plain} scores, more \
             than the {MAX_ELEMENTS} the benchmark allows (lower --plain-up-to)",
            args.plain_up_to,
            args.heads
        );
    }
    let device = device.clone().autodiff();
    println!(
        "attention forward + backward, batch 1, {} heads of {}, tile {}; memory: peak bytes allocated beyond the inputs{}",
        args.heads,
        args.head_dim,
        args.tile,
        if args.host {
            ""
        } else {
            " (not counted: device memory)"
        }
    );
    println!("tokens   tiled s   tiled MiB   plain s   plain MiB");
    // One untimed run of each path first: what the first call of a process allocates once (thread
    // pools, caches) is not attention's.
    let warm = args.tokens.iter().copied().min().unwrap_or(1).min(256);
    measure(&device, warm, args, Some(args.tile));
    measure(&device, warm, args, None);
    for &n in args.tokens {
        let tiled = measure(&device, n, args, Some(args.tile));
        let plain = (n <= args.plain_up_to).then(|| measure(&device, n, args, None));
        let mib = |m: &Measured| {
            if args.host {
                format!("{:.1}", m.peak as f64 / (1 << 20) as f64)
            } else {
                "-".into()
            }
        };
        let (ps, pm) = match &plain {
            Some(p) => (format!("{:.3}", p.seconds), mib(p)),
            None => ("-".into(), "-".into()),
        };
        println!(
            "{n:>6}  {:>8.3}  {:>10}  {ps:>8}  {pm:>10}",
            tiled.seconds,
            mib(&tiled)
        );
    }
    Ok(())
}

fn measure(device: &Device, n: usize, args: &AttentionArgs, tile: Option<usize>) -> Measured {
    let shape = [1, args.heads, n, args.head_dim];
    let input = || Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.0), device);
    let (q, k, v) = (
        input().require_grad(),
        input().require_grad(),
        input().require_grad(),
    );
    let weights = input();
    let scale = 1.0 / (args.head_dim as f64).sqrt();
    let base = GLOBAL.reset_peak();
    let start = Instant::now();
    let out = match tile {
        Some(t) => mvmp_kernels::attention(q.clone(), k.clone(), v.clone(), scale, t),
        None => mvmp_kernels::plain_attention(q.clone(), k.clone(), v.clone(), scale),
    };
    let grads = (out * weights).sum().backward();
    // Reading the gradients back waits for a backend that computes asynchronously.
    let total: f32 = [&q, &k, &v]
        .iter()
        .map(|t| {
            t.grad(&grads)
                .map_or(0.0, |g| g.abs().sum().into_scalar::<f32>())
        })
        .sum();
    let seconds = start.elapsed().as_secs_f64();
    std::hint::black_box(total);
    Measured {
        seconds,
        peak: GLOBAL.peak().saturating_sub(base),
    }
}
