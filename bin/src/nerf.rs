//! `extranerf train`, `render` and `eval`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context as _};
use extranerf_gpu::Context;
use extranerf_nerf::autoconfig::{
    model_covering, model_for_scene, ndc_pixels_in_cube, GridBox, NdcFit, SampleRange,
};
use extranerf_nerf::field::mlp::{MlpMode, MlpPath};
use extranerf_nerf::metrics::{psnr, ssim, Lpips, LpipsNet, PooledError};
use extranerf_nerf::model::{Precision, Sampler};
use extranerf_nerf::mvs_depth::MvsDepthSettings;
use extranerf_nerf::renderer::{March, Nerf};
use extranerf_nerf::run::{
    load_checkpoint, training_views, write_png, write_ray_depth_exr, DepthRequest, RunConfig,
    SceneSpec,
};
use extranerf_nerf::train::{default_lpips_dir, fit_budget, train_loop, TrainRun, ViewSet};
use extranerf_nerf::trainer::{RgbLossKind, TrainConfig, Trainer, STAT_SLOTS};
use extranerf_nerf::views::TrainData;
use extranerf_prims::Prims;

use crate::args::{depth_request, KernelPath, MarchArgs, SplitArgs};
use crate::report::Console;
use extranerf_extrapolate::demo::{demo as run_demo, DemoSpec, DemoStop};
use extranerf_extrapolate::rounds::Stage2Spec;
use extranerf_extrapolate::visibility::{FieldVisibility, VisSettings};
use extranerf_nerf::camera_path::PathSource;
use extranerf_nerf::video::VideoWriter;

/// Arguments of `extranerf train`.
#[derive(clap::Args, Debug)]
pub struct TrainArgs {
    /// Scene: an LLFF folder (poses_bounds.npy + images_N/) or a transforms.json scene.
    #[arg(long, value_name = "DIR", required_unless_present = "resume")]
    scene: Option<PathBuf>,
    #[command(flatten)]
    views: SplitArgs,
    /// Run folder: config.json, checkpoint.safetensors, progress.jsonl.
    #[arg(long, value_name = "RUN")]
    out: PathBuf,
    /// Continue the run in --out from its checkpoint (its saved settings win; --steps may extend it).
    #[arg(long)]
    resume: bool,
    /// Optimiser steps (the paper: 5000).
    #[arg(long)]
    steps: Option<u32>,
    /// Choose the model from the scene and print why: the ray space, the finest grid
    /// resolution from the pixel footprint, the levels and the table size from that. The
    /// default; explicit model flags still win.
    #[arg(long, conflicts_with = "no_auto")]
    auto: bool,
    /// Use the fixed default model (16 levels up to 2048, a 2^19 table) instead of choosing it
    /// from the scene.
    #[arg(long)]
    no_auto: bool,
    /// Training time budget in seconds (held-out evaluations not counted): a 20-step probe
    /// measures samples/s and sets the steps that fit (at most 50000; when fewer than 400 steps
    /// of 256 rays fit, the table and levels are reduced first), and the
    /// steps and the learning-rate schedule are re-fitted to the clock as the run goes, so it
    /// ends when the budget is spent. Explicit --steps wins.
    #[arg(long, value_name = "SECONDS")]
    budget: Option<f64>,
    /// Rays per step [default: 1024].
    #[arg(long)]
    rays: Option<u32>,
    /// Samples per ray [default: 16 with the proposal sampler, 32 with uniform strata].
    #[arg(long)]
    samples: Option<u32>,
    /// log2 of the hash table size per level (paper: 19).
    #[arg(long)]
    log2_table: Option<u32>,
    /// Hash-grid levels (paper: 16).
    #[arg(long)]
    levels: Option<u32>,
    /// Where each ray's --samples go: proposal (Mip-NeRF 360's: a small density-only field, a
    /// 6-level 2^16 hash grid and a 16-wide MLP, is evaluated at --proposal-samples strata per
    /// ray, and the samples are drawn from its weights' histogram; an interlevel loss trains
    /// it; renders, evaluations and visibility maps take its samples; it uses no occupancy
    /// grid) or uniform (jittered strata over the sampling range). On fern few-shot 17 the
    /// proposal's 32 strata for 16 samples reach uniform 32's final PSNR in 0.35x its time
    /// (results/proposal_lavapipe) [default: proposal; uniform when --occupancy-res is given].
    #[arg(long, value_enum)]
    sampler: Option<SamplerArg>,
    /// The proposal field's strata per ray, 2 to 256 [default: 32].
    #[arg(long, value_name = "N")]
    proposal_samples: Option<u32>,
    /// Finest hash-grid resolution (paper: 2048).
    #[arg(long)]
    max_res: Option<u32>,
    /// Hidden width of both MLPs (paper: 64).
    #[arg(long)]
    width: Option<u32>,
    /// f32, or f16: the forward pass reads an f16 copy of the hash table and the MLP backward
    /// keeps its saved activations and gradients in f16 with per-segment power-of-two scales
    /// (f32 master weights and arithmetic; needs 2 features per level, MLP widths in multiples
    /// of 4, and a device with shaderFloat16 and 16-bit storage).
    #[arg(long, value_enum)]
    precision: Option<Precision>,
    /// Depth targets of the training views. auto: the depth files the capture's frames name
    /// (nerfstudio's depth_file_path: 16-bit PNG or .npy, millimetres), else the dense maps the
    /// scene ships (a depth/ folder), else multi-view stereo depth of the training views (`extranerf mvs` at half
    /// resolution, 64 planes; computed once and cached in RUN/depth_mvs; its confidence weights
    /// each pixel) plus COLMAP's sparse points where the scene has them (they win where they
    /// fall). sparse: the COLMAP points only (the default before 2026-12-06). mvs: the MVS
    /// depth only. capture: the capture's depth files only. none: no depth loss. DIR: dense
    /// maps `<image stem>.npy` or `.exr`, view depth in the capture's units [default: auto].
    #[arg(
        long,
        value_name = "auto|sparse|mvs|capture|none|DIR",
        conflicts_with = "depth_dir"
    )]
    depth: Option<DepthRequest>,
    /// The same as --depth DIR.
    #[arg(long, value_name = "DIR")]
    depth_dir: Option<PathBuf>,
    /// MVS depth: Jacobi sweeps of the colour-guided fill of the pixels the sweep kept no
    /// depth for (in inverse depth at the matching resolution; filled pixels weigh 0.25)
    /// [default: 0, no fill].
    #[arg(long, value_name = "ITERATIONS")]
    mvs_fill: Option<u32>,
    /// Depth loss weight (0: off).
    #[arg(long)]
    depth_lambda: Option<f32>,
    /// Distortion loss weight (0: off).
    #[arg(long)]
    distortion_lambda: Option<f32>,
    /// Hash decay weight (0: off).
    #[arg(long)]
    hash_decay: Option<f32>,
    /// Scale gradients by min(1, d^2) at depth d near the cameras (Floaters No More); world-space
    /// fields only (NDC refuses it: no sample lies nearer than depth 1, so it changes nothing).
    #[arg(long)]
    grad_scaling: bool,
    /// Seed of the initialisation and batches.
    #[arg(long)]
    seed: Option<u64>,
    /// NDC scenes: the hash grid's box. cameras: the cube holding every sample of every
    /// camera, at the unit cube's cell size; training: the same for the cameras trained on
    /// only (held-out views' samples beyond it take a face's features); unit: NDC's unit cube,
    /// where samples outside take a face's features (the model before 2026-12, for
    /// comparisons) [default: cameras].
    #[arg(long, value_enum, value_name = "BOX")]
    grid_box: Option<GridBox>,
    /// NDC scenes: the sampled range of NDC t. bounds: between the cameras' depth bounds (0.9 x
    /// each camera's near bound to its far bound); full: 0 to 1, the near plane to infinity
    /// (before 2026-12, for comparisons) [default: bounds].
    #[arg(long, value_enum, value_name = "RANGE")]
    sample_range: Option<SampleRange>,
    /// Skip empty space while training: an occupancy grid of this many cells per axis (0:
    /// off, the default). Each ray's strata then cover only the part of it in occupied cells,
    /// so the same samples per ray sit closer together where there is content.
    #[arg(long, value_name = "CELLS")]
    occupancy_res: Option<u32>,
    /// Cascades of the training grid (default: 1 in NDC, enough to reach the far bound in
    /// world space).
    #[arg(long)]
    occupancy_cascades: Option<u32>,
    /// Steps per sweep of the training grid (each step refreshes 1/N of the cells; the
    /// occupied bits are rebuilt after every sweep) [default: 16].
    #[arg(long, value_name = "N")]
    occupancy_every: Option<u32>,
    /// Steps that sample whole rays before the grid takes over [default: 256].
    #[arg(long, value_name = "STEPS")]
    occupancy_warmup: Option<u32>,
    /// Probe intervals per ray tested against the grid (1 to 256) [default: 128].
    #[arg(long, value_name = "N")]
    occupancy_probes: Option<u32>,
    /// A cell counts as empty when one sample there would be less opaque than this, at the
    /// mean sample spacing (or when its density is below the grid's mean) [default: 0.01].
    #[arg(long, value_name = "ALPHA")]
    occupancy_opacity: Option<f32>,
    /// Training step kernels: fused (one kernel from pixels to gradients plus the MLP
    /// weight-gradient reduction; the default where the model allows it) or standalone (one
    /// kernel per stage, every sample in memory between them). precision f16 always uses
    /// standalone; both take --occupancy-res. May be given with --resume.
    #[arg(long, value_name = "KIND", value_enum)]
    step: Option<KernelPath>,
    /// MLP arithmetic: coop (cooperative matrices, VK_KHR_cooperative_matrix: f16 tiles with
    /// f32 accumulation, for the MLPs' forward pass, input gradient and weight gradient in the
    /// fused step, the standalone chain and the fused march; an error where the device lacks
    /// them),
    /// scalar (per-thread f32), or auto (coop on a GPU that offers a usable tile shape, with
    /// precision f32; scalar on CPU devices, where lavapipe's emulated tiles measured slower)
    /// [default: auto]. May be given with --resume.
    #[arg(long, value_name = "KIND", value_enum)]
    mlp: Option<MlpMode>,
    /// Steps between progress lines (1 to 64).
    #[arg(long, default_value_t = 25)]
    log_every: u32,
    /// Steps between checkpoints (the last step always saves).
    #[arg(long, default_value_t = 500)]
    checkpoint_every: u32,
    /// What lies behind each training ray: black, white, or random (a random colour per ray
    /// and step, so no ray fits a pixel by staying transparent; renders then use black, or
    /// white when the images have alpha). Images with alpha are composited over the same
    /// colour [default: random].
    #[arg(long, value_enum)]
    background: Option<BackgroundArg>,
    /// Learning rate of the first step (Adam, every parameter group) [default: 1e-2].
    #[arg(long, value_name = "LR")]
    lr_start: Option<f32>,
    /// Learning rate of the last step; the decay between is log-linear [default: 3e-3].
    #[arg(long, value_name = "LR")]
    lr_end: Option<f32>,
    /// Photometric loss of the captured views: l2 (squared error) or huber [default: l2].
    #[arg(long, value_enum, value_name = "LOSS")]
    rgb_loss: Option<RgbLossKind>,
    /// The Huber loss's threshold, in colour units [default: 0.1].
    #[arg(long, value_name = "DELTA")]
    huber_delta: Option<f32>,
    /// Which parameters Adam updates each step: dense (all) or sparse (the hash-table entries
    /// the batch reached, tiny-cuda-nn's rule, and the MLPs; the fused step with a table in
    /// one storage binding) [default: dense].
    #[arg(long, value_enum, value_name = "MODE")]
    adam: Option<extranerf_nerf::optim::AdamMode>,
    /// Every this many steps (and at the last), render the held-out views and append their
    /// mean PSNR, SSIM, LPIPS-alex (when the weights are found) and opacity to RUN/curve.jsonl
    /// with the training seconds so far, which leave out the evaluations themselves (0: off).
    #[arg(long, default_value_t = 0, value_name = "STEPS")]
    eval_every: u32,
    /// Views that --eval-every renders: test, train, all, or indices such as 0,8,16.
    #[arg(long, default_value = "test", value_name = "VIEWS")]
    eval_views: ViewSet,
}

