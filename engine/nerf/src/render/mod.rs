//! Rendering on the device: ray generation, stratified sampling, compositing, the photometric, depth and
//! distortion losses so far (the fused march that
//! samples, queries the field and composites in one kernel builds on the same WGSL functions).

pub mod composite;
pub mod loss;
pub mod occupancy;
pub mod rays;
pub mod sample;
