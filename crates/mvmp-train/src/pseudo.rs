//! SMPL-X pseudo-ground-truth fits as training targets for the people of joint-annotated datasets.
use std::path::PathBuf;

use mvmp_data::DataError;
use mvmp_data::loader::FrameSample;
use mvmp_data::sources::MeshSource;
use mvmp_smplx::{SmplxLayer, SmplxParams};

/// Fits in infer's layout (`DIR/<sequence>/<frame>/people.npz`, standard smplx keys). Each annotated person
/// takes the nearest fit whose pelvis is within `gate` metres of the person's root; that person then has
/// SMPL-X ground truth: the fit's pose, shape and expression, and the fit's pelvis as `T_wld`, so that the
/// mesh the batcher poses is the fit's mesh. The dataset's joints stay the joint targets.
pub struct PseudoGtMeshes {
    dir: PathBuf,
    layer: SmplxLayer,
    gate: f64,
}

impl PseudoGtMeshes {
    /// `layer` poses the fits (the body model they were fitted with).
    pub fn new(dir: PathBuf, layer: SmplxLayer, gate: f64) -> Self {
        PseudoGtMeshes { dir, layer, gate }
    }
}

fn first10(v: &[f64]) -> [f32; 10] {
    let mut out = [0f32; 10];
    for (o, &x) in out.iter_mut().zip(v) {
        *o = x as f32;
    }
    out
}

impl MeshSource for PseudoGtMeshes {
    fn attach(&self, sample: &mut FrameSample) -> Result<(), DataError> {
        let path = self
            .dir
            .join(&sample.scene)
            .join(&sample.frame)
            .join("people.npz");
        if !path.is_file() {
            return Err(DataError::file(
                &path,
                "no pseudo-ground-truth for this frame (every training frame of a source with pseudo_gt needs one)",
            ));
        }
        let stored = crate::output::read_people_npz(&path)
            .map_err(|e| DataError::file(&path, e.to_string()))?;
        if stored.is_empty() || sample.people.is_empty() {
            return Ok(());
        }
        let fits: Vec<(SmplxParams, f64)> =
            stored.into_iter().map(|s| (s.params, s.score)).collect();
        let posed = crate::predict::pose_params(&self.layer, &fits);
        let fit_pelvis: Vec<[f64; 3]> = posed.iter().map(|p| p.joints[0]).collect();
        let roots: Vec<[f64; 3]> = sample
            .people
            .iter()
            .map(|p| p.pelvis.map(f64::from))
            .collect();
        for (fi, gi) in mvmp_eval::match_people(&fit_pelvis, &roots, self.gate) {
            let params = &fits[fi].0;
            let person = &mut sample.people[gi];
            person.pose = params.full_pose().iter().map(|&x| x as f32).collect();
            person.betas = first10(&params.betas);
            person.expression = first10(&params.expression);
            person.pelvis = fit_pelvis[fi].map(|x| x as f32);
            person.smplx = true;
        }
        Ok(())
    }
}