/// `bench train --step`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum BenchSteps {
    /// The fused step only.
    Fused,
    /// The standalone chain only.
    Standalone,
    /// Both, the standalone chain last.
    Both,
}

/// `train --sampler`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum SamplerArg {
    /// The same jittered strata on every ray.
    Uniform,
    /// A proposal field's histogram.
    Proposal,
}

/// The sampler `--sampler` and `--proposal-samples` ask for, for a main grid of finest
/// resolution `max_res` (the proposal's grid is no finer).
fn sampler(kind: SamplerArg, samples: Option<u32>, max_res: u32) -> anyhow::Result<Sampler> {
    Ok(match kind {
        SamplerArg::Uniform => {
            if samples.is_some() {
                bail!("--proposal-samples applies to --sampler proposal");
            }
            Sampler::Uniform
        }
        SamplerArg::Proposal => {
            Sampler::Proposal(extranerf_nerf::autoconfig::proposal_for(max_res, samples))
        }
    })
}

/// `train --background`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackgroundArg {
    /// Black behind every ray.
    Black,
    /// White behind every ray.
    White,
    /// A random colour per ray and step.
    Random,
}

fn apply<T>(dst: &mut T, v: Option<T>) {
    if let Some(v) = v {
        *dst = v;
    }
}

/// `extranerf train`.
pub fn train(ctx: &Context, a: &TrainArgs) -> anyhow::Result<()> {
    // A new run that fails before its first checkpoint leaves no folder behind, not even the
    // MVS depth it cached there.
    let new_folder = !a.resume && !a.out.exists();
    let r = train_run(ctx, a);
    if r.is_err() && new_folder && !a.out.join(extranerf_nerf::run::CHECKPOINT_FILE).exists() {
        let _ = std::fs::remove_dir_all(&a.out);
    }
    r
}

fn train_run(ctx: &Context, a: &TrainArgs) -> anyhow::Result<()> {
    if !(1..=STAT_SLOTS).contains(&a.log_every) {
        bail!("--log-every must be 1 to {STAT_SLOTS}");
    }
    if a.checkpoint_every == 0 {
        bail!("--checkpoint-every must be positive");
    }
    if a.resume {
        let given: Vec<&str> = [
            ("--scene", a.scene.is_some()),
            ("--rays", a.rays.is_some()),
            ("--samples", a.samples.is_some()),
            ("--log2-table", a.log2_table.is_some()),
            ("--levels", a.levels.is_some()),
            ("--sampler", a.sampler.is_some()),
            ("--proposal-samples", a.proposal_samples.is_some()),
            ("--max-res", a.max_res.is_some()),
            ("--width", a.width.is_some()),
            ("--precision", a.precision.is_some()),
            ("--depth", a.depth.is_some()),
            ("--depth-dir", a.depth_dir.is_some()),
            ("--mvs-fill", a.mvs_fill.is_some()),
            ("--depth-lambda", a.depth_lambda.is_some()),
            ("--distortion-lambda", a.distortion_lambda.is_some()),
            ("--hash-decay", a.hash_decay.is_some()),
            ("--grad-scaling", a.grad_scaling),
            ("--seed", a.seed.is_some()),
            ("--grid-box", a.grid_box.is_some()),
            ("--sample-range", a.sample_range.is_some()),
            ("--auto", a.auto),
            ("--no-auto", a.no_auto),
            ("--occupancy-res", a.occupancy_res.is_some()),
            ("--occupancy-cascades", a.occupancy_cascades.is_some()),
            ("--occupancy-every", a.occupancy_every.is_some()),
            ("--occupancy-warmup", a.occupancy_warmup.is_some()),
            ("--occupancy-probes", a.occupancy_probes.is_some()),
            ("--occupancy-opacity", a.occupancy_opacity.is_some()),
            ("--budget", a.budget.is_some()),
            ("--lr-start", a.lr_start.is_some()),
            ("--background", a.background.is_some()),
            ("--lr-end", a.lr_end.is_some()),
            ("--rgb-loss", a.rgb_loss.is_some()),
            ("--huber-delta", a.huber_delta.is_some()),
        ]
        .iter()
        .filter(|g| g.1)
        .map(|g| g.0)
        .collect();
        if !given.is_empty() {
            bail!(
                "--resume continues with the run's saved settings (see {}); drop {}",
                a.out.join(extranerf_nerf::run::CONFIG_FILE).display(),
                given.join(", ")
            );
        }
    }
    let (mut cfg, start, params, moments) = if a.resume {
        let ck = load_checkpoint(&a.out).context("resuming")?;
        eprintln!("resuming {} at step {}", a.out.display(), ck.step);
        (ck.config, ck.step, Some(ck.params), ck.moments)
    } else {
        if a.out.join(extranerf_nerf::run::CHECKPOINT_FILE).exists() {
            bail!(
                "{} already holds a run; pass --resume to continue it or choose another --out",
                a.out.display()
            );
        }
        let dir = a.scene.clone().unwrap_or_default();
        let mut scene = SceneSpec {
            split: a.views.kind(&dir),
            dir,
            fewshot_views: a.views.fewshot_views,
            factor: a.views.factor,
            sparse_depth: false,
            depth_dir: None,
            mvs_depth: None,
            capture_depth: false,
        };
        let loaded = scene.load()?;
        let mvs = MvsDepthSettings {
            fill: a.mvs_fill.unwrap_or_default(),
            ..MvsDepthSettings::default()
        };
        let said = depth_request(&a.depth, &a.depth_dir).resolve(&mut scene, &loaded, mvs)?;
        if a.mvs_fill.is_some() && scene.mvs_depth.is_none() {
            bail!(
                "--mvs-fill applies to MVS depth, and this run's depth is {}",
                scene.depth_label()
            );
        }
        eprintln!("{said}");
        let auto = !a.no_auto;
        let fit = NdcFit {
            grid_box: a.grid_box.unwrap_or_default(),
            range: a.sample_range.unwrap_or_default(),
        };
        let mut model = if auto {
            let choice = extranerf_nerf::autoconfig::auto_model_covering(
                &loaded.scene,
                &loaded.split.train,
                &[],
                fit,
            );
            eprintln!("auto-config:");
            for r in &choice.reasons {
                eprintln!("  {r}");
            }
            choice.model
        } else {
            model_covering(&loaded.scene, &loaded.split.train, &[], fit)
        };
        apply(&mut model.log2_table, a.log2_table);
        apply(&mut model.levels, a.levels);
        apply(&mut model.max_res, a.max_res);
        apply(&mut model.precision, a.precision);
        if let Some(w) = a.width {
            model.density_width = w;
            model.color_width = w;
        }
        let kind = match a.sampler {
            Some(k) => k,
            None if a.occupancy_res.is_some_and(|r| r > 0) => {
                eprintln!("sampler: uniform strata (--occupancy-res asks for the occupancy grid, which the proposal sampler, the default, does not use)");
                SamplerArg::Uniform
            }
            None => {
                eprintln!("{}", extranerf_nerf::autoconfig::DEFAULT_SAMPLER_WHY);
                SamplerArg::Proposal
            }
        };
        model.sampler = sampler(kind, a.proposal_samples, model.max_res)?;
        let mut train = TrainConfig::default();
        if model.sampler.proposal().is_some() {
            train.samples = extranerf_nerf::autoconfig::PROPOSAL_MAIN_SAMPLES;
        }
        apply(&mut train.rays, a.rays);
        apply(&mut train.samples, a.samples);
        apply(&mut train.depth_lambda, a.depth_lambda);
        apply(&mut train.distortion_lambda, a.distortion_lambda);
        apply(&mut train.hash_decay_lambda, a.hash_decay);
        apply(&mut train.seed, a.seed);
        apply(&mut train.lr_start, a.lr_start);
        apply(&mut train.lr_end, a.lr_end);
        apply(&mut train.rgb_loss, a.rgb_loss);
        apply(&mut train.huber_delta, a.huber_delta);
        apply(&mut train.adam, a.adam);
        match a.background {
            None => {
                // RGBA captures (NeRF-synthetic) are scored over white, as published tables
                // are: renders use white, training keeps random backgrounds.
                if let Some(&first) = loaded.split.train.first() {
                    let cam = &loaded.scene.cameras[first];
                    if extranerf_nerf::data::load_image(&cam.image)?
                        .alpha
                        .is_some()
                    {
                        train.background = [1.0; 3];
                        eprintln!(
                            "background: {} has alpha; training composites it over random \
                             colours, renders and evaluation over white (--background to choose)",
                            cam.image.display()
                        );
                    }
                }
            }
            Some(BackgroundArg::Black) => {
                train.background = [0.0; 3];
                train.random_background = false;
            }
            Some(BackgroundArg::White) => {
                train.background = [1.0; 3];
                train.random_background = false;
            }
            Some(BackgroundArg::Random) => {
                train.background = [0.0; 3];
                train.random_background = true;
            }
        }
        apply(&mut train.occupancy_res, a.occupancy_res);
        apply(&mut train.occupancy_cascades, a.occupancy_cascades);
        apply(&mut train.occupancy_every, a.occupancy_every);
        apply(&mut train.occupancy_warmup, a.occupancy_warmup);
        apply(&mut train.occupancy_probes, a.occupancy_probes);
        apply(&mut train.occupancy_opacity, a.occupancy_opacity);
        train.grad_scaling = a.grad_scaling;
        if let Some(s) = a.steps {
            train.steps = s;
            train.decay_steps = s;
        }
        let mut cfg = RunConfig {
            scene,
            model,
            train,
        };
        if let (Some(budget), None) = (a.budget, a.steps) {
            fit_budget(
                ctx,
                &mut cfg,
                budget,
                a.log2_table.is_none() && a.levels.is_none(),
                &a.out,
                &mut Console::new(),
            )?;
        }
        (cfg, 0, None, None)
    };
    if a.resume {
        if let Some(s) = a.steps {
            cfg.train.steps = s;
        }
    }
    if let Some(step) = a.step {
        cfg.train.fused_step = step == KernelPath::Fused;
    }
    if let Some(mlp) = a.mlp {
        cfg.train.mlp = mlp;
    }
    let run = TrainRun {
        out: a.out.clone(),
        start,
        log_every: a.log_every,
        checkpoint_every: a.checkpoint_every,
        eval_every: a.eval_every,
        eval_views: a.eval_views.clone(),
        budget: if a.resume || a.steps.is_some() {
            None
        } else {
            a.budget
        },
    };
    Ok(train_loop(
        ctx,
        &cfg,
        &run,
        params,
        moments,
        &mut Console::new(),
    )?)
}

