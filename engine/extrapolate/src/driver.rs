//! The BaseNeRF training driver: a trainer from a run configuration, time budgets (a probe
//! that sets the steps, re-fitted to the clock as the run goes), the training loop with its
//! checkpoints, `progress.jsonl`, NaN abort and held-out curves (`curve.jsonl`).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context as _};
use extranerf_gpu::Context;
use extranerf_nerf::metrics::{psnr, ssim, Lpips, LpipsNet};
use extranerf_nerf::mvs_depth::CacheUse;
use extranerf_nerf::renderer::Nerf;
use extranerf_nerf::run::{save_checkpoint, training_views_in, Checkpoint, LoadedScene, RunConfig};
use extranerf_nerf::trainer::{StepStats, Trainer};
use extranerf_nerf::views::TrainData;
use extranerf_prims::Prims;

/// Where the driver's progress and notes go (the command line draws them).
pub trait Reporter {
    /// A line of information: the model, the budget's decisions, a held-out evaluation.
    fn note(&mut self, line: &str);
    /// Progress after a window of steps (or views: a stage's progress counts its own units).
    fn progress(&mut self, p: &Progress);
    /// A pipeline stage starts (progress from here on is that stage's).
    fn stage(&mut self, _name: &str) {}
}

/// What a [`Progress`] counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Unit {
    /// Training steps (loss, PSNR and pace apply).
    #[default]
    Steps,
    /// Views rendered, mapped or inpainted (only the counts and seconds apply).
    Views,
    /// Optimiser steps of a model without a batch PSNR or a pace in samples (the stage-3
    /// enhancer): the loss, seconds and ETA apply.
    ModelSteps,
}

/// A training loop's progress after a window of steps, or a stage's over its views.
#[derive(Clone, Debug, PartialEq)]
pub struct Progress {
    /// What `step` and `total` count.
    pub unit: Unit,
    /// Steps done and planned (a budget re-fits the plan).
    pub step: u32,
    pub total: u32,
    /// Mean loss and batch PSNR of the window.
    pub loss: f64,
    pub psnr: f64,
    /// Samples per second and training seconds of this run so far (evaluations left out).
    pub samples_per_s: f64,
    pub secs: f64,
    /// Seconds left at this pace.
    pub eta: f64,
}

/// A reporter that keeps nothing (probes, tests).
#[derive(Clone, Copy, Debug, Default)]
pub struct Quiet;

impl Reporter for Quiet {
    fn note(&mut self, _line: &str) {}
    fn progress(&mut self, _p: &Progress) {}
}

/// A trainer for `cfg` from freshly initialised parameters, and its training views on the
/// device (after checking the settings); MVS depth, when the scene asks for it, is cached in
/// `run_dir`.
pub fn fresh_trainer(
    ctx: &Context,
    cfg: &RunConfig,
    loaded: &LoadedScene,
    run_dir: &Path,
) -> anyhow::Result<(Trainer, TrainData)> {
    cfg.model.validate()?;
    cfg.train.validate()?;
    let (views, _) = training_views_in(ctx, &cfg.scene, loaded, &cfg.model, run_dir)?;
    let params = extranerf_nerf::model::init_params(&cfg.model, cfg.train.seed);
    let nerf = Nerf::new(ctx, cfg.model.clone(), &params, cfg.train.background)?;
    let data = TrainData::new(ctx, &views)?;
    Ok((Trainer::new(ctx, nerf, cfg.train.clone(), 0, None)?, data))
}

/// What the training views and the whole run hold on the device, for the start of training.
pub fn memory_note(ctx: &Context, data: &TrainData) -> anyhow::Result<String> {
    let mib = |b: u64| b as f64 / (1u64 << 20) as f64;
    let (live, held) = ctx.allocated_bytes()?;
    let local: u64 = ctx
        .info()
        .heaps
        .iter()
        .filter(|h| h.device_local)
        .map(|h| h.size)
        .sum();
    Ok(format!(
        "device memory: {} training pixels of {} views, {:.1} MiB in {} binding(s) of at most \
         {:.0} MiB; {:.1} MiB allocated in all ({:.1} MiB held) of {:.0} MiB device-local",
        data.pixels(),
        data.views(),
        mib(data.device_bytes()),
        data.bindings(),
        mib(ctx.info().max_storage_buffer_range),
        mib(live),
        mib(held),
        mib(local)
    ))
}

