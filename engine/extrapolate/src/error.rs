//! The one error type of the ExtraNeRF crate: [`ExtrapolateError`], composed from the errors of
//! the crates it drives, so that a caller can tell a bad input from a device failure, a stage
//! that failed from a run folder that refused to resume.

use std::path::{Path, PathBuf};

use extranerf_diffusion::device::DeviceError;
use extranerf_diffusion::DiffusionError;
use extranerf_gpu::GpuError;
use extranerf_nerf::cameras::CameraError;
use extranerf_nerf::data::DataError;
use extranerf_nerf::metrics::MetricsError;
use extranerf_nerf::run::RunError;
use extranerf_nerf::train::TrainError;
use extranerf_nerf::video::VideoError;

use crate::inpaint::InpaintError;

/// What can go wrong in the ExtraNeRF pipeline.
///
/// The variants that wrap another crate's error print it unchanged. The others keep an OS
/// error or an inner error in their message, not as a separate source, so that a chain of
/// sources does not print it twice; [`ExtrapolateError::cause`] looks through the stage that
/// failed.
#[derive(Debug, thiserror::Error)]
pub enum ExtrapolateError {
    /// A stage failed (its name, and why).
    #[error("stage {stage}: {error}")]
    Stage {
        /// The stage's name in the manifest (`base`, `visibility`, `stage2-harmonic`, ...).
        stage: String,
        error: Box<ExtrapolateError>,
    },
    /// The run folder cannot be continued as asked: it holds a run and `resume` was not given,
    /// it holds none and it was, it was made from another scene, or a stage was run with
    /// settings that the one asked for may not change.
    #[error("{}: {reason}", dir.display())]
    Resume { dir: PathBuf, reason: String },
    /// A run folder lacks what was asked of it (no manifest, a stage not finished).
    #[error("{}: {what}", dir.display())]
    Incomplete { dir: PathBuf, what: String },
    /// A setting, a flag or an argument of a call that cannot work.
    #[error("{0}")]
    Usage(String),
    /// A file or folder of the run could not be read, written or created.
    #[error("{what} {}: {error}", path.display())]
    Io {
        /// What was being done: reading, writing, creating, removing.
        what: &'static str,
        path: PathBuf,
        error: std::io::Error,
    },
    /// A file exists but its content is not what it should be.
    #[error("{}: {problem}", path.display())]
    Malformed { path: PathBuf, problem: String },
    /// A round's training stopped being finite; the rounds finished before it are intact.
    #[error("{what}: the loss became {loss}; the last finished round in {} is intact", dir.display())]
    Diverged {
        /// The training that diverged (`stage2-harmonic round 2`, a data round).
        what: String,
        loss: f64,
        /// The stage's folder.
        dir: PathBuf,
    },
    /// Work on one view failed (the view, and why): an inpainting or an enhancement.
    #[error("{view}: {error}")]
    View {
        /// `virtual view 3, round 1`, `training view 0, data round 2`, `triplet fresh_100_002`.
        view: String,
        error: Box<ExtrapolateError>,
    },
    /// An inpainter refused its input.
    #[error(transparent)]
    Inpaint(#[from] InpaintError),
    /// A run's scene, its checkpoint or its settings ([`extranerf_nerf::run`]).
    #[error(transparent)]
    Run(#[from] RunError),
    /// A scene or tensor file ([`extranerf_nerf::data`]).
    #[error(transparent)]
    Data(#[from] DataError),
    /// The Vulkan device.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// Training the BaseNeRF ([`extranerf_nerf::train`]).
    #[error(transparent)]
    Train(#[from] TrainError),
    /// A metric (LPIPS, PSNR, SSIM) or its weights.
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    /// A diffusion model (the inpainter, the enhancer) or the burn device the models and the
    /// Inception network run on.
    #[error(transparent)]
    Diffusion(#[from] DiffusionError),
    /// A video (the fly-through) could not be written.
    #[error(transparent)]
    Video(#[from] VideoError),
    /// The run folder is another process's: its lock names the holder.
    #[error("{}: in use by {holder}; wait for it to finish or stop it", dir.display())]
    Locked { dir: PathBuf, holder: String },
}

impl From<DeviceError> for ExtrapolateError {
    fn from(e: DeviceError) -> Self {
        ExtrapolateError::Diffusion(DiffusionError::Device(e))
    }
}

/// The virtual cameras' settings cannot make cameras.
impl From<CameraError> for ExtrapolateError {
    fn from(e: CameraError) -> Self {
        ExtrapolateError::Usage(e.to_string())
    }
}

/// A run folder held by another process is [`ExtrapolateError::Locked`]; one that cannot be
/// locked (made, opened) an I/O error creating it.
impl From<extranerf_gpu::files::LockError> for ExtrapolateError {
    fn from(e: extranerf_gpu::files::LockError) -> Self {
        use extranerf_gpu::files::LockError;
        match e {
            LockError::Held { dir, holder } => ExtrapolateError::Locked { dir, holder },
            LockError::Io { path, error } => ExtrapolateError::Io {
                what: "creating",
                path,
                error,
            },
        }
    }
}

impl ExtrapolateError {
    /// An I/O error doing `what` to `path`.
    pub fn io(what: &'static str, path: &Path, error: std::io::Error) -> ExtrapolateError {
        ExtrapolateError::Io {
            what,
            path: path.to_path_buf(),
            error,
        }
    }

    /// `path` holds something other than it should: `problem`.
    pub fn malformed(path: &Path, problem: impl Into<String>) -> ExtrapolateError {
        ExtrapolateError::Malformed {
            path: path.to_path_buf(),
            problem: problem.into(),
        }
    }

    /// A setting that cannot work.
    pub fn usage(message: impl Into<String>) -> ExtrapolateError {
        ExtrapolateError::Usage(message.into())
    }

    /// The run folder `dir` lacks `what`.
    pub fn incomplete(dir: &Path, what: impl Into<String>) -> ExtrapolateError {
        ExtrapolateError::Incomplete {
            dir: dir.to_path_buf(),
            what: what.into(),
        }
    }

    /// The run folder `dir` cannot be continued: `reason`.
    pub fn resume(dir: &Path, reason: impl Into<String>) -> ExtrapolateError {
        ExtrapolateError::Resume {
            dir: dir.to_path_buf(),
            reason: reason.into(),
        }
    }

    /// This error as the failure of the work on `view`.
    pub fn in_view(self, view: impl Into<String>) -> ExtrapolateError {
        ExtrapolateError::View {
            view: view.into(),
            error: Box::new(self),
        }
    }

    /// This error as the failure of stage `stage`.
    pub fn in_stage(self, stage: &str) -> ExtrapolateError {
        ExtrapolateError::Stage {
            stage: stage.to_string(),
            error: Box::new(self),
        }
    }

    /// The error under the stage and the view that failed (itself when it is neither's).
    pub fn cause(&self) -> &ExtrapolateError {
        match self {
            ExtrapolateError::Stage { error, .. } | ExtrapolateError::View { error, .. } => {
                error.cause()
            }
            e => e,
        }
    }

    /// The stage that failed, if any.
    pub fn stage(&self) -> Option<&str> {
        match self {
            ExtrapolateError::Stage { stage, .. } => Some(stage),
            _ => None,
        }
    }
}

/// Result alias of the pipeline.
pub type Result<T, E = ExtrapolateError> = std::result::Result<T, E>;

/// Creates folder `dir` and its parents.
pub(crate) fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| ExtrapolateError::io("creating", dir, e))
}

/// Reads `path` as text.
pub(crate) fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| ExtrapolateError::io("reading", path, e))
}

/// Writes `value` as pretty JSON (and a newline) into `path` atomically.
pub(crate) fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    let json = serde_json::to_string_pretty(value)
        .map_err(|e| ExtrapolateError::malformed(path, format!("cannot serialise: {e}")))?;
    extranerf_nerf::safetensors::write_atomic(path, (json + "\n").as_bytes())?;
    Ok(())
}
