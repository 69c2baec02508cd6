//! Training of the BaseNeRF field on the device (rendering: [`crate::renderer`]; the views it
//! trains on: [`crate::views`]). A training step is one recording
//! with no host traffic: draw a batch of pixels from the training images, generate rays,
//! sample them, evaluate the field, composite, take the losses, back-propagate, zero-and-fill
//! the flat gradient buffer and update it with Adam; the batch loss and MSE land in a small
//! ring of device slots that the host reads only when it prints progress.

use serde::{Deserialize, Serialize};

use extranerf_gpu::kernels::render::{batch as kb, pixels as kp};
use extranerf_gpu::{Buffer, Context, GpuError, GpuTimer, Kernel, Recorder, Result};
use extranerf_prims::{Prims, ReducePlan};

use crate::field::mlp::{MlpMode, MlpPath};
use crate::field::proposal::{ProposalUse, ProposalWork};
use crate::model::{mark, Profiler, Space};
use crate::optim::{Adam, AdamConfig, AdamMode, SparseTable, TableDecay};
use crate::render::composite::{Background, RayGrads, Samples};
use crate::render::loss::{LossConfig, RayLoss, RgbLoss, Targets};
use crate::render::occupancy::{Occupancy, OccupancyConfig};
use crate::render::proposal::MainBins;
use crate::render::sample::{SkipEmpty, MAX_PROBES};
use crate::render::train_step::{FusedStep, GivenSamples, StepLosses, StepOutputs};
use crate::renderer::{Nerf, SamplesFrom, Workspace};
use crate::views::{DrawnBatch, TrainData};

/// Steps whose loss and MSE the device keeps between progress reads.
pub const STAT_SLOTS: u32 = 64;
/// Floats between stat slots (the reduce output is bound as a slice, 256-byte aligned).
const SLOT: usize = 64;

/// Training hyperparameters (the paper's schedule by default).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// Optimiser steps.
    pub steps: u32,
    /// Rays per batch.
    pub rays: u32,
    /// Samples per ray.
    pub samples: u32,
    /// The photometric loss.
    pub rgb_loss: RgbLossKind,
    /// Huber threshold.
    pub huber_delta: f32,
    /// Depth loss weight (rays with a depth target only).
    pub depth_lambda: f32,
    /// Distortion loss weight (mip-NeRF 360).
    pub distortion_lambda: f32,
    /// Hash decay weight (Zip-NeRF).
    pub hash_decay_lambda: f32,
    /// Scale sample gradients by min(1, t^2), t the sample's depth (Floaters No More);
    /// world-space fields only (refused in NDC, where it would change nothing).
    pub grad_scaling: bool,
    /// Learning rate at the first step.
    pub lr_start: f32,
    /// Learning rate at `decay_steps`.
    pub lr_end: f32,
    /// Steps of the log-linear decay.
    pub decay_steps: u32,
    /// Seed of the initialisation and the batches.
    pub seed: u64,
    /// Background colour added with each ray's final transmittance (renders; training too
    /// unless `random_background`).
    pub background: [f32; 3],
    /// Train with a random background colour per ray ([`Background::Random`]) instead of
    /// `background`, so that a ray cannot fit a dark or light pixel by staying transparent.
    #[serde(default)]
    pub random_background: bool,
    /// Occupancy grid cells per axis for skipping empty space while training (0: off; the
    /// strata of each ray then cover only its occupied part, see [`SkipEmpty`]).
    #[serde(default)]
    pub occupancy_res: u32,
    /// Cascades of that grid (0: from the model's bounds, `autoconfig::occupancy_cascades`).
    #[serde(default)]
    pub occupancy_cascades: u32,
    /// Steps per sweep of the grid: each step refreshes 1/every of the cells (density EMA,
    /// decay 0.95 per refresh) and the occupied bits are rebuilt after each sweep.
    #[serde(default = "default_occupancy_every")]
    pub occupancy_every: u32,
    /// Steps that sample whole rays before the grid starts to decide (the EMA runs meanwhile).
    #[serde(default = "default_occupancy_warmup")]
    pub occupancy_warmup: u32,
    /// Probe intervals per ray that test the grid (1 to 256).
    #[serde(default = "default_occupancy_probes")]
    pub occupancy_probes: u32,
    /// A cell is empty when one sample there would be less opaque than this (Instant-NGP's
    /// 0.01): the density threshold is this times the samples per unit of ray between near and
    /// far, or the grid's mean density when that is lower.
    #[serde(default = "default_occupancy_opacity")]
    pub occupancy_opacity: f32,
    /// Train with the fused step (one kernel from pixels to gradients, plus the MLP
    /// weight-gradient reduction; see [`FusedStep`]) where the model allows it; false, or a
    /// model it does not support (precision f16, MLP shapes that do not fit the uniform
    /// block), uses the standalone chain.
    #[serde(default = "default_fused_step")]
    pub fused_step: bool,
    /// How the MLPs run ([`MlpMode`]): forward pass, input gradient and weight gradient, in the
    /// fused step, the standalone chain and the fused march of evaluations, through
    /// cooperative matrices (`coop`, an error where the device cannot; `auto`, where a GPU
    /// offers them) or per-thread f32 (`scalar`).
    #[serde(default)]
    pub mlp: MlpMode,
    /// Core of the virtual views' colour loss (`ViewKind::Virtual`: ExtraNeRF's w(t)-weighted
    /// L1): 0, plain L1, whose gradient has the same size for any error however small; above 0,
    /// smooth L1, quadratic for per-channel errors below the core (see
    /// [`crate::render::loss::LossConfig::l1_core`]).
    #[serde(default)]
    pub virtual_l1_core: f32,
    /// Which parameters Adam updates each step ([`AdamMode`]): all (`dense`), or the hash
    /// table's entries the batch reached and the MLPs (`sparse`; the fused step with an
    /// unsplit table only).
    #[serde(default)]
    pub adam: AdamMode,
}