/// Measured samples/s of `cfg`'s training step: 5 warm-up steps, then 20 timed (MVS depth
/// cached in `run_dir`, as [`fresh_trainer`]).
pub fn probe_samples_per_s(ctx: &Context, cfg: &RunConfig, run_dir: &Path) -> anyhow::Result<f64> {
    let loaded = cfg.scene.load()?;
    let (mut trainer, data) = fresh_trainer(ctx, cfg, &loaded, run_dir)?;
    let prims = Prims::new(ctx)?;
    trainer.run_steps(ctx, &prims, &data, 5)?;
    let t = Instant::now();
    trainer.run_steps(ctx, &prims, &data, 20)?;
    Ok(20.0 * trainer.samples_per_step() as f64 / t.elapsed().as_secs_f64())
}

/// Below this many rays processed (400 steps of 256 rays) `--budget` shrinks the model first.
/// Counted in rays, not samples, since the proposal sampler became the default: its 16 samples
/// per ray do the work of uniform 32 (`autoconfig::default_sampling`), so the floor stays where
/// it was measured for uniform 32 (3.3 M samples then). On fern a smaller table or fewer
/// levels cost about as much PSNR as the steps they buy (results/tradeoff_fern_lavapipe). With a 60 s budget, shrinking to 2^15 x 8 levels for 865
/// steps of 256 x 32 scored 17.50 dB / LPIPS 0.865, and keeping the auto model for 744 steps
/// 17.54 dB / 0.850.
const MIN_BUDGET_RAYS: f64 = 400.0 * 256.0;

/// The most steps `--budget` sets. It used to stop at the paper's 5000, which at 256 rays per
/// step ends long before a 15-minute budget on fern (about 0.12 s per step on two cores).
const MAX_BUDGET_STEPS: f64 = 50000.0;

/// `--budget`: sets the steps to what a measured probe says fits in `budget` seconds (at most
/// 50000). Below [`MIN_BUDGET_RAYS`], and when `shrink` (no explicit table or level flags),
/// the table and levels are reduced first, down to 2^15 and 8 levels.
pub fn fit_budget(
    ctx: &Context,
    cfg: &mut RunConfig,
    budget: f64,
    shrink: bool,
    run_dir: &Path,
    rep: &mut dyn Reporter,
) -> anyhow::Result<()> {
    if !(budget > 0.0 && budget.is_finite()) {
        bail!("--budget {budget}: give a positive number of seconds");
    }
    loop {
        let sps = probe_samples_per_s(ctx, cfg, run_dir)?;
        let per_step = cfg.train.rays as f64 * cfg.train.samples as f64;
        // 5% margin: the probe's first steps run a little faster than a whole run.
        let fit = (0.95 * budget * sps / per_step).floor();
        let steps = fit.clamp(1.0, MAX_BUDGET_STEPS) as u32;
        let m = &cfg.model;
        if fit * (cfg.train.rays as f64) < MIN_BUDGET_RAYS
            && shrink
            && (m.log2_table > 15 || m.levels > 8)
        {
            // Only what is above its floor shrinks.
            let table = if m.log2_table > 15 {
                m.log2_table - 1
            } else {
                m.log2_table
            };
            let levels = if m.levels > 8 {
                (m.levels - 2).max(8)
            } else {
                m.levels
            };
            rep.note(&format!(
                "budget {budget:.0} s: {sps:.3e} samples/s fits {fit:.0} steps with table 2^{} and {} levels; reducing to 2^{table} and {levels} levels",
                m.log2_table,
                m.levels,
            ));
            cfg.model.log2_table = table;
            cfg.model.levels = levels;
            continue;
        }
        rep.note(&format!(
            "budget {budget:.0} s: measured {sps:.3e} samples/s with {} rays x {} samples per step: {steps} steps{}",
            cfg.train.rays,
            cfg.train.samples,
            if fit > MAX_BUDGET_STEPS {
                " (the most --budget takes; the budget allows more)"
            } else {
                ""
            }
        ));
        cfg.train.steps = steps;
        cfg.train.decay_steps = steps;
        return Ok(());
    }
}

/// The total steps that fit `budget` training seconds at the pace of the `done` steps in `secs`
/// (now at step `step`, `total` planned): None while too little has run to tell (under 5% of
/// the budget or 20 s), else at least `step` (the budget is spent) and at most 50000.
pub fn refit_budget(budget: f64, secs: f64, done: u32, step: u32, total: u32) -> Option<u32> {
    if done == 0 || secs < (0.05 * budget).min(20.0) {
        return None;
    }
    let left = (budget - secs).max(0.0) * done as f64 / secs;
    let steps = (step as f64 + left.floor()).min(MAX_BUDGET_STEPS.max(step as f64)) as u32;
    (steps != total).then_some(steps)
}

