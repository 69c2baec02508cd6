//! The enhancer stage (`RUN/stage3-enhancer`): the enhancer trained on the data stage's
//! triplets ([`extranerf_diffusion::enhancer`]).

use std::time::Instant;

use anyhow::{bail, Context as _};
use extranerf_diffusion::enhancer;
use extranerf_gpu::Context;
use serde_json::{json, Value};

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

impl Stage for EnhancerStage {
    fn name(&self) -> String {
        ENHANCER_STAGE.into()
    }

    fn config(&self) -> Value {
        json!({"enhancer": self.spec.enhancer, "backend": self.spec.backend})
    }

    fn inputs(&self) -> Vec<String> {
        vec![DATA_STAGE.into()]
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> anyhow::Result<Value> {
        let triplets = Triplets::load(&dir.root.join(DATA_STAGE))?;
        let e = &self.spec.enhancer;
        if e.crop > triplets.width.min(triplets.height) {
            bail!(
                "--enhancer-crop {} is larger than the {}x{} training views at the virtual views' scale",
                e.crop,
                triplets.width,
                triplets.height
            );
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
        std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
        // A check of an earlier enhancer in this folder no longer holds.
        let check = out.join(CHECK_FILE);
        if check.exists() {
            std::fs::remove_file(&check)
                .with_context(|| format!("removing {}", check.display()))?;
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