/// Arguments of `extranerf render`.
#[derive(clap::Args, Debug)]
pub struct RenderArgs {
    /// Run folder written by `extranerf train`.
    run: PathBuf,
    /// Which views: test, train, all, or indices such as 0,4,9.
    #[arg(long, default_value = "test")]
    views: ViewSet,
    /// Output folder (default RUN/render).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Samples per ray (default: the training setting).
    #[arg(long)]
    samples: Option<u32>,
    /// Rays per pass.
    #[arg(long, default_value_t = 8192)]
    chunk: u32,
    #[command(flatten)]
    march: MarchArgs,
    /// Render along a camera path instead of the scene's views: a named trajectory around the
    /// training cameras (spiral: LLFF's path; ellipse: in the rig's plane, looking at its
    /// focus; sweep: across the rig and past both ends; line:I,J: from view I to view J), or a
    /// file: the transforms.json that `extranerf cameras` writes, or a nerfstudio
    /// camera_path.json. Writes OUT/frame_NNNN.png, OUT/path.mp4 (H.264, which browsers
    /// play) and OUT/camera_path.json (the path as rendered, for nerfstudio or another
    /// render); default OUT: RUN/path. Example: `extranerf render RUN --path spiral --frames
    /// 120 --width 252`.
    #[arg(
        long,
        value_name = "spiral|ellipse|sweep|line:I,J|FILE",
        conflicts_with = "views"
    )]
    path: Option<PathSource>,
    /// Frames of a named path.
    #[arg(long, default_value_t = 120)]
    frames: usize,
    /// How far a named path reaches beyond the rig, as a factor of its extent (1: its edge).
    #[arg(long, default_value_t = 1.0)]
    range: f64,
    /// Frame width in pixels, the height keeping the aspect [default: the path's cameras'].
    #[arg(long)]
    width: Option<u32>,
    /// Frames per second of the path and its video [default: the path file's, else 30].
    #[arg(long)]
    fps: Option<f64>,
    /// With --path, also write OUT/depth.mp4: the field's depth along the path, near bright
    /// (grey, scaled by the first frame's 1st and 99th percentiles for the whole video).
    #[arg(long, requires = "path")]
    depth_video: bool,
    /// With --path, also write OUT/visibility.mp4: how much of what each pixel shows the
    /// training cameras saw (grey, white: seen), as the extrapolate pipeline's visibility
    /// stage computes it by default (the second largest transmittance toward the training
    /// cameras, through their transmittance volumes; at most 32 training views).
    #[arg(long, requires = "path")]
    visibility_video: bool,
}

/// A view rendered from a run, with its ground truth.
struct Rendered {
    index: usize,
    role: &'static str,
    width: u32,
    height: u32,
    rgb: Vec<f32>,
    depth: Vec<f32>,
    opacity: Vec<f32>,
    truth: Vec<f32>,
    seconds: f64,
    camera: extranerf_nerf::data::Camera,
    /// The grid's cube (centre, half side) of an NDC field.
    ndc_cube: Option<(glam::DVec3, f64)>,
}

/// A trained run's field, ready to render: its config, the field, samples per ray and march.
struct Field {
    cfg: RunConfig,
    nerf: Nerf,
    samples: u32,
    how: March,
}

/// Loads the field of `run` for rendering with `march` (and its occupancy grid, if asked for).
fn open_field(
    ctx: &Context,
    run: &Path,
    samples: Option<u32>,
    march: &MarchArgs,
) -> anyhow::Result<Field> {
    let ck = load_checkpoint(run)?;
    let cfg = ck.config;
    let mut nerf = Nerf::new(ctx, cfg.model.clone(), &ck.params, cfg.train.background)?;
    let mlp_path = nerf.set_mlp(ctx, march.mlp)?;
    eprintln!("MLPs: {mlp_path}");
    let samples = samples.unwrap_or(cfg.train.samples);
    let mut how = march.march()?;
    if nerf.has_proposal() && how != March::Standalone && mlp_path != MlpPath::Scalar {
        eprintln!(
            "note: the fused march takes the proposal sampler's samples with scalar MLPs only; rendering through the standalone chain ({mlp_path} MLPs)"
        );
        how = March::Standalone;
    }
    if let Some(occ) = march.occupancy(&cfg.model)? {
        let t = Instant::now();
        let prims = Prims::new(ctx)?;
        if let Some(st) = nerf.build_occupancy(ctx, &prims, Some(occ), march.occupancy_passes)? {
            eprintln!(
                "occupancy grid {}^3 x {} cascade(s): {} of {} cells occupied ({:.1}%), built in {:.1} s",
                occ.res,
                occ.cascades,
                st.occupied,
                st.cells,
                100.0 * st.occupied as f64 / st.cells as f64,
                t.elapsed().as_secs_f64()
            );
        }
    }
    Ok(Field {
        cfg,
        nerf,
        samples,
        how,
    })
}