/// The photometric loss of captured views, as configs and the command line name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum RgbLossKind {
    /// Squared error.
    L2,
    /// Huber with `TrainConfig::huber_delta`.
    Huber,
}

impl RgbLossKind {
    /// The name in configs and reports.
    pub fn name(self) -> &'static str {
        match self {
            RgbLossKind::L2 => "l2",
            RgbLossKind::Huber => "huber",
        }
    }
}

fn default_fused_step() -> bool {
    true
}

fn default_occupancy_opacity() -> f32 {
    0.01
}

fn default_occupancy_every() -> u32 {
    16
}

fn default_occupancy_warmup() -> u32 {
    256
}

fn default_occupancy_probes() -> u32 {
    128
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            steps: 5000,
            // Measured on fern few-shot 17 at equal samples processed (results/curves/README.md,
            // tools/recipe_fern.sh): 1024 x 32 fits within 0.1 dB of 256 x 32, and on lavapipe
            // processes samples faster (tools/bench_recipe.sh); 2048 rays, or 128 samples per
            // ray, fit worse.
            rays: 1024,
            samples: 32,
            rgb_loss: RgbLossKind::L2,
            huber_delta: 0.1,
            depth_lambda: 0.1,
            distortion_lambda: 1e-3,
            hash_decay_lambda: 1e-5,
            grad_scaling: false,
            lr_start: 1e-2,
            // 3e-3, not the paper's 3e-4: at the step counts a few minutes allow, a schedule
            // that decays 30x leaves the field under-fitted (results/curves/README.md).
            lr_end: 3e-3,
            decay_steps: 5000,
            seed: 0,
            background: [0.0; 3],
            // Random backgrounds: renders of opaque scenes come out opaque (fern few-shot 17:
            // held-out opacity 0.62 with black, 0.99 with random) and fit better.
            random_background: true,
            occupancy_res: 0,
            occupancy_cascades: 0,
            occupancy_every: default_occupancy_every(),
            occupancy_warmup: default_occupancy_warmup(),
            occupancy_probes: default_occupancy_probes(),
            occupancy_opacity: default_occupancy_opacity(),
            fused_step: default_fused_step(),
            mlp: MlpMode::Auto,
            virtual_l1_core: 0.0,
            adam: AdamMode::Dense,
        }
    }
}

impl TrainConfig {
    /// The loss settings.
    pub fn loss(&self) -> Result<LossConfig> {
        let rgb = match self.rgb_loss {
            RgbLossKind::L2 => RgbLoss::L2,
            RgbLossKind::Huber if !(self.huber_delta.is_finite() && self.huber_delta > 0.0) => {
                return Err(GpuError::Usage(format!(
                    "the Huber loss needs a finite, positive threshold, not {}",
                    self.huber_delta
                )))
            }
            RgbLossKind::Huber => RgbLoss::Huber(self.huber_delta),
        };
        Ok(LossConfig {
            rgb,
            depth_lambda: self.depth_lambda,
            l1_core: self.virtual_l1_core,
        })
    }

    /// The optimiser settings.
    pub fn adam(&self) -> AdamConfig {
        AdamConfig {
            lr_start: self.lr_start,
            lr_end: self.lr_end,
            decay_steps: self.decay_steps,
            ..AdamConfig::default()
        }
    }

