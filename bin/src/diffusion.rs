//! `extranerf diffusion ...` and `extranerf bench diffusion`: the inpainting models (issue 5).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context as _};
use burn::module::Module;
use burn::tensor::Device;
use clap::{Args, Subcommand, ValueEnum as _};
use extranerf_diffusion::config::{
    UNetConfig, VaeConfig, CROSS_ATTN_DOWN, CROSS_ATTN_UP, DOWN, UP,
};
use extranerf_diffusion::device::{diffusion_device, Backend};
use extranerf_diffusion::fill;
use extranerf_diffusion::inpaint::{seeded_noise, Codec, SampleSettings, SplitMix};
use extranerf_diffusion::lora::{self, LoraConfig};
use extranerf_diffusion::pipeline::Pipeline;
use extranerf_diffusion::scheduler::{Prediction, SchedulerConfig};
use extranerf_diffusion::text::LearnedTokens;
use extranerf_diffusion::train::{self, Augment, Progress, TrainImage, TrainSettings, Trainable};
use extranerf_diffusion::train_state::{self, Checkpointing};
use extranerf_diffusion::unet::UNet2DConditionModel;
use extranerf_gpu::Context;
use extranerf_nerf::data::load_image;
use extranerf_nerf::data::split::SplitKind;
use extranerf_nerf::image_ops::{crop, downscale_rgb};
use extranerf_nerf::run::{write_png, SceneSpec};

use crate::bench::write_json;

/// `--diffusion-backend`.
#[derive(Args, Debug, Clone)]
pub struct BackendArgs {
    /// Where the diffusion model runs: `device` (burn's wgpu backend on the engine's own
    /// VkDevice), `cpu` (burn's CPU backend), or `auto` (the device unless it is itself a CPU
    /// implementation such as lavapipe, where the CPU backend measured faster; see `bench
    /// diffusion`).
    #[arg(long = "diffusion-backend", value_enum, default_value_t = Backend::Auto)]
    pub backend: Backend,
}

impl BackendArgs {
    fn device(&self, ctx: &Context) -> anyhow::Result<(Backend, Device)> {
        let (b, d) =
            diffusion_device(ctx, self.backend).context("starting burn on the engine's device")?;
        eprintln!("diffusion backend: {}", b.name());
        Ok((b, d))
    }
}

/// `extranerf diffusion <command>`.
#[derive(Subcommand, Debug)]
pub enum DiffusionCommand {
    /// Train a scene prior from scratch: a small pixel-space inpainting diffusion model
    /// (diffusers UNet2DConditionModel layout, learned conditioning tokens) on the scene's
    /// training views with crops, flips, colour jitter and random masks, holding out regions
    /// of every view; then score its inpainting of those regions and of holes cut into the
    /// split's test views (PSNR inside the hole, LPIPS around it) against the mean-colour,
    /// harmonic and edge-aware diffusion fills.
    Prior(PriorArgs),
    /// Inpaint an image where a mask is white, with a model folder (and optional LoRA).
    Inpaint(InpaintArgs),
    /// Enhance a whole image (a NeRF render) with an enhancer: noised to --strength and
    /// denoised with itself as guidance (ExtraNeRF's stage 3). --model is an enhancer folder
    /// (`extrapolate`'s RUN/stage3-enhancer) or a model folder with enhancer adapters.
    Enhance(EnhanceArgs),
    /// DreamBooth-style LoRA fine-tuning of a model folder on a scene's training views with
    /// their pseudo-disocclusion masks (`extranerf visibility --training-masks`) plus random
    /// masks; writes the adapters apart from the model.
    Finetune(FinetuneArgs),
    /// Write a randomly initialised model folder in diffusers' layout (tests, benchmarks, and
    /// the starting point of `finetune` when no pretrained weights exist).
    Init(InitArgs),
}

/// `extranerf diffusion prior`.
#[derive(Args, Debug)]
pub struct PriorArgs {
    /// Scene folder (LLFF or transforms.json).
    #[arg(long)]
    pub scene: PathBuf,
    /// Output folder: model/, loss.csv, loss.svg, prior_eval.json, eval/*.png.
    #[arg(long)]
    pub out: PathBuf,
    /// Which views train the prior: the training views of this split (as `train --split`;
    /// ExtraNeRF's benchmark is `extrapolation`) [default: given when the scene has
    /// transforms_train.json, else holdout].
    #[arg(long, value_enum)]
    pub split: Option<SplitKind>,
    /// LLFF image folder factor (images_N).
    #[arg(long, default_value_t = 8)]
    pub factor: u32,
    /// Further box downscaling of the views before training.
    #[arg(long, default_value_t = 2)]
    pub downscale: u32,
    /// Optimiser steps.
    #[arg(long, default_value_t = 1500)]
    pub steps: usize,
    /// Crops per step.
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Crop side (a multiple of 2^(levels - 1)).
    #[arg(long, default_value_t = 48)]
    pub crop: usize,
    /// Channels per U-Net level (the last level has self- and cross-attention).
    #[arg(long, value_delimiter = ',', default_value = "32,64,96")]
    pub channels: Vec<usize>,
    /// AdamW learning rate.
    #[arg(long, default_value_t = 2e-3)]
    pub lr: f64,
    /// What the U-Net predicts: `v_prediction` (stable at every noise level), `epsilon` (the
    /// noise, as SD 1.x) or `sample` (the clean image).
    #[arg(long, value_enum, default_value_t = Prediction::V)]
    pub prediction: Prediction,
    /// Regions per view to score: held out of every training view (never in the loss) and
    /// cut into every test view of the split (which training never sees).
    #[arg(long, default_value_t = 2)]
    pub holes: usize,
    /// Held-out region side in pixels (at the downscaled resolution).
    #[arg(long, default_value_t = 16)]
    pub hole_size: usize,
    /// DDIM steps of the inpainting from pure noise.
    #[arg(long, default_value_t = 25)]
    pub eval_steps: usize,
    /// Noise strength of the refinement run, which starts from the harmonic fill (as ExtraNeRF
    /// starts from a render).
    #[arg(long, default_value_t = 0.5)]
    pub refine_strength: f64,
    /// DDIM steps of the refinement run (ExtraNeRF: about 10).
    #[arg(long, default_value_t = 10)]
    pub refine_steps: usize,
    /// Seed (holes, crops, noise).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub state: StateArgs,
    /// Score an existing prior (a `model/` folder this command wrote, with its
    /// prior_holes.json) instead of training one.
    #[arg(long, conflicts_with = "resume")]
    pub model: Option<PathBuf>,
    /// Folder with lpips_alex_v0.1.safetensors (default: $EXTRANERF_MODELS/lpips, else
    /// ../shared/models/lpips).
    #[arg(long)]
    pub lpips: Option<PathBuf>,
    #[command(flatten)]
    pub backend: BackendArgs,
}

