//! `mvmp body ...` and `mvmp bench smplx`.
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS};
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::tensor::{Device, Tensor, TensorData};
use nalgebra::{Matrix3, Vector3};

use mvmp_geom::Camera;
use mvmp_io::write_atomic_with;
use mvmp_render::{Frame, Light, MeshRef, draw};
use mvmp_smplx::export::{write_obj, write_ply};
use mvmp_smplx::{BodyModel, ParamTensors, SmplxLayer, SmplxParams, Translation, standin_model};
use npyz::WriterBuilder;

/// The body model: a file when given, else the stand-in (seed 0) generated in memory.
pub fn load_model(path: Option<&Path>) -> Result<BodyModel> {
    match path {
        Some(p) => Ok(BodyModel::load(p)?),
        None => Ok(standin_model(0)),
    }
}

pub fn make_standin(out: &Path, seed: u64) -> Result<()> {
    let model = standin_model(seed);
    model
        .write_npz(out)
        .with_context(|| format!("writing the stand-in model to {}", out.display()))?;
    println!(
        "wrote {}: stand-in SMPL-X model (seed {seed}), {} vertices, {} faces, {} shape components",
        out.display(),
        model.num_vertices(),
        model.num_faces(),
        model.num_shape_components
    );
    Ok(())
}

/// Per body, a list of 3D points.
type Points = Vec<Vec<[f32; 3]>>;