    /// Checks the settings.
    pub fn validate(&self) -> Result<()> {
        self.loss()?;
        if self.rays == 0 || self.samples == 0 || self.steps == 0 {
            return Err(GpuError::Usage(format!(
                "rays ({}), samples per ray ({}) and steps ({}) must be positive",
                self.rays, self.samples, self.steps
            )));
        }
        let ok = |v: f32| v.is_finite() && v >= 0.0;
        if !(ok(self.distortion_lambda) && ok(self.hash_decay_lambda) && ok(self.depth_lambda)) {
            return Err(GpuError::Usage(
                "loss weights must be finite and >= 0".into(),
            ));
        }
        if self.background.iter().any(|c| !c.is_finite()) {
            return Err(GpuError::Usage("background must be finite".into()));
        }
        let lr = |v: f32| v.is_finite() && v > 0.0;
        if !(lr(self.lr_start) && lr(self.lr_end)) {
            return Err(GpuError::Usage(format!(
                "learning rates {} -> {} must be finite and positive",
                self.lr_start, self.lr_end
            )));
        }
        if self.occupancy_res > 0
            && (self.occupancy_res > 512
                || self.occupancy_cascades > 8
                || self.occupancy_every == 0
                || !(1..=MAX_PROBES).contains(&self.occupancy_probes)
                || !(self.occupancy_opacity > 0.0 && self.occupancy_opacity < 1.0))
        {
            return Err(GpuError::Usage(format!(
                "training occupancy grid: {} cells per axis (1-512), {} cascades (0-8), a sweep every {} steps (>= 1), {} probes per ray (1-{MAX_PROBES}), opacity threshold {} (between 0 and 1)",
                self.occupancy_res, self.occupancy_cascades, self.occupancy_every, self.occupancy_probes, self.occupancy_opacity
            )));
        }
        if self.decay_steps == 0 {
            return Err(GpuError::Usage(
                "the learning-rate decay needs a positive number of steps".into(),
            ));
        }
        Ok(())
    }
}

/// Progress of a window of steps, read from the device.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepStats {
    /// Mean batch loss (photometric + depth) over the window.
    pub loss: f64,
    /// Mean colour MSE over the window.
    pub mse: f64,
}

impl StepStats {
    /// PSNR of the window's mean MSE.
    pub fn psnr(&self) -> f64 {
        -10.0 * self.mse.max(1e-12).log10()
    }
}

/// The optimiser state and the kernels of a training step.
#[derive(Debug)]
pub struct Trainer {
    cfg: TrainConfig,
    nerf: Nerf,
    ws: Workspace,
    grads: Buffer<f32>,
    adam: Adam,
    loss: RayLoss,
    batch: Kernel,
    ray_mse: Kernel,
    reduce: ReducePlan,
    stats: Buffer<f32>,
    step: u32,
    /// The occupancy grid that training skips empty space with, when enabled.
    occupancy: Option<Occupancy>,
    /// The fused training step, when used.
    fused: Option<FusedStep>,
    /// With the sparse Adam: the table's touched mask (empty between steps), and whether the
    /// table's gradients may hold a step's leftovers (a step recorded without its update):
    /// the next step then zeroes the whole gradient buffer, not only the MLPs'.
    touched: Option<Buffer<u32>>,
    table_grads_dirty: std::cell::Cell<bool>,
    /// Why the standalone chain trains instead, when it does.
    standalone_reason: Option<String>,
    /// The MLP path the steps take.
    mlp_path: MlpPath,
    /// With the proposal sampler: its buffers (its field and kernels are the field's,
    /// [`Nerf`]'s).
    proposal: Option<ProposalWork>,
}

/// Why the fused step does not train with the proposal sampler and cooperative matrices.
const PROPOSAL_STANDALONE: &str = "the fused step takes the proposal sampler's samples with scalar MLPs only; with cooperative-matrix MLPs it trains with the standalone chain";