/// `extranerf diffusion inpaint`.
#[derive(Args, Debug)]
pub struct InpaintArgs {
    /// Model folder (model_index.json, unet/, text_encoder/, scheduler/, optional vae/).
    #[arg(long)]
    pub model: PathBuf,
    /// LoRA adapter folder (adapter_config.json + pytorch_lora_weights.safetensors).
    #[arg(long)]
    pub lora: Option<PathBuf>,
    /// Image (PNG/JPEG). Sides that are not multiples of the model's size step are padded by
    /// repeating the last row and column, and the output is cropped back.
    #[arg(long)]
    pub image: PathBuf,
    /// Mask image: white (> 0.5) = fill.
    #[arg(long)]
    pub mask: PathBuf,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Noise strength of the starting point in (0, 1] (1 = from pure noise).
    #[arg(long, default_value_t = 1.0)]
    pub strength: f64,
    /// DDIM steps.
    #[arg(long, default_value_t = 25)]
    pub steps: usize,
    /// Classifier-free guidance scale (1 = off).
    #[arg(long, default_value_t = 1.0)]
    pub guidance: f64,
    /// Seed of the noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Prompt for Stable Diffusion folders with a CLIP text encoder (this project's models
    /// carry learned tokens instead).
    #[arg(long, default_value = "a photo of a scene")]
    pub prompt: String,
    #[command(flatten)]
    pub backend: BackendArgs,
}

