//! `extranerf extrapolate` (the ExtraNeRF pipeline) and `extranerf eval` on its run folders.

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use extranerf_diffusion::device::Backend;
use extranerf_diffusion::enhancer::{EnhancerOutput, EnhancerSpec};
use extranerf_extrapolate::eval::inception::{default_weights as default_inception, Inception};
use extranerf_extrapolate::eval::{compare, KidEval, KidSpec};
use extranerf_extrapolate::inpaint::DiffusionSpec;
use extranerf_extrapolate::inpaint::InpainterKind;
use extranerf_extrapolate::rounds::Stage2Spec;
use extranerf_extrapolate::run::{extrapolate as run_pipeline, Options};
use extranerf_extrapolate::stage::VirtualSpec;
use extranerf_extrapolate::stage3::{Stage3Enhancer, Stage3Gate, Stage3Spec};
use extranerf_extrapolate::stages::flythrough::DEFAULT_DOWNSCALE;
use extranerf_extrapolate::stages::{BaseSpec, FlythroughSpec, FrameSize};
use extranerf_extrapolate::visibility::VisSettings;
use extranerf_gpu::Context;
use extranerf_nerf::cameras::Trajectory;
use extranerf_nerf::demo::GT_VISIBILITY_DIR;
use extranerf_nerf::metrics::{Lpips, LpipsNet};
use extranerf_nerf::train::{default_lpips_dir, Reporter};

use crate::args::SplitArgs;
use crate::report::{Console, Logged};
use crate::visibility::Measure;

/// `extrapolate --trajectory`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrajectoryArg {
    /// Translated outward in the rig's plane.
    Outward,
    /// A widened LLFF spiral looking at the focus point.
    Spiral,
    /// Turned about the up axis beyond the captured yaw.
    Rotate,
}

impl From<TrajectoryArg> for Trajectory {
    fn from(t: TrajectoryArg) -> Trajectory {
        match t {
            TrajectoryArg::Outward => Trajectory::Outward,
            TrajectoryArg::Spiral => Trajectory::Spiral,
            TrajectoryArg::Rotate => Trajectory::Rotate,
        }
    }
}

