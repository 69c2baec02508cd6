//! Stage 3's settings, and the target it makes of a virtual view's render.

use std::path::PathBuf;

use extranerf_diffusion::device::Backend;
use extranerf_diffusion::enhancer::EnhancerSpec;
use extranerf_diffusion::inpaint::SampleSettings;
use extranerf_nerf::image_ops::unsharp;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::error::{ExtrapolateError, Result};
use crate::manifest::{OnResume, StageSpec};

/// Stage 3's settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Stage3Spec {
    /// Rounds of the inpainting-supervised field that makes training data (each: render the
    /// training views, inpaint their masks, train, render them again as triplets).
    pub data_rounds: u32,
    /// Training steps per data round.
    pub data_steps_per_round: u32,
    /// Step counts of a fresh field at which the training views are rendered as triplets
    /// (the blur of an under-fitted field); empty: none.
    pub base_checkpoints: Vec<u32>,
    /// The enhancer's training.
    pub enhancer: EnhancerSpec,
    /// Rounds over the virtual views (each: render, enhance, train).
    pub rounds: u32,
    /// Training steps per round (the paper: 500 iterations in all).
    pub steps_per_round: u32,
    /// Noise strength t the renders are enhanced from (a fraction of the schedule's timesteps,
    /// as stage 2's t); the loss weight is w(t) = sqrt(1 - t^2), as in stage 2.
    pub t: f32,
    /// DDIM steps per enhancement.
    pub ddim_steps: usize,
    /// Colour anchoring (0: off): the enhanced view keeps only its detail above a box blur of
    /// this radius (applied twice), on the render's own blur; see
    /// [`crate::inpaint::low_plus_detail`].
    pub anchor_radius: usize,
    /// Smoothing of the enhancement (0: off): the enhanced view keeps only its change to the
    /// render below a box blur of this radius (applied twice), on the render's own detail, i.e.
    /// `render + blur(enhanced - render)`; applied after the colour anchoring. An enhancer that
    /// adds pixel-level noise of its own (a different one in every view) gives the field targets
    /// that disagree between views, which it averages into blur.
    pub smooth_radius: usize,
    /// Weight of a virtual view's seen pixels relative to its not-visible ones (1: the whole
    /// enhanced view, as the paper; 0: only where no input camera saw).
    pub visible_weight: f32,
    /// Core of the virtual views' colour loss (0: the paper's plain L1; above 0: smooth L1,
    /// quadratic for per-channel errors below the core; see
    /// [`extranerf_nerf::trainer::TrainConfig::virtual_l1_core`]). Plain L1 pulls every seen
    /// pixel whose target is within noise of the render with a gradient as large as a real
    /// error's.
    pub l1_core: f32,
    /// Fraction of each batch's rays drawn from the virtual views.
    pub virtual_fraction: f32,
    /// Learning rate (constant) of the stage's steps.
    pub lr: f32,
    /// Seed of the enhancement noise.
    pub seed: u64,
    /// Where the enhancer runs.
    pub backend: Backend,
    /// What enhances the virtual views ([`Stage3Enhancer`]).
    #[serde(default)]
    pub enhance: Stage3Enhancer,
    /// [`Stage3Enhancer::Unsharp`]: how much of the render's detail above the blur is added.
    #[serde(default = "default_unsharp_amount")]
    pub unsharp_amount: f32,
    /// [`Stage3Enhancer::Unsharp`]: the box-blur radius (applied twice: a tent).
    #[serde(default = "default_unsharp_radius")]
    pub unsharp_radius: usize,
    /// Whether the enhancer is checked before stage 3 trusts it ([`Stage3Gate`]).
    #[serde(default)]
    pub gate: Stage3Gate,
    /// The folder of the LPIPS weights the gate scores with (None: [`extranerf_nerf::train::default_lpips_dir`]);
    /// where none load, it scores with PSNR.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips: Option<PathBuf>,
}

fn default_unsharp_amount() -> f32 {
    0.5
}

fn default_unsharp_radius() -> usize {
    1
}

