//! The enhancer stage (`RUN/stage3-enhancer`): the enhancer trained on the data stage's
//! triplets ([`extranerf_diffusion::enhancer`]).

use std::time::Instant;

use extranerf_diffusion::device::Backend;
use extranerf_diffusion::enhancer;
use extranerf_diffusion::enhancer::EnhancerSpec;
use extranerf_gpu::Context;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::error::{create_dir, ExtrapolateError, Result};
use crate::manifest::{OnResume, Recorded, StageSpec};

use crate::stage::{RunDir, Stage, DATA_STAGE, ENHANCER_STAGE};
use crate::stage3::gate::CHECK_FILE;
use crate::stage3::spec::Stage3Spec;
use crate::stage3::triplets::Triplets;
use extranerf_nerf::train::{Progress, Reporter, Unit};

/// The enhancer, trained on the data stage's triplets.
#[derive(Clone, Debug)]
pub struct EnhancerStage {
    pub spec: Stage3Spec,
}

/// The enhancer's settings, as its manifest record holds them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnhancerStageSpec {
    pub enhancer: EnhancerSpec,
    /// Where it trains.
    pub backend: Backend,
}

impl StageSpec for EnhancerStageSpec {
    const ON_RESUME: &'static [(&'static str, OnResume)] = &[
        ("enhancer", OnResume::Rerun),
        // Where it trains: the same training on another device.
        ("backend", OnResume::MayChange),
    ];
}

impl Stage for EnhancerStage {
    fn name(&self) -> String {
        ENHANCER_STAGE.into()
    }

    fn config(&self) -> Recorded {
        Recorded::of(&EnhancerStageSpec {
            enhancer: self.spec.enhancer.clone(),
            backend: self.spec.backend,
        })
    }

    fn inputs(&self) -> Vec<String> {
        vec![DATA_STAGE.into()]
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value> {
        let triplets = Triplets::load(&dir.root.join(DATA_STAGE))?;
        let e = &self.spec.enhancer;
        if e.crop > triplets.width.min(triplets.height) {
            return Err(ExtrapolateError::usage(format!(
                "--enhancer-crop {} is larger than the {}x{} training views at the virtual views' scale",
                e.crop, triplets.width, triplets.height
            )));
        }
        let (b, device) = extranerf_diffusion::device::diffusion_device(ctx, self.spec.backend)?;
        rep.note(&format!(
            "{ENHANCER_STAGE}: {} on {} triplets of {} views, on {}",
            match &e.base_model {
                Some(m) => format!("LoRA rank {} on {}", e.rank, m.display()),
                None => format!(
                    "a pixel-space U-Net {:?} from scratch (no pretrained weights)",
                    e.channels
                ),
            },
            triplets.entries.len(),
            triplets.photos.len(),
            b.name()
        ));
        let out = dir.enhancer();
        create_dir(&out)?;
        // A check of an earlier enhancer in this folder no longer holds.
        let check = out.join(CHECK_FILE);
        if check.exists() {
            std::fs::remove_file(&check)
                .map_err(|e| ExtrapolateError::io("removing", &check, e))?;
        }
        let t = Instant::now();
        let rec = enhancer::train_enhancer(&triplets.train_images(), e, &out, &device, &mut |p| {
            let secs = t.elapsed().as_secs_f64();
            rep.progress(&Progress {
                unit: Unit::ModelSteps,
                step: p.step as u32,
                total: p.steps as u32,
                loss: p.loss,
                psnr: 0.0,
                samples_per_s: 0.0,
                secs,
                eta: secs / p.step.max(1) as f64 * p.steps.saturating_sub(p.step) as f64,
            });
        })?;
        Ok(json!({
            "params": rec.params,
            "final_loss": rec.curve.last().map(|c| c.1),
            "train_seconds": rec.seconds,
            "backend": b.name(),
        }))
    }
}
