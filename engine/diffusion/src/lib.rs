//! The diffusion half of ExtraNeRF through burn, on the engine's Vulkan device.
//!
//! - [`device`] hands the engine's device to burn (wgpu backend), lets engine kernels bind
//!   burn's tensors in place, and chooses the backend (`--diffusion-backend`).
//! - [`unet`], [`vae`], [`text`]: diffusers' UNet2DConditionModel (inpainting: 9 input
//!   channels), AutoencoderKL and the conditioning (CLIP text encoder or learned tokens), with
//!   diffusers' structure and parameter names, sized by diffusers `config.json` files
//!   ([`config`]).
//! - [`scheduler`]: DDPM training noise, DDIM sampling from a noised image, guidance, w(t).
//! - [`weights`]: diffusers-layout safetensors folders in and out.
//! - [`lora`]: LoRA adapters on attention (and optionally convolutions), saved apart.
//! - [`enhancer`]: stage 3's enhancer (guidance not masked), trained on render/photo pairs.
//! - [`train`]: the training loops (from scratch, LoRA fine-tuning) and [`inpaint`] the
//!   inpainting pipeline; [`fill`] the simple fills they are measured against.
#![forbid(unsafe_code)]

use std::path::{Path, PathBuf};

pub mod blocks;
pub mod clip;
pub mod config;
pub mod device;
pub mod enhancer;
pub mod fill;
pub mod inpaint;
pub mod layers;
pub mod lora;
pub mod pipeline;
pub mod scheduler;
pub mod text;
pub mod train;
pub mod train_spec;
pub mod train_state;
pub mod unet;
pub mod vae;
pub mod weights;

/// Everything that can go wrong in the diffusion crate.
#[derive(Debug, thiserror::Error)]
pub enum DiffusionError {
    /// A file could not be read or written.
    #[error("{}: {error}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error (in the message, not a separate source, so a chain does not print it
        /// twice).
        error: std::io::Error,
    },
    /// A configuration file is malformed or asks for something not modelled.
    #[error("{}: {problem}", path.display())]
    Config {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        problem: String,
    },
    /// A configuration given in code is invalid.
    #[error("invalid model configuration: {0}")]
    InvalidConfig(String),
    /// A weight file is malformed, misses tensors or has tensors of the wrong shape.
    #[error("{}: {problem}", path.display())]
    Weights {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        problem: String,
    },
    /// Inputs of the wrong size or content.
    #[error("{0}")]
    Input(String),
    /// Training diverged.
    #[error("{0}")]
    Diverged(String),
    /// The device hand-over failed.
    #[error(transparent)]
    Device(#[from] device::DeviceError),
}

impl DiffusionError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> DiffusionError {
        DiffusionError::Io {
            path: path.to_path_buf(),
            error: source,
        }
    }
}

/// Result alias of the crate.
pub type Result<T, E = DiffusionError> = std::result::Result<T, E>;

/// Writes a file so that a crash leaves either the old or the new content
/// ([`extranerf_gpu::files::write_atomic`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    extranerf_gpu::files::write_atomic(path, bytes).map_err(|e| DiffusionError::io(path, e))
}