/// What stage 3 enhances the virtual views with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Stage3Enhancer {
    /// The diffusion enhancer trained on the scene's corrupted renders (the paper): stages
    /// `stage3-data` and `stage3-enhancer` make it.
    #[default]
    Diffusion,
    /// An unsharp mask of the render, `render + amount * (render - blur(render))` ([`unsharp`]):
    /// no model, no training data, no noise; it sharpens what is there and invents nothing.
    Unsharp,
}

/// Whether stage 3 first checks that its enhancer helps.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Stage3Gate {
    /// Enhance one corrupted render per training view (its triplets, the sources taken in
    /// turn) as stage 3 would, and run stage 3 only when that brings them closer to their
    /// photos (mean LPIPS lowered; PSNR raised where no LPIPS weights load). Otherwise the
    /// stage keeps the stage-2 field and says why: an enhancer that cannot improve renders of
    /// the views it was trained on would supervise the virtual views with its own errors.
    #[default]
    Check,
    /// Always run stage 3 (the paper's ablation, whatever the enhancer does).
    Off,
}

impl Default for Stage3Spec {
    fn default() -> Self {
        Stage3Spec {
            data_rounds: 3,
            data_steps_per_round: 100,
            base_checkpoints: vec![100, 400],
            enhancer: EnhancerSpec::default(),
            rounds: 2,
            steps_per_round: 250,
            t: 0.3,
            ddim_steps: 10,
            anchor_radius: 0,
            smooth_radius: 0,
            visible_weight: 1.0,
            l1_core: 0.0,
            virtual_fraction: 0.3,
            lr: 3e-3,
            seed: 0,
            backend: Backend::Auto,
            enhance: Stage3Enhancer::Diffusion,
            unsharp_amount: default_unsharp_amount(),
            unsharp_radius: default_unsharp_radius(),
            gate: Stage3Gate::Check,
            lpips: None,
        }
    }
}

/// What a stage-3 variant enhances its virtual views with, and its settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Enhancement {
    /// [`Stage3Enhancer::Diffusion`], checked by the gate or not.
    Diffusion { gate: Stage3Gate },
    /// [`Stage3Enhancer::Unsharp`].
    Unsharp { amount: f32, radius: usize },
}

/// The settings of stage 3 for one variant, as its manifest record holds them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnhanceSpec {
    pub rounds: u32,
    pub steps_per_round: u32,
    pub t: f32,
    pub ddim_steps: usize,
    pub virtual_fraction: f32,
    pub lr: f32,
    pub seed: u64,
    pub anchor_radius: usize,
    pub smooth_radius: usize,
    pub visible_weight: f32,
    pub l1_core: f32,
    pub enhance: Enhancement,
}

impl EnhanceSpec {
    /// The settings of `s` that stage 3's loop uses.
    pub fn of(s: &Stage3Spec) -> EnhanceSpec {
        EnhanceSpec {
            rounds: s.rounds,
            steps_per_round: s.steps_per_round,
            t: s.t,
            ddim_steps: s.ddim_steps,
            virtual_fraction: s.virtual_fraction,
            lr: s.lr,
            seed: s.seed,
            anchor_radius: s.anchor_radius,
            smooth_radius: s.smooth_radius,
            visible_weight: s.visible_weight,
            l1_core: s.l1_core,
            enhance: match s.enhance {
                Stage3Enhancer::Diffusion => Enhancement::Diffusion { gate: s.gate },
                Stage3Enhancer::Unsharp => Enhancement::Unsharp {
                    amount: s.unsharp_amount,
                    radius: s.unsharp_radius,
                },
            },
        }
    }
}

