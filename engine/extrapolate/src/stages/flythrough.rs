//! The fly-through of a field (`RUN/flythrough`): frames along the virtual trajectory and a
//! looping GIF.

use std::time::Instant;

use extranerf_gpu::Context;
use extranerf_nerf::cameras::virtual_cameras;
use extranerf_nerf::data::Camera;
use extranerf_nerf::renderer::Nerf;
use extranerf_nerf::run::{load_checkpoint, write_png};
use extranerf_nerf::train::Reporter;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::base::BaseField;
use crate::error::{create_dir, ExtrapolateError, Result};
use crate::manifest::{OnResume, Recorded, StageSpec};
use crate::stage::{progress_views, render, FieldRef, RunDir, Stage, VirtualSpec};

/// The fly-through: frames along the virtual cameras' trajectory, rendered from the
/// BaseNeRF and from each stage-2 variant.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlythroughSpec {
    /// Frames along the path (0: no fly-through).
    pub frames: u32,
    /// Divide the virtual views' resolution by this for the frames.
    pub downscale: u32,
    /// Milliseconds per frame of the animation.
    pub delay_ms: u32,
}

impl Default for FlythroughSpec {
    fn default() -> Self {
        FlythroughSpec {
            frames: 24,
            downscale: 2,
            delay_ms: 100,
        }
    }
}

/// The fly-through of one field: `frames` cameras along the virtual trajectory (the path the
/// virtual views sample, sampled densely), rendered into `RUN/flythrough/NAME/frame_NNN.png`
/// and `RUN/flythrough/NAME.gif`. NAME is `base` or a variant's folder name.
#[derive(Clone, Debug)]
pub struct FlythroughStage {
    /// The field rendered.
    pub field: FieldRef,
    /// Its settings (what its manifest record holds).
    pub config: FlythroughConfig,
}

/// A fly-through's settings: the trajectory it follows and its frames.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlythroughConfig {
    #[serde(rename = "virtual")]
    pub virt: VirtualSpec,
    #[serde(rename = "flythrough")]
    pub spec: FlythroughSpec,
}

impl StageSpec for FlythroughConfig {
    const ON_RESUME: &'static [(&'static str, OnResume)] = &[
        // The path, and the frames along it (their delay is in the GIF).
        ("virtual", OnResume::Rerun),
        ("flythrough", OnResume::Rerun),
    ];
}

impl FlythroughStage {
    fn field_name(&self) -> String {
        self.field.name()
    }
}

impl Stage for FlythroughStage {
    fn name(&self) -> String {
        format!("flythrough-{}", self.field_name())
    }

    fn config(&self) -> Recorded {
        Recorded::of(&self.config)
    }

    fn inputs(&self) -> Vec<String> {
        vec!["base".into(), self.field_name()]
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value> {
        let s = &self.config.spec;
        if s.frames == 0 || s.downscale == 0 || s.delay_ms == 0 {
            return Err(ExtrapolateError::usage("the fly-through needs at least one frame, a downscale of at least 1 and a positive delay"));
        }
        let base = BaseField::load(ctx, &dir.base)?;
        let samples = base.ck.config.train.samples;
        let (nerf, step) = match self.field {
            FieldRef::Stage2(_) | FieldRef::Stage3(_) => {
                let name = self.field.name();
                let ck = load_checkpoint(&dir.root.join(&name))?;
                let cfg = &ck.config;
                (
                    Nerf::new(ctx, cfg.model.clone(), &ck.params, cfg.train.background)?,
                    ck.step,
                )
            }
            FieldRef::Base => (base.nerf, base.ck.step),
        };
        let train: Vec<Camera> = base
            .loaded
            .split
            .train
            .iter()
            .map(|&i| base.loaded.scene.cameras[i].clone())
            .collect();
        let cams = virtual_cameras(
            &train,
            self.config.virt.trajectory,
            s.frames as usize,
            self.config.virt.range,
        )?;
        let name = self.field_name();
        let out = dir.flythrough().join(&name);
        create_dir(&out)?;
        let mut frames = Vec::with_capacity(cams.len());
        let (mut w, mut h) = (0, 0);
        let t = Instant::now();
        for (i, c) in cams.iter().enumerate() {
            let cam = c.downscaled(self.config.virt.downscale.max(1) * s.downscale);
            let (rgb, _, _) = render(ctx, &nerf, &cam, samples)?;
            write_png(
                &out.join(format!("frame_{i:03}.png")),
                cam.width,
                cam.height,
                &rgb,
            )?;
            (w, h) = (cam.width, cam.height);
            frames.push(rgb);
            progress_views(rep, i + 1, s.frames as usize, &t);
        }
        let gif = dir.flythrough().join(format!("{name}.gif"));
        crate::anim::write_gif(&gif, w, h, &frames, s.delay_ms)?;
        rep.note(&format!(
            "{}: {} frames of {w}x{h} ({}), {:.1} s",
            gif.display(),
            frames.len(),
            self.field_name(),
            t.elapsed().as_secs_f64()
        ));
        Ok(json!({"frames": frames.len(), "width": w, "height": h, "field_step": step}))
    }
}
