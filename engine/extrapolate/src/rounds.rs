//! What the round-based stages (stage 2, stage 3 and its data collector) share: the noise
//! schedule of the rounds ([`Stage2Spec`]), the state between rounds and its resume, training a
//! round, and the held-out views' renders that `eval` scores.

use std::path::{Path, PathBuf};
use std::time::Instant;

use extranerf_gpu::Context;
use extranerf_nerf::data::{Camera, Image};
use extranerf_nerf::renderer::Nerf;
use extranerf_nerf::run::{load_checkpoint, save_checkpoint, write_png, Checkpoint, RunConfig};
use extranerf_nerf::trainer::{StepStats, TrainConfig, Trainer};
use extranerf_nerf::views::{TrainData, View, ViewKind, ViewSampling};
use extranerf_prims::Prims;
use serde::{Deserialize, Serialize};

use crate::error::{read_text, ExtrapolateError, Result};
use crate::inpaint::Fill;
use crate::stage::render;
use extranerf_nerf::train::{Progress, Reporter, Unit};

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
    pub fn validate(&self) -> Result<()> {
        if self.rounds == 0 || self.steps_per_round == 0 {
            return Err(ExtrapolateError::usage(
                "stage 2 needs at least one round of at least one step",
            ));
        }
        if !(0.0..=1.0).contains(&self.virtual_fraction) {
            return Err(ExtrapolateError::usage(format!(
                "--virtual-fraction {}: use a value in [0, 1]",
                self.virtual_fraction
            )));
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return Err(ExtrapolateError::usage(format!(
                "--stage2-lr {}: use a positive learning rate",
                self.lr
            )));
        }
        if !(0.0..=1.0).contains(&self.visible_weight) {
            return Err(ExtrapolateError::usage(format!(
                "--visible-weight {}: use a value in [0, 1]",
                self.visible_weight
            )));
        }
        for t in [self.t_start, self.t_end] {
            if !(0.0..1.0).contains(&t) {
                return Err(ExtrapolateError::usage(format!(
                    "noise levels must be in [0, 1), not {t}"
                )));
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

/// The stage-2 and stage-3 state between rounds (`round.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct RoundState {
    pub rounds_done: u32,
    pub seconds: f64,
}

/// The file of [`RoundState`].
pub(crate) const ROUND_FILE: &str = "round.json";

/// The last finished round of a round-based stage in `out`, with its checkpoint.
pub(crate) fn load_round(out: &Path) -> Result<Option<(RoundState, Checkpoint)>> {
    let state_path = out.join(ROUND_FILE);
    if !(state_path.exists() && out.join(extranerf_nerf::run::CHECKPOINT_FILE).exists()) {
        return Ok(None);
    }
    let s: RoundState = serde_json::from_str(&read_text(&state_path)?)
        .map_err(|e| ExtrapolateError::malformed(&state_path, e.to_string()))?;
    Ok(Some((s, load_checkpoint(out)?)))
}

/// A finished round: the checkpoint, then the state that points at it. A crash between the
/// two leaves a checkpoint one round ahead of its record, which [`rounds_done`] reads as the
/// round finished.
pub(crate) fn save_round(
    out: &Path,
    cfg: &RunConfig,
    tcfg: &TrainConfig,
    trainer: &Trainer,
    state: &RoundState,
) -> Result<()> {
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
    // Compact: one line.
    let path = out.join(ROUND_FILE);
    let json = serde_json::to_string(state)
        .map_err(|e| ExtrapolateError::malformed(&path, format!("cannot serialise: {e}")))?;
    extranerf_nerf::safetensors::write_atomic(&path, json.as_bytes())?;
    Ok(())
}

/// The rounds a stage's checkpoint at `step` holds, checked against its record `state`: the
/// recorded rounds, or one more where a crash came between the round's checkpoint and its
/// record. Any other step is an error naming both (the folder was written by something else).
pub(crate) fn rounds_done(
    out: &Path,
    name: &str,
    state: &RoundState,
    step: u32,
    first_step: u32,
    steps_per_round: u32,
) -> Result<u32> {
    let at = |rounds: u32| first_step as u64 + rounds as u64 * steps_per_round as u64;
    if step as u64 == at(state.rounds_done) {
        Ok(state.rounds_done)
    } else if step as u64 == at(state.rounds_done + 1) {
        Ok(state.rounds_done + 1)
    } else {
        Err(ExtrapolateError::malformed(
            &out.join(ROUND_FILE),
            format!(
                "{} rounds done (step {}), but its checkpoint holds step {step}; run it again with --resume --redo {name}",
                state.rounds_done,
                at(state.rounds_done)
            ),
        ))
    }
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
) -> Result<(Option<StepStats>, f64)> {
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
) -> Result<Option<StepStats>> {
    let tt = Instant::now();
    let mut left = steps;
    let mut last = None;
    while left > 0 {
        let n = left.min(25);
        let stats = trainer.run_steps(ctx, prims, data, n)?;
        if !(stats.loss.is_finite() && stats.mse.is_finite()) {
            return Err(ExtrapolateError::Diverged {
                what: what.to_string(),
                loss: stats.loss,
                dir: out.to_path_buf(),
            });
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

/// The held-out views rendered from `nerf` into `out/test_NNN.png` (what `eval` scores), or
/// where the split holds none out the training views into `out/train_NNN.png`.
pub(crate) fn write_test_renders(
    ctx: &Context,
    nerf: &Nerf,
    loaded: &extranerf_nerf::run::LoadedScene,
    samples: u32,
    out: &Path,
) -> Result<()> {
    let shown = crate::shown::Shown::of(&loaded.split);
    for &i in &shown.views {
        let cam = &loaded.scene.cameras[i];
        let (rgb, _, _) = render(ctx, nerf, cam, samples)?;
        write_png(
            &out.join(format!("{}.png", shown.name(i))),
            cam.width,
            cam.height,
            &rgb,
        )?;
    }
    Ok(())
}

/// A round-based stage's trainer: resumed after the last finished round in its folder, or
/// started from a field (params and Adam moments) at round 0.
pub(crate) struct Rounds {
    pub trainer: Trainer,
    pub prims: Prims,
    /// The first round to run.
    pub start: u32,
    /// The stage's seconds before this run (its earlier rounds).
    pub seconds: f64,
    /// The stage's folder.
    pub out: PathBuf,
    /// The run configuration its checkpoints carry, with the stage's training settings.
    pub cfg: RunConfig,
    pub tcfg: TrainConfig,
}

impl Rounds {
    /// Opens the rounds of the stage `name` in `out`: its trainer at `first_step + rounds done
    /// * steps_per_round`, on `cfg`'s field with the stage's training settings `tcfg`, from
    /// `from` (a checkpoint's params and moments) when no round is done.
    #[allow(clippy::too_many_arguments)] // each is a distinct input of the stage
    pub(crate) fn open(
        ctx: &Context,
        out: &Path,
        name: &str,
        cfg: &RunConfig,
        tcfg: TrainConfig,
        from: &Checkpoint,
        first_step: u32,
        steps_per_round: u32,
        rep: &mut dyn Reporter,
    ) -> Result<Rounds> {
        let resumed = load_round(out)?;
        let (start, seconds) = match &resumed {
            Some((s, ck)) => {
                let done = rounds_done(out, name, s, ck.step, first_step, steps_per_round)?;
                if done != s.rounds_done {
                    rep.note(&format!(
                        "{name}: round {done}'s checkpoint was saved but not its record ({ROUND_FILE} says {} rounds); the round is kept, its time not counted",
                        s.rounds_done
                    ));
                }
                rep.note(&format!("{name}: resuming after round {done}"));
                (done, s.seconds)
            }
            None => (0, 0.0),
        };
        let ck = resumed.as_ref().map_or(from, |(_, ck)| ck);
        let nerf = Nerf::new(ctx, cfg.model.clone(), &ck.params, cfg.train.background)?;
        let moments = ck
            .moments
            .as_ref()
            .map(|(m, v)| (m.as_slice(), v.as_slice()));
        let trainer = Trainer::new(
            ctx,
            nerf,
            tcfg.clone(),
            first_step + start * steps_per_round,
            moments,
        )?;
        Ok(Rounds {
            trainer,
            prims: Prims::new(ctx)?,
            start,
            seconds,
            out: out.to_path_buf(),
            cfg: cfg.clone(),
            tcfg,
        })
    }

    /// The end of round `round` (started at `t0`): [`train_round`] on `views` into the stage's
    /// folder.
    #[allow(clippy::too_many_arguments)] // each is a distinct input of the loop
    pub(crate) fn train(
        &mut self,
        ctx: &Context,
        views: &[View],
        virtual_fraction: f32,
        steps: u32,
        what: &str,
        (round, t0): (u32, Instant),
        rep: &mut dyn Reporter,
    ) -> Result<(Option<StepStats>, f64)> {
        train_round(
            ctx,
            &mut self.trainer,
            &self.prims,
            views,
            virtual_fraction,
            steps,
            what,
            &RoundSink {
                out: &self.out,
                cfg: &self.cfg,
                tcfg: &self.tcfg,
            },
            (round, t0, &mut self.seconds),
            rep,
        )
    }
}

/// A virtual view at `cam` supervised by `fill`: each pixel's colour with the loss weight
/// `weight(m)` and its depth with the confidence `conf(m)`, `m` its `mask` value (>= 0.5: a
/// filled pixel).
pub(crate) fn fill_view(
    cam: &Camera,
    fill: &Fill,
    mask: &[f32],
    weight: impl Fn(f32) -> f32,
    conf: impl Fn(f32) -> f32,
) -> View {
    View {
        camera: cam.clone(),
        image: Image::opaque(cam.width, cam.height, fill.rgb.clone()),
        depth: Some(
            fill.depth
                .iter()
                .zip(mask)
                .map(|(&d, &m)| [d, conf(m)])
                .collect(),
        ),
        weight: Some(mask.iter().map(|&m| weight(m)).collect()),
        kind: ViewKind::Virtual,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_checkpoint_a_round_ahead_of_its_record_counts_and_any_other_is_refused() {
        let out = Path::new("run/stage3-harmonic");
        let s = RoundState {
            rounds_done: 2,
            seconds: 5.0,
        };
        // Stage 3 starts at the stage-2 checkpoint's step 300, 50 steps a round.
        let done = |step| rounds_done(out, "stage3-harmonic", &s, step, 300, 50);
        assert_eq!(done(400).unwrap(), 2);
        assert_eq!(done(450).unwrap(), 3);
        for bad in [350, 500, 401, 0] {
            let e = done(bad).unwrap_err().to_string();
            assert!(
                e.contains("round.json")
                    && e.contains(&format!("holds step {bad}"))
                    && e.contains("--redo stage3-harmonic"),
                "{e}"
            );
        }
    }
}
