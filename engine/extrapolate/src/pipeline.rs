//! `extranerf extrapolate`: the ExtraNeRF pipeline as stages over one run folder.
//!
//! - [`BaseStage`]: the BaseNeRF (trained into `RUN/base` under a time budget, or an existing
//!   run reused with `--base`);
//! - [`VisibilityStage`]: virtual cameras beyond the rig, and the visibility of the virtual and
//!   the held-out views against the training cameras (`RUN/visibility`);
//! - [`InpaintStage`]: the stage-2 loop for one inpainter (`RUN/stage2-NAME`): rounds of
//!   render, mask, inpaint and train on the virtual views mixed with the captured ones;
//! - [`FlythroughStage`]: frames along the virtual trajectory and a looping GIF, for the
//!   BaseNeRF and each variant (`RUN/flythrough`).
//!
//! - stage 3 ([`crate::stage3`]): the enhancer's training data (`RUN/stage3-data`), the
//!   enhancer (`RUN/stage3-enhancer`), and per stage-2 variant the enhancement loop
//!   (`RUN/stage3-NAME`).
//!
//! Each stage records its resolved
//! configuration in `extrapolate.json` ([`Manifest`]); a resumed run skips the stages done,
//! refuses one asked for with other settings, and continues an unfinished stage 2 from its
//! last finished round.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context as _};
use extranerf_gpu::Context;
use extranerf_nerf::cameras::{virtual_cameras, write_transforms, Trajectory};
use extranerf_nerf::data::{load_image, Camera, Image};
use extranerf_nerf::demo::{demo_seen, DEMO_MARKER};
use extranerf_nerf::render::march::MarchCuts;
use extranerf_nerf::render::visibility::{mask_all_but, VisibilityMap};
use extranerf_nerf::renderer::{March, Nerf};
use extranerf_nerf::run::{
    load_checkpoint, save_checkpoint, training_views_in, write_png, Checkpoint, RunConfig,
    SceneSpec,
};
use extranerf_nerf::safetensors::{SafeTensors, Tensor};
use extranerf_nerf::trainer::{TrainConfig, Trainer};
use extranerf_nerf::views::{TrainData, View, ViewKind, ViewSampling};
use extranerf_prims::Prims;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::base::BaseField;
use crate::driver::{fit_budget, train_loop, Progress, Reporter, TrainRun, Unit};
use crate::inpaint::{Fill, InpainterKind, Source, Target};
use crate::manifest::{Manifest, StageRecord};
use crate::visibility::{FieldVisibility, VisSettings};
use extranerf_nerf::image_ops::{downscale_image, grey_to_rgb};
use extranerf_nerf::trainer::StepStats;

/// Where the BaseNeRF comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BaseSpec {
    /// An existing run folder to reuse (None: train one into `RUN/base`).
    pub from: Option<PathBuf>,
    /// Training seconds for a new BaseNeRF (the `train --budget` fit).
    pub budget: f64,
}

/// The virtual cameras.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VirtualSpec {
    pub trajectory: Trajectory,
    /// How many.
    pub count: usize,
    /// How far beyond the rig (1: its edge).
    pub range: f64,
    /// Divide the training resolution by this for the virtual views.
    pub downscale: u32,
}

/// The stage-2 loop.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Stage2Spec {
    /// Rounds over the virtual views (each: render, inpaint, train).
    pub rounds: u32,
    /// Training steps per round.
    pub steps_per_round: u32,
    /// Fraction of each batch's rays drawn from the virtual views.
    pub virtual_fraction: f32,
    /// Learning rate (constant) of the stage's steps.
    pub lr: f32,
    /// Noise level t of the first and the last round (the diffusion inpainter starts its
    /// sampling there; every inpainter's loss is weighted by w(t) = sqrt(1 - t^2)).
    pub t_start: f32,
    pub t_end: f32,
    /// Weight of a virtual view's seen pixels relative to its filled ones (0: only the filled
    /// pixels supervise; the seen ones are the field's own render, left to the captured views).
    pub visible_weight: f32,
    /// Keep fills consistent across views: pixels that an earlier virtual view of the round
    /// filled are reprojected with their completed depth and count as seen.
    pub reproject: bool,
    /// Seed of the inpainters.
    pub seed: u64,
}

impl Default for Stage2Spec {
    fn default() -> Self {
        Stage2Spec {
            rounds: 4,
            steps_per_round: 250,
            virtual_fraction: 0.3,
            lr: 3e-3,
            t_start: 0.6,
            t_end: 0.2,
            visible_weight: 0.0,
            reproject: true,
            seed: 0,
        }
    }
}

impl Stage2Spec {
    /// Checks the settings.
    pub fn validate(&self) -> anyhow::Result<()> {
        if self.rounds == 0 || self.steps_per_round == 0 {
            bail!("stage 2 needs at least one round of at least one step");
        }
        if !(0.0..=1.0).contains(&self.virtual_fraction) {
            bail!(
                "--virtual-fraction {}: use a value in [0, 1]",
                self.virtual_fraction
            );
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            bail!("--stage2-lr {}: use a positive learning rate", self.lr);
        }
        if !(0.0..=1.0).contains(&self.visible_weight) {
            bail!(
                "--visible-weight {}: use a value in [0, 1]",
                self.visible_weight
            );
        }
        for t in [self.t_start, self.t_end] {
            if !(0.0..1.0).contains(&t) {
                bail!("noise levels must be in [0, 1), not {t}");
            }
        }
        Ok(())
    }

    /// Noise level of `round`.
    pub fn t(&self, round: u32) -> f32 {
        if self.rounds <= 1 {
            return self.t_start;
        }
        let f = round as f32 / (self.rounds - 1) as f32;
        self.t_start + (self.t_end - self.t_start) * f
    }

    /// The loss weight w(t) = sqrt(1 - t^2) (the signal level of a render noised to t).
    pub fn weight(&self, round: u32) -> f32 {
        let t = self.t(round);
        (1.0 - t * t).max(0.0).sqrt()
    }
}

