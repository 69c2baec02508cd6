//! The stages of `extranerf extrapolate` before stage 3 ([`crate::stage3`]), one file each.
//! Each depends on [`crate::stage`] and [`crate::rounds`], never on another stage.

pub mod base;
pub mod flythrough;
pub mod stage2;
pub mod visibility;

pub use base::{default_run_config, BaseSpec, BaseStage};
pub use flythrough::{
    FlythroughConfig, FlythroughSpec, FlythroughStage, FlythroughVideoStage, FrameSize,
};
pub use stage2::{reproject, InpaintSpec, InpaintStage};
pub use visibility::VisibilityStage;
