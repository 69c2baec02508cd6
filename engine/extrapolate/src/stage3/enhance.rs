//! Stage 3 of one stage-2 variant (`RUN/stage3-NAME`): rounds of rendering the virtual
//! views, enhancing them, and training on them mixed with the captured views.

use std::path::Path;
use std::time::Instant;

use extranerf_diffusion::enhancer;
use extranerf_gpu::Context;
use extranerf_nerf::data::{Camera, Image};
use extranerf_nerf::image_ops::detail_energy;
use extranerf_nerf::run::{load_checkpoint, training_views_in, write_png, RunConfig};
use extranerf_nerf::train::Reporter;
use extranerf_nerf::views::{View, ViewKind};
use serde_json::{json, Value};

use crate::base::BaseField;
use crate::error::{create_dir, ExtrapolateError, Result};
use crate::inpaint::InpainterKind;
use crate::manifest::Recorded;
use crate::rounds::{write_test_renders, Rounds, ROUND_FILE};
use crate::stage::{make_virtual, render, RunDir, Stage, VirtualSpec, ENHANCER_STAGE};
use crate::stage3::gate::{check_enhancer, EnhancerCheck};
use crate::stage3::spec::EnhanceSpec;
use crate::stage3::spec::{virtual_weights, Stage3Enhancer, Stage3Gate, Stage3Spec};
use crate::visibility::{virtual_masks, VisSettings};

/// Stage 3 of one stage-2 variant.
#[derive(Clone, Debug)]
pub struct EnhanceStage {
    /// The stage-2 variant it continues.
    pub kind: InpainterKind,
    pub spec: Stage3Spec,
    pub virt: VirtualSpec,
    pub vis: VisSettings,
}

impl EnhanceStage {
    fn stage2_name(&self) -> String {
        format!("stage2-{}", self.kind.name())
    }
}

impl Stage for EnhanceStage {
    fn name(&self) -> String {
        format!("stage3-{}", self.kind.name())
    }

    fn config(&self) -> Recorded {
        Recorded::of(&EnhanceSpec::of(&self.spec))
    }

