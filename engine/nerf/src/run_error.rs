//! The error type of runs ([`crate::run`]) and of the files they write ([`crate::write`]).

use crate::data::DataError;

/// What can go wrong with a run.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// Scene or checkpoint files.
    #[error(transparent)]
    Data(#[from] DataError),
    /// The device.
    #[error(transparent)]
    Gpu(#[from] extranerf_gpu::GpuError),
    /// A setting that cannot work.
    #[error("{0}")]
    Config(String),
}

/// Result alias of runs.
pub type Result<T, E = RunError> = std::result::Result<T, E>;
