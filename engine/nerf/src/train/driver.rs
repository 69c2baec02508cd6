//! The training loop of a run folder: logging (`progress.jsonl`), checkpoints, the NaN abort,
//! a budget's re-fit and the held-out curve.

use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use extranerf_gpu::files::{remove_stale_temporaries, RunLock};
use extranerf_gpu::Context;
use extranerf_prims::Prims;

use super::budget::refit_budget;
use super::held_out::HeldOut;
use super::report::{Progress, Reporter, Unit};
use super::view_set::ViewSet;
use super::{memory_note, Result, TrainError};
use crate::mvs_depth::CacheUse;
use crate::renderer::Nerf;
use crate::run::{save_checkpoint, training_views_in, Checkpoint, LoadedScene, RunConfig};
use crate::trainer::Trainer;
use crate::views::{TrainData, View};

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
) -> Result<()> {
    let start = a.start;
    cfg.model.validate()?;
    cfg.train.validate()?;
    // The folder is this process's until it returns; what an interrupted write left goes.
    let _lock = RunLock::acquire(&a.out)?;
    let stale =
        remove_stale_temporaries(&a.out).map_err(|e| TrainError::io("cleaning", &a.out, e))?;
    if !stale.is_empty() {
        rep.note(&format!(
            "removed {} temporary file(s) an interrupted write left in {}",
            stale.len(),
            a.out.display()
        ));
    }
    let loaded = cfg.scene.load()?;
    let views = depth_and_views(ctx, cfg, &loaded, a, rep)?;
    let params = params.unwrap_or_else(|| crate::model::init_params(&cfg.model, cfg.train.seed));
    let nerf = Nerf::new(ctx, cfg.model.clone(), &params, cfg.train.background)?;
    let data = TrainData::new(ctx, &views)?;
    let prims = Prims::new(ctx)?;
    let moments = moments.as_ref().map(|(m, v)| (m.as_slice(), v.as_slice()));
    let mut trainer = Trainer::new(ctx, nerf, cfg.train.clone(), start, moments)?;
    rep.note(&memory_note(ctx, &data)?);
    model_notes(cfg, &trainer, rep);
    std::fs::create_dir_all(&a.out).map_err(|e| TrainError::io("creating", &a.out, e))?;
    let log_path = a.out.join("progress.jsonl");
    let mut log = super::open_step_log(&log_path, start)?;
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
            return Err(TrainError::Diverged {
                loss: stats.loss,
                step: trainer.step(),
                dir: a.out.clone(),
            });
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
        )
        .map_err(|e| TrainError::io("writing", &log_path, e))?;
        if trainer.step() % a.checkpoint_every == 0 || trainer.step() == total {
            save(&trainer, cfg, a)?;
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

/// The checkpoint of `t` in the run folder, with a budget's re-fitted schedule.
fn save(t: &Trainer, cfg: &RunConfig, a: &TrainRun) -> Result<()> {
    let params = t.nerf().params().read()?;
    let moments = t.moments()?;
    let mut config = cfg.clone();
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
}

/// The training views with their depth targets (MVS depth cached in the run folder), with
/// notes of where the depth came from and of the split.
fn depth_and_views(
    ctx: &Context,
    cfg: &RunConfig,
    loaded: &LoadedScene,
    a: &TrainRun,
    rep: &mut dyn Reporter,
) -> Result<Vec<View>> {
    let t_depth = Instant::now();
    let (views, cache) = training_views_in(ctx, &cfg.scene, loaded, &cfg.model, &a.out)?;
    let cache_dir = a.out.join(crate::mvs_depth::CACHE_DIR);
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
    Ok(views)
}

/// Notes of the model, the sampler, the training step's kernels and the occupancy grid.
fn model_notes(cfg: &RunConfig, trainer: &Trainer, rep: &mut dyn Reporter) {
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
}
