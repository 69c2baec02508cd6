//! NeRF algorithms of extranerf, on the engine's Vulkan layer; no `unsafe` here.
//!
//! So far: [`data`], the scene loaders (LLFF `poses_bounds.npy`, instant-ngp / nerfstudio
//! `transforms.json`, COLMAP `cameras.bin` / `points3D.bin`) and the evaluation splits;
//! [`field`], the multi-resolution hash encoding on the GPU (forward and backward); and
//! [`reference`], plain-Rust f64 definitions the kernels are tested against. The MLPs, the
//! fused march, the losses and the trainer of the BaseNeRF issue build on these.
#![forbid(unsafe_code)]

pub mod data;
pub mod field;
pub mod optim;
pub mod reference;
pub mod render;