    fn inputs(&self) -> Vec<String> {
        match self.spec.enhance {
            Stage3Enhancer::Diffusion => vec![
                "base".into(),
                "visibility".into(),
                self.stage2_name(),
                ENHANCER_STAGE.into(),
            ],
            Stage3Enhancer::Unsharp => {
                vec!["base".into(), "visibility".into(), self.stage2_name()]
            }
        }
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value> {
        self.spec.validate()?;
        let out = dir.root.join(self.name());
        create_dir(&out)?;
        // The diffusion enhancer and where it runs; None: the unsharp mask.
        let model = match self.spec.enhance {
            Stage3Enhancer::Diffusion => {
                let (b, device) =
                    extranerf_diffusion::device::diffusion_device(ctx, self.spec.backend)?;
                let pipe = enhancer::load(&dir.enhancer(), &device)?;
                Some((b, device, pipe))
            }
            Stage3Enhancer::Unsharp => None,
        };
        let check = match self.gate(dir, &model, &out, rep)? {
            Gate::Skipped(report) => return Ok(report),
            Gate::Passed(check) => check,
        };
        let base = BaseField::load(ctx, &dir.base)?;
        let from = load_checkpoint(&dir.root.join(self.stage2_name()))?;
        let cfg: RunConfig = from.config.clone();
        let samples = cfg.train.samples;
        let virt = make_virtual(&self.virt, &base.train_cameras())?;
        let masks = virtual_masks(&dir.visibility(), &virt, &self.vis)?;
        let (captured, _) =
            training_views_in(ctx, &cfg.scene, &base.loaded, &cfg.model, &dir.base)?;
        let mut tcfg = cfg.train.clone();
        let total = self.spec.rounds * self.spec.steps_per_round;
        tcfg.steps = from.step + total;
        tcfg.decay_steps = tcfg.steps;
        tcfg.lr_start = self.spec.lr;
        tcfg.lr_end = self.spec.lr;
        tcfg.virtual_l1_core = self.spec.l1_core;
        let mut r = Rounds::open(
            ctx,
            &out,
            &self.name(),
            &cfg,
            tcfg,
            &from,
            from.step,
            self.spec.steps_per_round,
            rep,
        )?;
        rep.note(&format!(
            "{}: {}, loss weight {:.3}",
            self.name(),
            match &model {
                Some((b, _, _)) => format!(
                    "enhancer on {}, from t = {} in {} DDIM steps",
                    b.name(),
                    self.spec.t,
                    self.spec.ddim_steps
                ),
                None => format!(
                    "unsharp mask, amount {} radius {}",
                    self.spec.unsharp_amount, self.spec.unsharp_radius
                ),
            },
            self.spec.weight()
        ));
        let enhancer = model.as_ref().map(|(_, device, pipe)| (pipe, device));
        let mut rounds = Vec::new();
        for round in r.start..self.spec.rounds {
            let t0 = Instant::now();
            let mut views = captured.clone();
            let figures = self.enhance_round(
                ctx,
                &r,
                enhancer,
                (&virt, &masks),
                samples,
                (round, &out),
                &mut views,
            )?;
            let (last, train_s) = r.train(
                ctx,
                &views,
                self.spec.virtual_fraction,
                self.spec.steps_per_round,
                &format!("{} round {round}", self.name()),
                (round, t0),
                rep,
            )?;
            let f = &figures;
            rep.note(&format!(
                "{} round {}/{}: render {:.1} s, enhance {:.1} s, train {train_s:.1} s; enhancement changed the renders by {:.4} (mean absolute), detail energy x{:.2}",
                self.name(),
                round + 1,
                self.spec.rounds,
                f.render_s,
                f.enhance_s,
                f.mean_change,
                f.detail_ratio,
            ));
            let mut row = json!({
                "round": round,
                "render_seconds": f.render_s,
                "enhance_seconds": f.enhance_s,
                "mean_abs_change": f.mean_change,
                "detail_ratio": f.detail_ratio,
            });
            row["train_seconds"] = json!(train_s);
            row["batch_psnr"] = json!(last.map(|s| s.psnr()));
            rounds.push(row);
        }
        write_test_renders(ctx, r.trainer.nerf(), &base.loaded, samples, &out)?;
        Ok(json!({"rounds": rounds, "seconds": r.seconds, "check": check}))
    }
}

/// The enhancer as stage 3 runs it: its backend's name, the device and the model.
type Model = (
    extranerf_diffusion::device::Backend,
    burn::tensor::Device,
    extranerf_diffusion::pipeline::Pipeline,
);

/// What a round's enhancement measured: its render and enhancement seconds, the mean absolute
/// change the enhancement made, and the detail energy of the targets over the renders'.
struct RoundFigures {
    render_s: f64,
    enhance_s: f64,
    mean_change: f64,
    detail_ratio: f64,
}

/// What the gate decided.
enum Gate {
    /// Stage 3 runs (with the check it passed, when one was made).
    Passed(Option<EnhancerCheck>),
    /// Stage 3 kept the stage-2 field: the stage's report.
    Skipped(Value),
}

impl EnhanceStage {
    /// The gate ([`Stage3Gate::Check`]) of a diffusion enhancer: a stage with rounds done passed
    /// it when it started (a skipped one writes none) and resumes without judging again; an
    /// enhancer that does not help is skipped, keeping the stage-2 field in `out`.
    fn gate(
        &self,
        dir: &RunDir,
        model: &Option<Model>,
        out: &Path,
        rep: &mut dyn Reporter,
    ) -> Result<Gate> {
        let resuming = out.join(ROUND_FILE).exists();
        let check = match (model, self.spec.gate) {
            (Some(_), Stage3Gate::Check) if resuming => {
                rep.note(&format!(
                    "{}: resuming, the enhancer check passed when it started",
                    self.name()
                ));
                None
            }
            (Some((_, device, pipe)), Stage3Gate::Check) => {
                let c = check_enhancer(dir, &self.spec, pipe, device, rep)?;
                rep.note(&format!(
                    "{}: enhancer check, {}",
                    self.name(),
                    c.describe()
                ));
                Some(c)
            }
            _ => None,
        };
        if let Some(c) = check.as_ref().filter(|c| !c.helps()) {
            let why = format!(
                "skipped: the enhancer made the renders of its own training views worse ({}); \
                 the field is {}'s (--stage3-gate off runs stage 3 anyway)",
                c.describe(),
                self.stage2_name()
            );
            rep.note(&format!("{}: {why}", self.name()));
            keep_stage2(&dir.root.join(self.stage2_name()), out)?;
            return Ok(Gate::Skipped(
                json!({"rounds": [], "seconds": 0.0, "check": c, "skipped": why}),
            ));
        }
        Ok(Gate::Passed(check))
    }