#[allow(clippy::too_many_arguments)] // each is a distinct setting
fn render_views(
    ctx: &Context,
    run: &Path,
    which: &ViewSet,
    samples: Option<u32>,
    chunk: u32,
    march: &MarchArgs,
    mut each: impl FnMut(&Rendered) -> anyhow::Result<()>,
) -> anyhow::Result<RunConfig> {
    let field = open_field(ctx, run, samples, march)?;
    let (cfg, nerf, samples, how) = (field.cfg, field.nerf, field.samples, field.how);
    let loaded = cfg.scene.load()?;
    let role = |i: usize| {
        if loaded.split.train.contains(&i) {
            "train"
        } else if loaded.split.test.contains(&i) {
            "test"
        } else {
            "other"
        }
    };
    let list: Vec<(usize, &'static str)> = which
        .indices(&loaded.split, loaded.scene.cameras.len(), "--views")?
        .into_iter()
        .map(|i| (i, role(i)))
        .collect();
    for (i, role) in list {
        let cam = &loaded.scene.cameras[i];
        let t = Instant::now();
        let (rgb, depth, opacity) = nerf.render_with(ctx, cam, chunk, samples, how)?;
        let seconds = t.elapsed().as_secs_f64();
        let truth = extranerf_nerf::data::load_image_over(&cam.image, cfg.train.background)?;
        eprintln!(
            "rendered {role} view {i} ({}x{}, {} march) in {seconds:.2} s",
            cam.width,
            cam.height,
            march.march.name()
        );
        each(&Rendered {
            index: i,
            role,
            width: cam.width,
            height: cam.height,
            rgb,
            depth,
            opacity,
            truth: truth.rgb,
            seconds,
            camera: cam.clone(),
            ndc_cube: (cfg.model.space == extranerf_nerf::model::Space::Ndc).then(|| {
                let c = cfg.model.center.map(f64::from);
                (glam::DVec3::from(c), cfg.model.radius as f64)
            }),
        })?;
    }
    Ok(cfg)
}

/// `extranerf render --path`: the frames of a camera path, with the time they will take said
/// before they start (from a probe frame) and a progress bar.
fn render_path(ctx: &Context, a: &RenderArgs, source: &PathSource) -> anyhow::Result<()> {
    use extranerf_nerf::camera_path::{
        named_path, read_path_file, resized, write_camera_path, PathSource as P,
    };
    use extranerf_nerf::train::{Progress, Reporter, Unit};
    if let Some(f) = a.fps {
        if !(f.is_finite() && f > 0.0 && f <= 1000.0) {
            bail!("--fps {f}: use a rate in (0, 1000]");
        }
    }
    if a.width == Some(0) {
        bail!("--width must be at least 1");
    }
    let field = open_field(ctx, &a.run, a.samples, &a.march)?;
    let (cams, file_fps) = match source {
        P::Named(n) => {
            let loaded = field.cfg.scene.load()?;
            let rig = loaded.train_cameras();
            (
                named_path(&rig, &loaded.scene.cameras, *n, a.frames, a.range)?,
                None,
            )
        }
        P::File(f) => read_path_file(f)?,
    };
    let cams: Vec<_> = match a.width {
        Some(w) => cams.iter().map(|c| resized(c, w)).collect(),
        None => cams,
    };
    let fps = a.fps.or(file_fps).unwrap_or(30.0);
    let out = a.out.clone().unwrap_or_else(|| a.run.join("path"));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    // Frames of an earlier path in this folder would mix with these: they go first.
    let mut stale = 0;
    for e in std::fs::read_dir(&out).with_context(|| format!("reading {}", out.display()))? {
        let p = e?.path();
        let name = p.file_name().map(|n| n.to_string_lossy().into_owned());
        if name.is_some_and(|n| n.starts_with("frame_") && n.ends_with(".png")) {
            std::fs::remove_file(&p).with_context(|| format!("removing {}", p.display()))?;
            stale += 1;
        }
    }
    if stale > 0 {
        eprintln!(
            "removed {stale} frames of an earlier path from {}",
            out.display()
        );
    }
    write_camera_path(&out.join("camera_path.json"), &cams, fps)?;
    let size = (cams[0].width, cams[0].height);
    if let Some(c) = cams.iter().find(|c| (c.width, c.height) != size) {
        bail!(
            "the path's frames are not all one size ({}x{} and {}x{}): pass --width",
            size.0,
            size.1,
            c.width,
            c.height
        );
    }
    let video_path = out.join("path.mp4");
    let mut video = VideoWriter::create(&video_path, size.0, size.1, fps)?;
    let mut depth_video = if a.depth_video {
        Some(VideoWriter::create(
            &out.join("depth.mp4"),
            size.0,
            size.1,
            fps,
        )?)
    } else {
        None
    };
    let mut vis_video = if a.visibility_video {
        let t = Instant::now();
        let train = field.cfg.scene.load()?.train_cameras();
        let settings = VisSettings::default();
        let vis = FieldVisibility::new(ctx, &field.nerf, &train, &settings)?;
        let cfg = settings.config(settings.rank, field.samples)?;
        eprintln!(
            "visibility against {} training cameras: transmittance volumes built in {:.1} s",
            train.len(),
            t.elapsed().as_secs_f64()
        );
        let mask = extranerf_nerf::render::visibility::mask_all_but(train.len(), None);
        Some((
            vis,
            cfg,
            settings.chunk,
            mask,
            VideoWriter::create(&out.join("visibility.mp4"), size.0, size.1, fps)?,
        ))
    } else {
        None
    };
    let mut depth_range: Option<(f32, f32)> = None;
    let mut encode_s = 0.0;
    // The estimate: after a warm-up frame (the first dispatches), probe frames at an eighth
    // and a quarter of the first frame's width give a cost per frame and one per pixel.
    let render_s = |c: &extranerf_nerf::data::Camera| -> anyhow::Result<f64> {
        let t = Instant::now();
        field
            .nerf
            .render_with(ctx, c, a.chunk, field.samples, field.how)?;
        Ok(t.elapsed().as_secs_f64())
    };
    let probe = |div: u32| resized(&cams[0], (cams[0].width / div).max(8));
    let area = |c: &extranerf_nerf::data::Camera| (c.width * c.height) as f64;
    render_s(&probe(16))?;
    let (small, large) = (probe(8), probe(4));
    let (ts, tl) = (render_s(&small)?, render_s(&large)?);
    let per_pixel = ((tl - ts) / (area(&large) - area(&small)).max(1.0)).max(0.0);
    let per_frame = (ts - per_pixel * area(&small)).max(0.0);
    let pixels: f64 = cams.iter().map(area).sum();
    eprintln!(
        "{} frames of {}x{} at {fps} fps ({:.1} s of video): about {:.0} s to render ({:.3} s and {:.3} s for {}x{} and {}x{} probe frames{})",
        cams.len(),
        cams[0].width,
        cams[0].height,
        cams.len() as f64 / fps,
        per_frame * cams.len() as f64 + per_pixel * pixels,
        ts,
        tl,
        small.width,
        small.height,
        large.width,
        large.height,
        if a.visibility_video {
            "; the visibility video adds its own"
        } else {
            ""
        }
    );
    let mut rep = Console::new();
    rep.stage("render path");
    let t = Instant::now();
    for (k, cam) in cams.iter().enumerate() {
        let (rgb, depth, _) =
            field
                .nerf
                .render_with(ctx, cam, a.chunk, field.samples, field.how)?;
        write_png(
            &out.join(format!("frame_{k:04}.png")),
            cam.width,
            cam.height,
            &rgb,
        )?;
        let te = Instant::now();
        video.push(&rgb)?;
        if let Some(v) = depth_video.as_mut() {
            let (lo, hi) = *depth_range.get_or_insert_with(|| depth_percentiles(&depth));
            let grey: Vec<f32> = depth
                .iter()
                .flat_map(|&d| {
                    let g = ((hi - d) / (hi - lo).max(1e-6)).clamp(0.0, 1.0);
                    [g, g, g]
                })
                .collect();
            v.push(&grey)?;
        }
        encode_s += te.elapsed().as_secs_f64();
        if let Some((vis, cfg, chunk, mask, v)) = vis_video.as_mut() {
            let m = vis.map(ctx, &field.nerf, cam, *mask, cfg, *chunk)?;
            let grey: Vec<f32> = m.visibility.iter().flat_map(|&g| [g, g, g]).collect();
            let te = Instant::now();
            v.push(&grey)?;
            encode_s += te.elapsed().as_secs_f64();
        }
        let secs = t.elapsed().as_secs_f64();
        let done = (k + 1) as f64;
        rep.progress(&Progress {
            unit: Unit::Views,
            step: k as u32 + 1,
            total: cams.len() as u32,
            loss: 0.0,
            psnr: 0.0,
            samples_per_s: 0.0,
            secs,
            eta: secs / done * (cams.len() as f64 - done),
        });
    }
    let te = Instant::now();
    video.finish()?;
    if let Some(v) = depth_video {
        v.finish()?;
    }
    if let Some((.., v)) = vis_video {
        v.finish()?;
    }
    encode_s += te.elapsed().as_secs_f64();
    let total = t.elapsed().as_secs_f64();
    rep.note(&format!(
        "wrote {} frames, {} and camera_path.json to {} in {total:.1} s; the video took {encode_s:.2} s of it ({:.1}% of the rendering's {:.1} s)",
        cams.len(),
        [
            Some("path.mp4"),
            a.depth_video.then_some("depth.mp4"),
            a.visibility_video.then_some("visibility.mp4"),
        ]
        .into_iter()
        .flatten()
        .collect::<Vec<_>>()
        .join(", "),
        out.display(),
        100.0 * encode_s / (total - encode_s).max(1e-9),
        total - encode_s
    ));
    Ok(())
}

/// The 1st and 99th percentiles of a frame's depths where it has any (the depth video's
/// range), else (0, 1).
fn depth_percentiles(depth: &[f32]) -> (f32, f32) {
    let mut d: Vec<f32> = depth
        .iter()
        .copied()
        .filter(|v| v.is_finite() && *v > 0.0)
        .collect();
    if d.is_empty() {
        return (0.0, 1.0);
    }
    d.sort_by(f32::total_cmp);
    let at = |q: f64| d[((d.len() - 1) as f64 * q).round() as usize];
    (at(0.01), at(0.99))
}

/// `extranerf render`.
pub fn render(ctx: &Context, a: &RenderArgs) -> anyhow::Result<()> {
    if let Some(p) = &a.path {
        return render_path(ctx, a, p);
    }
    let out = a.out.clone().unwrap_or_else(|| a.run.join("render"));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    render_views(ctx, &a.run, &a.views, a.samples, a.chunk, &a.march, |r| {
        let base = out.join(format!("{}_{:03}", r.role, r.index));
        write_png(&base.with_extension("png"), r.width, r.height, &r.rgb)?;
        write_ray_depth_exr(&base.with_extension("exr"), r.width, r.height, &r.depth)?;
        Ok(())
    })?;
    eprintln!("wrote {}", out.display());
    Ok(())
}

/// Arguments of `extranerf eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Run folder written by `extranerf train`, or by `extranerf extrapolate` (then the
    /// comparison table of the BaseNeRF and each stage-2 and stage-3 variant, with KID, goes to
    /// RUN/eval.json, RUN/eval.md and RUN/report.html; only --lpips and the --kid flags apply).
    run: PathBuf,
    /// Metrics file (default RUN/metrics.json).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Folder with lpips_alex_v0.1.safetensors and lpips_vgg_v0.1.safetensors (default:
    /// $EXTRANERF_MODELS/lpips, else ../shared/models/lpips).
    #[arg(long)]
    lpips: Option<PathBuf>,
    /// Samples per ray (default: the training setting).
    #[arg(long)]
    samples: Option<u32>,
    /// Rays per pass.
    #[arg(long, default_value_t = 8192)]
    chunk: u32,
    /// Also save the rendered test views as PNG into RUN/eval.
    #[arg(long)]
    save_images: bool,
    /// A folder of visibility masks named as the views' images (`../shared/data/synth2/
    /// gt_visibility`: image000.png, white where training views see the surface): each held-out
    /// view that has one is also scored over its visible and its not-visible pixels. On an
    /// extrapolate run the default is the scene's own `gt_visibility/` where it has one (the
    /// demo scene and synth2 do).
    #[arg(long, value_name = "DIR")]
    visibility_masks: Option<PathBuf>,
    /// Which views: all (held-out and training), test, train, or indices such as 0,4,9.
    #[arg(long, default_value = "all")]
    views: ViewSet,
    /// LPIPS backbones to run: alex, vgg or alex,vgg (VGG costs about 10 s per 504x378 view
    /// on two cores).
    #[arg(long, default_value = "alex,vgg", value_delimiter = ',')]
    lpips_nets: Vec<String>,
    #[command(flatten)]
    march: MarchArgs,
    #[command(flatten)]
    pub kid: crate::extrapolate::KidArgs,
}