/// Arguments of `extranerf extrapolate`.
#[derive(clap::Args, Debug)]
pub struct ExtrapolateArgs {
    /// Scene: an LLFF folder or a transforms.json scene (not needed with --base).
    #[arg(long, value_name = "DIR", required_unless_present_any = ["base", "resume"])]
    scene: Option<PathBuf>,
    #[command(flatten)]
    views: SplitArgs,
    /// Run folder: extrapolate.json (the manifest), base/, visibility/, stage2-NAME/,
    /// stage3-data/, stage3-enhancer/, stage3-NAME/, flythrough/, extrapolate.log.
    #[arg(long, value_name = "RUN")]
    out: PathBuf,
    /// Reuse a trained BaseNeRF (a run folder of `extranerf train`) instead of training one;
    /// its scene and split are used.
    #[arg(long, value_name = "RUN")]
    base: Option<PathBuf>,
    /// Depth targets of a new BaseNeRF: auto, sparse, mvs, capture, none or a folder of dense
    /// maps, as
    /// `train --depth` (MVS depth is cached in RUN/base/depth_mvs and read again by the stages
    /// that train on the captured views) [default: auto].
    #[arg(long, value_name = "auto|sparse|mvs|capture|none|DIR", conflicts_with_all = ["depth_dir", "base"])]
    depth: Option<extranerf_nerf::run::DepthRequest>,
    /// The same as --depth DIR.
    #[arg(long, value_name = "DIR", conflicts_with = "base")]
    depth_dir: Option<PathBuf>,
    /// Training seconds of a new BaseNeRF (`train --budget`).
    #[arg(long, default_value_t = 900.0, value_name = "SECONDS")]
    base_budget: f64,
    /// Inpainters, one stage-2 variant each (comma-separated): harmonic, exemplar, hybrid,
    /// diffusion (needs --diffusion-model; with --diffusion-lora's adapters when given),
    /// diffusion-base (the same model without the adapters: the un-fine-tuned ablation row).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "harmonic")]
    inpainter: Vec<InpainterKind>,
    /// The diffusion inpainter's model: a diffusers inpainting folder (Stable Diffusion
    /// inpainting when you have its weights, or `extranerf diffusion prior`'s model).
    #[arg(long, value_name = "DIR")]
    diffusion_model: Option<PathBuf>,
    /// LoRA adapters for that model (`extranerf diffusion finetune`).
    #[arg(long, value_name = "DIR")]
    diffusion_lora: Option<PathBuf>,
    /// DDIM steps per inpainting (ExtraNeRF: about 10).
    #[arg(long, default_value_t = 10)]
    diffusion_steps: usize,
    /// burn backend of the diffusion inpainter and the enhancer: auto (the engine's device, or burn's CPU
    /// backend on a CPU Vulkan driver such as lavapipe), device or cpu.
    #[arg(long, value_enum, default_value_t = Backend::Auto)]
    diffusion_backend: Backend,
    /// Virtual views.
    #[arg(long = "virtual", default_value_t = 8, value_name = "N")]
    virtual_views: usize,
    /// Path of the virtual cameras.
    #[arg(long, value_enum, default_value = "spiral")]
    trajectory: TrajectoryArg,
    /// How far beyond the rig the virtual cameras go (1: its edge).
    #[arg(long, default_value_t = 1.5)]
    range: f64,
    /// Divide the training resolution by this for the virtual views and the visibility maps.
    #[arg(long, default_value_t = 2)]
    virtual_downscale: u32,
    /// Stage-2 rounds over the virtual views.
    #[arg(long, default_value_t = Stage2Spec::default().rounds)]
    rounds: u32,
    /// Training steps per round.
    #[arg(long, default_value_t = Stage2Spec::default().steps_per_round)]
    steps_per_round: u32,
    /// Fraction of each batch's rays drawn from the virtual views.
    #[arg(long, default_value_t = Stage2Spec::default().virtual_fraction)]
    virtual_fraction: f32,
    /// Learning rate of the stage-2 steps.
    #[arg(long, default_value_t = Stage2Spec::default().lr)]
    stage2_lr: f32,
    /// Weight of a virtual view's seen pixels relative to its inpainted ones (0: only the
    /// inpainted pixels supervise the field; 1: the whole view, as the paper's loss reads).
    #[arg(long, default_value_t = Stage2Spec::default().visible_weight)]
    visible_weight: f32,
    /// Do not reproject earlier fills of a round into later views (each view is filled on
    /// its own).
    #[arg(long)]
    no_reproject: bool,
    /// Pixels whose seen share (visibility over opacity) is below this are inpainted.
    #[arg(long, default_value_t = VisSettings::default().threshold)]
    threshold: f32,
    /// Which transmittance the visibility stage measures: relative to the pixel ray's own
    /// (robust to surfaces rendered as semi-transparent shells) or absolute (the paper).
    #[arg(long, value_enum, default_value_t = Measure::Relative)]
    visibility_measure: Measure,
    /// Seed of the inpainters.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Frames of the fly-through along the virtual trajectory, rendered from the BaseNeRF and
    /// each variant into RUN/flythrough/NAME (PNG frames), then put side by side, each
    /// labelled, into RUN/flythrough/flythrough.mp4 (H.264, which browsers play); 0: none.
    #[arg(long, default_value_t = FlythroughSpec::default().frames, value_name = "FRAMES")]
    flythrough: u32,
    /// Divide the virtual views' resolution by this for each field's fly-through frames.
    #[arg(long, default_value_t = DEFAULT_DOWNSCALE)]
    flythrough_downscale: u32,
    /// Each field's fly-through frames this many pixels wide instead (the height keeps the
    /// views' aspect); the video is the fields side by side, at most 4 to a row.
    #[arg(long, value_name = "PIXELS", conflicts_with = "flythrough_downscale")]
    flythrough_width: Option<u32>,
    /// Frames per second of the fly-through video.
    #[arg(long, default_value_t = FlythroughSpec::default().fps)]
    flythrough_fps: f64,
    /// Stop after stage 2 (no enhancer, no stage 3).
    #[arg(long)]
    no_stage3: bool,
    /// Stage 3: rounds of the inpainting-supervised field whose renders of the training views
    /// train the enhancer.
    #[arg(long, default_value_t = Stage3Spec::default().data_rounds)]
    data_rounds: u32,
    /// Stage 3: training steps per data round.
    #[arg(long, default_value_t = Stage3Spec::default().data_steps_per_round)]
    data_steps_per_round: u32,
    /// Stage 3: step counts of a fresh field whose renders of the training views (the blur of
    /// an under-fitted field) also train the enhancer; `none` for none.
    #[arg(long, value_delimiter = ',', default_value = "100,400", value_parser = parse_checkpoint)]
    fresh_checkpoints: Vec<Option<u32>>,
    /// Stage 3: a Stable Diffusion inpainting folder (diffusers layout) to adapt into the
    /// enhancer with LoRA; without it the enhancer is a pixel-space U-Net trained from scratch
    /// on the scene.
    #[arg(long, value_name = "DIR")]
    enhancer_model: Option<PathBuf>,
    /// Stage 3: channels per level of the from-scratch enhancer.
    #[arg(long, value_delimiter = ',', default_value = "32,64,96")]
    enhancer_channels: Vec<usize>,
    /// Stage 3: what the from-scratch enhancer predicts: `v`, as the scene prior, or
    /// `residual`, the photo's difference from the render it is shown (an untrained enhancer
    /// is the identity; on fern it added no pixel noise but shifted colours, see docs/results.md).
    #[arg(long, value_enum, default_value_t = EnhancerOutput::default())]
    enhancer_output: EnhancerOutput,
    /// Stage 3: LoRA rank (with --enhancer-model).
    #[arg(long, default_value_t = EnhancerSpec::default().rank)]
    enhancer_rank: usize,
    /// Stage 3: the enhancer's optimiser steps.
    #[arg(long, default_value_t = EnhancerSpec::default().steps)]
    enhancer_steps: usize,
    /// Stage 3: crops per enhancer step.
    #[arg(long, default_value_t = EnhancerSpec::default().batch)]
    enhancer_batch: usize,
    /// Stage 3: the enhancer's crop side (a multiple of its size step, at most the training
    /// views' side at the virtual views' scale).
    #[arg(long, default_value_t = EnhancerSpec::default().crop)]
    enhancer_crop: usize,
    /// Stage 3: the enhancer's AdamW learning rate.
    #[arg(long, default_value_t = EnhancerSpec::default().lr)]
    enhancer_lr: f64,
    /// Stage 3: rounds over the virtual views (render, enhance, train).
    #[arg(long, default_value_t = Stage3Spec::default().rounds)]
    stage3_rounds: u32,
    /// Stage 3: training steps per round (the paper: 500 in all).
    #[arg(long, default_value_t = Stage3Spec::default().steps_per_round)]
    stage3_steps_per_round: u32,
    /// Stage 3: the noise strength the renders are enhanced from (the loss weight is
    /// sqrt(1 - t^2)).
    #[arg(long, default_value_t = Stage3Spec::default().t)]
    stage3_t: f32,
    /// Stage 3: colour anchoring, a box-blur radius in pixels (0: off). The enhanced views
    /// keep only their detail above that blur, on the render's own blurred colours, which
    /// removes an enhancer's colour drift.
    #[arg(long, default_value_t = Stage3Spec::default().anchor_radius)]
    stage3_anchor: usize,
    /// Stage 3: smoothing of the enhancement, a box-blur radius in pixels (0: off). The
    /// targets keep only the enhancer's change below that blur, on the render's own detail
    /// (render + blur(enhanced - render)), which removes pixel noise that an enhancer adds
    /// differently in every view. Applied after --stage3-anchor.
    #[arg(long, default_value_t = Stage3Spec::default().smooth_radius)]
    stage3_smooth: usize,
    /// Stage 3: weight of the virtual views' seen pixels relative to the not-visible ones (1:
    /// the whole enhanced view, as the paper; 0: only where no input camera saw).
    #[arg(long, default_value_t = Stage3Spec::default().visible_weight)]
    stage3_visible_weight: f32,
    /// Stage 3: core of the virtual views' colour loss (0: the paper's plain L1). Above 0,
    /// smooth L1: per-channel errors below the core are penalised quadratically, so a seen
    /// pixel whose target is within noise of the render pulls with a gradient that vanishes
    /// with the error rather than with the full size of a real error's.
    #[arg(long, default_value_t = Stage3Spec::default().l1_core)]
    stage3_l1_core: f32,
    /// Stage 3: DDIM steps per enhancement.
    #[arg(long, default_value_t = Stage3Spec::default().ddim_steps)]
    stage3_ddim_steps: usize,
    /// Stage 3: fraction of each batch's rays drawn from the virtual views.
    #[arg(long, default_value_t = Stage3Spec::default().virtual_fraction)]
    stage3_virtual_fraction: f32,
    /// Stage 3: learning rate of its steps.
    #[arg(long, default_value_t = Stage3Spec::default().lr)]
    stage3_lr: f32,
    /// Stage 3: what enhances the virtual views: `diffusion`, the enhancer trained on the
    /// scene's corrupted renders (the paper; stages stage3-data and stage3-enhancer), or
    /// `unsharp`, an unsharp mask of the render (no model or training data; it sharpens what
    /// is there and invents nothing)
    #[arg(long, value_enum, default_value_t = Stage3Enhancer::default())]
    stage3_enhancer: Stage3Enhancer,
    /// Stage 3 with `--stage3-enhancer unsharp`: the amount, render + amount * (render -
    /// blur(render))
    #[arg(long, default_value_t = Stage3Spec::default().unsharp_amount)]
    stage3_unsharp_amount: f32,
    /// Stage 3 with `--stage3-enhancer unsharp`: the blur, a box of this radius in pixels
    /// applied twice
    #[arg(long, default_value_t = Stage3Spec::default().unsharp_radius)]
    stage3_unsharp_radius: usize,
    /// Stage 3 with the diffusion enhancer: `check` enhances one corrupted render of each
    /// training view as stage 3 would and runs stage 3 only when that lowers their LPIPS
    /// against the photos (PSNR, raised, where no LPIPS weights load); otherwise the stage-2
    /// field is kept and the log, manifest and `eval` say why. `off`: always run it (the
    /// paper's ablation; runs made before the gate need it to resume)
    #[arg(long, value_enum, default_value_t = Stage3Gate::default())]
    stage3_gate: Stage3Gate,
    /// Folder with lpips_alex_v0.1.safetensors for --stage3-gate (default:
    /// $EXTRANERF_MODELS/lpips, else ../shared/models/lpips)
    #[arg(long, value_name = "DIR")]
    lpips: Option<PathBuf>,
    /// Continue the run in --out: finished stages are skipped, stages 2 and 3 resume after
    /// their last finished round, the enhancer's training at its last save. The settings must
    /// be those it was started with.
    #[arg(long)]
    resume: bool,
    /// With --resume: stages to run again from nothing, comma-separated (e.g.
    /// `stage3-harmonic`); their settings may differ from the recorded ones, and the stages
    /// that read them run again too.
    #[arg(long, value_delimiter = ',', value_name = "STAGE", requires = "resume")]
    redo: Vec<String>,
}