/// Where and how a training loop runs.
#[derive(Clone, Debug)]
pub struct TrainRun {
    /// Run folder.
    pub out: PathBuf,
    /// Steps already done (resume).
    pub start: u32,
    /// Steps between progress lines.
    pub log_every: u32,
    /// Steps between checkpoints.
    pub checkpoint_every: u32,
    /// Steps between held-out evaluations into `curve.jsonl` (0: none).
    pub eval_every: u32,
    /// Which views those evaluations render.
    pub eval_views: ViewSet,
    /// A time budget in training seconds (evaluations left out): the steps are re-fitted to
    /// it from the pace measured as the run goes, so the run ends when it is spent.
    pub budget: Option<f64>,
}

/// Trains `cfg` from `params` (None: initialise) and `moments`, logging and checkpointing.
pub fn train_loop(
    ctx: &Context,
    cfg: &RunConfig,
    a: &TrainRun,
    params: Option<Vec<f32>>,
    moments: Option<(Vec<f32>, Vec<f32>)>,
    rep: &mut dyn Reporter,
) -> anyhow::Result<()> {
    let start = a.start;
    cfg.model.validate()?;
    cfg.train.validate()?;
    let loaded = cfg.scene.load()?;
    let t_depth = Instant::now();
    let (views, cache) = training_views_in(ctx, &cfg.scene, &loaded, &cfg.model, &a.out)?;
    let cache_dir = a.out.join(extranerf_nerf::mvs_depth::CACHE_DIR);
    rep.note(&match cache {
        None => format!("depth: {}", cfg.scene.depth_label()),
        Some(CacheUse::Reused) => format!(
            "depth: {} (maps reused from {})",
            cfg.scene.depth_label(),
            cache_dir.display()
        ),
        Some(CacheUse::Computed) => format!(
            "depth: {} (computed in {:.1} s, cached in {})",
            cfg.scene.depth_label(),
            t_depth.elapsed().as_secs_f64(),
            cache_dir.display()
        ),
    });
    let depth_targets: usize = views
        .iter()
        .filter_map(|v| v.depth.as_ref())
        .map(|d| d.iter().filter(|p| p[1] > 0.0).count())
        .sum();
    rep.note(&format!(
        "scene {}: {} views, training on {:?}, testing on {:?}; {} depth targets; space {}",
        cfg.scene.dir.display(),
        loaded.scene.cameras.len(),
        loaded.split.train,
        loaded.split.test,
        depth_targets,
        cfg.model.space
    ));
    let params =
        params.unwrap_or_else(|| extranerf_nerf::model::init_params(&cfg.model, cfg.train.seed));
    let nerf = Nerf::new(ctx, cfg.model.clone(), &params, cfg.train.background)?;
    let data = TrainData::new(ctx, &views)?;
    let prims = Prims::new(ctx)?;
    let moments = moments.as_ref().map(|(m, v)| (m.as_slice(), v.as_slice()));
    let mut trainer = Trainer::new(ctx, nerf, cfg.train.clone(), start, moments)?;
    rep.note(&memory_note(ctx, &data)?);
    rep.note(&format!(
        "model: hash grid {}x{}x2^{} (N {}..{}, {}), MLPs {:?} and {:?}, {} parameters; {} rays x {} samples per step",
        cfg.model.levels,
        cfg.model.features,
        cfg.model.log2_table,
        cfg.model.min_res,
        cfg.model.max_res,
        cfg.model.precision,
        cfg.model.density_mlp().dims,
        cfg.model.color_mlp().dims,
        trainer.nerf().field().layout().total,
        cfg.train.rays,
        cfg.train.samples
    ));
    if let Some(p) = cfg.model.sampler.proposal() {
        rep.note(&format!(
            "sampler: proposal: a density field (hash grid {}x{}x2^{}, N {}..{}, MLP {:?}) at {} strata per ray; the {} samples per ray drawn from its weights; interlevel loss weight {}",
            p.levels,
            p.features,
            p.log2_table,
            p.min_res,
            p.max_res,
            p.mlp().dims,
            p.samples,
            cfg.train.samples,
            p.interlevel
        ));
    }
    match trainer.standalone_reason() {
        None => rep.note(
            "training step: fused kernel (pixels to gradients) + MLP weight-gradient reduction",
        ),
        Some(why) => rep.note(&format!("training step: standalone kernels ({why})")),
    }
    rep.note(&format!(
        "MLPs: {} (--mlp {}; the weight gradient, and with the standalone step the forward pass and input gradient too)",
        trainer.mlp_path(),
        cfg.train.mlp.name()
    ));
    if let Some(occ) = trainer.occupancy() {
        let g = occ.config();
        rep.note(&format!(
            "skipping empty space: occupancy grid {}^3 x {} cascade(s), a sweep every {} steps, {} probes per ray, from step {}",
            g.res,
            g.cascades,
            cfg.train.occupancy_every,
            cfg.train.occupancy_probes,
            cfg.train.occupancy_warmup + 1
        ));
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let mut log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(a.out.join("progress.jsonl"))
        .with_context(|| format!("opening {}", a.out.join("progress.jsonl").display()))?;
    let save = |t: &Trainer| -> anyhow::Result<()> {
        let params = t.nerf().params().read()?;
        let moments = t.moments()?;
        let mut config = cfg.clone();
        // A budget's re-fitted schedule.
        config.train.steps = t.config().steps;
        config.train.decay_steps = t.config().decay_steps;
        save_checkpoint(
            &a.out,
            &Checkpoint {
                config,
                step: t.step(),
                params,
                moments: Some(moments),
            },
        )?;
        Ok(())
    };
    let mut curve = if a.eval_every > 0 {
        Some(HeldOut::new(
            &loaded,
            &a.eval_views,
            &a.out,
            start,
            cfg.train.background,
            rep,
        )?)
    } else {
        None
    };
    let t0 = Instant::now();
    // Seconds spent in held-out evaluations, left out of the training time.
    let mut eval_secs = 0.0;
    let mut total = cfg.train.steps;
    while trainer.step() < total {
        let to_ckpt = a.checkpoint_every - trainer.step() % a.checkpoint_every;
        let to_eval = if a.eval_every > 0 {
            a.eval_every - trainer.step() % a.eval_every
        } else {
            u32::MAX
        };
        let count = a
            .log_every
            .min(total - trainer.step())
            .min(to_ckpt)
            .min(to_eval);
        let stats = trainer.run_steps(ctx, &prims, &data, count)?;
        if !(stats.loss.is_finite() && stats.mse.is_finite()) {
            bail!(
                "the loss became {} at step {}; the last checkpoint in {} is intact",
                stats.loss,
                trainer.step(),
                a.out.display()
            );
        }
        let done = trainer.step() - start;
        let secs = t0.elapsed().as_secs_f64() - eval_secs;
        if let Some(budget) = a.budget {
            if let Some(steps) = refit_budget(budget, secs, done, trainer.step(), total) {
                if (steps as f64 - total as f64).abs() > 0.02 * total as f64 {
                    rep.note(&format!(
                        "budget {budget:.0} s: {:.1} s for {done} steps; the run now ends at step {steps} (was {total})",
                        secs
                    ));
                }
                trainer.set_steps(steps)?;
                total = steps;
            }
        }
        let sps = done as f64 * trainer.samples_per_step() as f64 / secs;
        let eta = secs / done as f64 * (total - trainer.step()) as f64;
        rep.progress(&Progress {
            unit: Unit::Steps,
            step: trainer.step(),
            total,
            loss: stats.loss,
            psnr: stats.psnr(),
            samples_per_s: sps,
            secs,
            eta,
        });
        writeln!(
            log,
            "{}",
            serde_json::json!({"step": trainer.step(), "loss": stats.loss, "mse": stats.mse, "psnr": stats.psnr(), "samples_per_s": sps, "elapsed_s": secs})
        )?;
        if trainer.step() % a.checkpoint_every == 0 || trainer.step() == total {
            save(&trainer)?;
        }
        if let Some(c) = &mut curve {
            if trainer.step() % a.eval_every == 0 || trainer.step() == total {
                let te = Instant::now();
                c.evaluate(ctx, &trainer, &stats, secs, rep)?;
                eval_secs += te.elapsed().as_secs_f64();
            }
        }
    }
    let secs = t0.elapsed().as_secs_f64() - eval_secs;
    rep.note(&format!(
        "trained {} steps in {:.1} s ({:.3e} samples/s); checkpoint in {}",
        trainer.step() - start,
        secs,
        (trainer.step() - start) as f64 * trainer.samples_per_step() as f64 / secs.max(1e-9),
        a.out.display()
    ));
    if let Some(f) = trainer.occupied_fraction()? {
        rep.note(&format!(
            "occupancy grid: {:.1}% of cells occupied at the end",
            100.0 * f
        ));
    }
    Ok(())
}

/// Which of a scene's views a command reads: `test`, `train`, `all` or indices such as
/// `0,8,16`, parsed when the command line is (before any device or file is touched).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ViewSet {
    /// The split's held-out views.
    Test,
    /// The split's training views.
    Train,
    /// The held-out views, then the training views.
    All,
    /// These views, in this order.
    Indices(Vec<usize>),
}

