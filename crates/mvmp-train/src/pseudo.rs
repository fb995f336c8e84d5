//! SMPL-X pseudo-ground-truth fits as training targets for the people of joint-annotated datasets.
use mvmp_data::DataError;
use mvmp_data::dataset::MeshSource;
use mvmp_data::loader::FrameSample;
use mvmp_eval::drivers::PseudoGt;

/// The fits of [`PseudoGt`] as SMPL-X ground truth: a person with a matched fit takes the fit's pose,
/// shape and expression, and the fit's pelvis as `T_wld`, so that the mesh the batcher poses is the fit's
/// mesh. The dataset's joints stay the joint targets.
pub struct PseudoGtMeshes(pub PseudoGt);

fn first10(v: &[f64]) -> [f32; 10] {
    let mut out = [0f32; 10];
    for (o, &x) in out.iter_mut().zip(v) {
        *o = x as f32;
    }
    out
}

impl MeshSource for PseudoGtMeshes {
    fn attach(&self, sample: &mut FrameSample) -> Result<(), DataError> {
        let roots: Vec<[f64; 3]> = sample
            .people
            .iter()
            .map(|p| p.pelvis.map(f64::from))
            .collect();
        let path = self.0.dir.join(&sample.scene).join(&sample.frame);
        let fits = self
            .0
            .fits(&sample.scene, &sample.frame, &roots)
            .map_err(|e| match e {
                mvmp_infer::InferError::File { path, what } => DataError::file(path, what),
                e => DataError::file(path.join("people.npz"), e.to_string()),
            })?;
        for (person, fit) in sample.people.iter_mut().zip(fits) {
            let Some(fit) = fit else { continue };
            person.pose = fit.params.full_pose().iter().map(|&x| x as f32).collect();
            person.betas = first10(&fit.params.betas);
            person.expression = first10(&fit.params.expression);
            person.pelvis = fit.posed.joints[0].map(|x| x as f32);
            person.smplx = true;
        }
        Ok(())
    }
}