impl EvalArgs {
    /// Whether the Vulkan context must be one that burn's wgpu runtime can adopt (KID's
    /// network on the device).
    pub fn needs_wgpu(&self) -> bool {
        extranerf_extrapolate::manifest::Manifest::path(&self.run).exists() && self.kid.on_device()
    }
}

/// `extranerf eval`: PSNR, SSIM, LPIPS (AlexNet and VGG) on the held-out views, PSNR on the
/// training views.
pub fn eval(ctx: &Context, a: &EvalArgs) -> anyhow::Result<()> {
    if extranerf_extrapolate::manifest::Manifest::path(&a.run).exists() {
        return crate::extrapolate::eval_run(
            ctx,
            &a.run,
            a.lpips.as_deref(),
            &a.kid,
            a.visibility_masks.as_deref(),
        );
    }
    let dir = a.lpips.clone().unwrap_or_else(default_lpips_dir);
    let mut nets = Vec::new();
    for n in &a.lpips_nets {
        let (net, file) = match n.as_str() {
            "alex" => (LpipsNet::Alex, "lpips_alex_v0.1.safetensors"),
            "vgg" => (LpipsNet::Vgg, "lpips_vgg_v0.1.safetensors"),
            o => bail!("--lpips-nets {o}: use alex and/or vgg"),
        };
        nets.push((format!("lpips_{n}"), Lpips::load(&dir.join(file), net)?));
    }
    let mut per_view = Vec::new();
    let t0 = Instant::now();
    let img_dir = a.run.join("eval");
    if a.save_images {
        std::fs::create_dir_all(&img_dir)?;
    }
    let mut sizes = std::collections::BTreeSet::new();
    // Per role: the pooled error of the pixels inside NDC's unit cube and outside it.
    let mut regions: std::collections::BTreeMap<&str, (PooledError, PooledError)> =
        Default::default();
    let cfg = render_views(ctx, &a.run, &a.views, a.samples, a.chunk, &a.march, |r| {
        sizes.insert(format!("{}x{}", r.width, r.height));
        let p = psnr(&r.rgb, &r.truth)?;
        let mut m = serde_json::json!({
            "view": r.index,
            "role": r.role,
            "psnr": p,
            "render_seconds": r.seconds,
        });
        if let Some((centre, half)) = r.ndc_cube {
            // Where each pixel's rendered point (its expected depth) lies: NDC's unit cube (the
            // grid's box before auto-config fitted it to the cameras) and the model's own
            // cube. Pixels the field leaves transparent have no point and count in neither.
            let opaque: Vec<bool> = r.opacity.iter().map(|&o| o > 1e-3).collect();
            let depth: Vec<f32> = r
                .depth
                .iter()
                .zip(&r.opacity)
                .map(|(&d, &o)| d / o.max(1e-3))
                .collect();
            let unit = ndc_pixels_in_cube(&r.camera, &depth, glam::DVec3::ZERO, 1.0);
            let own = ndc_pixels_in_cube(&r.camera, &depth, centre, half);
            let inside: Vec<bool> = unit.iter().zip(&opaque).map(|(&u, &o)| u && o).collect();
            let outside: Vec<bool> = unit.iter().zip(&opaque).map(|(&u, &o)| !u && o).collect();
            let seen = opaque.iter().filter(|&&o| o).count().max(1) as f64;
            let out_of =
                |v: &[bool]| v.iter().zip(&opaque).filter(|(&x, &o)| !x && o).count() as f64 / seen;
            m["outside_unit_cube"] = out_of(&unit).into();
            m["outside_grid_box"] = out_of(&own).into();
            let e = regions.entry(r.role).or_default();
            e.0.add(&r.rgb, &r.truth, &inside)?;
            e.1.add(&r.rgb, &r.truth, &outside)?;
        }
        if let (Some(dir), "test") = (&a.visibility_masks, r.role) {
            if let Some(seen) =
                extranerf_extrapolate::eval::truth_mask(dir, &r.camera.image, r.width, r.height)?
            {
                let unseen: Vec<bool> = seen.iter().map(|&v| !v).collect();
                for (key, chosen) in [("psnr_visible", &seen), ("psnr_not_visible", &unseen)] {
                    let mut e = PooledError::default();
                    e.add(&r.rgb, &r.truth, chosen)?;
                    m[key] = e.psnr().into();
                }
                m["visible_fraction"] =
                    (seen.iter().filter(|&&v| v).count() as f64 / seen.len() as f64).into();
            }
        }
        if r.role == "test" {
            m["ssim"] = ssim(&r.rgb, &r.truth, r.width, r.height)?.into();
            for (key, net) in &nets {
                m[key.as_str()] = net.distance(&r.rgb, &r.truth, r.width, r.height)?.into();
            }
            if a.save_images {
                write_png(
                    &img_dir.join(format!("test_{:03}.png", r.index)),
                    r.width,
                    r.height,
                    &r.rgb,
                )?;
            }
        }
        eprintln!("  {m}");
        per_view.push(m);
        Ok(())
    })?;
    // Published tables say at which resolution and over which background they score.
    let resolution = sizes.into_iter().collect::<Vec<_>>().join(", ");
    let mean = |role: &str, key: &str| -> Option<f64> {
        let v: Vec<f64> = per_view
            .iter()
            .filter(|m| m["role"] == role)
            .filter_map(|m| m[key].as_f64())
            .collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let summary = serde_json::json!({
        "test": {
            "psnr": mean("test", "psnr"),
            "ssim": mean("test", "ssim"),
            "lpips_alex": mean("test", "lpips_alex"),
            "lpips_vgg": mean("test", "lpips_vgg"),
            // With --visibility-masks: the mean over the views that have a mask.
            "psnr_visible": mean("test", "psnr_visible"),
            "psnr_not_visible": mean("test", "psnr_not_visible"),
        },
        "train": {"psnr": mean("train", "psnr")},
        // NDC fields: PSNR of the (not transparent) pixels whose rendered point lies inside
        // NDC's unit cube and outside it, pooled over the views of each role.
        "unit_cube": regions.iter().map(|(role, (i, o))| {
            (role.to_string(), serde_json::json!({
                "psnr_inside": i.psnr(),
                "psnr_outside": o.psnr(),
                "outside_fraction": o.values as f64 / (i.values + o.values).max(1) as f64,
            }))
        }).collect::<serde_json::Map<_, _>>(),
        "views": per_view,
        "seconds": t0.elapsed().as_secs_f64(),
        "render": a.march.json(),
        "device": ctx.info().name,
        "split": cfg.scene.split,
        "resolution": resolution,
        "background": cfg.train.background,
        "depth": cfg.scene.depth_label(),
    });
    let out = a.out.clone().unwrap_or_else(|| a.run.join("metrics.json"));
    extranerf_nerf::safetensors::write_atomic(
        &out,
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )?;
    if summary["test"]["psnr"].is_null() {
        // `--split all`: every view trained; say so rather than print empty means.
        println!(
            "test: no held-out view (the {} split holds none; --views train or all scores the training views); train PSNR {:.2}; {resolution}, background {:?}; depth {}; wrote {}",
            cfg.scene.split,
            summary["train"]["psnr"].as_f64().unwrap_or(f64::NAN),
            cfg.train.background,
            cfg.scene.depth_label(),
            out.display()
        );
        return Ok(());
    }
    println!(
        "test: PSNR {:.2} SSIM {:.4} LPIPS(alex) {:.4} LPIPS(vgg) {:.4}; train PSNR {:.2}; {} split, {resolution}, background {:?}; depth {}; wrote {}",
        summary["test"]["psnr"].as_f64().unwrap_or(f64::NAN),
        summary["test"]["ssim"].as_f64().unwrap_or(f64::NAN),
        summary["test"]["lpips_alex"].as_f64().unwrap_or(f64::NAN),
        summary["test"]["lpips_vgg"].as_f64().unwrap_or(f64::NAN),
        summary["train"]["psnr"].as_f64().unwrap_or(f64::NAN),
        cfg.scene.split,
        cfg.train.background,
        cfg.scene.depth_label(),
        out.display()
    );
    Ok(())
}

/// Arguments of `extranerf bench train`.
#[derive(clap::Args, Debug)]
pub struct BenchTrainArgs {
    /// Scene (default: $EXTRANERF_DATA/llff/fern, else ../shared/data/llff/fern).
    #[arg(long, value_name = "DIR")]
    scene: Option<PathBuf>,
    /// Rays per step.
    #[arg(long, default_value_t = 256)]
    rays: u32,
    /// Samples per ray.
    #[arg(long, default_value_t = 32)]
    samples: u32,
    /// log2 of the hash table size per level.
    #[arg(long, default_value_t = 19)]
    log2_table: u32,
    /// Hidden width of both MLPs.
    #[arg(long, default_value_t = 64)]
    width: u32,
    /// Hash-grid levels.
    #[arg(long, default_value_t = 16)]
    levels: u32,
    /// Finest grid resolution (default: the scene's model without auto-config: 2048 over NDC's
    /// unit cube, scaled to the grid box).
    #[arg(long, value_name = "N")]
    max_res: Option<u32>,
    /// Timed steps (after 2 warm-up steps that also compile the kernels).
    #[arg(long, default_value_t = 10)]
    steps: u32,
    /// Step kernels to measure: fused, standalone, or both (the standalone chain is then the
    /// same-run reference of the fused step's speed).
    #[arg(long, value_name = "KIND", value_enum, default_value_t = BenchSteps::Both)]
    step: BenchSteps,
    /// MLP paths to measure (forward pass, input and weight gradients), each with every --step
    /// kind: auto, coop, scalar, or several (comma-separated, e.g. coop,scalar).
    #[arg(
        long,
        value_name = "KIND",
        value_enum,
        value_delimiter = ',',
        default_value = "auto"
    )]
    mlp: Vec<MlpMode>,
    /// Train with an occupancy grid of this many cells per axis (0: none), with no warm-up:
    /// each step also runs its share of the grid's sweep, and once the first sweep has set
    /// the bits (step --occupancy-every) the strata cover only the rays' occupied probe
    /// intervals (every cell counts as occupied before).
    #[arg(long, default_value_t = 0, value_name = "N")]
    occupancy_res: u32,
    /// Steps per sweep of that grid.
    #[arg(long, default_value_t = 16, value_name = "STEPS")]
    occupancy_every: u32,
    /// Adam: dense (every parameter) or sparse (the table entries each batch reached; with
    /// `--step fused` only).
    #[arg(long, value_enum, default_value_t = extranerf_nerf::optim::AdamMode::Dense)]
    adam: extranerf_nerf::optim::AdamMode,
    /// Where the samples go: uniform strata, or the proposal sampler's histogram (`train
    /// --sampler`).
    #[arg(long, value_enum, default_value_t = SamplerArg::Uniform)]
    sampler: SamplerArg,
    /// The proposal field's strata per ray (with `--sampler proposal`) [default: 32].
    #[arg(long, value_name = "N")]
    proposal_samples: Option<u32>,
    /// Profiled steps (each with a GPU timestamp after every stage, after the timed ones); the
    /// stage table gives each stage's median over them.
    #[arg(long, default_value_t = 1, value_name = "N")]
    profile_steps: u32,
    /// Also write the results as JSON.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
}