impl ExtrapolateArgs {
    /// Whether burn may run on the engine's own device (the context must then be shareable).
    pub fn needs_wgpu(&self) -> bool {
        (self.inpainter.iter().any(|k| k.uses_diffusion())
            || (!self.no_stage3 && self.stage3_enhancer == Stage3Enhancer::Diffusion))
            && self.diffusion_backend != Backend::Cpu
    }
}

/// A `--fresh-checkpoints` entry: a step count, or `none`.
fn parse_checkpoint(s: &str) -> Result<Option<u32>, String> {
    if s == "none" {
        return Ok(None);
    }
    match s.parse::<u32>() {
        Ok(n) if n > 0 => Ok(Some(n)),
        _ => Err(format!("{s:?}: give positive step counts, or `none`")),
    }
}

/// `extranerf extrapolate`.
pub fn extrapolate(ctx: &Context, a: &ExtrapolateArgs) -> anyhow::Result<()> {
    // A resumed run keeps the depth its BaseNeRF was trained with (runs from before --depth
    // recorded the COLMAP points whatever the scene had).
    let recorded = if a.resume {
        extranerf_extrapolate::manifest::Manifest::load(&a.out)?.map(|m| m.scene)
    } else {
        None
    };
    if let (Some(r), true) = (&recorded, a.depth.is_some() || a.depth_dir.is_some()) {
        anyhow::bail!(
            "--resume keeps the run's depth targets ({}); drop --depth / --depth-dir",
            r.depth_label()
        );
    }
    let scene = match &a.scene {
        Some(dir) if a.base.is_none() => {
            let mut spec = a.views.spec(dir.clone(), false);
            if let Some(r) = &recorded {
                spec.sparse_depth = r.sparse_depth;
                spec.depth_dir = r.depth_dir.clone();
                spec.mvs_depth = r.mvs_depth.clone();
                spec.capture_depth = r.capture_depth;
            } else {
                let loaded = spec.load()?;
                let line = crate::args::depth_request(&a.depth, &a.depth_dir).resolve(
                    &mut spec,
                    &loaded,
                    Default::default(),
                )?;
                eprintln!("{line}");
            }
            Some(spec)
        }
        Some(dir) => Some(a.views.spec(dir.clone(), true)),
        None => None,
    };
    let scene = match (scene, a.resume, &a.base) {
        (None, true, None) => {
            let m =
                extranerf_extrapolate::manifest::Manifest::load(&a.out)?.with_context(|| {
                    format!("--resume: {} holds no extrapolate run", a.out.display())
                })?;
            Some(m.scene)
        }
        (s, _, _) => s,
    };
    let o = Options {
        out: a.out.clone(),
        scene,
        base: BaseSpec {
            from: a.base.clone(),
            budget: a.base_budget,
        },
        virt: VirtualSpec {
            trajectory: a.trajectory.into(),
            count: a.virtual_views,
            range: a.range,
            downscale: a.virtual_downscale,
        },
        vis: VisSettings {
            threshold: a.threshold,
            measure: a.visibility_measure.into(),
            ..VisSettings::default()
        },
        stage2: Stage2Spec {
            rounds: a.rounds,
            steps_per_round: a.steps_per_round,
            virtual_fraction: a.virtual_fraction,
            lr: a.stage2_lr,
            reproject: !a.no_reproject,
            visible_weight: a.visible_weight,
            seed: a.seed,
            ..Stage2Spec::default()
        },
        inpainters: a.inpainter.clone(),
        diffusion: a.diffusion_model.as_ref().map(|m| DiffusionSpec {
            model: m.clone(),
            lora: a.diffusion_lora.clone(),
            steps: a.diffusion_steps,
            backend: a.diffusion_backend,
        }),
        flythrough: FlythroughSpec {
            frames: a.flythrough,
            size: match a.flythrough_width {
                Some(w) => FrameSize::Width(w),
                None => FrameSize::Downscale(a.flythrough_downscale),
            },
            fps: a.flythrough_fps,
        },
        stage3: (!a.no_stage3).then(|| Stage3Spec {
            data_rounds: a.data_rounds,
            data_steps_per_round: a.data_steps_per_round,
            base_checkpoints: a.fresh_checkpoints.iter().flatten().copied().collect(),
            enhancer: EnhancerSpec {
                base_model: a.enhancer_model.clone(),
                channels: a.enhancer_channels.clone(),
                rank: a.enhancer_rank,
                steps: a.enhancer_steps,
                batch: a.enhancer_batch,
                crop: a.enhancer_crop,
                lr: a.enhancer_lr,
                seed: a.seed,
                output: a.enhancer_output,
                ..EnhancerSpec::default()
            },
            rounds: a.stage3_rounds,
            steps_per_round: a.stage3_steps_per_round,
            t: a.stage3_t,
            anchor_radius: a.stage3_anchor,
            smooth_radius: a.stage3_smooth,
            l1_core: a.stage3_l1_core,
            visible_weight: a.stage3_visible_weight,
            ddim_steps: a.stage3_ddim_steps,
            virtual_fraction: a.stage3_virtual_fraction,
            lr: a.stage3_lr,
            seed: a.seed,
            backend: a.diffusion_backend,
            enhance: a.stage3_enhancer,
            unsharp_amount: a.stage3_unsharp_amount,
            unsharp_radius: a.stage3_unsharp_radius,
            gate: a.stage3_gate,
            lpips: a.lpips.clone(),
        }),
        resume: a.resume,
        redo: a.redo.clone(),
    };
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let log = a.out.join("extrapolate.log");
    let file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log)
        .with_context(|| format!("opening {}", log.display()))?;
    let mut rep = Logged {
        inner: Console::new(),
        file,
    };
    let m = run_pipeline(ctx, &o, &mut rep)?;
    for s in &m.stages {
        rep.note(&format!("{:>20}: {:.1} s", s.name, s.seconds));
    }
    rep.note(&format!(
        "done; `extranerf eval {}` writes the comparison table",
        a.out.display()
    ));
    Ok(())
}

