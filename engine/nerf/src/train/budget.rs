//! `--budget`: the steps that fit a time budget, from a measured probe, and re-fitted to the
//! clock as the run goes.

use std::path::Path;
use std::time::Instant;

use extranerf_gpu::Context;
use extranerf_prims::Prims;

use super::report::Reporter;
use super::{fresh_trainer, Result, TrainError};
use crate::run::RunConfig;

/// Measured samples/s of `cfg`'s training step: 5 warm-up steps, then 20 timed (MVS depth
/// cached in `run_dir`, as [`fresh_trainer`]).
pub fn probe_samples_per_s(ctx: &Context, cfg: &RunConfig, run_dir: &Path) -> Result<f64> {
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
/// 50000). Below `MIN_BUDGET_RAYS`, and when `shrink` (no explicit table or level flags),
/// the table and levels are reduced first, down to 2^15 and 8 levels.
pub fn fit_budget(
    ctx: &Context,
    cfg: &mut RunConfig,
    budget: f64,
    shrink: bool,
    run_dir: &Path,
    rep: &mut dyn Reporter,
) -> Result<()> {
    if !(budget > 0.0 && budget.is_finite()) {
        return Err(TrainError::Usage(format!(
            "--budget {budget}: give a positive number of seconds"
        )));
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