/// Each stage's median GPU milliseconds over `steps` (at least 1) profiled steps.
fn profiled_stages(
    ctx: &Context,
    t: &mut Trainer,
    prims: &Prims,
    data: &TrainData,
    steps: u32,
) -> anyhow::Result<Vec<(&'static str, f64)>> {
    let mut profiles = Vec::new();
    for _ in 0..steps.max(1) {
        profiles.push(t.profile_step(ctx, prims, data)?);
    }
    Ok(profiles[0]
        .iter()
        .enumerate()
        .map(|(i, &(name, _))| {
            (
                name,
                crate::bench::median(profiles.iter().map(|p| p[i].1).collect()),
            )
        })
        .collect())
}

/// `extranerf bench train`: samples/s of whole training steps (wall clock, one submission of
/// `--steps` steps) and the GPU time of every stage of one profiled step.
pub fn bench_train(ctx: &Context, a: &BenchTrainArgs) -> anyhow::Result<()> {
    if a.profile_steps == 0 {
        bail!("--profile-steps must be at least 1");
    }
    let scene = a.scene.clone().unwrap_or_else(|| {
        std::env::var_os("EXTRANERF_DATA")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("../shared/data"))
            .join("llff/fern")
    });
    if !scene.exists() {
        bail!(
            "scene {} not found: pass --scene or set EXTRANERF_DATA to the folder holding llff/fern",
            scene.display()
        );
    }
    let spec = SceneSpec {
        dir: scene,
        split: extranerf_nerf::data::split::SplitKind::Extrapolation,
        fewshot_views: 3,
        factor: 8,
        sparse_depth: true,
        depth_dir: None,
        mvs_depth: None,
        capture_depth: false,
    };
    let loaded = spec.load()?;
    let mut model = model_for_scene(&loaded.scene);
    model.log2_table = a.log2_table;
    model.levels = a.levels;
    apply(&mut model.max_res, a.max_res);
    model.density_width = a.width;
    model.color_width = a.width;
    model.sampler = sampler(a.sampler, a.proposal_samples, model.max_res)?;
    let views = training_views(&spec, &loaded, &model)?;
    let data = TrainData::new(ctx, &views)?;
    let prims = Prims::new(ctx)?;
    println!("device: {}", ctx.info().name);
    // The standalone chain last.
    let kinds: &[bool] = match a.step {
        BenchSteps::Fused => &[true],
        BenchSteps::Standalone => &[false],
        BenchSteps::Both => &[true, false],
    };
    let mut results = Vec::new();
    let runs: Vec<(bool, MlpMode)> = kinds
        .iter()
        .flat_map(|&f| a.mlp.iter().map(move |&m| (f, m)))
        .collect();
    for (fused, mlp) in runs {
        let train = TrainConfig {
            rays: a.rays,
            samples: a.samples,
            fused_step: fused,
            mlp,
            occupancy_res: a.occupancy_res,
            occupancy_every: a.occupancy_every,
            occupancy_warmup: 0,
            adam: a.adam,
            ..TrainConfig::default()
        };
        let params = extranerf_nerf::model::init_params(&model, 0);
        let nerf = Nerf::new(ctx, model.clone(), &params, train.background)?;
        let mut t = Trainer::new(ctx, nerf, train, 0, None)?;
        let label = match t.standalone_reason() {
            None => "fused step".to_string(),
            Some(why) if fused => format!("standalone kernels ({why})"),
            Some(_) => "standalone kernels".to_string(),
        };
        let label = format!(
            "{label}, MLPs {}, Adam {}",
            t.mlp_path(),
            match a.adam {
                extranerf_nerf::optim::AdamMode::Dense => "dense",
                extranerf_nerf::optim::AdamMode::Sparse => "sparse",
            }
        );
        let warm = Instant::now();
        t.run_steps(ctx, &prims, &data, 2)?;
        let warm_s = warm.elapsed().as_secs_f64();
        let mut done = 0;
        let t0 = Instant::now();
        while done < a.steps {
            let c = (a.steps - done).min(STAT_SLOTS);
            t.run_steps(ctx, &prims, &data, c)?;
            done += c;
        }
        let secs = t0.elapsed().as_secs_f64();
        let sps = a.steps as f64 * t.samples_per_step() as f64 / secs;
        let stages = profiled_stages(ctx, &mut t, &prims, &data, a.profile_steps)?;
        let total: f64 = stages.iter().map(|s| s.1).sum();
        println!(
            "model: hash grid {}x{}x2^{}, MLPs {:?} + {:?}; {} rays x {} samples = {} samples/step",
            model.levels,
            model.features,
            model.log2_table,
            model.density_mlp().dims,
            model.color_mlp().dims,
            a.rays,
            a.samples,
            t.samples_per_step()
        );
        if let Some(p) = model.sampler.proposal() {
            println!(
                "sampler: proposal, its field (hash grid {}x{}x2^{}, MLP {:?}) at {} strata per ray",
                p.levels,
                p.features,
                p.log2_table,
                p.mlp().dims,
                p.samples
            );
        }
        // With the sparse Adam: the share of the table one step's batch reached.
        let touched = match a.adam {
            extranerf_nerf::optim::AdamMode::Dense => None,
            extranerf_nerf::optim::AdamMode::Sparse => {
                t.gradient(ctx, &prims, &data)?;
                t.touched_mask()?.map(|m| {
                    let bits: u64 = m.iter().map(|w| w.count_ones() as u64).sum();
                    let vec4s = (model.grid().param_count()).div_ceil(4);
                    (bits, vec4s)
                })
            }
        };
        if let Some((bits, vec4s)) = touched {
            println!(
                "sparse Adam: one step's batch reached {bits} of the table's {vec4s} vec4s ({:.1}%)",
                100.0 * bits as f64 / vec4s as f64
            );
        }
        let occupied = t.occupied_fraction()?;
        if let (Some(f), Some(occ)) = (occupied, t.occupancy()) {
            let g = occ.config();
            println!(
                "occupancy grid: {}^3 x {} cascade(s), a sweep every {} steps, {:.1}% of cells occupied after the run",
                g.res,
                g.cascades,
                a.occupancy_every,
                100.0 * f
            );
        }
        println!(
            "{label}: {:.1} ms wall per step ({} steps), {:.3e} samples/s; warm-up incl. kernel compilation {:.1} s",
            secs * 1e3 / a.steps as f64,
            a.steps,
            sps,
            warm_s
        );
        println!(
            "{:<60} {:>10} {:>7} {:>12}",
            if a.profile_steps == 1 {
                "stage (one profiled step)".to_string()
            } else {
                format!("stage (median of {} profiled steps)", a.profile_steps)
            },
            "ms",
            "%",
            "samples/s"
        );
        for (name, ms) in &stages {
            println!(
                "{name:<60} {ms:>10.3} {:>6.1}% {:>12.3e}",
                100.0 * ms / total,
                t.samples_per_step() as f64 / (ms * 1e-3)
            );
        }
        println!("{:<60} {total:>10.3}", "total (GPU timestamps)");
        results.push(serde_json::json!({
            "step": label,
            "fused": t.is_fused(),
            "mlp": t.mlp_path().to_string(),
            "sampler": model.sampler.name(),
            "proposal_samples": model.sampler.proposal().map(|p| p.samples),
            "step_ms_wall": secs * 1e3 / a.steps as f64,
            "samples_per_s": sps,
            "warmup_s": warm_s,
            "occupied_fraction": occupied,
            "profile_steps": a.profile_steps,
            "stages_ms": stages.iter().map(|(n, ms)| serde_json::json!({"stage": n, "ms": ms})).collect::<Vec<_>>(),
        }));
    }
    // Each fused kind against the standalone chain measured in this run.
    let mut ratios = Vec::new();
    if let Some(base) = results.iter().find(|r| r["fused"] == false) {
        let b = base["samples_per_s"].as_f64().unwrap_or(f64::NAN);
        for r in results.iter().filter(|r| r["fused"] == true) {
            let x = r["samples_per_s"].as_f64().unwrap_or(f64::NAN) / b;
            println!(
                "{} vs standalone kernels in this run: {x:.2}x the samples/s",
                r["step"].as_str().unwrap_or("?")
            );
            ratios.push(serde_json::json!({"step": r["step"], "over_standalone": x}));
        }
    }
    if let Some(path) = &a.json {
        let v = serde_json::json!({
            "device": ctx.info().name,
            "driver": format!("{} {}", ctx.info().driver_name, ctx.info().driver_info),
            "model": model,
            "mlp_dims": {"density": model.density_mlp().dims, "color": model.color_mlp().dims},
            // Each hash-grid level: resolution, table entries, dense (1) or hashed (0).
            "grid_levels": model.grid().level_layout().iter().map(|l| serde_json::json!({"res": l.res, "size": l.size, "dense": l.dense & 1})).collect::<Vec<_>>(),
            "rays": a.rays,
            "samples_per_ray": a.samples,
            "steps": a.steps,
            "runs": results,
            "ratios": ratios,
        });
        extranerf_nerf::safetensors::write_atomic(
            path,
            serde_json::to_string_pretty(&v)?.as_bytes(),
        )?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// Arguments of `extranerf demo`.
#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    /// Output folder: scene/ (the generated capture), basenerf/ (the BaseNeRF's run),
    /// extranerf/ (the ExtraNeRF run: report.html, eval.md, outside_views.png). A folder an
    /// earlier demo made is replaced; any other is refused.
    #[arg(long, default_value = "runs/demo")]
    out: PathBuf,
    /// Image width of the generated views (height is 3/4 of it).
    #[arg(long, default_value_t = DemoSpec::default().width)]
    width: u32,
    /// BaseNeRF training steps (512 rays of 24 samples each).
    #[arg(long, default_value_t = DemoSpec::default().base_steps)]
    steps: u32,
    /// Stage-2 rounds (render the virtual views, inpaint, train).
    #[arg(long, default_value_t = DemoSpec::default().stage2.rounds)]
    rounds: u32,
    /// Stage-2 training steps per round.
    #[arg(long, default_value_t = DemoSpec::default().stage2.steps_per_round)]
    steps_per_round: u32,
    /// Stop after stage 2.
    #[arg(long)]
    no_stage3: bool,
    /// Stage-3 rounds (the unsharp-mask enhancer).
    #[arg(long, default_value_t = DemoSpec::DEFAULT_STAGE3.0)]
    stage3_rounds: u32,
    /// Stage-3 training steps per round.
    #[arg(long, default_value_t = DemoSpec::DEFAULT_STAGE3.1)]
    stage3_steps_per_round: u32,
    /// Divide the views' resolution by this for the virtual views and visibility maps.
    #[arg(long, default_value_t = DemoSpec::default().virtual_downscale)]
    virtual_downscale: u32,
    /// Fly-through frames of each field (0: none).
    #[arg(long, default_value_t = DemoSpec::default().flythrough)]
    flythrough: u32,
    /// Folder with lpips_alex_v0.1.safetensors (default: $EXTRANERF_MODELS/lpips, else
    /// ../shared/models/lpips); without it the table has no LPIPS.
    #[arg(long, value_name = "DIR")]
    lpips: Option<PathBuf>,
    /// Stop after the scene (OUT/scene) or the BaseNeRF (OUT/basenerf), for tools that train
    /// or extrapolate on them themselves.
    #[arg(long, value_enum, default_value_t = DemoStop::default())]
    stop_after: DemoStop,
}

