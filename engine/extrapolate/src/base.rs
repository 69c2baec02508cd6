//! A trained run's BaseNeRF loaded for queries: checkpoint -> scene -> field.

use std::path::Path;

use extranerf_gpu::Context;
use extranerf_nerf::data::Camera;
use extranerf_nerf::renderer::Nerf;
use extranerf_nerf::run::{load_checkpoint, Checkpoint, LoadedScene};

use crate::error::Result;

/// The scene, field and views of a run's BaseNeRF.
pub struct BaseField {
    /// The checkpoint (configuration, parameters, step).
    pub ck: Checkpoint,
    /// The scene and its split.
    pub loaded: LoadedScene,
    /// The field with the checkpoint's parameters.
    pub nerf: Nerf,
}

impl std::fmt::Debug for BaseField {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BaseField")
            .field("step", &self.ck.step)
            .finish_non_exhaustive()
    }
}

impl BaseField {
    /// Loads `dir`'s checkpoint and scene.
    pub fn load(ctx: &Context, dir: &Path) -> Result<BaseField> {
        let ck = load_checkpoint(dir)?;
        let loaded = ck.config.scene.load()?;
        let nerf = Nerf::new(
            ctx,
            ck.config.model.clone(),
            &ck.params,
            ck.config.train.background,
        )?;
        Ok(BaseField { ck, loaded, nerf })
    }

    /// The training cameras.
    pub fn train_cameras(&self) -> Vec<Camera> {
        self.loaded.train_cameras()
    }

    /// Whether the field is in NDC.
    pub fn ndc(&self) -> bool {
        self.ck.config.model.space == extranerf_nerf::model::Space::Ndc
    }
}