impl StageSpec for EnhanceSpec {
    const ON_RESUME: &'static [(&'static str, OnResume)] = &[
        ("rounds", OnResume::Rerun),
        ("steps_per_round", OnResume::Rerun),
        ("t", OnResume::Rerun),
        ("ddim_steps", OnResume::Rerun),
        ("virtual_fraction", OnResume::Rerun),
        ("lr", OnResume::Rerun),
        ("seed", OnResume::Rerun),
        ("anchor_radius", OnResume::Rerun),
        ("smooth_radius", OnResume::Rerun),
        ("visible_weight", OnResume::Rerun),
        ("l1_core", OnResume::Rerun),
        ("enhance", OnResume::Rerun),
    ];

    /// Also reads the flat layout of builds up to fc82428 (`EnhanceSpecV1`).
    fn from_record(v: &Value) -> std::result::Result<Self, String> {
        if v.get("enhance").is_some_and(Value::is_object) {
            return Self::deserialize(v).map_err(|e| e.to_string());
        }
        let o = EnhanceSpecV1::deserialize(v).map_err(|e| e.to_string())?;
        let enhance = match o.enhance.unwrap_or(Stage3Enhancer::Diffusion) {
            // Runs made before the gate existed ran stage 3 always.
            Stage3Enhancer::Diffusion => Enhancement::Diffusion {
                gate: o.gate.unwrap_or(Stage3Gate::Off),
            },
            Stage3Enhancer::Unsharp => Enhancement::Unsharp {
                amount: o
                    .unsharp_amount
                    .ok_or("the unsharp enhancer without its amount")?,
                radius: o
                    .unsharp_radius
                    .ok_or("the unsharp enhancer without its radius")?,
            },
        };
        Ok(EnhanceSpec {
            rounds: o.rounds,
            steps_per_round: o.steps_per_round,
            t: o.t,
            ddim_steps: o.ddim_steps,
            virtual_fraction: o.virtual_fraction,
            lr: o.lr,
            seed: o.seed,
            anchor_radius: o.anchor_radius,
            smooth_radius: o.smooth_radius,
            visible_weight: o.visible_weight,
            l1_core: o.l1_core,
            enhance,
        })
    }
}

/// The record of [`EnhanceSpec`] up to fc82428: flat, with each setting that came later
/// recorded only when it was not its default (so that the runs before it still resumed), and
/// the gate only when checked.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct EnhanceSpecV1 {
    rounds: u32,
    steps_per_round: u32,
    t: f32,
    ddim_steps: usize,
    virtual_fraction: f32,
    lr: f32,
    seed: u64,
    #[serde(default)]
    anchor_radius: usize,
    #[serde(default = "one")]
    visible_weight: f32,
    #[serde(default)]
    smooth_radius: usize,
    #[serde(default)]
    l1_core: f32,
    gate: Option<Stage3Gate>,
    enhance: Option<Stage3Enhancer>,
    unsharp_amount: Option<f32>,
    unsharp_radius: Option<usize>,
}

fn one() -> f32 {
    1.0
}

impl Stage3Spec {
    /// Checks the settings.
    pub fn validate(&self) -> Result<()> {
        if self.rounds == 0 || self.steps_per_round == 0 {
            return Err(ExtrapolateError::usage(
                "stage 3 needs at least one round of at least one step",
            ));
        }
        if self.data_rounds == 0 || self.data_steps_per_round == 0 {
            return Err(ExtrapolateError::usage(
                "stage 3's data collection needs at least one round of at least one step",
            ));
        }
        if !(self.t > 0.0 && self.t < 1.0) {
            return Err(ExtrapolateError::usage(format!(
                "--stage3-t {}: use a noise level in (0, 1)",
                self.t
            )));
        }
        if self.ddim_steps == 0 {
            return Err(ExtrapolateError::usage(
                "--stage3-ddim-steps must be at least 1",
            ));
        }
        if !(0.0..=1.0).contains(&self.virtual_fraction) {
            return Err(ExtrapolateError::usage(format!(
                "--stage3-virtual-fraction {}: use a value in [0, 1]",
                self.virtual_fraction
            )));
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return Err(ExtrapolateError::usage(format!(
                "--stage3-lr {}: use a positive learning rate",
                self.lr
            )));
        }
        for (flag, r) in [
            ("--stage3-anchor", self.anchor_radius),
            ("--stage3-smooth", self.smooth_radius),
        ] {
            if r > MAX_RADIUS {
                return Err(ExtrapolateError::usage(format!(
                    "{flag} {r}: use a radius of at most {MAX_RADIUS} pixels (0: off)"
                )));
            }
        }
        if !(self.l1_core.is_finite() && (0.0..=1.0).contains(&self.l1_core)) {
            return Err(ExtrapolateError::usage(format!(
                "--stage3-l1-core {}: use a colour error in [0, 1] (0: plain L1)",
                self.l1_core
            )));
        }
        if !(0.0..=1.0).contains(&self.visible_weight) {
            return Err(ExtrapolateError::usage(format!(
                "--stage3-visible-weight {}: use a value in [0, 1]",
                self.visible_weight
            )));
        }
        if self.enhance == Stage3Enhancer::Unsharp
            && !(self.unsharp_amount.is_finite()
                && self.unsharp_amount > 0.0
                && self.unsharp_amount <= 4.0
                && (1..=MAX_RADIUS).contains(&self.unsharp_radius))
        {
            return Err(ExtrapolateError::usage(format!("--stage3-unsharp-amount {} and --stage3-unsharp-radius {}: use an amount in (0, 4] and a radius of 1 to {MAX_RADIUS} pixels",
                self.unsharp_amount,
                self.unsharp_radius)));
        }
        let e = &self.enhancer;
        if e.steps == 0 || e.batch == 0 || e.crop == 0 || !(e.lr.is_finite() && e.lr > 0.0) {
            return Err(ExtrapolateError::usage(format!("the enhancer needs steps ({}), batch ({}) and crop ({}) of at least 1 and a positive learning rate ({})",
                e.steps,
                e.batch,
                e.crop,
                e.lr)));
        }
        Ok(())
    }