/// The fly-through: frames along the virtual cameras' trajectory, rendered from the
/// BaseNeRF and from each stage-2 variant.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlythroughSpec {
    /// Frames along the path (0: no fly-through).
    pub frames: u32,
    /// Divide the virtual views' resolution by this for the frames.
    pub downscale: u32,
    /// Milliseconds per frame of the animation.
    pub delay_ms: u32,
}

impl Default for FlythroughSpec {
    fn default() -> Self {
        FlythroughSpec {
            frames: 24,
            downscale: 2,
            delay_ms: 100,
        }
    }
}

/// Everything `extranerf extrapolate` was asked to do.
#[derive(Clone, Debug)]
pub struct Options {
    /// Run folder.
    pub out: PathBuf,
    /// The scene (ignored with `base.from`, whose scene is used).
    pub scene: Option<SceneSpec>,
    pub base: BaseSpec,
    pub virt: VirtualSpec,
    pub vis: VisSettings,
    pub stage2: Stage2Spec,
    /// One stage-2 variant per inpainter, each from the same BaseNeRF.
    pub inpainters: Vec<InpainterKind>,
    /// The diffusion inpainter's model (needed when `inpainters` holds it).
    pub diffusion: Option<DiffusionSpec>,
    /// Stage 3 (None: stop after stage 2).
    pub stage3: Option<crate::stage3::Stage3Spec>,
    /// The fly-through of the BaseNeRF and each variant.
    pub flythrough: FlythroughSpec,
    /// Continue a run folder that holds a manifest.
    pub resume: bool,
    /// Stages to run again from nothing (with `resume`), whatever their record says; their
    /// settings may differ from the recorded ones. The stages that read them run again too.
    pub redo: Vec<String>,
}

/// The run folder's layout.
#[derive(Clone, Debug)]
pub struct RunDir {
    pub root: PathBuf,
    /// The BaseNeRF's run folder.
    pub base: PathBuf,
}

impl RunDir {
    pub fn visibility(&self) -> PathBuf {
        self.root.join("visibility")
    }

    pub fn stage2(&self, kind: InpainterKind) -> PathBuf {
        self.root.join(format!("stage2-{}", kind.name()))
    }

    pub fn flythrough(&self) -> PathBuf {
        self.root.join("flythrough")
    }
}