impl Trainer {
    /// A trainer for `nerf` (its parameters are trained in place), at step `step` with Adam
    /// moments `moments` (`None`: fresh).
    pub fn new(
        ctx: &Context,
        nerf: Nerf,
        cfg: TrainConfig,
        step: u32,
        moments: Option<(&[f32], &[f32])>,
    ) -> Result<Trainer> {
        cfg.validate()?;
        if cfg.grad_scaling && nerf.field.config().space == Space::Ndc {
            // Floaters No More scales by min(1, d^2) for a sample at distance d from the
            // camera, in scene units; NDC's near plane lies at depth 1, so no sample is nearer
            // and the scaling would change nothing (NDC t in its place weakened every sample).
            return Err(GpuError::Usage(
                "gradient scaling applies to world-space fields: in NDC every sample lies at least the near plane's depth 1 from the camera, where min(1, d^2) is 1".into(),
            ));
        }
        let mut nerf = nerf;
        let mlp_path = nerf.set_mlp(ctx, cfg.mlp)?;
        let total = nerf.field.layout().total;
        if nerf.proposal.is_some() && cfg.occupancy_res > 0 {
            return Err(GpuError::Usage(
                crate::renderer::PROPOSAL_WITHOUT_OCCUPANCY.into(),
            ));
        }
        let why_not = if !cfg.fused_step {
            Some("the standalone chain was asked for".to_string())
        } else if nerf.proposal.is_some() && mlp_path != MlpPath::Scalar {
            Some(PROPOSAL_STANDALONE.to_string())
        } else {
            FusedStep::supports(&nerf.field)
                .err()
                .map(|e| e.to_string())
        };
        let fused = match why_not {
            None => Some(FusedStep::new(ctx, &nerf.field, cfg.rays, cfg.samples)?),
            Some(_) => None,
        };
        let proposal = match &nerf.proposal {
            None => None,
            Some(ps) => {
                let purpose = match fused {
                    Some(_) => ProposalUse::Fused,
                    None => ProposalUse::Standalone,
                };
                Some(ProposalWork::new(
                    ctx,
                    &ps.field,
                    cfg.rays,
                    cfg.samples,
                    purpose,
                )?)
            }
        };
        let ws = Workspace::new(
            ctx,
            &nerf.field,
            nerf.field.config(),
            cfg.rays,
            cfg.samples,
            true,
            fused.is_none(),
        )?;
        let adam = Adam::new(ctx, total as u64, cfg.adam())?;
        let touched = match cfg.adam {
            AdamMode::Dense => None,
            AdamMode::Sparse => {
                if fused.is_none() || nerf.field.grid().split().is_some() {
                    return Err(GpuError::Usage(format!(
                        "--adam sparse needs the fused step and a hash table in one storage binding; this run uses {}",
                        match (&why_not, nerf.field.grid().split()) {
                            (Some(w), _) => format!("the standalone chain ({w})"),
                            _ => "a table split over two bindings".to_string(),
                        }
                    )));
                }
                let words = crate::optim::touched_words(nerf.field.layout().table.1 as u64);
                Some(Buffer::from_slice(
                    ctx,
                    "touched mask",
                    &vec![0u32; words as usize],
                )?)
            }
        };
        if let Some((m, v)) = moments {
            adam.load_moments(m, v)?;
        }
        let model = nerf.field.config();
        // Density whose one-sample opacity 1 - exp(-sigma dt) is about occupancy_opacity at the
        // mean sample spacing.
        let spacing = ((model.far - model.near) / cfg.samples as f32).max(f32::MIN_POSITIVE);
        let threshold = -(1.0 - cfg.occupancy_opacity).ln() / spacing;
        let occupancy = match cfg.occupancy_res {
            0 => None,
            res => Some(Occupancy::new(
                ctx,
                OccupancyConfig {
                    res,
                    cascades: match cfg.occupancy_cascades {
                        0 => crate::autoconfig::occupancy_cascades(nerf.field.config()),
                        c => c,
                    },
                    threshold,
                    ..OccupancyConfig::default()
                },
            )?),
        };
        Ok(Trainer {
            occupancy,
            grads: Buffer::new(ctx, "field gradients", total)?,
            touched,
            // Nothing is known of a new buffer's contents: the first step zeroes it whole.
            table_grads_dirty: std::cell::Cell::new(true),
            adam,
            loss: RayLoss::new(ctx)?,
            batch: Kernel::new(ctx, &kb::sample_batch::DESC)?,
            ray_mse: Kernel::new(ctx, &kp::ray_mse::DESC)?,
            reduce: ReducePlan::new(ctx)?,
            stats: Buffer::from_slice(
                ctx,
                "step stats",
                &vec![0f32; 2 * STAT_SLOTS as usize * SLOT],
            )?,
            ws,
            nerf,
            cfg,
            step,
            fused,
            standalone_reason: why_not,
            mlp_path,
            proposal,
        })
    }

    /// The interlevel loss of the last step recorded (the batch mean times its weight), with
    /// the proposal sampler.
    pub fn interlevel_loss(&self) -> Result<Option<f64>> {
        self.proposal
            .as_ref()
            .map(|w| Ok(w.loss.read()?.iter().map(|&v| v as f64).sum()))
            .transpose()
    }

    /// The main samples of the last step recorded by the standalone chain or with the proposal
    /// sampler, `(t, dt)` for each
    /// of `samples` per ray, and each ray's rendered depth (where the proposal sampler put the
    /// samples against what the field renders).
    pub fn last_batch_samples(&self) -> Result<(Vec<[f32; 2]>, Vec<f32>)> {
        let t_dt = match (&self.fused, &self.proposal) {
            (None, _) => self.ws.t_dt.read()?,
            (Some(_), Some(w)) => w.main_t_dt.read()?,
            (Some(_), None) => {
                return Err(GpuError::Usage(
                    "the fused step places its strata in registers; the standalone chain and the proposal sampler store them".into(),
                ))
            }
        };
        Ok((t_dt, self.ws.out_depth.read()?))
    }

    /// True when steps run the fused kernel ([`FusedStep`]).
    pub fn is_fused(&self) -> bool {
        self.fused.is_some()
    }

    /// The MLP path the steps take (`TrainConfig::mlp` resolved on the device).
    pub fn mlp_path(&self) -> MlpPath {
        // The fused step's own kernel, when it trains.
        self.fused.as_ref().map_or(self.mlp_path, |f| f.mlp_path())
    }

    /// Why the standalone chain trains instead of the fused step, when it does.
    pub fn standalone_reason(&self) -> Option<&str> {
        self.standalone_reason.as_deref()
    }

    /// Steps taken so far.
    pub fn step(&self) -> u32 {
        self.step
    }

    /// The settings.
    pub fn config(&self) -> &TrainConfig {
        &self.cfg
    }

    /// Sets the total steps and the learning-rate decay to `steps` (at least the steps done):
    /// a time budget re-fits them from the pace measured so far.
    pub fn set_steps(&mut self, steps: u32) -> Result<()> {
        let steps = steps.max(self.step).max(1);
        self.adam.set_decay_steps(steps)?;
        self.cfg.steps = steps;
        self.cfg.decay_steps = steps;
        Ok(())
    }

