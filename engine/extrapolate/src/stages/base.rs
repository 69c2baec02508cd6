//! The BaseNeRF stage (`RUN/base`): trained under a time budget, or an existing run reused.

use std::path::PathBuf;

use extranerf_gpu::Context;
use extranerf_nerf::run::{load_checkpoint, RunConfig, SceneSpec};
use extranerf_nerf::trainer::TrainConfig;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::error::{ExtrapolateError, Result};
use crate::manifest::{difference, file_sha256, json_of, OnResume, Recorded, StageSpec};
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

/// The base stage's record: its spec, and whether its BaseNeRF is another run's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BaseRecord {
    /// The reused run's folder (None: trained into `RUN/base`).
    pub from: Option<PathBuf>,
    /// Training seconds for a new BaseNeRF.
    pub budget: f64,
    /// Whether the BaseNeRF is reused (`from` given).
    pub reused: bool,
}

impl BaseRecord {
    /// The record of `spec`.
    pub fn of(spec: &BaseSpec) -> BaseRecord {
        BaseRecord {
            from: spec.from.clone(),
            budget: spec.budget,
            reused: spec.from.is_some(),
        }
    }
}

impl StageSpec for BaseRecord {
    const ON_RESUME: &'static [(&'static str, OnResume)] = &[
        // The reused run is identified by its checkpoint's hash, not its path
        // (`BaseStage`'s `identity`): a copy of it may take its place; another run's
        // checkpoint makes the stages after it run again.
        ("from", OnResume::MayChange),
        // The budget decides the model's size and its steps.
        ("budget", OnResume::Rerun),
        // A run that trained its own BaseNeRF does not switch to another's, nor back.
        ("reused", OnResume::Rerun),
    ];

    /// Records of builds before `reused` hold the spec alone.
    fn from_record(v: &Value) -> std::result::Result<Self, String> {
        let mut spec = v.clone();
        let reused = spec
            .as_object_mut()
            .and_then(|o| o.remove("reused"))
            .and_then(|r| r.as_bool());
        let spec = BaseSpec::deserialize(&spec).map_err(|e| e.to_string())?;
        Ok(BaseRecord {
            reused: reused.unwrap_or(spec.from.is_some()),
            ..BaseRecord::of(&spec)
        })
    }
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
        Recorded::of(&BaseRecord::of(&self.spec))
    }

    /// The SHA-256 of the BaseNeRF's checkpoint (`--base`'s, or `RUN/base`'s once there).
    fn identity(&self, dir: &RunDir) -> Result<Option<String>> {
        let ck = dir.base.join(extranerf_nerf::run::CHECKPOINT_FILE);
        if !ck.is_file() {
            return Ok(None);
        }
        Ok(Some(file_sha256(&ck)?))
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
            // Interrupted: continue to the steps its last checkpoint planned, if it is this
            // run's (a folder's `base` trained on another scene is not).
            let ck = load_checkpoint(&dir.base)?;
            if ck.config.scene != self.scene {
                let (a, b) = (json_of(&ck.config.scene), json_of(&self.scene));
                return Err(ExtrapolateError::resume(
                    &dir.base,
                    format!(
                        "holds a BaseNeRF of another scene or split ({}); remove it or choose another --out",
                        difference(&a, &b, "scene").unwrap_or_else(|| "the scene differs".into())
                    ),
                ));
            }
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
