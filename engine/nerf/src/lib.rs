//! NeRF algorithms of extranerf, on the engine's Vulkan layer; no `unsafe` here.
//!
//! So far: [`data`], the scene loaders (LLFF `poses_bounds.npy`, instant-ngp / nerfstudio
//! `transforms.json`, COLMAP `cameras.bin` / `points3D.bin`) and the evaluation splits. The
//! field, renderer and trainer of the BaseNeRF issue build on these.
#![forbid(unsafe_code)]

pub mod data;