    /// Round `round`'s targets: each virtual view rendered from the field, enhanced into its
    /// target (written into `out/round_NN`) and pushed onto `views`.
    #[allow(clippy::too_many_arguments)] // each is a distinct input of the round
    fn enhance_round(
        &self,
        ctx: &Context,
        r: &Rounds,
        model: Option<(
            &extranerf_diffusion::pipeline::Pipeline,
            &burn::tensor::Device,
        )>,
        (virt, masks): (&[Camera], &[Vec<f32>]),
        samples: u32,
        (round, out): (u32, &Path),
        views: &mut Vec<View>,
    ) -> Result<RoundFigures> {
        let round_dir = out.join(format!("round_{round:02}"));
        create_dir(&round_dir)?;
        let weight = self.spec.weight();
        let (mut render_s, mut enhance_s, mut change) = (0.0, 0.0, 0.0);
        // Detail energy of the renders and of the targets made from them.
        let (mut detail_render, mut detail_target) = (0.0, 0.0);
        for (k, cam) in virt.iter().enumerate() {
            let tr = Instant::now();
            let (rgb, depth, _) = render(ctx, r.trainer.nerf(), cam, samples)?;
            render_s += tr.elapsed().as_secs_f64();
            let te = Instant::now();
            let (w, h) = (cam.width as usize, cam.height as usize);
            let seed = self.spec.seed ^ 0xe7_4a9c_e000 ^ ((round as u64) << 32) ^ k as u64;
            let target = self
                .spec
                .target(model, &rgb, &masks[k], w, h, seed)
                .map_err(|e| e.in_view(format!("enhancing virtual view {k}, round {round}")))?;
            // The anchoring and smoothing are counted too (a blur or two: milliseconds).
            enhance_s += te.elapsed().as_secs_f64();
            detail_render += detail_energy(&rgb, w, h);
            detail_target += detail_energy(&target, w, h);
            change += rgb
                .iter()
                .zip(&target)
                .map(|(a, b)| (a - b).abs() as f64)
                .sum::<f64>()
                / rgb.len() as f64;
            write_png(
                &round_dir.join(format!("virtual_{k:03}_render.png")),
                cam.width,
                cam.height,
                &rgb,
            )?;
            write_png(
                &round_dir.join(format!("virtual_{k:03}.png")),
                cam.width,
                cam.height,
                &target,
            )?;
            // The enhanced colours with w(t) (times --stage3-visible-weight where seen); the
            // depth loss on the field's own (stage-2 completed) depth keeps the geometry while
            // the colours change.
            views.push(View {
                camera: cam.clone(),
                image: Image::opaque(cam.width, cam.height, target),
                depth: Some(depth.iter().map(|&d| [d, 1.0]).collect()),
                weight: Some(virtual_weights(&masks[k], weight, self.spec.visible_weight)),
                kind: ViewKind::Virtual,
            });
        }
        Ok(RoundFigures {
            render_s,
            enhance_s,
            mean_change: change / virt.len().max(1) as f64,
            detail_ratio: detail_target / detail_render.max(1e-12),
        })
    }
}

/// A skipped stage 3: the stage-2 field and its renders of the views `eval` scores, copied from `from` to `out`
/// (what the fly-through and `eval` read).
fn keep_stage2(from: &Path, out: &Path) -> Result<()> {
    let entries = std::fs::read_dir(from).map_err(|e| ExtrapolateError::io("reading", from, e))?;
    for e in entries {
        let e = e.map_err(|e| ExtrapolateError::io("reading", from, e))?;
        let name = e.file_name().to_string_lossy().into_owned();
        let test =
            (name.starts_with("test_") || name.starts_with("train_")) && name.ends_with(".png");
        if test
            || name == extranerf_nerf::run::CHECKPOINT_FILE
            || name == extranerf_nerf::run::CONFIG_FILE
        {
            let to = out.join(&name);
            extranerf_gpu::files::copy_atomic(&e.path(), &to)
                .map_err(|e| ExtrapolateError::io("copying to", &to, e))?;
        }
    }
    Ok(())
}