/// `extranerf demo`: ExtraNeRF end to end on the procedural scene.
pub fn demo(ctx: &Context, a: &DemoArgs) -> anyhow::Result<()> {
    let t0 = Instant::now();
    let spec = DemoSpec {
        out: a.out.clone(),
        width: a.width,
        base_steps: a.steps,
        stage2: Stage2Spec {
            rounds: a.rounds,
            steps_per_round: a.steps_per_round,
            ..DemoSpec::default().stage2
        },
        stage3: (!a.no_stage3).then_some((a.stage3_rounds, a.stage3_steps_per_round)),
        virtual_downscale: a.virtual_downscale,
        flythrough: a.flythrough,
        lpips: a.lpips.clone().unwrap_or_else(default_lpips_dir),
        stop_after: a.stop_after,
    };
    let o = run_demo(ctx, &spec, &mut Console::new())?;
    let Some(table) = &o.table else {
        eprintln!(
            "demo: the scene is in {}{}",
            o.scene.display(),
            if a.stop_after == DemoStop::Basenerf {
                format!(", the BaseNeRF in {}", o.basenerf.display())
            } else {
                String::new()
            }
        );
        return Ok(());
    };
    println!("{}", table.markdown());
    for (name, secs) in &o.seconds {
        eprintln!("{name:>28}: {secs:.1} s");
    }
    eprintln!(
        "demo done in {:.0} s. Open {} (the BaseNeRF beside the final field on every view outside the rig); the table is in {}, the picture {}",
        t0.elapsed().as_secs_f64(),
        o.report.as_deref().unwrap_or(&o.run).display(),
        o.run.join("eval.md").display(),
        o.picture.as_deref().unwrap_or(&o.run).display(),
    );
    Ok(())
}

/// Arguments of `extranerf turntable`.
#[derive(clap::Args, Debug)]
pub struct TurntableArgs {
    /// Output folder (must be new or empty).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Image width and height (NeRF-synthetic's are 800).
    #[arg(long, default_value_t = 100)]
    size: u32,
    /// Training views (transforms_train.json).
    #[arg(long, default_value_t = 100)]
    train: usize,
    /// Held-out views (transforms_test.json).
    #[arg(long, default_value_t = 20)]
    test: usize,
}

/// `extranerf turntable`: writes the generated 360-degree scene.
pub fn turntable(a: &TurntableArgs) -> anyhow::Result<()> {
    if a.out.exists() && std::fs::read_dir(&a.out)?.next().is_some() {
        bail!(
            "{} exists and is not empty; pass another --out",
            a.out.display()
        );
    }
    let t = Instant::now();
    eprintln!(
        "turntable: ray tracing {} + {} views at {}x{} into {}",
        a.train,
        a.test,
        a.size,
        a.size,
        a.out.display()
    );
    extranerf_nerf::demo::write_turntable_scene(&a.out, a.size, a.size, a.train, a.test)?;
    eprintln!("done in {:.1} s", t.elapsed().as_secs_f64());
    Ok(())
}