/// A stage of the pipeline.
pub trait Stage {
    /// Its name in the manifest.
    fn name(&self) -> String;
    /// Its resolved configuration (what a resumed run must match).
    fn config(&self) -> Value;
    /// Runs it (resuming inside it where it can); returns its report.
    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> anyhow::Result<Value>;
    /// The stages whose output it reads: when one of them runs, this one runs again even if
    /// the manifest says it is done.
    fn inputs(&self) -> Vec<String> {
        Vec::new()
    }
    /// Discards what an earlier run of it left, before it runs again from nothing (because it
    /// was asked to be redone, or a stage it reads ran again): by default its folder
    /// `RUN/NAME`, which holds its resumable state.
    fn reset(&self, dir: &RunDir) -> anyhow::Result<()> {
        let d = dir.root.join(self.name());
        if d.exists() {
            std::fs::remove_dir_all(&d).with_context(|| format!("removing {}", d.display()))?;
        }
        Ok(())
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
) -> anyhow::Result<RunConfig> {
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

    fn config(&self) -> Value {
        json!({"from": self.spec.from, "budget": self.spec.budget})
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> anyhow::Result<Value> {
        if self.spec.from.is_some() {
            let ck = load_checkpoint(&dir.base)
                .with_context(|| format!("--base {}", dir.base.display()))?;
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
                    eval_views: crate::driver::ViewSet::Test,
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

/// The virtual cameras and the visibility maps.
#[derive(Clone, Debug)]
pub struct VisibilityStage {
    pub virt: VirtualSpec,
    pub vis: VisSettings,
}

/// The virtual cameras of `spec` for `train`, at the virtual views' resolution.
pub fn make_virtual(spec: &VirtualSpec, train: &[Camera]) -> anyhow::Result<Vec<Camera>> {
    if spec.downscale == 0 {
        bail!("--virtual-downscale must be at least 1");
    }
    Ok(
        virtual_cameras(train, spec.trajectory, spec.count, spec.range)?
            .into_iter()
            .enumerate()
            .map(|(i, c)| {
                let mut c = c.downscaled(spec.downscale);
                c.image = PathBuf::from(format!("virtual_{i:03}.png"));
                c
            })
            .collect(),
    )
}

/// Renders `cam` from `nerf` with the fused march: colour, depth, opacity.
pub fn render(
    ctx: &Context,
    nerf: &Nerf,
    cam: &Camera,
    samples: u32,
) -> anyhow::Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
    Ok(nerf.render_with(ctx, cam, 8192, samples, March::Fused(MarchCuts::EXACT))?)
}

/// Saves maps into a safetensors file (`NAME.visibility`, `NAME.opacity`, `NAME.depth`).
fn save_maps(path: &Path, maps: &[(String, VisibilityMap)]) -> anyhow::Result<()> {
    let mut st = SafeTensors::default();
    for (name, m) in maps {
        let shape = vec![m.height as usize, m.width as usize];
        for (what, v) in [
            ("visibility", &m.visibility),
            ("opacity", &m.opacity),
            ("depth", &m.depth),
        ] {
            st.tensors.insert(
                format!("{name}.{what}"),
                Tensor {
                    shape: shape.clone(),
                    data: v.clone(),
                },
            );
        }
    }
    st.write(path)?;
    Ok(())
}

/// Reads map `name` from a `save_maps` file.
pub fn load_map(st: &SafeTensors, path: &Path, name: &str) -> anyhow::Result<VisibilityMap> {
    let get = |what: &str| -> anyhow::Result<(Vec<usize>, Vec<f32>)> {
        let t = st
            .tensors
            .get(&format!("{name}.{what}"))
            .with_context(|| format!("{}: no map {name}.{what}", path.display()))?;
        Ok((t.shape.clone(), t.data.clone()))
    };
    let (shape, visibility) = get("visibility")?;
    let (_, opacity) = get("opacity")?;
    let (_, depth) = get("depth")?;
    if shape.len() != 2 || opacity.len() != visibility.len() || depth.len() != visibility.len() {
        bail!("{}: map {name} is malformed", path.display());
    }
    Ok(VisibilityMap {
        width: shape[1] as u32,
        height: shape[0] as u32,
        evals: vec![0.0; visibility.len()],
        visibility,
        opacity,
        depth,
    })
}

/// A mask against the truly unseen pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct MaskScore {
    /// Intersection over union of the masked and the truly unseen pixels (1 when both are
    /// empty).
    pub iou: f64,
    /// Share of pixels on which mask and truth agree.
    pub accuracy: f64,
    /// Masked share, truly unseen share.
    pub masked: f64,
    pub unseen: f64,
}

impl MaskScore {
    /// Scores `mask` (>= 0.5: to inpaint) against `unseen`.
    pub fn new(mask: &[f32], unseen: &[bool]) -> MaskScore {
        let (mut inter, mut union, mut agree, mut m, mut u) =
            (0usize, 0usize, 0usize, 0usize, 0usize);
        for (&x, &t) in mask.iter().zip(unseen) {
            let x = x >= 0.5;
            inter += usize::from(x && t);
            union += usize::from(x || t);
            agree += usize::from(x == t);
            m += usize::from(x);
            u += usize::from(t);
        }
        let n = mask.len().max(1) as f64;
        MaskScore {
            iou: if union == 0 {
                1.0
            } else {
                inter as f64 / union as f64
            },
            accuracy: agree as f64 / n,
            masked: m as f64 / n,
            unseen: u as f64 / n,
        }
    }

    /// The mean of several views' scores.
    pub fn mean(v: &[MaskScore]) -> MaskScore {
        let n = v.len().max(1) as f64;
        let f = |g: fn(&MaskScore) -> f64| v.iter().map(g).sum::<f64>() / n;
        MaskScore {
            iou: f(|s| s.iou),
            accuracy: f(|s| s.accuracy),
            masked: f(|s| s.masked),
            unseen: f(|s| s.unseen),
        }
    }
}

/// The scene index of a held-out view's map name (`test_NNN`).
fn test_index(name: &str) -> Option<usize> {
    name.strip_prefix("test_")?.parse().ok()
}

/// The maps file of the visibility stage.
pub const MAPS_FILE: &str = "maps.safetensors";

impl Stage for VisibilityStage {
    fn name(&self) -> String {
        "visibility".into()
    }

    fn config(&self) -> Value {
        json!({"virtual": self.virt, "settings": self.vis})
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> anyhow::Result<Value> {
        let out = dir.visibility();
        std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
        let base = BaseField::load(ctx, &dir.base)?;
        let train = base.train_cameras();
        let virt = make_virtual(&self.virt, &train)?;
        write_transforms(&out.join("virtual.json"), &virt)?;
        let cfg = self
            .vis
            .config(self.vis.rank, base.ck.config.train.samples)?;
        let t = Instant::now();
        let fv = FieldVisibility::new(ctx, &base.nerf, &train, &self.vis)?;
        let volume_s = t.elapsed().as_secs_f64();
        let all = mask_all_but(train.len(), None);
        // Virtual views, and the held-out views (mapped at the virtual views' scale, their
        // BaseNeRF renders at full size for `eval`).
        let mut views: Vec<(String, Camera, Camera)> = virt
            .iter()
            .enumerate()
            .map(|(i, c)| (format!("virtual_{i:03}"), c.clone(), c.clone()))
            .collect();
        for &i in &base.loaded.split.test {
            let full = base.loaded.scene.cameras[i].clone();
            let c = full.downscaled(self.virt.downscale);
            views.push((format!("test_{i:03}"), c, full));
        }
        let mut maps = Vec::new();
        let mut rows = Vec::new();
        let total = views.len() as u32;
        // The demo scene's generator knows what each rig camera sees: score the held-out
        // views' masks against it.
        let demo = base.ck.config.scene.dir.join(DEMO_MARKER).exists();
        let mut exact: Vec<MaskScore> = Vec::new();
        for (k, (name, cam, full)) in views.iter().enumerate() {
            let t = Instant::now();
            let m = fv.map(ctx, &base.nerf, cam, all, &cfg, self.vis.chunk)?;
            let mask = self.vis.mask(&m);
            write_png(
                &out.join(format!("{name}_vis.png")),
                m.width,
                m.height,
                &grey_to_rgb(&m.visibility),
            )?;
            write_png(
                &out.join(format!("{name}_mask.png")),
                m.width,
                m.height,
                &grey_to_rgb(&mask),
            )?;
            let (rgb, _, _) = render(ctx, &base.nerf, full, cfg.samples)?;
            write_png(
                &out.join(format!("{name}_base.png")),
                full.width,
                full.height,
                &rgb,
            )?;
            let masked = mask.iter().map(|&v| v as f64).sum::<f64>() / mask.len().max(1) as f64;
            let mut row = json!({
                "view": name,
                "width": m.width,
                "height": m.height,
                "mean_visibility": m.mean(),
                "mean_opacity": m.mean_opacity(),
                "masked_fraction": masked,
                "seconds": t.elapsed().as_secs_f64(),
            });
            if let (true, Some(i)) = (demo, test_index(name)) {
                let unseen: Vec<bool> = demo_seen(i, m.width, m.height, cfg.rank as usize)
                    .into_iter()
                    .map(|s| !s)
                    .collect();
                let s = MaskScore::new(&mask, &unseen);
                row["exact"] = json!(s);
                exact.push(s);
            }
            rows.push(row);
            rep.progress(&Progress {
                unit: Unit::Views,
                step: k as u32 + 1,
                total,
                loss: masked,
                psnr: 0.0,
                samples_per_s: 0.0,
                secs: 0.0,
                eta: 0.0,
            });
            rep.note(&format!(
                "{name}: {}x{}, {:.1}% to inpaint (mean opacity {:.3})",
                m.width,
                m.height,
                100.0 * masked,
                m.mean_opacity()
            ));
            maps.push((name.clone(), m));
        }
        save_maps(&out.join(MAPS_FILE), &maps)?;
        let exact_mean = (!exact.is_empty()).then(|| MaskScore::mean(&exact));
        if let Some(e) = &exact_mean {
            rep.note(&format!(
                "masks against the demo's exact visibility: IoU {:.3}, accuracy {:.3} ({:.1}% masked, {:.1}% truly unseen)",
                e.iou,
                e.accuracy,
                100.0 * e.masked,
                100.0 * e.unseen
            ));
        }
        let doc = json!({
            "exact_mean": exact_mean,
            "training_views": base.loaded.split.train,
            "settings": self.vis,
            "virtual": self.virt,
            "volume_seconds": volume_s,
            "views": rows,
        });
        extranerf_nerf::safetensors::write_atomic(
            &out.join("visibility.json"),
            serde_json::to_string_pretty(&doc)?.as_bytes(),
        )?;
        Ok(json!({"volume_seconds": volume_s, "views": rows.len(), "exact_mean": exact_mean}))
    }
}

/// The diffusion inpainter's model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionSpec {
    /// A diffusers inpainting folder.
    pub model: PathBuf,
    /// LoRA adapters (`diffusion finetune`).
    pub lora: Option<PathBuf>,
    /// DDIM steps per inpainting.
    pub steps: usize,
    /// burn backend.
    pub backend: extranerf_diffusion::device::Backend,
}

impl DiffusionSpec {
    /// What the inpainter `kind` uses of it: `diffusion-base` leaves the adapters out.
    pub fn for_kind(&self, kind: InpainterKind) -> DiffusionSpec {
        DiffusionSpec {
            lora: if kind == InpainterKind::DiffusionBase {
                None
            } else {
                self.lora.clone()
            },
            ..self.clone()
        }
    }
}

/// One stage-2 variant.
#[derive(Clone, Debug)]
pub struct InpaintStage {
    pub kind: InpainterKind,
    /// The model of the diffusion inpainter.
    pub diffusion: Option<DiffusionSpec>,
    pub spec: Stage2Spec,
    pub virt: VirtualSpec,
    pub vis: VisSettings,
}

/// Fills of earlier views, reprojected into `cam`: per pixel, the nearest reprojected colour
/// and its ray-space depth in `cam`.
pub fn reproject(
    earlier: &[(Camera, Fill, Vec<f32>)],
    cam: &Camera,
    ndc: bool,
) -> Vec<Option<([f32; 3], f32)>> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut best: Vec<Option<([f32; 3], f32, f64)>> = vec![None; w * h];
    for (src, fill, filled) in earlier {
        let sw = src.width as usize;
        for (i, &f) in filled.iter().enumerate() {
            if f < 0.5 {
                continue;
            }
            let (x, y) = ((i % sw) as f64 + 0.5, (i / sw) as f64 + 0.5);
            let Some(p) = src.ray_point(x, y, fill.depth[i] as f64, ndc) else {
                continue;
            };
            let (px, py, z) = cam.project(p);
            if !(z > 0.0 && px >= 0.0 && py >= 0.0 && px < w as f64 && py < h as f64) {
                continue;
            }
            let j = py as usize * w + px as usize;
            if best[j].is_some_and(|b| b.2 <= z) {
                continue;
            }
            // Ray-space depth in this camera: NDC t = 1 + 1 / z_world, else view depth.
            let t = if ndc {
                let pz = p.z;
                if pz >= -1.0 {
                    continue;
                }
                1.0 + 1.0 / pz
            } else {
                z
            };
            best[j] = Some((
                [fill.rgb[3 * i], fill.rgb[3 * i + 1], fill.rgb[3 * i + 2]],
                t as f32,
                z,
            ));
        }
    }
    best.into_iter()
        .map(|b| b.map(|(c, t, _)| (c, t)))
        .collect()
}

/// The stage-2 and stage-3 state between rounds (`round.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct RoundState {
    pub rounds_done: u32,
    pub seconds: f64,
}

/// The file of [`RoundState`].
pub(crate) const ROUND_FILE: &str = "round.json";

/// The last finished round of a round-based stage in `out`, with its checkpoint.
pub(crate) fn load_round(out: &Path) -> anyhow::Result<Option<(RoundState, Checkpoint)>> {
    let state_path = out.join(ROUND_FILE);
    if !(state_path.exists() && out.join(extranerf_nerf::run::CHECKPOINT_FILE).exists()) {
        return Ok(None);
    }
    let s: RoundState = serde_json::from_str(
        &std::fs::read_to_string(&state_path)
            .with_context(|| format!("reading {}", state_path.display()))?,
    )
    .with_context(|| format!("{}: malformed", state_path.display()))?;
    Ok(Some((s, load_checkpoint(out)?)))
}

/// A finished round: the checkpoint, then the state that points at it (a crash between the
/// two redoes the round).
pub(crate) fn save_round(
    out: &Path,
    cfg: &RunConfig,
    tcfg: &TrainConfig,
    trainer: &Trainer,
    state: &RoundState,
) -> anyhow::Result<()> {
    save_checkpoint(
        out,
        &Checkpoint {
            config: RunConfig {
                train: tcfg.clone(),
                ..cfg.clone()
            },
            step: trainer.step(),
            params: trainer.nerf().params().read()?,
            moments: Some(trainer.moments()?),
        },
    )?;
    extranerf_nerf::safetensors::write_atomic(
        &out.join(ROUND_FILE),
        serde_json::to_string(state)?.as_bytes(),
    )?;
    Ok(())
}

/// Where a stage-2 or stage-3 variant saves its rounds: its folder and the run configuration
/// its checkpoints carry.
pub(crate) struct RoundSink<'a> {
    pub out: &'a Path,
    pub cfg: &'a RunConfig,
    pub tcfg: &'a TrainConfig,
}