/// `extranerf eval`'s KID flags (extrapolate runs).
#[derive(clap::Args, Debug, Clone)]
pub struct KidArgs {
    /// Leave KID out (it runs Inception-v3 on every held-out view and crop of every variant:
    /// about 0.5 s an image on two cores).
    #[arg(long)]
    no_kid: bool,
    /// Inception-v3 weights (default: $EXTRANERF_INCEPTION, else
    /// $EXTRANERF_MODELS/inception/inception_fid.safetensors, else
    /// ../shared/models/inception/inception_fid.safetensors; tools/fetch_inception.sh makes it).
    #[arg(long)]
    inception: Option<PathBuf>,
    /// Patch KID: crops in all, spread evenly over the held-out views.
    #[arg(long, default_value_t = KidSpec::default().crops)]
    kid_crops: usize,
    /// Patch KID: the crops' side in pixels (at most the views' smaller side).
    #[arg(long, default_value_t = KidSpec::default().crop_size)]
    kid_crop_size: u32,
    /// Patch KID: share of each crop that the not-visible mask must cover.
    #[arg(long, default_value_t = KidSpec::default().min_fraction)]
    kid_min_fraction: f64,
    /// Subsets averaged (both protocols).
    #[arg(long, default_value_t = KidSpec::default().subsets)]
    kid_subsets: usize,
    /// Patch KID: crops per subset.
    #[arg(long, default_value_t = KidSpec::default().subset_size)]
    kid_subset_size: usize,
    /// Seed of the crops and subsets.
    #[arg(long, default_value_t = KidSpec::default().seed)]
    kid_seed: u64,
    /// burn backend of the Inception network: auto (the engine's device, or burn's CPU backend
    /// on a CPU Vulkan driver such as lavapipe), device or cpu.
    #[arg(long, value_enum, default_value_t = Backend::Auto)]
    kid_backend: Backend,
}

