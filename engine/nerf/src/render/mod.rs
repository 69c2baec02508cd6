//! Rendering on the device: ray generation, stratified sampling, compositing, the photometric,
//! depth and distortion losses, the occupancy grid, and the fused march that samples, queries
//! the field and composites in one kernel (built on the same WGSL functions), and the fused
//! training step that adds the losses and the backward pass to it.

pub mod composite;
pub mod loss;
pub mod march;
pub mod occupancy;
pub mod rays;
pub mod sample;
pub mod train_step;
pub mod visibility;