impl std::str::FromStr for ViewSet {
    type Err = String;

    fn from_str(s: &str) -> Result<ViewSet, String> {
        match s.trim() {
            "test" => Ok(ViewSet::Test),
            "train" => Ok(ViewSet::Train),
            "all" => Ok(ViewSet::All),
            list => list
                .split(',')
                .map(|v| v.trim().parse::<usize>())
                .collect::<Result<Vec<_>, _>>()
                .map(ViewSet::Indices)
                .map_err(|_| format!("`{s}`: use test, train, all or view indices like 0,8,16")),
        }
    }
}

impl std::fmt::Display for ViewSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ViewSet::Test => f.write_str("test"),
            ViewSet::Train => f.write_str("train"),
            ViewSet::All => f.write_str("all"),
            ViewSet::Indices(v) => {
                let s: Vec<String> = v.iter().map(usize::to_string).collect();
                f.write_str(&s.join(","))
            }
        }
    }
}

impl ViewSet {
    /// The view indices in `split` of a scene of `n` views; an index past the scene is an error
    /// naming `flag`.
    pub fn indices(
        &self,
        split: &extranerf_nerf::data::split::SplitIndices,
        n: usize,
        flag: &str,
    ) -> anyhow::Result<Vec<usize>> {
        Ok(match self {
            ViewSet::Test => split.test.clone(),
            ViewSet::Train => split.train.clone(),
            ViewSet::All => split.test.iter().chain(&split.train).copied().collect(),
            ViewSet::Indices(v) => {
                if let Some(i) = v.iter().find(|&&i| i >= n) {
                    bail!("{flag}: view {i} does not exist (the scene has {n})");
                }
                v.clone()
            }
        })
    }
}

