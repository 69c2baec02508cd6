//! Visibility of views against a trained field's training cameras (ExtraNeRF's multi-view
//! transmittance), as the pipeline and `extranerf visibility` compute it: settings, the
//! transmittance volumes, maps, and the inpainting mask a map implies.

use anyhow::bail;
use extranerf_gpu::Context;
use extranerf_nerf::data::Camera;
use extranerf_nerf::render::visibility::{
    Density, TransmittanceVolume, Visibility, VisibilityConfig, VisibilityMap, VisibilityMeasure,
    MAX_RANK, MAX_TRAIN_CAMERAS,
};
use extranerf_nerf::trainer::Nerf;
use serde::{Deserialize, Serialize};

/// How visibility is computed and turned into a mask.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VisSettings {
    /// Samples per camera ray (0: the run's training setting).
    pub samples: u32,
    /// Which largest transmittance across the training cameras counts (2: the paper).
    pub rank: u32,
    /// Samples whose weight is at most this are not marched toward the cameras.
    pub min_weight: f32,
    /// Segments stop once their transmittance falls below this.
    pub min_transmittance: f32,
    /// Rays across each training camera's transmittance volume.
    pub volume_res: u32,
    /// Depth strata of the transmittance volumes.
    pub volume_depth: u32,
    /// A pixel is to be inpainted when the share of its rendered content that the training
    /// cameras saw (visibility over opacity) is below this.
    pub threshold: f32,
    /// ... or when its opacity is below this (the field renders nothing there).
    pub min_opacity: f32,
    /// Pixels per submission.
    pub chunk: u32,
    /// Transmittance absolute (the paper) or relative to the pixel ray's own (robust to a
    /// field that renders surfaces as semi-transparent shells). Manifests written before this
    /// setting existed computed the absolute one.
    #[serde(default = "absolute")]
    pub measure: VisibilityMeasure,
}

fn absolute() -> VisibilityMeasure {
    VisibilityMeasure::Absolute
}

impl Default for VisSettings {
    fn default() -> Self {
        VisSettings {
            samples: 0,
            rank: 2,
            min_weight: 1e-3,
            min_transmittance: 1e-3,
            volume_res: 128,
            volume_depth: 128,
            threshold: 0.5,
            min_opacity: 0.1,
            chunk: 4096,
            measure: VisibilityMeasure::Relative,
        }
    }
}

impl VisSettings {
    /// The kernel configuration at `rank` for a field trained with `train_samples` per ray.
    pub fn config(&self, rank: u32, train_samples: u32) -> anyhow::Result<VisibilityConfig> {
        if !(1..=MAX_RANK).contains(&rank) {
            bail!("visibility rank {rank}: use 1 to {MAX_RANK}");
        }
        for (what, v) in [
            ("min-weight", self.min_weight),
            ("min-transmittance", self.min_transmittance),
        ] {
            if !(0.0..1.0).contains(&v) {
                bail!("visibility {what} {v}: use a value in [0, 1)");
            }
        }
        if !(0.0..=1.0).contains(&self.threshold) || !(0.0..=1.0).contains(&self.min_opacity) {
            bail!(
                "visibility threshold {} and minimum opacity {}: use values in [0, 1]",
                self.threshold,
                self.min_opacity
            );
        }
        if self.volume_res == 0 || self.volume_depth == 0 || self.chunk == 0 {
            bail!("the transmittance volume's size and the chunk must be positive");
        }
        Ok(VisibilityConfig {
            samples: if self.samples == 0 {
                train_samples
            } else {
                self.samples
            },
            vis_samples: 32,
            rank,
            min_weight: self.min_weight,
            min_transmittance: self.min_transmittance,
            measure: self.measure,
        })
    }

    /// The inpainting mask of a map: 1 where the pixel is to be filled.
    pub fn mask(&self, m: &VisibilityMap) -> Vec<f32> {
        m.visibility
            .iter()
            .zip(&m.opacity)
            .map(|(&v, &o)| {
                let seen = v / o.max(1e-6);
                f32::from(o < self.min_opacity || seen < self.threshold)
            })
            .collect()
    }
}

/// A field's density for the visibility kernels.
pub fn density(nerf: &Nerf) -> anyhow::Result<Density<'_>> {
    Ok(Density::Field {
        field: nerf.field(),
        params: nerf.field().layout().sections(nerf.params())?,
        occupancy: nerf.occupancy(),
    })
}

/// The visibility kernels with one set of training cameras' transmittance volumes.
pub struct FieldVisibility {
    vis: Visibility,
    volume: TransmittanceVolume,
    train: Vec<Camera>,
}

impl std::fmt::Debug for FieldVisibility {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FieldVisibility")
            .field("cameras", &self.train.len())
            .field("volume", &self.volume.size())
            .finish_non_exhaustive()
    }
}

impl FieldVisibility {
    /// Builds the transmittance volumes of `train` through `nerf`.
    pub fn new(
        ctx: &Context,
        nerf: &Nerf,
        train: &[Camera],
        s: &VisSettings,
    ) -> anyhow::Result<FieldVisibility> {
        if train.is_empty() || train.len() > MAX_TRAIN_CAMERAS {
            bail!(
                "visibility needs 1 to {MAX_TRAIN_CAMERAS} training cameras, not {}",
                train.len()
            );
        }
        let vis = Visibility::new(ctx)?;
        let volume = vis.build_volume(ctx, &density(nerf)?, train, s.volume_res, s.volume_depth)?;
        Ok(FieldVisibility {
            vis,
            volume,
            train: train.to_vec(),
        })
    }

    /// The map of `cam` against the training cameras of `mask` (bit i: camera i counts).
    pub fn map(
        &self,
        ctx: &Context,
        nerf: &Nerf,
        cam: &Camera,
        mask: u32,
        cfg: &VisibilityConfig,
        chunk: u32,
    ) -> anyhow::Result<VisibilityMap> {
        Ok(self.vis.map(
            ctx,
            &density(nerf)?,
            cam,
            &self.train,
            mask,
            cfg,
            Some(&self.volume),
            chunk,
        )?)
    }
}