/// Run the layer on parameters and return vertices `[N][V]` and joints `[N][J]` as f32 triples.
fn pose(model: &BodyModel, bodies: &[SmplxParams], device: &Device) -> Result<(Points, Points)> {
    let layer = SmplxLayer::new(model, device);
    let p = ParamTensors::from_params(bodies, device);
    let out = layer.forward_axis_angle(
        p.pose,
        p.betas,
        p.expression,
        p.transl,
        Translation::Standard,
    );
    let n = bodies.len();
    let split = |t: Tensor<3>| -> Result<Points> {
        let [_, k, _] = t.dims();
        let flat: Vec<f32> = t
            .into_data()
            .try_into_vec()
            .map_err(|e| anyhow::anyhow!("reading tensor: {e:?}"))?;
        if let Some(i) = flat.iter().position(|v| !v.is_finite()) {
            bail!(
                "bodies[{}]: the forward produced a non-finite point {} (its parameters are finite and \
                 within range: a body model with extreme directions?)",
                i / (k * 3),
                (i / 3) % k
            );
        }
        Ok(flat
            .chunks_exact(k * 3)
            .map(|b| b.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
            .collect())
    };
    let v = split(out.vertices)?;
    let j = split(out.joints)?;
    debug_assert_eq!(v.len(), n);
    Ok((v, j))
}

pub fn forward(model: Option<&Path>, params: &Path, out: &Path, device: &Device) -> Result<()> {
    for name in ["output.npz", "output.json"] {
        crate::paths::not_over_input("--out", &out.join(name), params)?;
    }
    let bodies = SmplxParams::read_json(params)?;
    let model = load_model(model)?;
    let (verts, joints) = pose(&model, &bodies, device)?;
    // Every file is written to a staging directory, moved into place once all are written.
    let staged = mvmp_io::StagedDir::new(out)?.owning(|name| {
        name.starts_with("body_") && (name.ends_with(".obj") || name.ends_with(".ply"))
    });
    let dir = staged.path();
    let n = bodies.len();
    let nv = verts[0].len();
    let nj = joints[0].len();
    // output.npz: vertices [N, V, 3], joints [N, J, 3], float32 metres.
    write_atomic_with(&dir.join("output.npz"), |w| {
        let mut npz = npyz::npz::NpzWriter::new(std::io::Cursor::new(Vec::new()));
        for (name, data, k) in [("vertices", &verts, nv), ("joints", &joints, nj)] {
            let mut a = npz
                .array::<f32>(name, Default::default())?
                .default_dtype()
                .shape(&[n as u64, k as u64, 3])
                .begin_nd()?;
            a.extend(data.iter().flatten().flatten().copied())?;
            a.finish()?;
        }
        let bytes = npz.zip_writer().finish()?.into_inner();
        w.write_all(&bytes)
    })?;
    let json = serde_json::json!({ "vertices": verts, "joints": joints, "units": "m" });
    write_atomic_with(&dir.join("output.json"), |w| {
        serde_json::to_writer(w, &json).map_err(std::io::Error::other)
    })?;
    for (i, v) in verts.iter().enumerate() {
        write_obj(&dir.join(format!("body_{i:03}.obj")), v, &model.faces)?;
        write_ply(&dir.join(format!("body_{i:03}.ply")), v, &model.faces)?;
    }
    staged.finish()?;
    let (npz_path, json_path) = (out.join("output.npz"), out.join("output.json"));
    println!(
        "posed {n} bod{} ({nv} vertices, {nj} joints each); wrote {}, {} and body_000..{:03}.obj/.ply in {}",
        if n == 1 { "y" } else { "ies" },
        npz_path.display(),
        json_path.display(),
        n - 1,
        out.display()
    );
    Ok(())
}

use std::io::Write;

pub fn render(
    model: Option<&Path>,
    params: Option<&Path>,
    out: &Path,
    size: u32,
    device: &Device,
) -> Result<()> {
    if !(16..=8192).contains(&size) {
        bail!("--size {size}: expected 16 to 8192 pixels");
    }
    for input in params.into_iter().chain(model) {
        crate::paths::not_over_input("--out", out, input)?;
    }
    let bodies = match params {
        Some(p) => SmplxParams::read_json(p)?,
        None => vec![SmplxParams::default()],
    };
    let model = load_model(model)?;
    let (verts, _) = pose(&model, &bodies, device)?;
    let what = params.map_or("the bodies".into(), |p| p.display().to_string());
    let (verts, extent, front) = centred(&verts, &what)?;
    let cam = preview_camera(size, extent, front)?;
    let mut frame = Frame::new(size, size, [0.93, 0.94, 0.96]);
    let palette = [
        [0.80, 0.55, 0.45],
        [0.45, 0.60, 0.80],
        [0.55, 0.75, 0.50],
        [0.80, 0.70, 0.40],
    ];
    let meshes: Vec<MeshRef> = verts
        .iter()
        .enumerate()
        .map(|(i, v)| MeshRef {
            vertices: v,
            faces: &model.faces,
            color: palette[i % palette.len()],
            face_colors: None,
        })
        .collect();
    let light = Light {
        dir: [-0.4, -0.6, -1.0],
        ambient: 0.25,
        color: [1.0; 3],
    };
    draw(&mut frame, &cam, &meshes, &light);
    let img = image::RgbImage::from_raw(size, size, frame.to_rgb8())
        .context("building the image buffer")?;
    write_atomic_with(out, |w| {
        let mut buf = std::io::Cursor::new(Vec::new());
        img.write_to(&mut buf, image::ImageFormat::Png)
            .map_err(std::io::Error::other)?;
        w.write_all(buf.get_ref())
    })?;
    println!("wrote {} ({size} x {size})", out.display());
    Ok(())
}

/// The bodies moved so that their bounds are centred on the origin (bodies far from it render as near
/// it), with the bounds' larger extent across x and y and how far their front (+z) reaches.
type Centred = (Vec<Vec<[f32; 3]>>, f64, f64);
fn centred(verts: &[Vec<[f32; 3]>], what: &str) -> Result<Centred> {
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for v in verts.iter().flatten() {
        for a in 0..3 {
            lo[a] = lo[a].min(v[a]);
            hi[a] = hi[a].max(v[a]);
        }
    }
    let c: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]) as f64);
    let extent = ((hi[0] - lo[0]).max(hi[1] - lo[1]) as f64).max(0.1);
    // One picture frames every body: people kilometres apart would be specks, and a camera that far
    // out is past what the projection takes.
    const MAX_EXTENT: f64 = 1.0e3;
    if extent > MAX_EXTENT || !extent.is_finite() {
        bail!(
            "{what}: the bodies span {extent:.0} m, more than a preview frames ({MAX_EXTENT} m); render people far apart in files of their own"
        );
    }
    let moved = verts
        .iter()
        .map(|v| {
            v.iter()
                .map(|p| std::array::from_fn(|a| (p[a] as f64 - c[a]) as f32))
                .collect()
        })
        .collect();
    Ok((moved, extent, hi[2] as f64 - c[2]))
}

/// A camera on +z (the model faces +z, y up), turned 20 degrees about the vertical for a slight
/// three-quarter view, looking at the origin from where bounds of `extent` fill the picture.
fn preview_camera(size: u32, extent: f64, front: f64) -> Result<Camera> {
    let f = size as f64 * 2.0;
    let dist = f * extent * 1.15 / size as f64 + front;
    let yaw = 20f64.to_radians();
    let eye = Vector3::new(dist * yaw.sin(), 0.1 * dist, dist * yaw.cos());
    let z = (-eye).normalize();
    let x = z.cross(&Vector3::y()).normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let half = size as f64 / 2.0;
    let k = Matrix3::new(f, 0.0, half, 0.0, f, half, 0.0, 0.0, 1.0);
    Ok(Camera::new(
        "preview",
        k,
        r,
        -(r * eye),
        [0.0; 5],
        size,
        size,
    )?)
}

