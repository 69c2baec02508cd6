//! The BaseNeRF stage (`RUN/base`): trained under a time budget, or an existing run reused.

use std::path::PathBuf;

use extranerf_gpu::Context;
use extranerf_nerf::run::{load_checkpoint, RunConfig, SceneSpec};
use extranerf_nerf::trainer::TrainConfig;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::error::Result;
use crate::manifest::{OnResume, Recorded, StageSpec};
use crate::stage::{make_virtual, RunDir, Stage, VirtualSpec};
use extranerf_nerf::train::{fit_budget, train_loop, Reporter, TrainRun};

/// Where the BaseNeRF comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BaseSpec {
    /// An existing run folder to reuse (None: train one into `RUN/base`).
    pub from: Option<PathBuf>,
    /// Training seconds for a new BaseNeRF (the `train --budget` fit).
    pub budget: f64,
}

impl StageSpec for BaseSpec {
    const ON_RESUME: &'static [(&'static str, OnResume)] = &[
        // Another BaseNeRF is another run.
        ("from", OnResume::Rerun),
        // The budget decides the model's size and its steps.
        ("budget", OnResume::Rerun),
    ];
}

/// The BaseNeRF.
#[derive(Clone, Debug)]
pub struct BaseStage {
    pub spec: BaseSpec,
    pub scene: SceneSpec,
    /// The virtual views the later stages render: the field's box holds them too.
    pub virt: VirtualSpec,
}

/// The default training configuration for a scene (as `extranerf train` with no flags: the
/// proposal sampler, [`extranerf_nerf::autoconfig::default_sampling`]), its grid box also
/// holding the virtual views of `virt`.
pub fn default_run_config(
    scene: &SceneSpec,
    virt: &VirtualSpec,
    rep: &mut dyn Reporter,
) -> Result<RunConfig> {
    let loaded = scene.load()?;
    let train = loaded.train_cameras();
    let extra = make_virtual(virt, &train)?;
    let choice = extranerf_nerf::autoconfig::auto_model_covering(
        &loaded.scene,
        &loaded.split.train,
        &extra,
        extranerf_nerf::autoconfig::NdcFit::default(),
    );
    for r in &choice.reasons {
        rep.note(&format!("auto-config: {r}"));
    }
    let mut model = choice.model;
    let (sampler, samples) = extranerf_nerf::autoconfig::default_sampling(&model);
    rep.note(&format!(
        "auto-config: {}",
        extranerf_nerf::autoconfig::DEFAULT_SAMPLER_WHY
    ));
    model.sampler = sampler;
    Ok(RunConfig {
        scene: scene.clone(),
        model,
        train: TrainConfig {
            samples,
            ..TrainConfig::default()
        },
    })
}

impl Stage for BaseStage {
    fn name(&self) -> String {
        "base".into()
    }

    fn config(&self) -> Recorded {
        Recorded::of(&self.spec)
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value> {
        if self.spec.from.is_some() {
            let ck = load_checkpoint(&dir.base)?;
            return Ok(json!({"reused": dir.base, "step": ck.step}));
        }
        let run = |cfg: &RunConfig, start, budget, params, moments, rep: &mut dyn Reporter| {
            train_loop(
                ctx,
                cfg,
                &TrainRun {
                    out: dir.base.clone(),
                    start,
                    log_every: 25,
                    checkpoint_every: 500,
                    eval_every: 0,
                    eval_views: extranerf_nerf::train::ViewSet::Test,
                    budget,
                },
                params,
                moments,
                rep,
            )
        };
        if dir.base.join(extranerf_nerf::run::CHECKPOINT_FILE).exists() {
            // Interrupted: continue to the steps its last checkpoint planned.
            let ck = load_checkpoint(&dir.base)?;
            rep.note(&format!("base: resuming at step {}", ck.step));
            if ck.step < ck.config.train.steps {
                run(&ck.config, ck.step, None, Some(ck.params), ck.moments, rep)?;
            }
        } else {
            let mut cfg = default_run_config(&self.scene, &self.virt, rep)?;
            fit_budget(ctx, &mut cfg, self.spec.budget, true, &dir.base, rep)?;
            run(&cfg, 0, Some(self.spec.budget), None, None, rep)?;
        }
        let ck = load_checkpoint(&dir.base)?;
        Ok(json!({"step": ck.step}))
    }
}
