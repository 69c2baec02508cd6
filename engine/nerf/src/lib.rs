//! NeRF algorithms of extranerf, on the engine's Vulkan layer; no `unsafe` here.
//!
//! [`data`]: scene loaders (LLFF, `transforms.json`, COLMAP) and splits; [`field`] and
//! [`render`]: the device kernels (hash grid, MLPs, rays, sampling, compositing, losses,
//! occupancy); [`model`]: the BaseNeRF field over one flat parameter buffer; [`trainer`]: the
//! training step; [`train`]: the BaseNeRF training driver (budgets, the training loop, held-out
//! curves); [`renderer`]: rendering a field; [`views`]: the views training reads; [`run`]: run
//! folders and checkpoints ([`write`](mod@write): the images and depth maps they hold); [`metrics`]: PSNR,
//! SSIM, LPIPS; [`reference`](mod@reference): plain-Rust f64 definitions the kernels are tested
//! against.
#![forbid(unsafe_code)]

/// `Display` as the enum's `name()`, the name its configs and reports use.
macro_rules! display_by_name {
    ($($t:ty),* $(,)?) => {
        $(impl std::fmt::Display for $t {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.name())
            }
        })*
    };
}

pub mod autoconfig;
pub mod camera_path;
pub mod cameras;
pub mod data;
pub mod demo;
pub mod depth_completion;
pub mod field;
pub mod image_ops;
pub mod metrics;
pub mod model;
pub mod mvs;
pub mod mvs_depth;
pub mod optim;
pub mod reference;
pub mod render;
pub mod renderer;
pub mod run;
pub mod run_error;
pub mod safetensors;
pub mod train;
pub mod trainer;
pub mod video;
pub mod views;
pub mod write;

display_by_name!(
    model::Space,
    model::Precision,
    field::encodings::Contraction,
    data::split::SplitKind,
    trainer::RgbLossKind,
);
