//! The ExtraNeRF pipeline (issue 17): the stages that turn a scene into an extrapolating field.
//! Today it holds the BaseNeRF training driver ([`driver`]), which `extranerf train`, `demo`
//! and the trade-off sweeps run and which the later stages (visibility, inpainting,
//! enhancement) will call; they are not built yet.
//!
//! Nothing here prints: progress and notes go to a [`driver::Reporter`] that the caller
//! supplies (the command line draws them as progress bars or log lines).

pub mod driver;
