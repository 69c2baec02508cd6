//! The diffusion half of ExtraNeRF through burn, on the engine's Vulkan device.
//!
//! [`device`] hands the engine's device to burn (wgpu backend) and lets engine kernels bind
//! burn's tensors in place. The models, schedulers and LoRA come next (issue 5).
#![forbid(unsafe_code)]

pub mod device;
