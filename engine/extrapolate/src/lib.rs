//! The ExtraNeRF pipeline: the stages that turn a scene into an extrapolating field.
//!
//! - [`run`]: `extranerf extrapolate`, the one file that knows every stage: it assembles them
//!   from the options and runs them over one run folder, with a manifest ([`manifest`]) that
//!   makes every stage boundary resumable;
//! - [`stage`]: what every stage shares (the [`stage::Stage`] trait, the run folder, the
//!   virtual cameras); [`rounds`]: what the round-based stages share (the noise schedule,
//!   resuming, training a round);
//! - [`stages`]: the BaseNeRF, the visibility of the virtual views, stage 2 (one per
//!   inpainter) and the fly-through; [`stage3`]: the enhancer's training data, the enhancer,
//!   its gate and the enhancement loop;
//! - [`base`]: a trained run's BaseNeRF loaded from its checkpoint (trained by
//!   [`extranerf_nerf::train`], the BaseNeRF training driver);
//! - [`inpaint`]: the inpainters (depth-aware harmonic, exemplar PatchMatch, hybrid, diffusion);
//! - [`visibility`]: visibility settings, maps and their files, masks and depth completion over
//!   a trained field (what `extranerf visibility` runs);
//! - [`eval`]: the comparison table of an extrapolate run, KID on Inception features, and the
//!   self-contained HTML report;
//! - [`demo`]: `extranerf demo`, the whole pipeline on the procedural demo scene;
//! - [`montage`]: fields' frames side by side under labels (the fly-through video's frames);
//! - [`error`]: [`ExtrapolateError`], the error of every fallible public function here (a
//!   record that does not read as a stage's settings says why in a string, which
//!   [`manifest::Recorded::check`] turns into one).
//!
//! Nothing here prints: progress and notes go to a [`extranerf_nerf::train::Reporter`] that the caller
//! supplies (the command line draws them as progress bars or log lines).

// Pixel loops index several images and channels by the same index; iterators would hide it.
#![allow(clippy::needless_range_loop)]

pub mod base;
pub mod demo;
pub mod error;
pub mod eval;
pub mod inpaint;
pub mod manifest;
pub mod montage;
pub mod rounds;
pub mod run;
pub mod shown;
pub mod stage;
pub mod stage3;
pub mod stages;
pub mod visibility;

pub use error::{ExtrapolateError, Result};
