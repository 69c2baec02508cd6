//! The ExtraNeRF pipeline: the stages that turn a scene into an extrapolating field.
//! - [`base`]: a trained run's BaseNeRF loaded from its checkpoint;
//! - [`driver`]: the BaseNeRF training driver (budgets, checkpoints, held-out curves), which
//!   `extranerf train`, `demo` and the trade-off sweeps run;
//! - [`pipeline`]: `extranerf extrapolate`, stages over one run folder (BaseNeRF, visibility
//!   of virtual views, the stage-2 inpainting loop per inpainter, the fly-through) with a manifest
//!   ([`manifest`]) that makes every stage boundary resumable;
//! - [`inpaint`]: the inpainters (depth-aware harmonic, exemplar PatchMatch, hybrid);
//! - [`visibility`]: visibility settings, maps, masks and depth completion over a trained field
//!   (what `extranerf visibility` runs);
//! - [`eval`]: the comparison table of an extrapolate run, with KID on [`inception`]'s
//!   features; [`report`]: its self-contained HTML page.
//!
//! - [`demo`]: `extranerf demo`, the whole pipeline on the procedural demo scene;
//! - [`anim`]: looping GIFs of rendered frames (the fly-through).
//!
//! - [`stage3`]: stage 3, the enhancer's training data, the enhancer and the enhancement loop.
//!
//! Nothing here prints: progress and notes go to a [`driver::Reporter`] that the caller
//! supplies (the command line draws them as progress bars or log lines).

// Pixel loops index several images and channels by the same index; iterators would hide it.
#![allow(clippy::needless_range_loop)]

pub mod anim;
pub mod base;
pub mod demo;
pub mod driver;
pub mod eval;
pub mod inception;
pub mod inpaint;
pub mod manifest;
pub mod pipeline;
pub mod report;
pub mod stage3;
pub mod visibility;