pub fn bench(
    model: Option<&Path>,
    batch: usize,
    iters: usize,
    backward: bool,
    device: &Device,
) -> Result<()> {
    if batch == 0 || iters == 0 {
        bail!("--batch and --iters must be positive (got {batch} and {iters})");
    }
    let model = load_model(model)?;
    if backward {
        return bench_backward(&model, batch, iters, device);
    }
    let layer = SmplxLayer::new(&model, device);
    let (pose, betas, expr, transl) = bench_inputs(batch, device);
    let run = || {
        let out = layer.forward_axis_angle(
            pose.clone(),
            betas.clone(),
            expr.clone(),
            transl.clone(),
            Translation::Standard,
        );
        // Reading a value back waits for the device to finish.
        let _ = out.vertices.sum().into_scalar::<f32>();
    };
    let median = median_ms(iters, run);
    // The line on stdout keeps its documented form; which path ran goes to stderr.
    let path = if layer.is_fused() {
        "the fused CPU pass"
    } else {
        "tensor ops"
    };
    eprintln!("smplx forward on {device:?}: {path}");
    println!("smplx forward batch {batch}: {median:.2} ms");
    Ok(())
}

/// Fixed, random-ish bodies for the benchmarks: small angles on every joint, varied shapes.
fn bench_inputs(batch: usize, device: &Device) -> (Tensor<3>, Tensor<2>, Tensor<2>, Tensor<2>) {
    let pose: Vec<f32> = (0..batch * NUM_JOINTS * 3)
        .map(|i| ((i * 7919 % 1000) as f32 / 1000.0 - 0.5) * 0.6)
        .collect();
    let betas: Vec<f32> = (0..batch * NUM_BETAS)
        .map(|i| (i * 104729 % 1000) as f32 / 500.0 - 1.0)
        .collect();
    (
        Tensor::from_data(TensorData::new(pose, [batch, NUM_JOINTS, 3]), device),
        Tensor::from_data(TensorData::new(betas, [batch, NUM_BETAS]), device),
        Tensor::zeros([batch, NUM_EXPRESSION], device),
        Tensor::zeros([batch, 3], device),
    )
}

/// The median of `iters` timed runs after 3 warm-up runs, in milliseconds.
fn median_ms(iters: usize, mut run: impl FnMut()) -> f64 {
    for _ in 0..3 {
        run();
    }
    let mut times: Vec<f64> = (0..iters)
        .map(|_| {
            let t0 = Instant::now();
            run();
            t0.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

/// Forward and backward as training runs them (autodiff, gradients of every input): the fused
/// operation beside the tensor ops where the layer has it (flex), the tensor ops elsewhere.
fn bench_backward(model: &BodyModel, batch: usize, iters: usize, device: &Device) -> Result<()> {
    let device = device.clone().autodiff();
    let layer = SmplxLayer::new(model, &device);
    let (pose, betas, expr, transl) = bench_inputs(batch, &device);
    let paths: &[(&str, bool)] = if layer.is_fused() {
        &[("fused", true), ("tensor ops", false)]
    } else {
        &[("tensor ops", false)]
    };
    for &(name, fused) in paths {
        let median = median_ms(iters, || {
            let (p, b) = (pose.clone().require_grad(), betas.clone().require_grad());
            let rot = mvmp_geom::rotation::axis_angle_to_matrix(
                p.clone().reshape([batch * NUM_JOINTS, 3]),
            )
            .reshape([batch, NUM_JOINTS, 3, 3]);
            let (e, t) = (expr.clone(), transl.clone());
            let out = if fused {
                layer.forward(rot, b.clone(), e, t, Translation::Standard)
            } else {
                layer.forward_tensor_ops(rot, b.clone(), e, t, Translation::Standard)
            };
            let grads = (out.vertices.sum() + out.joints.sum()).backward();
            // Reading a gradient back waits for the device to finish.
            let _ = p.grad(&grads).map(|g| g.sum().into_scalar::<f32>());
        });
        println!("smplx forward+backward batch {batch}, {name}: {median:.2} ms");
    }
    Ok(())
}