/// Arguments of `extranerf bench render`.
#[derive(clap::Args, Debug)]
pub struct BenchRenderArgs {
    /// Run folder written by `extranerf train` (a trained field: empty space and early
    /// termination depend on what was learned).
    run: PathBuf,
    /// Which views: test, train, all, or indices such as 0,4,9.
    #[arg(long, default_value = "test")]
    views: ViewSet,
    /// Samples per ray (default: the training setting).
    #[arg(long)]
    samples: Option<u32>,
    /// Rays per pass.
    #[arg(long, default_value_t = 8192)]
    chunk: u32,
    /// Also write the results as JSON.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
}

/// `extranerf bench render`: the standalone training kernels against the fused march, exact
/// and with each accuracy cut, on a trained run's views. For each: wall time per view, rays/s,
/// samples/s (rays x samples per ray, skipped or not), PSNR against the photos and the largest
/// and mean colour difference from the exact render.
pub fn bench_render(ctx: &Context, a: &BenchRenderArgs) -> anyhow::Result<()> {
    let fused = |res: u32, w: f32, t: f32| MarchArgs {
        occupancy_res: res,
        min_weight: w,
        min_transmittance: t,
        ..MarchArgs::default()
    };
    let configs: Vec<(&str, MarchArgs)> = vec![
        (
            "standalone kernels",
            MarchArgs {
                march: KernelPath::Standalone,
                ..MarchArgs::default()
            },
        ),
        ("fused, exact (default)", MarchArgs::default()),
        ("fused, early stop 1e-4", fused(0, 0.0, 1e-4)),
        ("fused, early stop + colour cut 1e-4", fused(0, 1e-4, 1e-4)),
        ("fused, cuts + occupancy 32^3", fused(32, 1e-4, 1e-4)),
        ("fused, cuts + occupancy 64^3", fused(64, 1e-4, 1e-4)),
        ("fused, cuts + occupancy 128^3", fused(128, 1e-4, 1e-4)),
    ];
    // Every path with scalar MLPs, then the fused ones again through cooperative matrices
    // where the device offers them.
    let scalar = |m: MarchArgs| MarchArgs {
        mlp: MlpMode::Scalar,
        ..m
    };
    let mut configs: Vec<(String, MarchArgs)> = configs
        .into_iter()
        .map(|(name, m)| (name.to_string(), scalar(m)))
        .collect();
    match ctx.info().coop_tile() {
        Some(t) => {
            let coop: Vec<(String, MarchArgs)> = configs
                .iter()
                .filter(|(_, m)| m.march == KernelPath::Fused)
                .map(|(name, m)| {
                    (
                        format!("{name}, coop {t}x{t}"),
                        MarchArgs {
                            mlp: MlpMode::Coop,
                            ..m.clone()
                        },
                    )
                })
                .collect();
            configs.extend(coop);
        }
        None => println!(
            "no cooperative-matrix MLPs on this device (VK_KHR_cooperative_matrix with 8x8x8 or 16x16x16 f16*f16+f32 subgroup tiles)"
        ),
    }
    let mut exact: Vec<Vec<f32>> = Vec::new();
    let mut rows = Vec::new();
    println!("device: {}", ctx.info().name);
    println!(
        "{:<50} {:>9} {:>11} {:>11} {:>8} {:>10} {:>10}",
        "render path", "s/view", "rays/s", "samples/s", "PSNR", "max |d|", "mean |d|"
    );
    // Kernels compile when each path's pipelines are created, before the timed renders.
    for (ci, (name, m)) in configs.iter().enumerate() {
        let mut secs = 0.0;
        let mut rays = 0u64;
        let mut psnrs = Vec::new();
        let (mut max_d, mut sum_d, mut count) = (0f32, 0f64, 0u64);
        let mut view = 0;
        let cfg = render_views(ctx, &a.run, &a.views, a.samples, a.chunk, m, |r| {
            secs += r.seconds;
            rays += (r.width * r.height) as u64;
            psnrs.push(psnr(&r.rgb, &r.truth)?);
            if ci == 0 {
                exact.push(r.rgb.clone());
            } else {
                for (p, q) in r.rgb.iter().zip(&exact[view]) {
                    let d = (p - q).abs();
                    max_d = max_d.max(d);
                    sum_d += d as f64;
                    count += 1;
                }
            }
            view += 1;
            Ok(())
        })?;
        let samples = a.samples.unwrap_or(cfg.train.samples);
        let views = psnrs.len().max(1) as f64;
        let mean_psnr = psnrs.iter().sum::<f64>() / views;
        let rays_s = rays as f64 / secs;
        let mean_d = if count > 0 { sum_d / count as f64 } else { 0.0 };
        println!(
            "{:<50} {:>9.3} {:>11.3e} {:>11.3e} {:>8.3} {:>10.2e} {:>10.2e}",
            name,
            secs / views,
            rays_s,
            rays_s * samples as f64,
            mean_psnr,
            max_d,
            mean_d
        );
        rows.push(serde_json::json!({
            "path": name,
            "settings": m.json(),
            "seconds_per_view": secs / views,
            "rays_per_s": rays_s,
            "samples_per_s": rays_s * samples as f64,
            "samples_per_ray": samples,
            "psnr": mean_psnr,
            "max_abs_diff_vs_standalone": max_d,
            "mean_abs_diff_vs_standalone": mean_d,
        }));
    }
    if let Some(path) = &a.json {
        crate::bench::write_json(
            path,
            &serde_json::json!({
                "device": ctx.info().name,
                "run": a.run,
                "views": a.views.to_string(),
                "results": rows,
            }),
        )?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// A scene and the views of a split: for the commands that read a scene without a run.
#[derive(clap::Args, Debug, Clone)]
pub struct SceneArgs {
    /// Scene: an LLFF folder (poses_bounds.npy + images_N/) or a transforms.json scene.
    #[arg(long, value_name = "DIR")]
    pub scene: PathBuf,
    #[command(flatten)]
    pub views: SplitArgs,
}

impl SceneArgs {
    /// The scene spec (no depth supervision).
    pub fn spec(&self) -> SceneSpec {
        self.views.spec(self.scene.clone(), false)
    }
}

/// Arguments of `extranerf cameras`.
#[derive(clap::Args, Debug)]
pub struct CamerasArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// outward (translated in the rig's plane), spiral (LLFF's path, widened, looking at the
    /// focus point) or rotate (turned about the up axis past the captured yaw).
    #[arg(long, default_value = "outward")]
    trajectory: extranerf_nerf::cameras::Trajectory,
    /// Cameras to generate.
    #[arg(long, default_value_t = 8)]
    count: usize,
    /// How far beyond the rig, as a factor of its extent (1: at its edge).
    #[arg(long, default_value_t = 1.5)]
    range: f64,
    /// Output file.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
}

/// `extranerf cameras`: extrapolated virtual cameras as transforms.json.
pub fn cameras(a: &CamerasArgs) -> anyhow::Result<()> {
    let spec = a.scene.spec();
    let loaded = spec.load()?;
    let rig = loaded.train_cameras();
    let cams = extranerf_nerf::cameras::virtual_cameras(&rig, a.trajectory, a.count, a.range)?;
    extranerf_nerf::cameras::write_transforms(&a.out, &cams)?;
    eprintln!(
        "{} {:?} cameras at {}x the extent of the {}-view rig ({} split) written to {}",
        cams.len(),
        a.trajectory,
        a.range,
        rig.len(),
        spec.split,
        a.out.display()
    );
    Ok(())
}

/// Arguments of `extranerf export`.
#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// Scene: an LLFF folder, a transforms.json scene or a COLMAP capture.
    #[arg(long, value_name = "DIR")]
    scene: PathBuf,
    /// Downsampling factor the scene is read at (images_N); the export holds those images.
    #[arg(long, default_value_t = 8)]
    factor: u32,
    /// The model's format: text (cameras.txt, images.txt, points3D.txt) or binary (.bin).
    #[arg(long, value_enum, default_value = "text")]
    format: extranerf_nerf::data::colmap::ModelFormat,
    /// Output folder (new or empty).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

/// `extranerf export`: a scene as a COLMAP capture.
pub fn export(a: &ExportArgs) -> anyhow::Result<()> {
    use extranerf_nerf::data::colmap_scene::{export_colmap, sparse_of};
    let spec = SceneSpec {
        dir: a.scene.clone(),
        split: extranerf_nerf::data::split::SplitKind::All,
        fewshot_views: 0,
        factor: a.factor,
        sparse_depth: false,
        depth_dir: None,
        mvs_depth: None,
        capture_depth: false,
    };
    let loaded = spec.load()?;
    let (points, ids) = sparse_of(&a.scene)?;
    let done = export_colmap(&loaded.scene, &points, &ids, &a.out, a.format)?;
    eprintln!(
        "{} views ({} camera(s), {} points) of {} written as a COLMAP capture: model {}, \
         images {}; read it with `--scene {} --factor 1`",
        done.views,
        done.cameras,
        done.points,
        a.scene.display(),
        done.model.display(),
        done.images.display(),
        a.out.display()
    );
    Ok(())
}