/// The end of a stage-2 or stage-3 round: trains `steps` steps on `views` (virtual views
/// drawn at `virtual_fraction`), then saves the round as done (`round + 1` rounds; `seconds`,
/// the stage's time before this round, grows by the round's time since `t0`). Returns the last
/// window's statistics and the training seconds.
#[allow(clippy::too_many_arguments)] // each is a distinct input of the loop
pub(crate) fn train_round(
    ctx: &Context,
    trainer: &mut Trainer,
    prims: &Prims,
    views: &[View],
    virtual_fraction: f32,
    steps: u32,
    what: &str,
    sink: &RoundSink<'_>,
    (round, t0, seconds): (u32, Instant, &mut f64),
    rep: &mut dyn Reporter,
) -> anyhow::Result<(Option<StepStats>, f64)> {
    let data =
        TrainData::with_sampling(ctx, views, ViewSampling::VirtualFraction(virtual_fraction))?;
    let tt = Instant::now();
    let last = train_steps(ctx, trainer, prims, &data, steps, what, sink.out, rep)?;
    let train_s = tt.elapsed().as_secs_f64();
    *seconds += t0.elapsed().as_secs_f64();
    save_round(
        sink.out,
        sink.cfg,
        sink.tcfg,
        trainer,
        &RoundState {
            rounds_done: round + 1,
            seconds: *seconds,
        },
    )?;
    Ok((last, train_s))
}