    /// The field being trained.
    pub fn nerf(&self) -> &Nerf {
        &self.nerf
    }

    /// Adam's moments (for checkpoints).
    pub fn moments(&self) -> Result<(Vec<f32>, Vec<f32>)> {
        self.adam.moments()
    }

    /// Samples per step.
    pub fn samples_per_step(&self) -> u64 {
        self.cfg.rays as u64 * self.cfg.samples as u64
    }

    /// The occupancy grid of training, when enabled. It is not part of checkpoints: a resumed
    /// run rebuilds it over its first sweep.
    pub fn occupancy(&self) -> Option<&Occupancy> {
        self.occupancy.as_ref()
    }

    /// The fraction of the training grid's cells marked occupied (`None` without a grid).
    pub fn occupied_fraction(&self) -> Result<Option<f64>> {
        let Some(occ) = &self.occupancy else {
            return Ok(None);
        };
        let set: u64 = occ
            .bits()
            .read()?
            .iter()
            .map(|w| w.count_ones() as u64)
            .sum();
        Ok(Some(set as f64 / occ.config().cells() as f64))
    }

    /// Records step `step`'s share of the occupancy sweep: the density EMA of the next window
    /// of cells and, when a sweep ends after the warm-up, the bits. Returns the sampling that
    /// skips empty space from the warm-up on.
    fn record_occupancy<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        prims: &'a Prims,
        step: u32,
        seed: u32,
    ) -> Result<Option<SkipEmpty<'a>>> {
        let Some(occ) = &self.occupancy else {
            return Ok(None);
        };
        let nerf = &self.nerf;
        let cells = occ.config().cells();
        let every = self.cfg.occupancy_every as u64;
        let per = cells.div_ceil(every);
        let window = (step as u64 - 1) % every;
        let first = window * per;
        if first < cells {
            nerf.marcher.update_occupancy(
                rec,
                &nerf.field,
                nerf.sections(&nerf.params)?,
                occ,
                first,
                per.min(cells - first),
                seed,
                occ.config().decay,
            )?;
        }
        if window + 1 == every && step >= self.cfg.occupancy_warmup {
            occ.record_bits(rec, prims)?;
        }
        Ok((step > self.cfg.occupancy_warmup).then(|| SkipEmpty {
            grid: occ,
            scene: *nerf.field.scene(),
            probes: self.cfg.occupancy_probes,
        }))
    }

    /// Records the batch of step `step`: each ray's pixel and its colour and depth targets, in
    /// the workspace. Returns the step's seed.
    fn record_batch<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        data: &'a TrainData,
        step: u32,
    ) -> Result<u32> {
        let ws = &self.ws;
        let seed = self.step_seed(step);
        // Targets are composited over the background the step adds to the same rays.
        let (bg, random_bg, _) = self.background(seed).parts();
        let p = kb::Params {
            n_rays: ws.rays,
            n_images: data.n_images,
            seed,
            random_bg,
            background: [bg[0], bg[1], bg[2], 0.0],
        };
        let b = kb::sample_batch::Bindings {
            places: data.places.binding(),
            store0: data.store_binding(0),
            store1: data.store_binding(1),
            store2: data.store_binding(2),
            store3: data.store_binding(3),
            store4: data.store_binding(4),
            store5: data.store_binding(5),
            store6: data.store_binding(6),
            store7: data.store_binding(7),
            pixels: ws.pixels.binding(),
            target_rgb: ws.target_rgb.binding(),
            target_depth: ws.target_depth.binding(),
            image_cdf: data.cdf.binding(),
        };
        rec.dispatch(&self.batch, b.into_array(), &p, ws.rays as u64)?;
        Ok(seed)
    }

    /// The seed of step `step`: its batch, strata jitter and random backgrounds.
    pub fn step_seed(&self, step: u32) -> u32 {
        (self.cfg.seed as u32) ^ step.wrapping_mul(0x9e37_79b9)
    }

    /// The background behind the rays of step `step` (1-based).
    pub fn step_background(&self, step: u32) -> Background {
        self.background(self.step_seed(step))
    }

    /// The batch that step `step` (1-based) draws from `data`: per ray the view's index and
    /// the pixel's (y * width + x), and the target colour with its signed colour weight
    /// ([`crate::views::colour_weight`]).
    pub fn draw_batch(&self, ctx: &Context, data: &TrainData, step: u32) -> Result<DrawnBatch> {
        let mut rec = ctx.recorder("draw batch")?;
        self.record_batch(&mut rec, data, step)?;
        ctx.run(rec)?;
        Ok(DrawnBatch {
            pixels: self.ws.pixels.read()?,
            targets: self.ws.target_rgb.read()?,
            depths: self.ws.target_depth.read()?,
        })
    }

    /// Records training step `step` (1-based); without `update`, everything but Adam (the
    /// gradient stays in the gradient buffer).
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    fn record_step<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        prims: &'a Prims,
        data: &'a TrainData,
        step: u32,
        update: bool,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        let seed = self.record_batch(rec, data, step)?;
        mark(prof, rec, "batch (pixels, targets)")?;
        let skip = self.record_occupancy(rec, prims, step, seed)?;
        mark(prof, rec, "occupancy update")?;
        match &self.fused {
            Some(fused) => self.record_fused(rec, fused, data, seed, skip.as_ref(), prof)?,
            None => self.record_standalone(rec, data, seed, skip.as_ref(), prof)?,
        }
        self.record_stats(rec, prims, step)?;
        mark(prof, rec, "loss and MSE stats")?;
        if !update {
            // The sparse Adam zeroes the table's gradient; without it the next step must.
            self.table_grads_dirty.set(true);
            return Ok(());
        }
        self.record_adam(rec, step)?;
        mark(prof, rec, "adam + hash decay")
    }

    /// Records the standalone chain's forward pass, losses and backward pass after the batch
    /// is drawn and the occupancy grid updated (every sample in memory between kernels).
    fn record_standalone<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        data: &'a TrainData,
        seed: u32,
        skip: Option<&SkipEmpty<'a>>,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        let ws = &self.ws;
        let n = ws.rays as u64;
        let ns = n * ws.samples as u64;
        let nerf = &self.nerf;
        // (The trainer refuses an occupancy grid with the proposal sampler: no skip then.)
        let from = match &self.proposal {
            None => SamplesFrom::Strata(skip),
            Some(w) => SamplesFrom::Proposal(w),
        };
        nerf.record_forward(
            rec,
            ws,
            data.cameras.binding(),
            data.n_images,
            n,
            Some(seed),
            Some(ws.target_rgb.binding()),
            from,
            self.background(seed),
            prof,
        )?;
        let samples = ws.samples(n);
        if self.cfg.distortion_lambda > 0.0 {
            nerf.comp.distortion(
                rec,
                &samples,
                ws.s_ds.binding(),
                // The kernel's loss is per ray; the batch mean (like the photometric loss).
                self.cfg.distortion_lambda / n as f32,
                ws.dist_loss.binding(),
                ws.d_weight.binding(),
            )?;
        } else {
            rec.fill_words(ws.d_weight.binding(), ns, 0)?;
        }
        mark(prof, rec, "distortion loss")?;
        let targets = Targets {
            rgb: ws.target_rgb.binding(),
            depth: ws.target_depth.binding(),
        };
        self.loss.record(
            rec,
            &self.cfg.loss()?,
            ws.out_rgba.binding(),
            ws.out_depth.binding(),
            &targets,
            ws.loss.binding(),
            ws.d_rgba.binding(),
            ws.d_depth.binding(),
            n,
        )?;
        let mp = kp::Params {
            n: ws.rays,
            camera: 0,
            first: 0,
            _pad: 0,
        };
        let b = kp::ray_mse::Bindings {
            rendered: ws.out_rgba.binding(),
            target_rgb: ws.target_rgb.binding(),
            mse: ws.mse.binding(),
        };
        rec.dispatch(&self.ray_mse, b.into_array(), &mp, n)?;
        mark(prof, rec, "losses, MSE")?;
        // Backward.
        rec.fill_words(self.grads.binding(), self.grads.len() as u64, 0)?;
        mark(prof, rec, "zero gradients")?;
        let g = RayGrads {
            d_rgba: ws.d_rgba.binding(),
            d_depth: ws.d_depth.binding(),
            d_weight: ws.d_weight.binding(),
            grad_scaling: self.cfg.grad_scaling,
        };
        nerf.comp.backward(
            rec,
            &samples,
            self.background(seed),
            &g,
            ws.d_sigma.binding(),
            ws.d_rgb.binding(),
        )?;
        mark(prof, rec, "composite bwd")?;
        let params = nerf.sections(&nerf.params)?;
        let d_params = nerf.sections(&self.grads)?;
        nerf.field.backward(
            rec,
            params,
            d_params,
            &ws.io(),
            &ws.field_grads(),
            ns,
            ws.samples,
            prof,
        )?;
        match &self.proposal {
            Some(w) => {
                let main = MainBins {
                    edges: w.main_edges.binding(),
                    sigma: ws.io().sigma,
                    t_dt: ws.t_dt.binding(),
                    count: ws.samples,
                };
                self.record_proposal_backward(rec, w, &main, prof)
            }
            None => Ok(()),
        }
    }

    /// The proposal sampler's half of the backward pass, after the main field's: the
    /// interlevel loss against the `main` samples' weights, its gradient through the
    /// proposal's compositing and field.
    fn record_proposal_backward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        w: &'a ProposalWork,
        main: &MainBins<'a>,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        let (ws, nerf) = (&self.ws, &self.nerf);
        let p = nerf.proposal_sampler()?;
        let n = ws.rays as u64;
        p.kernels.interlevel(
            rec,
            &w.source_bins(),
            main,
            ws.rays,
            p.field.config().interlevel / ws.rays as f32,
            w.loss.binding(),
            w.d_weight.binding(),
        )?;
        mark(prof, rec, "interlevel loss")?;
        let samples = Samples {
            rays: w.spans.binding(),
            sigma: w.sigma.binding(),
            rgb: w.zero_rgb.binding(),
            t_dt: w.t_dt.binding(),
            n_rays: n,
            n_samples: n * w.samples as u64,
        };
        let g = RayGrads {
            d_rgba: w.zero_rgb.binding(),
            d_depth: w.zero_rgb.binding(),
            d_weight: w.d_weight.binding(),
            grad_scaling: false,
        };
        nerf.comp.backward(
            rec,
            &samples,
            Background::Fixed([0.0; 3]),
            &g,
            w.d_sigma.binding(),
            w.d_rgb.binding(),
        )?;
        mark(prof, rec, "proposal composite bwd")?;
        p.field.backward(
            rec,
            nerf.proposal_sections(&nerf.params)?,
            nerf.proposal_sections(&self.grads)?,
            w,
            prof,
        )
    }

    /// The background of a step drawn with `seed`: random per ray when the config asks for it,
    /// else the field's colour.
    fn background(&self, seed: u32) -> Background {
        if self.cfg.random_background {
            Background::Random(seed)
        } else {
            Background::Fixed(self.nerf.background)
        }
    }

    /// Float offset of step `step`'s loss in the stat ring (its MSE sum is `SLOT` after it).
    fn stat_slot(step: u32) -> usize {
        ((step - 1) % STAT_SLOTS) as usize * 2 * SLOT
    }

    /// The mean loss and MSE of steps `first .. first + count`, read from the stat ring.
    fn read_stats(&self, first: u32, count: u32) -> Result<StepStats> {
        let stats = self.stats.read()?;
        let (mut loss, mut mse) = (0.0, 0.0);
        for s in first..first + count {
            let slot = Self::stat_slot(s);
            loss += stats[slot] as f64;
            mse += stats[slot + SLOT] as f64 / self.cfg.rays as f64;
        }
        Ok(StepStats {
            loss: loss / count as f64,
            mse: mse / count as f64,
        })
    }

    /// Records the reduction of the batch's per-ray loss and MSE into step `step`'s stat slot.
    fn record_stats<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        prims: &'a Prims,
        step: u32,
    ) -> Result<()> {
        let ws = &self.ws;
        let n = ws.rays as u64;
        let slot = Self::stat_slot(step);
        prims.reduce_sum(
            rec,
            &self.reduce,
            ws.loss.binding(),
            n,
            self.stats.slice(slot, 1)?,
        )?;
        prims.reduce_sum(
            rec,
            &self.reduce,
            ws.mse.binding(),
            n,
            self.stats.slice(slot + SLOT, 1)?,
        )
    }

    /// Records Adam's update of every parameter, with hash decay's gradient folded in.
    fn record_adam<'a>(&'a self, rec: &mut Recorder<'a>, step: u32) -> Result<()> {
        let nerf = &self.nerf;
        let decay = (self.cfg.hash_decay_lambda > 0.0).then(|| {
            let lay = nerf.field.layout();
            TableDecay {
                block: nerf.field.grid().level_block().binding(),
                levels: nerf.field.config().levels,
                start: lay.table.0 as u64,
                floats: lay.table.1 as u64,
                lambda: self.cfg.hash_decay_lambda,
            }
        });
        match &self.touched {
            None => self.adam.record_step(
                rec,
                nerf.params.binding(),
                self.grads.binding(),
                step,
                1.0,
                decay,
            ),
            Some(touched) => {
                let lay = nerf.field.layout();
                self.adam.record_step_sparse(
                    rec,
                    nerf.params.binding(),
                    self.grads.binding(),
                    step,
                    1.0,
                    decay,
                    SparseTable {
                        floats: lay.table.1 as u64,
                        touched: touched.binding(),
                        rest: lay.density.0 as u64,
                    },
                )
            }
        }
    }

    /// Records the fused step's forward and backward pass after the batch is drawn and the
    /// occupancy grid updated.
    fn record_fused<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        fused: &'a FusedStep,
        data: &'a TrainData,
        seed: u32,
        skip: Option<&SkipEmpty<'a>>,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        let ws = &self.ws;
        let nerf = &self.nerf;
        // After a sparse update the table's gradients are zero and its mask empty: only the
        // MLPs' gradients need zeroing. Otherwise everything (and the mask) does.
        let n = self.grads.len() as u64;
        match &self.touched {
            Some(_) if !self.table_grads_dirty.get() => {
                let rest = nerf.field.layout().density.0 as u64;
                let grads = self.grads.binding().sub(rest * 4, (n - rest) * 4)?;
                rec.fill_words(grads, n - rest, 0)?;
            }
            touched => {
                rec.fill_words(self.grads.binding(), n, 0)?;
                if let Some(t) = touched {
                    rec.fill_words(t.binding(), t.len() as u64, 0)?;
                    self.table_grads_dirty.set(false);
                }
            }
        }
        mark(prof, rec, "zero gradients")?;
        let given = match &self.proposal {
            None => None,
            Some(w) => {
                // The step builds its own rays; the samplers need them in the field's space
                // (not the world's, which only the standalone chain's colour MLP reads).
                nerf.record_field_rays(
                    rec,
                    ws,
                    data.cameras.binding(),
                    data.n_images,
                    ws.rays as u64,
                )?;
                mark(prof, rec, "rays")?;
                nerf.record_proposal_samples(
                    rec,
                    ws,
                    w,
                    ws.rays as u64,
                    Some(seed),
                    Some(ws.target_rgb.binding()),
                    &w.main_outputs(),
                    prof,
                )?;
                Some(GivenSamples {
                    t_dt: w.main_t_dt.binding(),
                    s_ds: w.main_s_ds.binding(),
                    sigma: w.main_sigma.binding(),
                })
            }
        };
        let losses = StepLosses {
            loss: self.cfg.loss()?,
            // The kernel's loss is per ray; the batch mean (like the photometric loss).
            distortion: self.cfg.distortion_lambda / ws.rays as f32,
            grad_scaling: self.cfg.grad_scaling,
        };
        fused.record(
            rec,
            &nerf.field,
            nerf.sections(&nerf.params)?,
            nerf.sections(&self.grads)?,
            data.cameras.binding(),
            data.n_images,
            ws.pixels.binding(),
            &Targets {
                rgb: ws.target_rgb.binding(),
                depth: ws.target_depth.binding(),
            },
            &losses,
            Some(seed),
            skip,
            self.background(seed),
            &StepOutputs {
                rgba: ws.out_rgba.binding(),
                depth: ws.out_depth.binding(),
                loss: ws.loss.binding(),
                mse: ws.mse.binding(),
                dist_loss: ws.dist_loss.binding(),
                touched: self.touched.as_ref().map(|t| t.binding()),
            },
            given.as_ref(),
        )?;
        mark(prof, rec, "fused step (march, losses, backward)")?;
        fused.record_weight_gradients(rec, &nerf.field, nerf.sections(&self.grads)?)?;
        mark(prof, rec, "MLP weight gradients")?;
        if let Some(w) = &self.proposal {
            let main = MainBins {
                edges: w.main_edges.binding(),
                sigma: w.main_sigma.binding(),
                t_dt: w.main_t_dt.binding(),
                count: ws.samples,
            };
            self.record_proposal_backward(rec, w, &main, prof)?;
        }
        Ok(())
    }

    /// Runs one training step with a timestamp after every stage: `(stage, ms)` in order.
    pub fn profile_step(
        &mut self,
        ctx: &Context,
        prims: &Prims,
        data: &TrainData,
    ) -> Result<Vec<(&'static str, f64)>> {
        let timer = GpuTimer::new(ctx, "train step profile", 64)?;
        let step = self.step + 1;
        let names = {
            let mut rec = ctx.recorder("profiled train step")?;
            rec.reset_timer(&timer)?;
            let mut prof = Some(Profiler::new(&timer));
            mark(&mut prof, &mut rec, "start")?;
            self.record_step(&mut rec, prims, data, step, true, &mut prof)?;
            ctx.run(rec)?;
            prof.map(|p| p.names().to_vec()).unwrap_or_default()
        };
        self.step = step;
        let t = timer.read_ns(names.len() as u32)?;
        Ok(names
            .iter()
            .skip(1)
            .zip(t.windows(2))
            .map(|(&name, w)| (name, (w[1] - w[0]) * 1e-6))
            .collect())
    }

    /// With the sparse Adam: the touched mask as the last recorded step left it (empty after
    /// an update; after [`Trainer::gradient`], the bits of the vec4s it reached).
    pub fn touched_mask(&self) -> Result<Option<Vec<u32>>> {
        self.touched.as_ref().map(|t| t.read()).transpose()
    }

    /// The gradient of the next step's batch loss with respect to every parameter (the flat
    /// layout), and that step's loss and MSE, without updating anything: the step counter and
    /// the parameters stay as they are, so the same batch is drawn again.
    pub fn gradient(
        &mut self,
        ctx: &Context,
        prims: &Prims,
        data: &TrainData,
    ) -> Result<(Vec<f32>, StepStats)> {
        let step = self.step + 1;
        {
            let mut rec = ctx.recorder("train gradient")?;
            self.record_step(&mut rec, prims, data, step, false, &mut None)?;
            ctx.run(rec)?;
        }
        Ok((self.grads.read()?, self.read_stats(step, 1)?))
    }

    /// Runs `count` steps (at most [`STAT_SLOTS`]) in one submission and returns their mean
    /// loss and MSE.
    pub fn run_steps(
        &mut self,
        ctx: &Context,
        prims: &Prims,
        data: &TrainData,
        count: u32,
    ) -> Result<StepStats> {
        if count == 0 || count > STAT_SLOTS {
            return Err(GpuError::Usage(format!(
                "run 1 to {STAT_SLOTS} steps per call, not {count}"
            )));
        }
        let first = self.step + 1;
        {
            let mut rec = ctx.recorder("train steps")?;
            for s in first..first + count {
                self.record_step(&mut rec, prims, data, s, true, &mut None)?;
            }
            ctx.run(rec)?;
        }
        self.step += count;
        self.read_stats(first, count)
    }
}