/// `extranerf diffusion enhance`.
#[derive(Args, Debug)]
pub struct EnhanceArgs {
    /// Enhancer folder (enhancer.json with model/ or lora/), or a model folder whose model
    /// (with --lora) was trained to enhance.
    #[arg(long)]
    pub model: PathBuf,
    /// LoRA adapter folder written for enhancement (with a plain model folder).
    #[arg(long)]
    pub lora: Option<PathBuf>,
    /// Image (PNG/JPEG).
    #[arg(long)]
    pub image: PathBuf,
    /// Mask image, white (> 0.5) where an earlier stage filled the image in (as in stage 3:
    /// the not-visible mask). Without it: nothing.
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Noise strength of the starting point in (0, 1] (stage 3's default).
    #[arg(long, default_value_t = 0.3)]
    pub strength: f64,
    /// DDIM steps.
    #[arg(long, default_value_t = 10)]
    pub steps: usize,
    /// Seed of the noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub backend: BackendArgs,
}

/// `extranerf diffusion finetune`.
#[derive(Args, Debug)]
pub struct FinetuneArgs {
    /// Model folder to adapt.
    #[arg(long)]
    pub model: PathBuf,
    /// Scene folder.
    #[arg(long)]
    pub scene: PathBuf,
    /// Folder of pseudo-disocclusion masks (white = disoccluded): `trainmask_NNN_mask.png` as
    /// `extranerf visibility RUN --training-masks` writes them (NNN = the view's index in the
    /// scene), or `<image stem>_mask.png`; resampled to the view's size (it must have the view's aspect). Without it, random
    /// masks only.
    #[arg(long)]
    pub masks: Option<PathBuf>,
    /// Output folder for the adapters, loss.csv and loss.svg.
    #[arg(long)]
    pub out: PathBuf,
    /// Views of this split's training set (as `train --split`; ExtraNeRF's benchmark is
    /// `extrapolation`) [default: given when the scene has transforms_train.json, else holdout].
    #[arg(long, value_enum)]
    pub split: Option<SplitKind>,
    /// LLFF image folder factor.
    #[arg(long, default_value_t = 8)]
    pub factor: u32,
    /// Further downscaling.
    #[arg(long, default_value_t = 2)]
    pub downscale: u32,
    /// LoRA rank (NeRFiller: 4).
    #[arg(long, default_value_t = 4)]
    pub rank: usize,
    /// LoRA alpha (the update is scaled by alpha / rank).
    #[arg(long, default_value_t = 4.0)]
    pub alpha: f64,
    /// Also adapt the ResNet convolutions (conv1, conv2), not only attention q/k/v/out.
    #[arg(long)]
    pub convs: bool,
    /// Steps (ExtraNeRF: 500; NeRFiller: 1000).
    #[arg(long, default_value_t = 500)]
    pub steps: usize,
    /// Crops per step.
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    /// Crop side in pixels.
    #[arg(long, default_value_t = 48)]
    pub crop: usize,
    /// U-Net LoRA learning rate (NeRFiller: 1e-3; ExtraNeRF's full U-Net: 5e-6).
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Learning rate of the conditioning tokens (the identifier; ExtraNeRF's text LoRA: 4e-5).
    #[arg(long, default_value_t = 1e-3)]
    pub token_lr: f64,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Starting prompt of the identifier tokens, for Stable Diffusion folders with a CLIP text
    /// encoder (DreamBooth's "a photo of sks scene").
    #[arg(long, default_value = "a photo of sks scene")]
    pub prompt: String,
    #[command(flatten)]
    pub state: StateArgs,
    #[command(flatten)]
    pub backend: BackendArgs,
}

/// Progress, checkpoints and resuming of `diffusion prior` and `diffusion finetune`.
#[derive(Args, Debug, Clone)]
pub struct StateArgs {
    /// Steps between loss reports.
    #[arg(long, default_value_t = 25)]
    pub log_every: usize,
    /// Steps between saves of the training state in OUT/train_state/ (parameters, AdamW
    /// moments, random state, loss curve; the last step always saves).
    #[arg(long, default_value_t = 100)]
    pub checkpoint_every: usize,
    /// Continue the training in --out from OUT/train_state/ after a crash or kill, with the
    /// same arguments (--steps may be raised to train further). On the CPU backend the result
    /// is bit for bit the one an uninterrupted run gives.
    #[arg(long)]
    pub resume: bool,
}

impl StateArgs {
    /// The checkpointing of a training whose outputs go to `out`; `identity` lists what a
    /// resume must share besides the training settings and images.
    fn checkpointing(
        &self,
        out: &Path,
        identity: serde_json::Value,
    ) -> anyhow::Result<Checkpointing> {
        if self.checkpoint_every == 0 || self.log_every == 0 {
            bail!("--checkpoint-every and --log-every must be at least 1");
        }
        let ck = Checkpointing {
            dir: out.join(TRAIN_STATE_DIR),
            every: self.checkpoint_every,
            resume: self.resume,
            identity,
        };
        if self.resume {
            match train_state::peek(&ck.dir)? {
                Some(st) => eprintln!("resuming {} at step {}", out.display(), st.step),
                None => bail!(
                    "{}: no training state to resume (--resume continues a killed `diffusion prior` or `diffusion finetune` in the same --out)",
                    ck.dir.display()
                ),
            }
        }
        Ok(ck)
    }
}

/// Folder of the resumable training state inside --out.
pub const TRAIN_STATE_DIR: &str = "train_state";

/// `extranerf diffusion init`.
#[derive(Args, Debug)]
pub struct InitArgs {
    /// `tiny` (latent inpainting U-Net 32/64 with a tiny VAE), `pixel` (a pixel-space
    /// inpainting U-Net), or `sd15-inpainting` (SD-1.5 inpainting shapes: 860M parameters,
    /// 3.4 GB).
    #[arg(long, value_enum, default_value_t = InitConfig::Tiny)]
    pub config: InitConfig,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of the initialisation.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// `diffusion init --config`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum InitConfig {
    /// A latent inpainting U-Net 32/64 with a tiny VAE.
    Tiny,
    /// A pixel-space inpainting U-Net.
    Pixel,
    /// Stable Diffusion 1.5 inpainting's shapes.
    Sd15Inpainting,
}

/// `extranerf bench diffusion`.
#[derive(Args, Debug)]
pub struct BenchDiffusionArgs {
    /// Backends to measure (`device` pays burn's shader compilation first, reported apart).
    #[arg(long, value_delimiter = ',', default_value = "cpu,device")]
    pub backends: Vec<String>,
    /// Timed iterations per row (after one warm-up iteration).
    #[arg(long, default_value_t = 3)]
    pub iters: usize,
    /// Also write the rows as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Only the tiny configuration (fast).
    #[arg(long)]
    pub tiny_only: bool,
}

pub fn run(ctx: &Context, cmd: &DiffusionCommand) -> anyhow::Result<()> {
    match cmd {
        DiffusionCommand::Prior(a) => prior(ctx, a),
        DiffusionCommand::Inpaint(a) => inpaint(ctx, a),
        DiffusionCommand::Enhance(a) => enhance(ctx, a),
        DiffusionCommand::Finetune(a) => finetune(ctx, a),
        DiffusionCommand::Init(a) => init(a),
    }
}

/// The pixel-space prior's U-Net ([`UNetConfig::pixel_space`]).
pub fn prior_unet_config(channels: &[usize], token_dim: usize) -> anyhow::Result<UNetConfig> {
    UNetConfig::pixel_space(channels, token_dim)
        .map_err(|e| anyhow::anyhow!("--channels {channels:?}: {e}"))
}

/// The prior's noise process ([`SchedulerConfig::pixel_space`]).
pub fn prior_scheduler(prediction: Prediction) -> SchedulerConfig {
    SchedulerConfig::pixel_space(prediction)
}

struct View {
    /// Camera index in the scene.
    index: usize,
    name: String,
    width: usize,
    height: usize,
    rgb: Vec<f32>,
}

/// The training views (and the held-out test views) of a split, downscaled.
fn load_view_sets(
    scene: &Path,
    split: SplitKind,
    factor: u32,
    downscale: u32,
) -> anyhow::Result<(Vec<View>, Vec<View>)> {
    let spec = SceneSpec {
        dir: scene.to_path_buf(),
        split,
        fewshot_views: 3,
        factor,
        sparse_depth: false,
        depth_dir: None,
        mvs_depth: None,
        capture_depth: false,
    };
    let loaded = spec
        .load()
        .with_context(|| format!("loading the scene {}", scene.display()))?;
    let load = |ids: &[usize]| -> anyhow::Result<Vec<View>> {
        let mut views = Vec::new();
        for &i in ids {
            let cam = &loaded.scene.cameras[i];
            let img = load_image(&cam.image)?;
            let (rgb, w, h) = downscale_rgb(&img.rgb, img.width, img.height, downscale)
                .with_context(|| format!("downscaling {} by --downscale", cam.image.display()))?;
            let name = cam
                .image
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| format!("view{i}"));
            views.push(View {
                index: i,
                name,
                width: w as usize,
                height: h as usize,
                rgb,
            });
        }
        Ok(views)
    };
    let train = load(&loaded.split.train)?;
    if train.is_empty() {
        bail!(
            "the {split} split of {} has no training views",
            scene.display()
        );
    }
    Ok((train, load(&loaded.split.test)?))
}

fn load_views(
    scene: &Path,
    split: SplitKind,
    factor: u32,
    downscale: u32,
) -> anyhow::Result<Vec<View>> {
    Ok(load_view_sets(scene, split, factor, downscale)?.0)
}

#[derive(Clone, Copy, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
struct Hole {
    view: usize,
    x: usize,
    y: usize,
    w: usize,
    h: usize,
}

/// Checks held-out regions read from a file against the views they name: each names one of
/// them and lies inside it (a prior trained on another scene, split or --downscale does not).
fn check_holes(holes: &[Hole], views: &[View], path: &Path) -> anyhow::Result<()> {
    for (k, h) in holes.iter().enumerate() {
        let Some(v) = views.get(h.view) else {
            bail!(
                "{}: region {k} is in training view {}, but this split has {} training views (a prior of another scene or split?)",
                path.display(),
                h.view,
                views.len()
            );
        };
        let inside = h.w > 0
            && h.h > 0
            && h.x.checked_add(h.w).is_some_and(|e| e <= v.width)
            && h.y.checked_add(h.h).is_some_and(|e| e <= v.height);
        if !inside {
            bail!(
                "{}: region {k} ({}x{} at {}, {}) does not lie inside view {} ({}x{}; a prior of another scene or --downscale?)",
                path.display(),
                h.w,
                h.h,
                h.x,
                h.y,
                v.name,
                v.width,
                v.height
            );
        }
    }
    Ok(())
}

/// `count` random rectangles of about `size` pixels per view, at least 2 pixels from the border
/// and fitting a `window` around them.
fn random_holes(
    views: &[View],
    count: usize,
    size: usize,
    window: usize,
    rng: &mut SplitMix,
) -> Vec<Hole> {
    let mut holes = Vec::new();
    for (vi, v) in views.iter().enumerate() {
        for _ in 0..count {
            let w = (size as f64 * (0.75 + rng.unit() * 0.5)) as usize;
            let h = (size as f64 * (0.75 + rng.unit() * 0.5)) as usize;
            let (w, h) = (w.clamp(2, window - 4), h.clamp(2, window - 4));
            let x = 2 + rng.below(v.width - w - 4);
            let y = 2 + rng.below(v.height - h - 4);
            holes.push(Hole {
                view: vi,
                x,
                y,
                w,
                h,
            });
        }
    }
    holes
}

fn progress_printer(label: &'static str) -> impl FnMut(&Progress) {
    move |p: &Progress| {
        let rate = p.step as f64 / p.elapsed.max(1e-9);
        let eta = (p.steps - p.step) as f64 / rate.max(1e-9);
        eprintln!(
            "{label} step {:>5}/{}  loss {:.5}  {:.2} it/s  {:.0} s elapsed  ETA {:.0} s",
            p.step, p.steps, p.loss, rate, p.elapsed, eta
        );
    }
}

fn write_curve(out: &Path, curve: &[(usize, f64)], title: &str) -> anyhow::Result<()> {
    let mut csv = String::from("step,loss\n");
    for (s, l) in curve {
        let _ = writeln!(csv, "{s},{l}");
    }
    extranerf_diffusion::write_atomic(&out.join("loss.csv"), csv.as_bytes())?;
    let (w, h, m) = (640.0, 360.0, 60.0);
    let smax = curve.last().map_or(1, |c| c.0).max(1) as f64;
    let logs: Vec<f64> = curve.iter().map(|c| c.1.max(1e-12).log10()).collect();
    let lo = logs.iter().cloned().fold(f64::INFINITY, f64::min);
    let hi = logs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let (lo, hi) = if lo.is_finite() && hi > lo {
        (lo, hi)
    } else {
        (lo - 1.0, lo + 1.0)
    };
    let x = |s: f64| m + s / smax * (w - 2.0 * m);
    let y = |l: f64| h - m - (l - lo) / (hi - lo) * (h - 2.0 * m);
    let pts: Vec<String> = curve
        .iter()
        .zip(&logs)
        .map(|((s, _), l)| format!("{:.1},{:.1}", x(*s as f64), y(*l)))
        .collect();
    let svg = format!(
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" font-size="12">
<rect width="{w}" height="{h}" fill="white"/>
<text x="{}" y="22" text-anchor="middle" font-size="14">{title}</text>
<line x1="{m}" y1="{}" x2="{}" y2="{}" stroke="black"/><line x1="{m}" y1="{m}" x2="{m}" y2="{}" stroke="black"/>
<text x="{}" y="{}" text-anchor="middle">step (0 .. {smax})</text>
<text x="{}" y="{}" text-anchor="end">{:.3}</text><text x="{}" y="{}" text-anchor="end">{:.3}</text>
<text x="16" y="{}" transform="rotate(-90 16 {})" text-anchor="middle">loss (log scale)</text>
<polyline points="{}" fill="none" stroke="royalblue" stroke-width="1.5"/>
</svg>
"#,
        w / 2.0,
        h - m,
        w - m,
        h - m,
        h - m,
        w / 2.0,
        h - 20.0,
        m - 4.0,
        y(hi) + 4.0,
        10f64.powf(hi),
        m - 4.0,
        y(lo) + 4.0,
        10f64.powf(lo),
        h / 2.0,
        h / 2.0,
        pts.join(" ")
    );
    extranerf_diffusion::write_atomic(&out.join("loss.svg"), svg.as_bytes())?;
    Ok(())
}

fn mse_in(a: &[f32], b: &[f32], mask: &[f32]) -> f64 {
    let mut s = 0f64;
    let mut n = 0usize;
    for (i, m) in mask.iter().enumerate() {
        if *m > 0.5 {
            for c in 0..3 {
                s += ((a[3 * i + c] - b[3 * i + c]) as f64).powi(2);
            }
            n += 3;
        }
    }
    s / n.max(1) as f64
}

fn psnr(mse: f64) -> f64 {
    -10.0 * mse.max(1e-12).log10()
}

/// One scored hole: its window (truth, the pixels unknown to the model, this hole's pixels).
struct Window {
    set: &'static str,
    view: String,
    hole: Hole,
    gt: Vec<f32>,
    unknown: Vec<f32>,
    this_hole: Vec<f32>,
    lpips_origin: (usize, usize),
}

fn windows_for(
    set: &'static str,
    views: &[View],
    holes: &[Hole],
    window: usize,
    lp: usize,
) -> Vec<Window> {
    holes
        .iter()
        .map(|h| {
            let v = &views[h.view];
            let ox = (h.x + h.w / 2)
                .saturating_sub(window / 2)
                .min(v.width - window);
            let oy = (h.y + h.h / 2)
                .saturating_sub(window / 2)
                .min(v.height - window);
            let inside = |hh: &Hole, x: usize, y: usize| {
                x >= hh.x && x < hh.x + hh.w && y >= hh.y && y < hh.y + hh.h
            };
            let mut unknown = vec![0f32; window * window];
            let mut this_hole = vec![0f32; window * window];
            for y in 0..window {
                for x in 0..window {
                    let (gx, gy) = (ox + x, oy + y);
                    if holes.iter().any(|o| o.view == h.view && inside(o, gx, gy)) {
                        unknown[y * window + x] = 1.0;
                    }
                    if inside(h, gx, gy) {
                        this_hole[y * window + x] = 1.0;
                    }
                }
            }
            let cx = (h.x + h.w / 2 - ox).saturating_sub(lp / 2).min(window - lp);
            let cy = (h.y + h.h / 2 - oy).saturating_sub(lp / 2).min(window - lp);
            Window {
                set,
                view: v.name.clone(),
                hole: *h,
                gt: crop(&v.rgb, v.width, (ox, ox + window, oy, oy + window)),
                unknown,
                this_hole,
                lpips_origin: (cx, cy),
            }
        })
        .collect()
}

/// Refuses an --out that already holds what the command would write (`marker` exists), as
/// `train` refuses a run folder: a model is hours of work.
fn refuse_to_replace(marker: &Path, out: &Path, what: &str) -> anyhow::Result<()> {
    if marker.exists() {
        bail!(
            "{} already holds {what} ({}); choose another --out or remove it first",
            out.display(),
            marker.display()
        );
    }
    Ok(())
}

/// Holds the training folder `out` for this process (a second trainer into it is refused,
/// naming this one) and removes what killed writes left there.
fn hold(out: &Path) -> anyhow::Result<extranerf_gpu::files::RunLock> {
    let lock = extranerf_gpu::files::RunLock::acquire(out)?;
    let stale = extranerf_gpu::files::remove_stale_temporaries(out)
        .with_context(|| format!("cleaning {}", out.display()))?;
    if !stale.is_empty() {
        eprintln!(
            "removed {} temporary file(s) an interrupted write left in {}",
            stale.len(),
            out.display()
        );
    }
    Ok(lock)
}

/// `extranerf diffusion prior`.
fn prior(ctx: &Context, a: &PriorArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let _lock = hold(&a.out)?;
    if a.model.is_none() && !a.state.resume {
        refuse_to_replace(
            &a.out.join("model").join("model_index.json"),
            &a.out,
            "a prior",
        )?;
    }
    if a.holes == 0 || a.hole_size < 2 {
        bail!(
            "--holes must be at least 1 and --hole-size at least 2 (the evaluation needs regions)"
        );
    }
    if a.eval_steps == 0 || a.refine_steps == 0 {
        bail!("--eval-steps and --refine-steps must be at least 1");
    }
    if !(a.refine_strength > 0.0 && a.refine_strength <= 1.0) {
        bail!("--refine-strength {} must be in (0, 1]", a.refine_strength);
    }
    let lpips = extranerf_nerf::train::lpips_alex(a.lpips.as_deref())?;
    let (backend, dev) = a.backend.device(ctx)?;
    let split = a.split.unwrap_or_else(|| SplitKind::default_for(&a.scene));
    let (views, test_views) = load_view_sets(&a.scene, split, a.factor, a.downscale)?;
    std::fs::create_dir_all(a.out.join("eval"))
        .with_context(|| format!("creating {}", a.out.display()))?;
    let cfg = match &a.model {
        Some(dir) => {
            extranerf_diffusion::config::UNetConfig::from_file(&dir.join("unet/config.json"))?
        }
        None => prior_unet_config(&a.channels, 64)?,
    };
    let multiple = cfg.size_multiple();
    let window = (a.hole_size * 3).max(32).div_ceil(multiple) * multiple;
    let lp = 32.min(window);
    for v in views.iter().chain(&test_views) {
        if v.width < window.max(a.crop) || v.height < window.max(a.crop) {
            bail!(
                "view {} is {}x{}: smaller than the {}-pixel --crop or the {window}-pixel evaluation window (lower --downscale, --crop or --hole-size)",
                v.name, v.width, v.height, a.crop
            );
        }
    }
    if !a.crop.is_multiple_of(multiple) {
        bail!(
            "--crop {} must be a multiple of {multiple} for {} levels",
            a.crop,
            cfg.levels()
        );
    }
    // Held-out regions of the training views (never in the loss, always holes to the model)
    // and synthetic holes in the split's test views, which training never sees at all.
    let mut rng = SplitMix(a.seed ^ 0x5eed);
    let holes = match &a.model {
        Some(dir) => {
            let p = dir.join("prior_holes.json");
            let text = std::fs::read_to_string(&p)
                .with_context(|| format!("{}: the held-out regions of this prior", p.display()))?;
            let holes: Vec<Hole> = serde_json::from_str(&text)
                .with_context(|| format!("{}: malformed", p.display()))?;
            check_holes(&holes, &views, &p)?;
            holes
        }
        None => random_holes(&views, a.holes, a.hole_size, window, &mut rng),
    };
    let mut test_rng = SplitMix(a.seed ^ 0x7e57);
    let test_holes = random_holes(&test_views, a.holes, a.hole_size, window, &mut test_rng);
    let (trained, train_s, curve, params) = match &a.model {
        Some(dir) => {
            let p = Pipeline::load(dir, &dev, "")?;
            let params = p.model.unet.num_params();
            eprintln!("scoring the prior in {} (no training)", dir.display());
            (p, 0.0, Vec::new(), params)
        }
        None => {
            let mut images = Vec::new();
            for (vi, v) in views.iter().enumerate() {
                let mut known = vec![1f32; v.width * v.height];
                for h in holes.iter().filter(|h: &&Hole| h.view == vi) {
                    for yy in h.y..h.y + h.h {
                        for xx in h.x..h.x + h.w {
                            known[yy * v.width + xx] = 0.0;
                        }
                    }
                }
                images.push(TrainImage {
                    width: v.width,
                    height: v.height,
                    rgb: v.rgb.clone(),
                    known,
                    masks: Vec::new(),
                    guides: Vec::new(),
                });
            }
            let ad = dev.clone().autodiff();
            ad.seed(a.seed);
            let sched_cfg = prior_scheduler(a.prediction);
            let pipe = Pipeline::new(cfg.clone(), None, sched_cfg.clone(), 4, &ad)?;
            let params = pipe.model.unet.num_params();
            let flops = 2 * pipe.model.unet.macs(a.crop, a.crop, 4);
            eprintln!(
                "scene prior (trained here from scratch; no pretrained weights): pixel-space U-Net {:?}, {params} parameters, {:.2} GFLOP per {}x{} forward; {} training views {}x{} with {} held-out regions; {} test views with {} holes",
                cfg.block_out_channels,
                flops as f64 / 1e9,
                a.crop,
                a.crop,
                views.len(),
                views[0].width,
                views[0].height,
                holes.len(),
                test_views.len(),
                test_holes.len()
            );
            let model = Trainable {
                unet: pipe.model.unet,
                tokens: pipe.model.tokens,
            };
            let settings = TrainSettings {
                steps: a.steps,
                batch: a.batch,
                lr: a.lr,
                token_lr: a.lr,
                seed: a.seed,
                log_every: a.state.log_every,
                ..TrainSettings::default()
            };
            let ck = a.state.checkpointing(
                &a.out,
                serde_json::json!({
                    "channels": a.channels,
                    "prediction": a.prediction,
                }),
            )?;
            let schedule = pipe.model.schedule.clone();
            let t_train = Instant::now();
            let (model, curve) = train::train(
                model,
                &pipe.model.codec,
                &schedule,
                &images,
                &Augment {
                    crop: a.crop,
                    ..Augment::default()
                },
                &settings,
                &ad,
                Some(&ck),
                &mut progress_printer("prior"),
            )?;
            let train_s = t_train.elapsed().as_secs_f64();
            write_curve(&a.out, &curve, "scene prior: diffusion loss")?;
            let model = model.valid();
            let trained = Pipeline {
                model: extranerf_diffusion::inpaint::InpaintModel {
                    unet: model.unet,
                    tokens: model.tokens,
                    codec: Codec::Pixels(Default::default()),
                    schedule,
                    task: extranerf_diffusion::inpaint::Task::Inpaint,
                },
                unet_config: cfg,
                vae_config: None,
                scheduler_config: sched_cfg,
                notes: vec!["trained from scratch on the scene's views".into()],
            };
            let mdir = a.out.join("model");
            trained.save(&mdir)?;
            extranerf_diffusion::write_atomic(
                &mdir.join("prior_holes.json"),
                serde_json::to_string(&holes)?.as_bytes(),
            )?;
            eprintln!("saved {}", mdir.display());
            (trained, train_s, curve, params)
        }
    };

    // Score: every method sees the same window around the hole, with every unknown pixel in
    // it unknown; PSNR over this hole's pixels, LPIPS on a 32x32 crop around it.
    let mut wins = windows_for(
        "training views, held-out regions",
        &views,
        &holes,
        window,
        lp,
    );
    wins.extend(windows_for(
        "test views (never trained on)",
        &test_views,
        &test_holes,
        window,
        lp,
    ));
    let n = wins.len();
    let mut fills: Vec<[Vec<f32>; 3]> = Vec::with_capacity(n);
    for w in &wins {
        fills.push([
            fill::mean_fill(&w.gt, &w.unknown, window, window)?,
            fill::harmonic_fill(&w.gt, &w.unknown, window, window, 4000, 1e-5)?,
            fill::edge_aware_fill(&w.gt, &w.unknown, window, window, 100, 0.05)?,
        ]);
    }
    // The prior, twice: from pure noise, and as ExtraNeRF uses it, from a blurry estimate (the
    // harmonic fill) noised to --refine-strength and denoised in --refine-steps.
    let run_prior = |starts: &[Vec<f32>],
                     strength: f64,
                     steps: usize,
                     seed: u64|
     -> anyhow::Result<(Vec<Vec<f32>>, f64)> {
        let t = Instant::now();
        let images: Vec<(&[f32], &[f32])> = wins
            .iter()
            .enumerate()
            .map(|(i, w)| (starts[i].as_slice(), w.unknown.as_slice()))
            .collect();
        let out = trained.model.inpaint_images(
            &images,
            window,
            window,
            seed,
            &SampleSettings {
                strength,
                steps,
                guidance: 1.0,
                keep_known: true,
            },
            &dev,
        )?;
        let per = out.into_iter().map(|o| o.rgb).collect();
        Ok((per, t.elapsed().as_secs_f64()))
    };
    let grey: Vec<Vec<f32>> = wins
        .iter()
        .map(|w| {
            let mut g = w.gt.clone();
            for (p, m) in w.unknown.iter().enumerate() {
                if *m > 0.5 {
                    g[3 * p..3 * p + 3].copy_from_slice(&[0.5; 3]);
                }
            }
            g
        })
        .collect();
    let (from_noise, noise_s) = run_prior(&grey, 1.0, a.eval_steps, a.seed ^ 0xe7a1)?;
    let harmonic: Vec<Vec<f32>> = fills.iter().map(|f| f[1].clone()).collect();
    let (refined, refine_s) = run_prior(
        &harmonic,
        a.refine_strength,
        a.refine_steps,
        a.seed ^ 0x4ef1,
    )?;
    let methods = [
        "mean colour",
        "harmonic fill",
        "edge-aware fill",
        "scene prior (from noise)",
        "scene prior (refining harmonic)",
    ];
    let k_methods = methods.len();
    let sets = [
        "training views, held-out regions",
        "test views (never trained on)",
    ];
    let mut psnrs = vec![vec![Vec::new(); k_methods]; 2];
    let mut lps = vec![vec![Vec::new(); k_methods]; 2];
    let mut per_hole = Vec::new();
    for (i, w) in wins.iter().enumerate() {
        let si = usize::from(w.set != sets[0]);
        let [mean_f, harm_f, edge_f] = fills[i].clone();
        let results = [
            mean_f,
            harm_f,
            edge_f,
            from_noise[i].clone(),
            refined[i].clone(),
        ];
        let (cx, cy) = w.lpips_origin;
        let gt_crop = crop(&w.gt, window, (cx, cx + lp, cy, cy + lp));
        let mut row = serde_json::Map::new();
        row.insert("set".into(), w.set.into());
        row.insert("view".into(), w.view.clone().into());
        let h = w.hole;
        row.insert("hole".into(), serde_json::json!([h.x, h.y, h.w, h.h]));
        let mut strip = w.gt.clone();
        let mut masked_vis = w.gt.clone();
        for (p, m) in w.unknown.iter().enumerate() {
            if *m > 0.5 {
                masked_vis[3 * p..3 * p + 3].copy_from_slice(&[1.0, 0.0, 1.0]);
            }
        }
        strip.extend(masked_vis);
        for (k, r) in results.iter().enumerate() {
            let p = psnr(mse_in(r, &w.gt, &w.this_hole));
            let l = lpips.distance(
                &crop(r, window, (cx, cx + lp, cy, cy + lp)),
                &gt_crop,
                lp as u32,
                lp as u32,
            )?;
            psnrs[si][k].push(p);
            lps[si][k].push(l);
            row.insert(
                methods[k].into(),
                serde_json::json!({"psnr_in_mask": p, "lpips_hole_crop": l}),
            );
            strip.extend_from_slice(r);
        }
        // Windows side by side: truth | unknown pixels (magenta) | one per method.
        let cols = 2 + k_methods;
        let mut side = vec![0f32; window * window * 3 * cols];
        for c in 0..cols {
            for y in 0..window {
                for x in 0..window {
                    let src = c * window * window * 3 + 3 * (y * window + x);
                    let dst = 3 * (y * window * cols + c * window + x);
                    side[dst..dst + 3].copy_from_slice(&strip[src..src + 3]);
                }
            }
        }
        let tag = if si == 0 { "train" } else { "test" };
        write_png(
            &a.out
                .join("eval")
                .join(format!("{tag}_{}_hole{i}.png", w.view)),
            (window * cols) as u32,
            window as u32,
            &side,
        )?;
        per_hole.push(serde_json::Value::Object(row));
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let mut summary = serde_json::Map::new();
    for (si, set) in sets.iter().enumerate() {
        let count = psnrs[si][0].len();
        println!(
            "{set}: {count} regions of about {hs}x{hs} px in {window}x{window} windows",
            hs = a.hole_size
        );
        println!(
            "  {:<32} {:>14} {:>22}",
            "method", "PSNR in hole", "LPIPS (alex, 32x32)"
        );
        let mut m = serde_json::Map::new();
        for k in 0..k_methods {
            println!(
                "  {:<32} {:>11.2} dB {:>22.4}",
                methods[k],
                mean(&psnrs[si][k]),
                mean(&lps[si][k])
            );
            m.insert(
                methods[k].into(),
                serde_json::json!({"psnr_in_mask": mean(&psnrs[si][k]), "lpips_hole_crop": mean(&lps[si][k]), "regions": count}),
            );
        }
        summary.insert((*set).into(), serde_json::Value::Object(m));
    }
    let report = serde_json::json!({
        "scene": a.scene,
        "model": match &a.model {
            Some(d) => format!("prior loaded from {}", d.display()),
            None => "scene prior trained from scratch here (no pretrained weights): pixel-space inpainting U-Net, diffusers layout".into(),
        },
        "backend": backend.name(),
        "channels": trained.unet_config.block_out_channels,
        "parameters": params,
        "steps": a.steps,
        "batch": a.batch,
        "crop": a.crop,
        "lr": a.lr,
        "prediction": trained.scheduler_config.prediction_type,
        "views": views.len(),
        "test_views": test_views.len(),
        "view_size": [views[0].width, views[0].height],
        "factor": a.factor,
        "downscale": a.downscale,
        "holes_per_view": a.holes,
        "hole_size": a.hole_size,
        "window": window,
        "lpips_crop": lp,
        "eval_ddim_steps": a.eval_steps,
        "refine_strength": a.refine_strength,
        "refine_ddim_steps": a.refine_steps,
        "train_seconds": train_s,
        "train_it_per_s": if train_s > 0.0 { a.steps as f64 / train_s } else { 0.0 },
        "inpaint_seconds": {"from_noise": noise_s, "refine": refine_s},
        "final_loss": curve.last().map(|c| c.1),
        "mean": summary,
        "per_hole": per_hole,
        "wall_seconds": started.elapsed().as_secs_f64(),
    });
    write_json(&a.out.join("prior_eval.json"), &report)?;
    println!("wrote {}", a.out.join("prior_eval.json").display());
    Ok(())
}

fn read_rgb(path: &Path) -> anyhow::Result<(usize, usize, Vec<f32>)> {
    let img = load_image(path)?;
    Ok((img.width as usize, img.height as usize, img.rgb))
}

/// `extranerf diffusion inpaint`.
fn inpaint(ctx: &Context, a: &InpaintArgs) -> anyhow::Result<()> {
    let (_, dev) = a.backend.device(ctx)?;
    // Anything the model draws at load (fresh tokens for an SD folder without a text encoder)
    // follows --seed too.
    dev.seed(a.seed);
    if !(a.strength > 0.0 && a.strength <= 1.0)
        || a.steps == 0
        || !(a.guidance.is_finite() && a.guidance >= 1.0)
    {
        bail!(
            "--strength {} must be in (0, 1], --steps {} at least 1 and --guidance {} at least 1",
            a.strength,
            a.steps,
            a.guidance
        );
    }
    let mut pipe = Pipeline::load(&a.model, &dev, &a.prompt)?;
    if let Some(dir) = &a.lora {
        pipe = pipe.with_lora(dir, &dev)?;
    }
    for n in &pipe.notes {
        eprintln!("model: {n}");
    }
    let (w, h, rgb) = read_rgb(&a.image)?;
    let mask = read_mask(&a.mask, &a.image, w, h)?;
    let t = Instant::now();
    let out = pipe.model.inpaint_image(
        &rgb,
        &mask,
        w,
        h,
        a.seed,
        &SampleSettings {
            strength: a.strength,
            steps: a.steps,
            guidance: a.guidance,
            keep_known: true,
        },
        &dev,
    )?;
    write_png(&a.out, w as u32, h as u32, &out.rgb)?;
    println!(
        "wrote {} ({} DDIM steps from t = {} (noise level {:.3}) in {:.1} s)",
        a.out.display(),
        a.steps,
        out.t_start,
        out.noise_level,
        t.elapsed().as_secs_f64()
    );
    Ok(())
}

/// A mask image as `[h, w]` (white > 0.5: 1), of the size `w x h` of `image`.
fn read_mask(path: &Path, image: &Path, w: usize, h: usize) -> anyhow::Result<Vec<f32>> {
    let (mw, mh, m) = read_rgb(path)?;
    if (mw, mh) != (w, h) {
        bail!(
            "{} is {mw}x{mh} but {} is {w}x{h}",
            path.display(),
            image.display()
        );
    }
    Ok(m.chunks(3)
        .map(|p| f32::from((p[0] + p[1] + p[2]) / 3.0 > 0.5))
        .collect())
}

/// `extranerf diffusion enhance`.
fn enhance(ctx: &Context, a: &EnhanceArgs) -> anyhow::Result<()> {
    if !(a.strength > 0.0 && a.strength <= 1.0) || a.steps == 0 {
        bail!(
            "--strength {} must be in (0, 1] and --steps {} at least 1",
            a.strength,
            a.steps
        );
    }
    let (_, dev) = a.backend.device(ctx)?;
    let pipe = extranerf_diffusion::enhancer::load_any(&a.model, a.lora.as_deref(), &dev)?;
    for n in &pipe.notes {
        eprintln!("model: {n}");
    }
    let (w, h, rgb) = read_rgb(&a.image)?;
    let mask = a
        .mask
        .as_ref()
        .map(|m| read_mask(m, &a.image, w, h))
        .transpose()?;
    let t = Instant::now();
    let out = pipe.model.enhance_image(
        &rgb,
        mask.as_deref(),
        w,
        h,
        a.seed,
        &SampleSettings {
            strength: a.strength,
            steps: a.steps,
            guidance: 1.0,
            keep_known: false,
        },
        &dev,
    )?;
    write_png(&a.out, w as u32, h as u32, &out.rgb)?;
    let change = rgb
        .iter()
        .zip(&out.rgb)
        .map(|(x, y)| f64::from((x - y).abs()))
        .sum::<f64>()
        / rgb.len() as f64;
    println!(
        "wrote {} ({} DDIM steps from t = {} (noise level {:.3}) in {:.1} s; mean absolute change {change:.4})",
        a.out.display(),
        a.steps,
        out.t_start,
        out.noise_level,
        t.elapsed().as_secs_f64()
    );
    Ok(())
}

/// `extranerf diffusion finetune`.
fn finetune(ctx: &Context, a: &FinetuneArgs) -> anyhow::Result<()> {
    let _lock = hold(&a.out)?;
    if !a.state.resume {
        refuse_to_replace(&a.out.join(lora::LORA_CONFIG), &a.out, "LoRA adapters")?;
    }
    let ck = a.state.checkpointing(
        &a.out,
        serde_json::json!({
            "model": std::fs::canonicalize(&a.model).unwrap_or_else(|_| a.model.clone()),
            "rank": a.rank,
            "alpha": a.alpha,
            "convs": a.convs,
            "prompt": a.prompt,
        }),
    )?;
    let (_, dev) = a.backend.device(ctx)?;
    let ad = dev.clone().autodiff();
    ad.seed(a.seed);
    let pipe = Pipeline::load(&a.model, &ad, &a.prompt)?;
    for n in &pipe.notes {
        eprintln!("model: {n}");
    }
    if a.rank == 0 {
        bail!("--rank must be at least 1");
    }
    let split = a.split.unwrap_or_else(|| SplitKind::default_for(&a.scene));
    let views = load_views(&a.scene, split, a.factor, a.downscale)?;
    let m = pipe.model.size_multiple();
    if a.crop == 0 || !a.crop.is_multiple_of(m) {
        bail!(
            "--crop {} must be a positive multiple of {m} for this model",
            a.crop
        );
    }
    if let Some(v) = views.iter().find(|v| v.width < a.crop || v.height < a.crop) {
        bail!(
            "view {} is {}x{}, smaller than --crop {} (lower --crop or --downscale)",
            v.name,
            v.width,
            v.height,
            a.crop
        );
    }
    let mut images = Vec::new();
    let mut with_masks = 0;
    for v in &views {
        let mut im = TrainImage::new(v.width, v.height, v.rgb.clone());
        if let Some(dir) = &a.masks {
            let candidates = [
                dir.join(format!("trainmask_{:03}_mask.png", v.index)),
                dir.join(format!("{}_mask.png", v.name)),
            ];
            match candidates.iter().find(|p| p.is_file()) {
                Some(p) => {
                    let (mw, mh, m) = read_rgb(p)?;
                    // Nearest resampling to the view (the visibility maps may be smaller), but
                    // only of a mask with the view's shape: another aspect is another view.
                    let (sx, sy) = (mw as f64 / v.width as f64, mh as f64 / v.height as f64);
                    if (sx / sy - 1.0).abs() > 0.02 {
                        bail!(
                            "{} is {mw}x{mh}, which does not have the aspect of view {} ({}x{} after --downscale): a mask of another view or scene?",
                            p.display(),
                            v.name,
                            v.width,
                            v.height
                        );
                    }
                    if (mw, mh) != (v.width, v.height) {
                        eprintln!(
                            "{}: {mw}x{mh} resampled to the view's {}x{}",
                            p.display(),
                            v.width,
                            v.height
                        );
                    }
                    let mut mask = vec![0f32; v.width * v.height];
                    for y in 0..v.height {
                        for x in 0..v.width {
                            let (sx, sy) = (x * mw / v.width, y * mh / v.height);
                            let k = 3 * (sy * mw + sx);
                            if (m[k] + m[k + 1] + m[k + 2]) / 3.0 > 0.5 {
                                mask[y * v.width + x] = 1.0;
                            }
                        }
                    }
                    im.masks.push(mask);
                    with_masks += 1;
                }
                None => eprintln!(
                    "no pseudo mask for {} ({} or {}): random masks only",
                    v.name,
                    candidates[0].display(),
                    candidates[1].display()
                ),
            }
        }
        images.push(im);
    }
    eprintln!(
        "fine-tuning on {} views ({with_masks} with pseudo-disocclusion masks), LoRA rank {}",
        views.len(),
        a.rank
    );
    let mut cfg = LoraConfig::attention(a.rank, a.alpha);
    if a.convs {
        cfg.target_modules.push("conv1".into());
        cfg.target_modules.push("conv2".into());
    }
    let unet = lora::apply(pipe.model.unet, &cfg, &ad)?;
    let (lp, _) = lora::params_by_kind(&unet);
    eprintln!("{} adapter tensors; base frozen", lp.len());
    let schedule = pipe.model.schedule.clone();
    let codec = pipe.model.codec.no_grad();
    let (model, curve) = train::train(
        Trainable {
            unet,
            tokens: pipe.model.tokens,
        },
        &codec,
        &schedule,
        &images,
        &Augment {
            crop: a.crop,
            ..Augment::default()
        },
        &TrainSettings {
            steps: a.steps,
            batch: a.batch,
            lr: a.lr,
            token_lr: a.token_lr,
            seed: a.seed,
            log_every: a.state.log_every,
            ..TrainSettings::default()
        },
        &ad,
        Some(&ck),
        &mut progress_printer("finetune"),
    )?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    lora::save(&a.out, &model.unet, &cfg)?;
    if a.token_lr > 0.0 {
        model.tokens.save(&a.out.join("text_encoder"))?;
    }
    write_curve(&a.out, &curve, "LoRA fine-tuning: diffusion loss")?;
    println!(
        "wrote {} (adapters), loss.csv, loss.svg; final loss {:.5}",
        a.out.display(),
        curve.last().map_or(f64::NAN, |c| c.1)
    );
    Ok(())
}

/// `extranerf diffusion init`.
fn init(a: &InitArgs) -> anyhow::Result<()> {
    refuse_to_replace(&a.out.join("model_index.json"), &a.out, "a model")?;
    let dev = Device::flex();
    dev.seed(a.seed);
    let pipe = match a.config {
        InitConfig::Tiny => Pipeline::new(
            UNetConfig::tiny_inpainting(),
            Some(VaeConfig::tiny()),
            SchedulerConfig::default(),
            4,
            &dev,
        )?,
        InitConfig::Pixel => Pipeline::new(
            prior_unet_config(&[32, 64, 96], 64)?,
            None,
            prior_scheduler(Prediction::V),
            4,
            &dev,
        )?,
        InitConfig::Sd15Inpainting => Pipeline::new(
            UNetConfig::sd15_inpainting(),
            Some(VaeConfig::sd()),
            SchedulerConfig::default(),
            8,
            &dev,
        )?,
    };
    pipe.save(&a.out)?;
    println!(
        "wrote {} ({}; U-Net {} parameters, randomly initialised, seed {})",
        a.out.display(),
        a.config
            .to_possible_value()
            .map(|v| v.get_name().to_string())
            .unwrap_or_default(),
        pipe.model.unet.num_params(),
        a.seed
    );
    Ok(())
}

struct BenchRow {
    config: &'static str,
    backend: &'static str,
    what: &'static str,
    warmup_s: f64,
    it_s: f64,
    gflop: f64,
}

fn time_it(iters: usize, mut f: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<(f64, f64)> {
    let t = Instant::now();
    f()?;
    let warm = t.elapsed().as_secs_f64();
    let t = Instant::now();
    for _ in 0..iters {
        f()?;
    }
    Ok((warm, t.elapsed().as_secs_f64() / iters.max(1) as f64))
}

/// `extranerf bench diffusion`.
pub fn bench(ctx: &Context, a: &BenchDiffusionArgs) -> anyhow::Result<()> {
    let medium = UNetConfig {
        sample_size: 32,
        block_out_channels: vec![64, 128, 256],
        down_block_types: vec![CROSS_ATTN_DOWN.into(), CROSS_ATTN_DOWN.into(), DOWN.into()],
        up_block_types: vec![UP.into(), CROSS_ATTN_UP.into(), CROSS_ATTN_UP.into()],
        layers_per_block: extranerf_diffusion::config::PerBlock::One(2),
        cross_attention_dim: 128,
        attention_head_dim: extranerf_diffusion::config::PerBlock::One(4),
        norm_num_groups: 32,
        ..UNetConfig::tiny_inpainting()
    };
    let mut configs: Vec<(&'static str, UNetConfig, usize)> =
        vec![("tiny 32/64 @16x16", UNetConfig::tiny_inpainting(), 16)];
    if !a.tiny_only {
        configs.push(("medium 64/128/256 @32x32", medium, 32));
    }
    let mut rows = Vec::new();
    for b in &a.backends {
        let backend = match b.as_str() {
            "cpu" => Backend::Cpu,
            "device" => Backend::Device,
            o => bail!("--backends: {o:?} is not cpu or device"),
        };
        let (_, dev) = diffusion_device(ctx, backend)?;
        let bname: &'static str = if backend == Backend::Cpu {
            "cpu (flex)"
        } else {
            "device (wgpu)"
        };
        for (name, cfg, side) in &configs {
            dev.seed(1);
            let unet = UNet2DConditionModel::new(cfg, &dev)?;
            let (n, s) = (2usize, 8usize);
            let macs = unet.macs(*side, *side, s) as f64 * n as f64;
            let x = seeded_noise([n, 9, *side, *side], 1, &dev);
            let ctx_t = seeded_noise([n, s, cfg.cross_attention_dim, 1], 2, &dev).reshape([
                n,
                s,
                cfg.cross_attention_dim,
            ]);
            let (warm, t) = time_it(a.iters, || {
                let y = unet.forward(x.clone(), &[500.0, 20.0], &ctx_t);
                let _ = y.sum().into_scalar::<f32>();
                Ok(())
            })?;
            rows.push(BenchRow {
                config: name,
                backend: bname,
                what: "forward (batch 2)",
                warmup_s: warm,
                it_s: t,
                gflop: 2.0 * macs / 1e9,
            });
            let ad = dev.clone().autodiff();
            ad.seed(1);
            let unet_ad = UNet2DConditionModel::new(cfg, &ad)?;
            let xa = seeded_noise([n, 9, *side, *side], 1, &ad);
            let ca = seeded_noise([n, s, cfg.cross_attention_dim, 1], 2, &ad).reshape([
                n,
                s,
                cfg.cross_attention_dim,
            ]);
            let (warm, t) = time_it(a.iters, || {
                let y = unet_ad.forward(xa.clone(), &[500.0, 20.0], &ca);
                let g = y.powi_scalar(2).mean().backward();
                let w = unet_ad.conv_in.weight.val().grad(&g);
                if let Some(w) = w {
                    let _ = w.sum().into_scalar::<f32>();
                }
                Ok(())
            })?;
            rows.push(BenchRow {
                config: name,
                backend: bname,
                what: "forward+backward",
                warmup_s: warm,
                it_s: t,
                gflop: 3.0 * 2.0 * macs / 1e9,
            });
            // One LoRA fine-tuning step (rank 4 on attention; base frozen): forward, backward
            // and AdamW on the adapters.
            let lunet = lora::apply(
                UNet2DConditionModel::new(cfg, &ad)?,
                &LoraConfig::attention(4, 4.0),
                &ad,
            )?;
            let mut model = Some(Trainable {
                unet: lunet,
                tokens: LearnedTokens::new(s, cfg.cross_attention_dim, &ad),
            });
            let sched = extranerf_diffusion::scheduler::Schedule::new(&SchedulerConfig::default())
                .map_err(anyhow::Error::msg)?;
            // A small VAE with SD's factor 8, so the latents are side x side.
            let vae = extranerf_diffusion::vae::AutoencoderKL::new(
                &VaeConfig {
                    block_out_channels: vec![16; 4],
                    down_block_types: vec!["DownEncoderBlock2D".into(); 4],
                    up_block_types: vec!["UpDecoderBlock2D".into(); 4],
                    ..VaeConfig::tiny()
                },
                &ad,
            )?
            .no_grad();
            let codec = Codec::Vae(vae);
            let px = side * 8;
            let images = vec![TrainImage::new(
                px,
                px,
                (0..3 * px * px).map(|i| (i % 11) as f32 / 11.0).collect(),
            )];
            let aug = Augment {
                crop: px,
                ..Augment::default()
            };
            let settings = TrainSettings {
                steps: 1,
                batch: n,
                log_every: 1,
                ..TrainSettings::default()
            };
            let (warm, t) = time_it(a.iters, || {
                let m = model.take().context("model")?;
                let (m, _) = train::train(
                    m,
                    &codec,
                    &sched,
                    &images,
                    &aug,
                    &settings,
                    &ad,
                    None,
                    &mut |_| {},
                )?;
                model = Some(m);
                Ok(())
            })?;
            rows.push(BenchRow {
                config: name,
                backend: bname,
                what: "LoRA step (VAE encode + fwd/bwd + AdamW)",
                warmup_s: warm,
                it_s: t,
                gflop: f64::NAN,
            });
        }
    }
    let sd = UNet2DConditionModel::new(&UNetConfig::sd15_inpainting(), &Device::flex())?;
    let sd_flops = 2.0 * sd.macs(64, 64, 77) as f64;
    println!(
        "{:<26} {:<14} {:<42} {:>10} {:>10} {:>9} {:>9}",
        "config", "backend", "what", "warm-up s", "s/it", "it/s", "GFLOP/s"
    );
    let mut json = Vec::new();
    for r in &rows {
        println!(
            "{:<26} {:<14} {:<42} {:>10.2} {:>10.4} {:>9.2} {:>9.2}",
            r.config,
            r.backend,
            r.what,
            r.warmup_s,
            r.it_s,
            1.0 / r.it_s,
            r.gflop / r.it_s
        );
        json.push(serde_json::json!({
            "config": r.config, "backend": r.backend, "what": r.what,
            "warmup_s": r.warmup_s, "s_per_it": r.it_s, "it_per_s": 1.0 / r.it_s,
            "gflop_per_it": if r.gflop.is_finite() { Some(r.gflop) } else { None },
            "gflop_per_s": if r.gflop.is_finite() { Some(r.gflop / r.it_s) } else { None },
        }));
    }
    println!(
        "SD-1.5 inpainting U-Net ({} parameters) at 64x64 latents, 77 tokens: {:.1} GFLOP per forward, {:.1} GFLOP per training step (3x), {:.0} GFLOP per 10-step DDIM visit with guidance (2x batch)",
        sd.num_params(),
        sd_flops / 1e9,
        3.0 * sd_flops / 1e9,
        20.0 * sd_flops / 1e9
    );
    if let Some(p) = &a.json {
        write_json(
            p,
            &serde_json::json!({
                "device": ctx.info().name,
                "rows": json,
                "sd15_inpainting_64x64": {"parameters": sd.num_params(), "gflop_forward": sd_flops / 1e9},
            }),
        )?;
        println!("wrote {}", p.display());
    }
    Ok(())
}