    /// The loss weight w(t) = sqrt(1 - t^2).
    pub fn weight(&self) -> f32 {
        (1.0 - self.t * self.t).max(0.0).sqrt()
    }

    /// Stage 3's target for an `[h, w, 3]` render with its not-visible `mask`: the render
    /// enhanced (by the diffusion `model` from t in the DDIM steps, seeded with `seed`; None:
    /// the unsharp mask), then anchored and smoothed ([`stage3_target`]). The loop and the
    /// gate's check both make their targets here.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn target(
        &self,
        model: Option<(
            &extranerf_diffusion::pipeline::Pipeline,
            &burn::tensor::Device,
        )>,
        render: &[f32],
        mask: &[f32],
        w: usize,
        h: usize,
        seed: u64,
    ) -> Result<Vec<f32>> {
        let enhanced = match model {
            Some((pipe, device)) => {
                pipe.model
                    .enhance_image(
                        render,
                        Some(mask),
                        w,
                        h,
                        seed,
                        &SampleSettings {
                            strength: f64::from(self.t),
                            steps: self.ddim_steps,
                            guidance: 1.0,
                            keep_known: false,
                        },
                        device,
                    )?
                    .rgb
            }
            None => unsharp(render, w, h, self.unsharp_amount, self.unsharp_radius),
        };
        Ok(stage3_target(
            render,
            &enhanced,
            w,
            h,
            self.anchor_radius,
            self.smooth_radius,
        ))
    }
}

/// The largest `--stage3-anchor` and `--stage3-smooth` radius (a blur wider than this is
/// most of a virtual view).
pub const MAX_RADIUS: usize = 64;

/// Stage 3's colour target of a virtual view from its `render` and the enhancer's output
/// (`[h, w, 3]` each): the enhanced view, colour-anchored when `anchor` > 0 (the render's blur
/// plus the enhanced view's detail above it), then smoothed when `smooth` > 0 (the render's
/// detail plus the blur of what the enhancement changed); see
/// [`crate::inpaint::low_plus_detail`].
pub fn stage3_target(
    render: &[f32],
    enhanced: &[f32],
    w: usize,
    h: usize,
    anchor: usize,
    smooth: usize,
) -> Vec<f32> {
    let mut t = enhanced.to_vec();
    if anchor > 0 {
        t = crate::inpaint::low_plus_detail(render, &t, w, h, anchor);
    }
    if smooth > 0 {
        t = crate::inpaint::low_plus_detail(&t, render, w, h, smooth);
    }
    t
}

/// A virtual view's per-pixel loss weights in stage 3: `weight` (w(t)) where `mask` is a hole
/// (not visible), `weight * visible` elsewhere.
pub fn virtual_weights(mask: &[f32], weight: f32, visible: f32) -> Vec<f32> {
    (0..mask.len())
        .map(|i| {
            if crate::inpaint::is_hole(mask, i) {
                weight
            } else {
                weight * visible
            }
        })
        .collect()
}
