//! What every stage of `extranerf extrapolate` shares: the [`Stage`] trait, the run folder's
//! layout ([`RunDir`], [`FieldRef`]), the virtual cameras ([`VirtualSpec`]) and the render of a
//! view from a field.

use std::path::PathBuf;
use std::time::Instant;

use extranerf_gpu::Context;
use extranerf_nerf::cameras::{virtual_cameras, Trajectory};
use extranerf_nerf::data::Camera;
use extranerf_nerf::render::march::MarchCuts;
use extranerf_nerf::renderer::{March, Nerf};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::error::{ExtrapolateError, Result};
use crate::manifest::Recorded;

use crate::inpaint::InpainterKind;
use extranerf_nerf::train::{Progress, Reporter, Unit};

/// The virtual cameras.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VirtualSpec {
    pub trajectory: Trajectory,
    /// How many.
    pub count: usize,
    /// How far beyond the rig (1: its edge).
    pub range: f64,
    /// Divide the training resolution by this for the virtual views.
    pub downscale: u32,
}

/// The run folder's layout.
#[derive(Clone, Debug)]
pub struct RunDir {
    pub root: PathBuf,
    /// The BaseNeRF's run folder.
    pub base: PathBuf,
}

impl RunDir {
    pub fn visibility(&self) -> PathBuf {
        self.root.join("visibility")
    }

    pub fn stage2(&self, kind: InpainterKind) -> PathBuf {
        self.root.join(format!("stage2-{}", kind.name()))
    }

    pub fn flythrough(&self) -> PathBuf {
        self.root.join("flythrough")
    }

    /// Stage 3's training data ([`DATA_STAGE`]).
    pub fn stage3_data(&self) -> PathBuf {
        self.root.join(DATA_STAGE)
    }

    /// Stage 3's enhancer ([`ENHANCER_STAGE`]).
    pub fn enhancer(&self) -> PathBuf {
        self.root.join(ENHANCER_STAGE)
    }
}

/// Stage 3's data stage: its name and folder.
pub const DATA_STAGE: &str = "stage3-data";
/// Stage 3's enhancer stage: its name and folder.
pub const ENHANCER_STAGE: &str = "stage3-enhancer";

/// A stage of the pipeline.
pub trait Stage {
    /// Its name in the manifest.
    fn name(&self) -> String;
    /// Its settings as the manifest records them: its [`StageSpec`](crate::manifest::StageSpec), whose declaration says
    /// which of them a resumed run may change.
    fn config(&self) -> Recorded;
    /// Runs it (resuming inside it where it can); returns its report.
    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value>;
    /// The stages whose output it reads: when one of them runs, this one runs again even if
    /// the manifest says it is done.
    fn inputs(&self) -> Vec<String> {
        Vec::new()
    }
    /// What identifies its output as it is now, where a file outside the manifest holds it
    /// (the BaseNeRF's checkpoint, which `--base` names or `RUN/base` holds): a done stage
    /// whose identity is no longer the one recorded is recorded again, and the stages that
    /// read it run again. None (the default): its record identifies it.
    fn identity(&self, _dir: &RunDir) -> Result<Option<String>> {
        Ok(None)
    }
    /// Discards what an earlier run of it left, before it runs again from nothing (because it
    /// was asked to be redone, or a stage it reads ran again): by default its folder
    /// `RUN/NAME`, which holds its resumable state.
    fn reset(&self, dir: &RunDir) -> Result<()> {
        let d = dir.root.join(self.name());
        if d.exists() {
            std::fs::remove_dir_all(&d).map_err(|e| ExtrapolateError::io("removing", &d, e))?;
        }
        Ok(())
    }
}

/// The virtual cameras of `spec` for `train`, at the virtual views' resolution.
pub fn make_virtual(spec: &VirtualSpec, train: &[Camera]) -> Result<Vec<Camera>> {
    if spec.downscale == 0 {
        return Err(ExtrapolateError::usage(
            "--virtual-downscale must be at least 1",
        ));
    }
    Ok(
        virtual_cameras(train, spec.trajectory, spec.count, spec.range)?
            .into_iter()
            .enumerate()
            .map(|(i, c)| {
                let mut c = c.downscaled(spec.downscale);
                c.image = PathBuf::from(format!("virtual_{i:03}.png"));
                c
            })
            .collect(),
    )
}

/// Renders `cam` from `nerf` with the fused march: colour, depth, opacity.
pub fn render(
    ctx: &Context,
    nerf: &Nerf,
    cam: &Camera,
    samples: u32,
) -> Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
    Ok(nerf.render_with(ctx, cam, 8192, samples, March::Fused(MarchCuts::EXACT))?)
}

/// A field the pipeline made: the BaseNeRF, a stage-2 variant, or that variant after stage 3.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FieldRef {
    Base,
    Stage2(InpainterKind),
    Stage3(InpainterKind),
}

impl FieldRef {
    /// Its stage's name (and folder, for the variants).
    pub fn name(self) -> String {
        match self {
            FieldRef::Base => "base".into(),
            FieldRef::Stage2(k) => format!("stage2-{}", k.name()),
            FieldRef::Stage3(k) => format!("stage3-{}", k.name()),
        }
    }

    /// Its label in the fly-through video.
    pub fn label(self) -> String {
        match self {
            FieldRef::Base => "BaseNeRF".into(),
            FieldRef::Stage2(k) => format!("stage 2 {}", k.name()),
            FieldRef::Stage3(k) => format!("stage 3 {}", k.name()),
        }
    }
}

/// Progress of a stage over views: `step` of `total` done, `t` its start.
pub(crate) fn progress_views(rep: &mut dyn Reporter, step: usize, total: usize, t: &Instant) {
    rep.progress(&Progress {
        unit: Unit::Views,
        step: step as u32,
        total: total as u32,
        loss: 0.0,
        psnr: 0.0,
        samples_per_s: 0.0,
        secs: t.elapsed().as_secs_f64(),
        eta: 0.0,
    });
}