/// Held-out evaluations during training (`train --eval-every`): each renders the chosen views
/// at the training samples per ray, as `render` would ([`Nerf::default_march`]: the fused march,
/// or the proposal sampler's samples when the field has one), and appends one line to
/// `curve.jsonl`.
pub struct HeldOut {
    views: Vec<(usize, extranerf_nerf::data::Camera, Vec<f32>)>,
    lpips: Option<Lpips>,
    log: std::fs::File,
    path: PathBuf,
}

impl std::fmt::Debug for HeldOut {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HeldOut")
            .field("views", &self.views.iter().map(|v| v.0).collect::<Vec<_>>())
            .field("lpips", &self.lpips.is_some())
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

impl HeldOut {
    /// The views `which` of `loaded` (ground truth composited over the renders' `background`),
    /// with LPIPS when its weights are found, appending to `out/curve.jsonl` (replaced when
    /// `start` is 0).
    pub fn new(
        loaded: &LoadedScene,
        which: &ViewSet,
        out: &Path,
        start: u32,
        background: [f32; 3],
        rep: &mut dyn Reporter,
    ) -> anyhow::Result<HeldOut> {
        let indices = which.indices(&loaded.split, loaded.scene.cameras.len(), "--eval-views")?;
        if indices.is_empty() {
            bail!("--eval-every: the split holds no held-out view to evaluate");
        }
        let mut views = Vec::new();
        for i in indices {
            let cam = loaded.scene.cameras[i].clone();
            let truth = extranerf_nerf::data::load_image_over(&cam.image, background)?;
            views.push((i, cam, truth.rgb));
        }
        let lpips = match lpips_alex(None) {
            Ok(l) => Some(l),
            Err(e) => {
                rep.note(&format!("--eval-every: no LPIPS in the curve ({e:#})"));
                None
            }
        };
        std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
        let path = out.join("curve.jsonl");
        if start == 0 && path.exists() {
            std::fs::remove_file(&path).with_context(|| format!("replacing {}", path.display()))?;
        }
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .with_context(|| format!("opening {}", path.display()))?;
        Ok(HeldOut {
            views,
            lpips,
            log,
            path,
        })
    }

