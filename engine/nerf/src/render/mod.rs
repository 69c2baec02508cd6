//! Rendering on the device: ray generation, compositing and the distortion loss so far (the fused march that
//! samples, queries the field and composites in one kernel builds on the same WGSL functions).

pub mod composite;
pub mod rays;
