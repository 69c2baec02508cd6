//! The integration tests on lavapipe, one module per file, in one test binary: the suite links
//! one executable instead of one per file, and its tests share one engine context
//! (`extranerf_tests::engine`). Tests that must be alone in a process (burn's random generator
//! is process-global: enhancer.rs, extrapolate.rs's stage 3) run in a child process of this
//! binary (rusty-fork) while the others go on.
//!
//! Run one module with a filter: `cargo test --release --workspace --test main field::`
//! (`--workspace`, so that the dependencies keep the features of the full build and are not
//! compiled again).

mod colmap;
mod data;
mod diffusion;
mod diffusion_models;
mod enhancer;
mod extrapolate;
mod field;
mod fuzz;
mod gpu;
mod layout;
mod march;
mod metrics;
mod mvs;
mod optim;
mod prims;
mod proposal;
mod render;
mod split;
mod stability;
mod train;
mod video;
mod visibility;