/// Trains `steps` steps on `data` with progress; a non-finite loss is an error that says the
/// last finished round in `out` is intact. Returns the last window's statistics.
#[allow(clippy::too_many_arguments)] // each is a distinct input of the loop
pub(crate) fn train_steps(
    ctx: &Context,
    trainer: &mut Trainer,
    prims: &Prims,
    data: &TrainData,
    steps: u32,
    what: &str,
    out: &Path,
    rep: &mut dyn Reporter,
) -> anyhow::Result<Option<StepStats>> {
    let tt = Instant::now();
    let mut left = steps;
    let mut last = None;
    while left > 0 {
        let n = left.min(25);
        let stats = trainer.run_steps(ctx, prims, data, n)?;
        if !(stats.loss.is_finite() && stats.mse.is_finite()) {
            bail!(
                "{what}: the loss became {}; the last finished round in {} is intact",
                stats.loss,
                out.display()
            );
        }
        left -= n;
        let done = steps - left;
        let secs = tt.elapsed().as_secs_f64();
        rep.progress(&Progress {
            unit: Unit::Steps,
            step: done,
            total: steps,
            loss: stats.loss,
            psnr: stats.psnr(),
            samples_per_s: done as f64 * trainer.samples_per_step() as f64 / secs,
            secs,
            eta: secs / done as f64 * left as f64,
        });
        last = Some(stats);
    }
    Ok(last)
}

/// The inpainter of `kind` (the diffusion one loaded from `diffusion`).
pub(crate) fn build_inpainter(
    ctx: &Context,
    kind: InpainterKind,
    diffusion: Option<&DiffusionSpec>,
    rep: &mut dyn Reporter,
) -> anyhow::Result<Box<dyn crate::inpaint::Inpainter>> {
    if let Some(i) = kind.build() {
        return Ok(i);
    }
    let Some(d) = diffusion.map(|d| d.for_kind(kind)) else {
        bail!("--inpainter {kind} needs --diffusion-model DIR (a diffusers inpainting folder, or `extranerf diffusion prior`'s model)");
    };
    let (b, device) = extranerf_diffusion::device::diffusion_device(ctx, d.backend)?;
    let inp = crate::inpaint::diffusion::DiffusionInpainter::load(
        &d.model,
        d.lora.as_deref(),
        device,
        d.steps,
    )?;
    rep.note(&format!(
        "{kind} inpainter on {}: {}",
        b.name(),
        inp.notes.join("; ")
    ));
    Ok(Box::new(inp))
}

/// The held-out views rendered from `nerf` into `out/test_NNN.png` (what `eval` scores).
pub(crate) fn write_test_renders(
    ctx: &Context,
    nerf: &Nerf,
    loaded: &extranerf_nerf::run::LoadedScene,
    samples: u32,
    out: &Path,
) -> anyhow::Result<()> {
    for &i in &loaded.split.test {
        let cam = &loaded.scene.cameras[i];
        let (rgb, _, _) = render(ctx, nerf, cam, samples)?;
        write_png(
            &out.join(format!("test_{i:03}.png")),
            cam.width,
            cam.height,
            &rgb,
        )?;
    }
    Ok(())
}

impl Stage for InpaintStage {
    fn name(&self) -> String {
        format!("stage2-{}", self.kind.name())
    }