    /// Renders the views from the trainer's current field and appends their means.
    pub fn evaluate(
        &mut self,
        ctx: &Context,
        trainer: &Trainer,
        stats: &StepStats,
        train_secs: f64,
        rep: &mut dyn Reporter,
    ) -> anyhow::Result<()> {
        let samples = trainer.config().samples;
        let (mut p, mut s, mut l, mut o) = (0.0, 0.0, 0.0, 0.0);
        for (_, cam, truth) in &self.views {
            let nerf = trainer.nerf();
            let (rgb, _, opacity) =
                nerf.render_with(ctx, cam, 8192, samples, nerf.default_march())?;
            p += psnr(&rgb, truth)?;
            s += ssim(&rgb, truth, cam.width, cam.height)?;
            if let Some(lp) = &self.lpips {
                l += lp.distance(&rgb, truth, cam.width, cam.height)?;
            }
            o += opacity.iter().map(|&v| v as f64).sum::<f64>() / opacity.len().max(1) as f64;
        }
        let n = self.views.len() as f64;
        let line = serde_json::json!({
            "step": trainer.step(),
            "train_seconds": train_secs,
            "test_psnr": p / n,
            "test_ssim": s / n,
            "test_lpips_alex": self.lpips.as_ref().map(|_| l / n),
            "test_opacity": o / n,
            "batch_psnr": stats.psnr(),
            "views": self.views.iter().map(|v| v.0).collect::<Vec<_>>(),
        });
        rep.note(&format!(
            "held-out at step {} ({train_secs:.1} s of training): PSNR {:.2} SSIM {:.3} LPIPS-alex {} opacity {:.3}",
            trainer.step(),
            p / n,
            s / n,
            self.lpips
                .as_ref()
                .map_or("-".to_string(), |_| format!("{:.3}", l / n)),
            o / n
        ));
        writeln!(self.log, "{line}").with_context(|| format!("writing {}", self.path.display()))?;
        Ok(())
    }
}

/// Where LPIPS weights are looked for by default: `$EXTRANERF_MODELS/lpips`, else
/// `../shared/models/lpips` (the project's shared folder beside the checkout).
pub fn default_lpips_dir() -> PathBuf {
    std::env::var_os("EXTRANERF_MODELS")
        .map(|m| PathBuf::from(m).join("lpips"))
        .unwrap_or_else(|| PathBuf::from("../shared/models/lpips"))
}

/// The AlexNet LPIPS from `dir` (default [`default_lpips_dir`]), the error naming the folder.
pub fn lpips_alex(dir: Option<&std::path::Path>) -> anyhow::Result<Lpips> {
    let dir = dir.map(PathBuf::from).unwrap_or_else(default_lpips_dir);
    Lpips::load(&dir.join("lpips_alex_v0.1.safetensors"), LpipsNet::Alex)
        .with_context(|| format!("LPIPS weights in {} (--lpips)", dir.display()))
}

#[cfg(test)]
mod tests {
    use super::refit_budget;

    #[test]
    fn budgets_refit_the_steps_to_the_clock() {
        // Too early to tell: under 20 s (and under 5% of a long budget).
        assert_eq!(refit_budget(900.0, 10.0, 100, 100, 5000), None);
        // 100 steps in 30 s with 870 s left: 2900 more.
        assert_eq!(refit_budget(900.0, 30.0, 100, 100, 5000), Some(3000));
        // Resumed or probed runs count only the steps done in this run for the pace.
        assert_eq!(refit_budget(600.0, 60.0, 200, 700, 1000), Some(2500));
        // Nothing to change.
        assert_eq!(refit_budget(900.0, 30.0, 100, 100, 3000), None);
        // The budget is spent: stop at the current step.
        assert_eq!(refit_budget(100.0, 120.0, 500, 500, 800), Some(500));
        // At most 50000 steps, but never fewer than those done.
        assert_eq!(refit_budget(1e6, 100.0, 1000, 1000, 5000), Some(50000));
        assert_eq!(refit_budget(1e6, 100.0, 1000, 60000, 70000), Some(60000));
        // A short budget is judged from 5% of it.
        assert_eq!(refit_budget(100.0, 5.0, 50, 50, 400), Some(1000));
    }
}