impl Default for KidArgs {
    fn default() -> Self {
        let d = KidSpec::default();
        KidArgs {
            no_kid: false,
            inception: None,
            kid_crops: d.crops,
            kid_crop_size: d.crop_size,
            kid_min_fraction: d.min_fraction,
            kid_subsets: d.subsets,
            kid_subset_size: d.subset_size,
            kid_seed: d.seed,
            kid_backend: Backend::Auto,
        }
    }
}

impl KidArgs {
    /// Whether the network may run on the engine's device (the context must then be shared).
    pub fn on_device(&self) -> bool {
        !self.no_kid && self.kid_backend != Backend::Cpu
    }

    fn spec(&self) -> anyhow::Result<KidSpec> {
        if !(0.0..=1.0).contains(&self.kid_min_fraction) {
            anyhow::bail!(
                "--kid-min-fraction {} is not a share in [0, 1]",
                self.kid_min_fraction
            );
        }
        if self.kid_crop_size == 0 || self.kid_subsets == 0 || self.kid_subset_size < 2 {
            anyhow::bail!(
                "--kid-crop-size and --kid-subsets must be positive and --kid-subset-size at least 2"
            );
        }
        Ok(KidSpec {
            crops: self.kid_crops,
            crop_size: self.kid_crop_size,
            min_fraction: self.kid_min_fraction,
            subsets: self.kid_subsets,
            subset_size: self.kid_subset_size,
            seed: self.kid_seed,
            ..KidSpec::default()
        })
    }
}