    fn config(&self) -> Value {
        let mut c = json!({"inpainter": self.kind, "loop": self.spec});
        if self.kind.uses_diffusion() {
            c["diffusion"] = json!(self.diffusion.as_ref().map(|d| d.for_kind(self.kind)));
        }
        c
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> anyhow::Result<Value> {
        self.spec.validate()?;
        let out = dir.stage2(self.kind);
        std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
        let base = BaseField::load(ctx, &dir.base)?;
        let ndc = base.ndc();
        let cfg = base.ck.config.clone();
        let samples = cfg.train.samples;
        let train = base.train_cameras();
        let virt = make_virtual(&self.virt, &train)?;
        let maps_path = dir.visibility().join(MAPS_FILE);
        let st = SafeTensors::read(&maps_path)?;
        let masks: Vec<Vec<f32>> = (0..virt.len())
            .map(|i| {
                let m = load_map(&st, &maps_path, &format!("virtual_{i:03}"))?;
                if (m.width, m.height) != (virt[i].width, virt[i].height) {
                    bail!(
                        "{}: virtual view {i}'s map has another size",
                        maps_path.display()
                    );
                }
                Ok(self.vis.mask(&m))
            })
            .collect::<anyhow::Result<_>>()?;
        let (captured, _) =
            training_views_in(ctx, &cfg.scene, &base.loaded, &cfg.model, &dir.base)?;
        // Exemplar sources: the training photos at the virtual views' scale, with the
        // BaseNeRF's depth.
        let mut source_imgs = Vec::new();
        for v in &captured {
            let cam = v.camera.downscaled(self.virt.downscale);
            let img = downscale_image(&v.image, cam.width, cam.height);
            let (_, depth, _) = render(ctx, &base.nerf, &cam, samples)?;
            source_imgs.push((cam, img, depth));
        }
        // Resume from the last finished round.
        let (start_round, mut seconds, params, moments) = match load_round(&out)? {
            Some((st, ck)) => {
                rep.note(&format!(
                    "{}: resuming after round {}",
                    self.name(),
                    st.rounds_done
                ));
                (st.rounds_done, st.seconds, ck.params, ck.moments)
            }
            None => (0, 0.0, base.ck.params.clone(), base.ck.moments.clone()),
        };
        let total_steps = self.spec.rounds * self.spec.steps_per_round;
        let mut tcfg = cfg.train.clone();
        tcfg.steps = total_steps;
        tcfg.decay_steps = total_steps;
        tcfg.lr_start = self.spec.lr;
        tcfg.lr_end = self.spec.lr;
        let nerf = Nerf::new(ctx, cfg.model.clone(), &params, cfg.train.background)?;
        let moments = moments.as_ref().map(|(m, v)| (m.as_slice(), v.as_slice()));
        let mut trainer = Trainer::new(
            ctx,
            nerf,
            tcfg.clone(),
            start_round * self.spec.steps_per_round,
            moments,
        )?;
        let prims = Prims::new(ctx)?;
        let mut inpainter = build_inpainter(ctx, self.kind, self.diffusion.as_ref(), rep)?;
        let sink = RoundSink {
            out: &out,
            cfg: &cfg,
            tcfg: &tcfg,
        };
        let mut rounds = Vec::new();
        for round in start_round..self.spec.rounds {
            let t0 = Instant::now();
            let t = self.spec.t(round);
            let weight = self.spec.weight(round);
            let round_dir = out.join(format!("round_{round:02}"));
            std::fs::create_dir_all(&round_dir)
                .with_context(|| format!("creating {}", round_dir.display()))?;
            let mut filled: Vec<(Camera, Fill, Vec<f32>)> = Vec::new();
            let mut inpaint_s = 0.0;
            let mut render_s = 0.0;
            let mut reprojected = 0usize;
            for (k, cam) in virt.iter().enumerate() {
                let tr = Instant::now();
                let (mut rgb, mut depth, _) = render(ctx, trainer.nerf(), cam, samples)?;
                render_s += tr.elapsed().as_secs_f64();
                let mut mask = masks[k].clone();
                if self.spec.reproject && !filled.is_empty() {
                    for (j, r) in reproject(&filled, cam, ndc).into_iter().enumerate() {
                        if let Some((c, d)) = r {
                            if mask[j] >= 0.5 {
                                rgb[3 * j..3 * j + 3].copy_from_slice(&c);
                                depth[j] = d;
                                mask[j] = 0.0;
                                reprojected += 1;
                            }
                        }
                    }
                }
                let sources: Vec<Source<'_>> = source_imgs
                    .iter()
                    .map(|(c, img, d)| Source {
                        width: c.width as usize,
                        height: c.height as usize,
                        rgb: &img.rgb,
                        depth: Some(d),
                    })
                    .collect();
                let target = Target {
                    width: cam.width as usize,
                    height: cam.height as usize,
                    rgb: &rgb,
                    depth: &depth,
                    mask: &mask,
                    t,
                };
                let ti = Instant::now();
                let seed = self.spec.seed ^ ((round as u64) << 32) ^ k as u64;
                let fill = if mask.iter().all(|&m| m < 0.5) {
                    Fill {
                        rgb: rgb.clone(),
                        depth: depth.clone(),
                    }
                } else {
                    inpainter
                        .inpaint(&target, &sources, seed)
                        .with_context(|| format!("virtual view {k}, round {round}"))?
                };
                inpaint_s += ti.elapsed().as_secs_f64();
                write_png(
                    &round_dir.join(format!("virtual_{k:03}.png")),
                    cam.width,
                    cam.height,
                    &fill.rgb,
                )?;
                write_png(
                    &round_dir.join(format!("virtual_{k:03}_mask.png")),
                    cam.width,
                    cam.height,
                    &grey_to_rgb(&masks[k]),
                )?;
                filled.push((cam.clone(), fill, masks[k].clone()));
                rep.progress(&Progress {
                    unit: Unit::Views,
                    step: k as u32 + 1,
                    total: virt.len() as u32,
                    loss: 0.0,
                    psnr: 0.0,
                    samples_per_s: 0.0,
                    secs: t0.elapsed().as_secs_f64(),
                    eta: 0.0,
                });
            }
            // Train on the captured views and this round's virtual views.
            let mut views = captured.clone();
            for (cam, fill, mask) in &filled {
                // The filled pixels carry w(t); the seen rest `visible_weight` of it (their
                // colour is the field's own render, which the captured views supervise).
                let w: Vec<f32> = mask
                    .iter()
                    .map(|&m| {
                        if m >= 0.5 {
                            weight
                        } else {
                            weight * self.spec.visible_weight
                        }
                    })
                    .collect();
                let conf = |m: f32| {
                    if m >= 0.5 || self.spec.visible_weight > 0.0 {
                        1.0
                    } else {
                        0.0
                    }
                };
                views.push(View {
                    camera: cam.clone(),
                    image: Image::opaque(cam.width, cam.height, fill.rgb.clone()),
                    depth: Some(
                        fill.depth
                            .iter()
                            .zip(mask)
                            .map(|(&d, &m)| [d, conf(m)])
                            .collect(),
                    ),
                    weight: Some(w),
                    kind: ViewKind::Virtual,
                });
            }
            let (last, train_s) = train_round(
                ctx,
                &mut trainer,
                &prims,
                &views,
                self.spec.virtual_fraction,
                self.spec.steps_per_round,
                &format!("{} round {round}", self.name()),
                &sink,
                (round, t0, &mut seconds),
                rep,
            )?;
            let row = json!({
                "round": round,
                "t": t,
                "weight": weight,
                "render_seconds": render_s,
                "inpaint_seconds": inpaint_s,
                "train_seconds": train_s,
                "reprojected_pixels": reprojected,
                "batch_psnr": last.map(|s| s.psnr()),
            });
            rep.note(&format!(
                "{} round {}/{}: t {t:.2}, render {render_s:.1} s, inpaint {inpaint_s:.1} s, train {train_s:.1} s; {reprojected} pixels reprojected",
                self.name(),
                round + 1,
                self.spec.rounds
            ));
            rounds.push(row);
        }
        // The held-out views' renders, for `eval`.
        write_test_renders(ctx, trainer.nerf(), &base.loaded, samples, &out)?;
        Ok(json!({"rounds": rounds, "seconds": seconds}))
    }
}

/// A field the pipeline made: the BaseNeRF, a stage-2 variant, or that variant after stage 3.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FieldRef {
    Base,
    Stage2(InpainterKind),
    Stage3(InpainterKind),
}

