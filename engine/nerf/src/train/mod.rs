//! The BaseNeRF training driver: a trainer from a run configuration, time budgets (a probe
//! that sets the steps, re-fitted to the clock as the run goes), the training loop with its run
//! folder (checkpoints, `progress.jsonl`, NaN abort) and held-out curves (`curve.jsonl`).
//! `extranerf train`, the demo, the trade-off sweeps and ExtraNeRF's BaseNeRF stage run it.
//!
//! - [`report`]: where progress and notes go ([`Reporter`]); nothing here prints;
//! - [`budget`]: `--budget`, the probe and the re-fit;
//! - [`driver`]: the training loop ([`train_loop`]);
//! - [`held_out`]: held-out evaluations during training, and the LPIPS weights they use;
//! - [`view_set`]: which of a scene's views a command reads.

pub mod budget;
pub mod driver;
pub mod held_out;
pub mod report;
pub mod step_log;
pub mod view_set;

pub use budget::{fit_budget, probe_samples_per_s, refit_budget};
pub use driver::{train_loop, TrainRun};
pub use held_out::{default_lpips_dir, lpips_alex, HeldOut};
pub use report::{Progress, Quiet, Reporter, Unit};
pub use step_log::open_step_log;
pub use view_set::ViewSet;

use std::path::{Path, PathBuf};

use extranerf_gpu::{Context, GpuError};

use crate::data::DataError;
use crate::metrics::MetricsError;
use crate::renderer::Nerf;
use crate::run::{training_views_in, LoadedScene, RunConfig, RunError};
use crate::trainer::Trainer;
use crate::views::TrainData;

/// What can go wrong training a run.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// The scene, its depth or the run folder's files.
    #[error(transparent)]
    Run(#[from] RunError),
    /// Reading a scene file.
    #[error(transparent)]
    Data(#[from] DataError),
    /// The device, or a setting the trainer refuses.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// A held-out evaluation's metric.
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    /// The run folder is another process's (its lock), or cannot be locked.
    #[error(transparent)]
    Locked(#[from] extranerf_gpu::files::LockError),
    /// A file of the run folder (the OS error is in the message, not a separate source, so a
    /// chain does not print it twice).
    #[error("{what} {}: {error}", path.display())]
    Io {
        /// What was being done: creating, opening, writing.
        what: &'static str,
        path: PathBuf,
        error: std::io::Error,
    },
    /// The LPIPS weights of the held-out curve or a check did not load.
    #[error("LPIPS weights in {} (--lpips): {error}", dir.display())]
    Lpips { dir: PathBuf, error: MetricsError },
    /// The loss stopped being finite; the last checkpoint is intact.
    #[error("the loss became {loss} at step {step}; the last checkpoint in {} is intact", dir.display())]
    Diverged { loss: f64, step: u32, dir: PathBuf },
    /// A setting or flag that cannot work.
    #[error("{0}")]
    Usage(String),
}

impl TrainError {
    /// An I/O error doing `what` to `path`.
    pub fn io(what: &'static str, path: &Path, error: std::io::Error) -> TrainError {
        TrainError::Io {
            what,
            path: path.to_path_buf(),
            error,
        }
    }
}

/// Result alias of training.
pub type Result<T, E = TrainError> = std::result::Result<T, E>;

/// A trainer for `cfg` from freshly initialised parameters, and its training views on the
/// device (after checking the settings); MVS depth, when the scene asks for it, is cached in
/// `run_dir`.
pub fn fresh_trainer(
    ctx: &Context,
    cfg: &RunConfig,
    loaded: &LoadedScene,
    run_dir: &Path,
) -> Result<(Trainer, TrainData)> {
    cfg.model.validate()?;
    cfg.train.validate()?;
    let (views, _) = training_views_in(ctx, &cfg.scene, loaded, &cfg.model, run_dir)?;
    let params = crate::model::init_params(&cfg.model, cfg.train.seed);
    let nerf = Nerf::new(ctx, cfg.model.clone(), &params, cfg.train.background)?;
    let data = TrainData::new(ctx, &views)?;
    Ok((Trainer::new(ctx, nerf, cfg.train.clone(), 0, None)?, data))
}

/// What the training views and the whole run hold on the device, for the start of training.
pub fn memory_note(ctx: &Context, data: &TrainData) -> Result<String> {
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