/// `extranerf eval` on an extrapolate run: writes RUN/eval.json, RUN/eval.md and
/// RUN/report.html.
pub fn eval_run(
    ctx: &Context,
    run: &Path,
    lpips: Option<&Path>,
    k: &KidArgs,
    truth_masks: Option<&Path>,
) -> anyhow::Result<()> {
    let dir = lpips.map(PathBuf::from).unwrap_or_else(default_lpips_dir);
    let lp = match Lpips::load(&dir.join("lpips_alex_v0.1.safetensors"), LpipsNet::Alex) {
        Ok(l) => Some(l),
        Err(e) => {
            eprintln!("no LPIPS in the table ({e})");
            None
        }
    };
    let spec = k.spec()?;
    // Exact visibility: the flag's folder, else the scene's own where it has one.
    let truth_masks = match truth_masks {
        Some(d) => Some(d.to_path_buf()),
        None => extranerf_extrapolate::manifest::Manifest::load(run)?
            .map(|m| m.scene.dir.join(GT_VISIBILITY_DIR))
            .filter(|d| d.is_dir()),
    };
    let net = if k.no_kid {
        None
    } else {
        let (backend, dev) = extranerf_diffusion::device::diffusion_device(ctx, k.kid_backend)?;
        let path = k.inception.clone().unwrap_or_else(default_inception);
        match Inception::load(&path, &dev) {
            Ok(n) => {
                eprintln!(
                    "KID: Inception-v3 from {} on {}",
                    path.display(),
                    backend.name()
                );
                Some(n)
            }
            Err(e) => {
                eprintln!("no KID in the table ({e:#})");
                None
            }
        }
    };
    let kid = net.as_ref().map(|net| KidEval { net, spec });
    let mut rep = Console::new();
    let t = compare(
        run,
        lp.as_ref(),
        kid.as_ref(),
        truth_masks.as_deref(),
        &mut rep,
    )?;
    let report = extranerf_extrapolate::eval::write_table(run, &t)?;
    let views = if t.held_out {
        "held-out views"
    } else {
        "no held-out view (the split trains on every view); scored: the training views"
    };
    println!("{views} {:?}\n\n{}", t.views, t.markdown());
    eprintln!(
        "wrote {}, eval.md and {}",
        run.join("eval.json").display(),
        report.display()
    );
    Ok(())
}