impl FieldRef {
    /// Its stage's name (and folder, for the variants).
    pub fn name(self) -> String {
        match self {
            FieldRef::Base => "base".into(),
            FieldRef::Stage2(k) => format!("stage2-{}", k.name()),
            FieldRef::Stage3(k) => format!("stage3-{}", k.name()),
        }
    }
}

/// The fly-through of one field: `frames` cameras along the virtual trajectory (the path the
/// virtual views sample, sampled densely), rendered into `RUN/flythrough/NAME/frame_NNN.png`
/// and `RUN/flythrough/NAME.gif`. NAME is `base` or a variant's folder name.
#[derive(Clone, Debug)]
pub struct FlythroughStage {
    /// The field rendered.
    pub field: FieldRef,
    pub virt: VirtualSpec,
    pub spec: FlythroughSpec,
}

impl FlythroughStage {
    fn field_name(&self) -> String {
        self.field.name()
    }
}

impl Stage for FlythroughStage {
    fn name(&self) -> String {
        format!("flythrough-{}", self.field_name())
    }

    fn config(&self) -> Value {
        json!({"virtual": self.virt, "flythrough": self.spec})
    }

    fn inputs(&self) -> Vec<String> {
        vec!["base".into(), self.field_name()]
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> anyhow::Result<Value> {
        let s = &self.spec;
        if s.frames == 0 || s.downscale == 0 || s.delay_ms == 0 {
            bail!("the fly-through needs at least one frame, a downscale of at least 1 and a positive delay");
        }
        let base = BaseField::load(ctx, &dir.base)?;
        let samples = base.ck.config.train.samples;
        let (nerf, step) = match self.field {
            FieldRef::Stage2(_) | FieldRef::Stage3(_) => {
                let name = self.field.name();
                let ck = load_checkpoint(&dir.root.join(&name))
                    .with_context(|| format!("the {name} variant's field"))?;
                let cfg = &ck.config;
                (
                    Nerf::new(ctx, cfg.model.clone(), &ck.params, cfg.train.background)?,
                    ck.step,
                )
            }
            FieldRef::Base => (base.nerf, base.ck.step),
        };
        let train: Vec<Camera> = base
            .loaded
            .split
            .train
            .iter()
            .map(|&i| base.loaded.scene.cameras[i].clone())
            .collect();
        let cams = virtual_cameras(
            &train,
            self.virt.trajectory,
            s.frames as usize,
            self.virt.range,
        )?;
        let name = self.field_name();
        let out = dir.flythrough().join(&name);
        std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
        let mut frames = Vec::with_capacity(cams.len());
        let (mut w, mut h) = (0, 0);
        let t = Instant::now();
        for (i, c) in cams.iter().enumerate() {
            let cam = c.downscaled(self.virt.downscale.max(1) * s.downscale);
            let (rgb, _, _) = render(ctx, &nerf, &cam, samples)?;
            write_png(
                &out.join(format!("frame_{i:03}.png")),
                cam.width,
                cam.height,
                &rgb,
            )?;
            (w, h) = (cam.width, cam.height);
            frames.push(rgb);
            rep.progress(&Progress {
                unit: Unit::Views,
                step: i as u32 + 1,
                total: s.frames,
                loss: 0.0,
                psnr: 0.0,
                samples_per_s: 0.0,
                secs: t.elapsed().as_secs_f64(),
                eta: 0.0,
            });
        }
        let gif = dir.flythrough().join(format!("{name}.gif"));
        crate::anim::write_gif(&gif, w, h, &frames, s.delay_ms)?;
        rep.note(&format!(
            "{}: {} frames of {w}x{h} ({}), {:.1} s",
            gif.display(),
            frames.len(),
            self.field_name(),
            t.elapsed().as_secs_f64()
        ));
        Ok(json!({"frames": frames.len(), "width": w, "height": h, "field_step": step}))
    }
}

/// Runs the pipeline: the base, the visibility stage, one stage-2 variant per inpainter, then
/// stage 3 (its data from the first inpainter's supervision, the enhancer, and one stage-3
/// field per variant) and the fly-throughs, skipping the stages a resumed run has done.
pub fn extrapolate(ctx: &Context, o: &Options, rep: &mut dyn Reporter) -> anyhow::Result<Manifest> {
    if o.inpainters.is_empty() {
        bail!("give at least one --inpainter");
    }
    o.stage2.validate()?;
    let existing = Manifest::load(&o.out)?;
    if existing.is_some() && !o.resume {
        bail!(
            "{} already holds an extrapolate run; pass --resume to continue it or choose another --out",
            o.out.display()
        );
    }
    if existing.is_none() && o.resume {
        bail!(
            "--resume: {} holds no {}",
            o.out.display(),
            crate::manifest::MANIFEST_FILE
        );
    }
    let base_dir = o.base.from.clone().unwrap_or_else(|| o.out.join("base"));
    let scene = match (&o.base.from, &o.scene) {
        (Some(from), _) => {
            load_checkpoint(from)
                .with_context(|| format!("--base {}", from.display()))?
                .config
                .scene
        }
        (None, Some(s)) => s.clone(),
        (None, None) => bail!("give --scene, or --base with a trained run"),
    };
    let mut manifest = match existing {
        Some(m) => {
            m.check_scene(&o.out, &scene)?;
            m
        }
        None => Manifest::new(scene.clone()),
    };
    std::fs::create_dir_all(&o.out).with_context(|| format!("creating {}", o.out.display()))?;
    let dir = RunDir {
        root: o.out.clone(),
        base: base_dir,
    };
    let mut stages: Vec<Box<dyn Stage>> = vec![
        Box::new(BaseStage {
            spec: o.base.clone(),
            scene,
            virt: o.virt.clone(),
        }),
        Box::new(VisibilityStage {
            virt: o.virt.clone(),
            vis: o.vis.clone(),
        }),
    ];
    for &kind in &o.inpainters {
        stages.push(Box::new(InpaintStage {
            kind,
            diffusion: o.diffusion.clone(),
            spec: o.stage2.clone(),
            virt: o.virt.clone(),
            vis: o.vis.clone(),
        }));
    }
    if let Some(s3) = &o.stage3 {
        s3.validate()?;
        // A fixed filter needs no training data and no model.
        if s3.enhance == crate::stage3::Stage3Enhancer::Diffusion {
            stages.push(Box::new(crate::stage3::EnhancerDataStage {
                spec: s3.clone(),
                inpainter: o.inpainters[0],
                diffusion: o.diffusion.clone(),
                stage2: o.stage2.clone(),
                virt: o.virt.clone(),
                vis: o.vis.clone(),
            }));
            stages.push(Box::new(crate::stage3::EnhancerStage { spec: s3.clone() }));
        }
        for &kind in &o.inpainters {
            stages.push(Box::new(crate::stage3::EnhanceStage {
                kind,
                spec: s3.clone(),
                virt: o.virt.clone(),
                vis: o.vis.clone(),
            }));
        }
    }
    if o.flythrough.frames > 0 {
        let mut fields = vec![FieldRef::Base];
        fields.extend(o.inpainters.iter().map(|&k| FieldRef::Stage2(k)));
        if o.stage3.is_some() {
            fields.extend(o.inpainters.iter().map(|&k| FieldRef::Stage3(k)));
        }
        for field in fields {
            stages.push(Box::new(FlythroughStage {
                field,
                virt: o.virt.clone(),
                spec: o.flythrough.clone(),
            }));
        }
    }
    let names: Vec<String> = stages.iter().map(|s| s.name()).collect();
    check_redo(&o.redo, &names, o.base.from.is_some())?;
    // Every stage's settings are checked before anything runs (a stage to redo may differ).
    for s in &stages {
        if !o.redo.contains(&s.name()) {
            manifest.stage(&o.out, &s.name(), &s.config())?;
        }
    }
    let mut ran: Vec<String> = Vec::new();
    for s in &stages {
        let name = s.name();
        let config = s.config();
        let redo = o.redo.contains(&name);
        let prior = if redo {
            None
        } else {
            manifest.stage(&o.out, &name, &config)?.cloned()
        };
        // The stages it reads that ran in this invocation: its output is stale.
        let rerun: Vec<String> = s.inputs().into_iter().filter(|i| ran.contains(i)).collect();
        let stale = !rerun.is_empty();
        if prior.as_ref().is_some_and(|r| r.done) && !stale {
            rep.note(&format!("stage {name}: done, skipped"));
            continue;
        }
        ran.push(name.clone());
        rep.stage(&name);
        // Its state from an earlier run was made from other inputs or settings: start over.
        let prior = if redo || stale {
            // (A stage that never ran before has nothing to discard, and says nothing.)
            if redo || prior.is_some() {
                rep.note(&format!(
                    "stage {name}: {}, its earlier output discarded",
                    if redo {
                        "redone (--redo)".to_string()
                    } else {
                        format!("runs again after {}", rerun.join(", "))
                    }
                ));
            }
            s.reset(&dir)?;
            None
        } else {
            prior
        };
        let before = prior.as_ref().map_or(0.0, |r| r.seconds);
        manifest.record(StageRecord {
            name: name.clone(),
            config: config.clone(),
            done: false,
            seconds: before,
            report: Value::Null,
        });
        manifest.save(&o.out)?;
        let t = Instant::now();
        let report = s
            .run(ctx, &dir, rep)
            .with_context(|| format!("stage {name}"))?;
        let seconds = before + t.elapsed().as_secs_f64();
        rep.note(&format!("stage {name}: done in {seconds:.1} s"));
        manifest.record(StageRecord {
            name,
            config,
            done: true,
            seconds,
            report,
        });
        manifest.save(&o.out)?;
    }
    Ok(manifest)
}

/// Refuses `--redo` names that are not stages of this run, or the BaseNeRF of another run.
pub fn check_redo(redo: &[String], stages: &[String], base_reused: bool) -> anyhow::Result<()> {
    for r in redo {
        if !stages.contains(r) {
            bail!(
                "--redo {r}: this run has no such stage (its stages: {})",
                stages.join(", ")
            );
        }
        if r == "base" && base_reused {
            bail!("--redo base: the BaseNeRF is --base's run, not this one's; retrain it there");
        }
    }
    Ok(())
}

/// Loads `path` as an image the size of `cam` (for evaluations).
pub fn load_view_image(cam: &Camera) -> anyhow::Result<Image> {
    let img = load_image(&cam.image)?;
    if (img.width, img.height) != (cam.width, cam.height) {
        bail!(
            "{}: {}x{}, its camera says {}x{}",
            cam.image.display(),
            img.width,
            img.height,
            cam.width,
            cam.height
        );
    }
    Ok(img)
}

#[cfg(test)]
mod tests {
    use super::check_redo;

    #[test]
    fn redo_names_a_stage_of_the_run_and_not_a_reused_base() {
        let stages: Vec<String> = ["base", "visibility", "stage2-harmonic"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        assert!(check_redo(&["stage2-harmonic".into()], &stages, true).is_ok());
        assert!(check_redo(&["base".into()], &stages, false).is_ok());
        let e = check_redo(&["stage3-harmonic".into()], &stages, false)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--redo stage3-harmonic: this run has no such stage"),
            "{e}"
        );
        assert!(e.contains("base, visibility, stage2-harmonic"), "{e}");
        let e = check_redo(&["base".into()], &stages, true)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--redo base: the BaseNeRF is --base's run"),
            "{e}"
        );
    }
}
