//! The fly-through of a run (`RUN/flythrough`): each field's frames along the virtual
//! trajectory, then one video of them side by side, each under its label
//! (`RUN/flythrough/flythrough.mp4`, H.264, which browsers play).

use std::time::Instant;

use extranerf_gpu::Context;
use extranerf_nerf::camera_path::resized;
use extranerf_nerf::cameras::virtual_cameras;
use extranerf_nerf::data::{load_image, Camera};
use extranerf_nerf::renderer::Nerf;
use extranerf_nerf::run::{load_checkpoint, write_png};
use extranerf_nerf::train::Reporter;
use extranerf_nerf::video::VideoWriter;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::base::BaseField;
use crate::error::{create_dir, ExtrapolateError, Result};
use crate::manifest::{OnResume, Recorded, StageSpec};
use crate::montage::{Layout, MAX_SIDE};
use crate::stage::{progress_views, render, FieldRef, RunDir, Stage, VirtualSpec};

/// The video's file name in `RUN/flythrough`.
pub const VIDEO_FILE: &str = "flythrough.mp4";

/// The fly-through frames' default downscale of the virtual views.
pub const DEFAULT_DOWNSCALE: u32 = 2;

/// The size of each field's frames in the fly-through.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameSize {
    /// The virtual views' resolution divided by this.
    Downscale(u32),
    /// This many pixels across, the height keeping the views' aspect.
    Width(u32),
}

/// The fly-through: frames along the virtual cameras' trajectory, rendered from the
/// BaseNeRF and from each variant, and the video of them side by side.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlythroughSpec {
    /// Frames along the path (0: no fly-through).
    pub frames: u32,
    /// Each field's frame size.
    pub size: FrameSize,
    /// Frames per second of the video.
    pub fps: f64,
}

impl Default for FlythroughSpec {
    fn default() -> Self {
        FlythroughSpec {
            frames: 24,
            size: FrameSize::Downscale(DEFAULT_DOWNSCALE),
            fps: 10.0,
        }
    }
}

impl FlythroughSpec {
    /// Refuses settings that make no video: no frames, a size of 0 or over what a video
    /// holds, a rate outside (0, 1000].
    pub fn check(&self) -> Result<()> {
        let size_ok = match self.size {
            FrameSize::Downscale(d) => d >= 1,
            FrameSize::Width(w) => (1..=MAX_SIDE).contains(&w),
        };
        if self.frames == 0
            || !size_ok
            || !(self.fps.is_finite() && self.fps > 0.0 && self.fps <= 1000.0)
        {
            return Err(ExtrapolateError::usage(format!(
                "the fly-through needs at least one frame, a downscale of at least 1 or a width of 1 to {MAX_SIDE} pixels, and a frame rate in (0, 1000]; asked: {} frames, {:?}, {} fps",
                self.frames, self.size, self.fps
            )));
        }
        Ok(())
    }

    /// `cam` (a virtual camera at the scene's resolution) at the frames' size, for virtual
    /// views downscaled by `virtual_downscale`.
    pub fn frame_camera(&self, cam: &Camera, virtual_downscale: u32) -> Camera {
        match self.size {
            FrameSize::Downscale(d) => cam.downscaled(virtual_downscale.max(1) * d.max(1)),
            FrameSize::Width(w) => resized(cam, w),
        }
    }

    /// Reads a record of these settings, those of builds that wrote a looping GIF included
    /// (`downscale` and `delay_ms`: the same frames, at 1000 / delay frames per second).
    fn from_value(v: &Value) -> std::result::Result<FlythroughSpec, String> {
        if let (Some(frames), Some(d), Some(delay)) = (
            v.get("frames").and_then(Value::as_u64),
            v.get("downscale").and_then(Value::as_u64),
            v.get("delay_ms").and_then(Value::as_u64),
        ) {
            return Ok(FlythroughSpec {
                frames: frames as u32,
                size: FrameSize::Downscale(d as u32),
                fps: 1000.0 / delay.max(1) as f64,
            });
        }
        FlythroughSpec::deserialize(v).map_err(|e| e.to_string())
    }
}

/// The fly-through of one field: `frames` cameras along the virtual trajectory (the path the
/// virtual views sample, sampled densely), rendered into `RUN/flythrough/NAME/frame_NNN.png`.
/// NAME is `base` or a variant's folder name.
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
        // The path, and the frames along it.
        ("virtual", OnResume::Rerun),
        ("flythrough", OnResume::Rerun),
    ];

    fn from_record(v: &Value) -> std::result::Result<Self, String> {
        Ok(FlythroughConfig {
            virt: VirtualSpec::deserialize(v.get("virtual").unwrap_or(&Value::Null))
                .map_err(|e| format!("virtual: {e}"))?,
            spec: FlythroughSpec::from_value(v.get("flythrough").unwrap_or(&Value::Null))
                .map_err(|e| format!("flythrough: {e}"))?,
        })
    }
}

/// The frame cameras of a fly-through (its spec checked) for the run's training cameras `train`.
fn frame_cameras(config: &FlythroughConfig, train: &[Camera]) -> Result<Vec<Camera>> {
    let s = &config.spec;
    Ok(virtual_cameras(
        train,
        config.virt.trajectory,
        s.frames as usize,
        config.virt.range,
    )?
    .iter()
    .map(|c| s.frame_camera(c, config.virt.downscale))
    .collect())
}

/// Frame `i`'s file in a field's fly-through folder.
fn frame_file(i: usize) -> String {
    format!("frame_{i:03}.png")
}

impl Stage for FlythroughStage {
    fn name(&self) -> String {
        format!("flythrough-{}", self.field.name())
    }

    fn config(&self) -> Recorded {
        Recorded::of(&self.config)
    }

    fn inputs(&self) -> Vec<String> {
        vec!["base".into(), self.field.name()]
    }

    /// Its frames are in `RUN/flythrough/NAME`, not in a folder of the stage's name.
    fn reset(&self, dir: &RunDir) -> Result<()> {
        let d = dir.flythrough().join(self.field.name());
        if d.exists() {
            std::fs::remove_dir_all(&d).map_err(|e| ExtrapolateError::io("removing", &d, e))?;
        }
        Ok(())
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value> {
        self.config.spec.check()?;
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
        let cams = frame_cameras(&self.config, &train)?;
        let name = self.field.name();
        let out = dir.flythrough().join(&name);
        create_dir(&out)?;
        let t = Instant::now();
        for (i, cam) in cams.iter().enumerate() {
            let (rgb, _, _) = render(ctx, &nerf, cam, samples)?;
            write_png(&out.join(frame_file(i)), cam.width, cam.height, &rgb)?;
            progress_views(rep, i + 1, cams.len(), &t);
        }
        let (w, h) = (cams[0].width, cams[0].height);
        rep.note(&format!(
            "{}: {} frames of {w}x{h}, {:.1} s",
            out.display(),
            cams.len(),
            t.elapsed().as_secs_f64()
        ));
        Ok(json!({"frames": cams.len(), "width": w, "height": h, "field_step": step}))
    }
}

/// The fly-through video: every field's frames side by side, each under its label, into
/// `RUN/flythrough/flythrough.mp4`.
#[derive(Clone, Debug)]
pub struct FlythroughVideoStage {
    /// The fields, in the order they stand in the video.
    pub fields: Vec<FieldRef>,
    /// The fly-throughs' settings.
    pub config: FlythroughConfig,
}

/// The video's settings: the fly-throughs' and the fields it shows.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlythroughVideoConfig {
    #[serde(flatten)]
    pub flythrough: FlythroughConfig,
    /// The fields' names, in order.
    pub fields: Vec<String>,
}

impl StageSpec for FlythroughVideoConfig {
    const ON_RESUME: &'static [(&'static str, OnResume)] = &[
        ("virtual", OnResume::Rerun),
        ("flythrough", OnResume::Rerun),
        ("fields", OnResume::Rerun),
    ];
}

impl Stage for FlythroughVideoStage {
    fn name(&self) -> String {
        "flythrough-video".into()
    }

    fn config(&self) -> Recorded {
        Recorded::of(&FlythroughVideoConfig {
            flythrough: self.config.clone(),
            fields: self.fields.iter().map(|f| f.name()).collect(),
        })
    }

    fn inputs(&self) -> Vec<String> {
        self.fields
            .iter()
            .map(|f| format!("flythrough-{}", f.name()))
            .collect()
    }

    fn reset(&self, dir: &RunDir) -> Result<()> {
        let f = dir.flythrough().join(VIDEO_FILE);
        if f.exists() {
            std::fs::remove_file(&f).map_err(|e| ExtrapolateError::io("removing", &f, e))?;
        }
        Ok(())
    }

    fn run(&self, _ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value> {
        let s = &self.config.spec;
        s.check()?;
        let frames = s.frames as usize;
        let fly = dir.flythrough();
        let t = Instant::now();
        let mut layout: Option<Layout> = None;
        let mut video: Option<VideoWriter> = None;
        let path = fly.join(VIDEO_FILE);
        let labels: Vec<String> = self.fields.iter().map(|f| f.label()).collect();
        for i in 0..frames {
            let mut tiles = Vec::with_capacity(self.fields.len());
            for f in &self.fields {
                let p = fly.join(f.name()).join(frame_file(i));
                let img = load_image(&p)?;
                let l = match layout {
                    Some(l) => l,
                    None => *layout.insert(Layout::new(self.fields.len(), img.width, img.height)?),
                };
                if (img.width, img.height) != l.tile {
                    return Err(ExtrapolateError::malformed(
                        &p,
                        format!(
                            "a {}x{} frame among frames of {}x{}",
                            img.width, img.height, l.tile.0, l.tile.1
                        ),
                    ));
                }
                tiles.push(img.rgb);
            }
            let Some(l) = layout else {
                return Err(ExtrapolateError::usage(
                    "the fly-through video needs at least one field",
                ));
            };
            let refs: Vec<(&str, &[f32])> = labels
                .iter()
                .zip(&tiles)
                .map(|(label, rgb)| (label.as_str(), rgb.as_slice()))
                .collect();
            let montage = l.compose(&refs)?;
            let v = match video.as_mut() {
                Some(v) => v,
                None => {
                    let (w, h) = l.size();
                    video.insert(VideoWriter::create(&path, w, h, s.fps)?)
                }
            };
            v.push(&montage)?;
            progress_views(rep, i + 1, frames, &t);
        }
        let (Some(video), Some(l)) = (video, layout) else {
            return Err(ExtrapolateError::usage(
                "the fly-through video needs at least one field and one frame",
            ));
        };
        video.finish()?;
        let bytes = std::fs::metadata(&path)
            .map_err(|e| ExtrapolateError::io("reading", &path, e))?
            .len();
        let (w, h) = l.size();
        rep.note(&format!(
            "{}: {frames} frames of {w}x{h} at {} fps ({}), {bytes} bytes, {:.1} s",
            path.display(),
            s.fps,
            labels.join(", "),
            t.elapsed().as_secs_f64()
        ));
        Ok(
            json!({"frames": frames, "width": w, "height": h, "fps": s.fps, "bytes": bytes, "fields": labels}),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use extranerf_nerf::cameras::Trajectory;

    fn config(spec: FlythroughSpec) -> FlythroughConfig {
        FlythroughConfig {
            virt: VirtualSpec {
                trajectory: Trajectory::Outward,
                count: 6,
                range: 1.5,
                downscale: 2,
            },
            spec,
        }
    }

    #[test]
    fn a_record_of_the_gif_fly_through_reads_as_the_same_frames_and_resumes() {
        let now = config(FlythroughSpec::default());
        let mut old = serde_json::to_value(&now).unwrap();
        old["flythrough"] = json!({"frames": 24, "downscale": 2, "delay_ms": 100});
        assert_eq!(FlythroughConfig::from_record(&old).unwrap(), now);
        let dir = std::path::Path::new("run");
        Recorded::of(&now)
            .check(dir, "flythrough-base", &old)
            .unwrap();
        // Other frames than recorded are a change that reruns.
        let more = config(FlythroughSpec {
            frames: 48,
            ..FlythroughSpec::default()
        });
        let e = Recorded::of(&more)
            .check(dir, "flythrough-base", &old)
            .unwrap_err()
            .to_string();
        assert!(e.contains("flythrough.frames: 24 -> 48"), "{e}");
        // The current layout round-trips; a record of neither layout says why it does not read.
        let rec = Recorded::of(&more);
        assert_eq!(FlythroughConfig::from_record(&rec.value).unwrap(), more);
        let bad = json!({"virtual": old["virtual"], "flythrough": {"frames": 3}});
        assert!(FlythroughConfig::from_record(&bad)
            .unwrap_err()
            .contains("flythrough"));
    }

    #[test]
    fn sizes_and_rates_that_make_no_video_are_refused() {
        let ok = FlythroughSpec::default();
        ok.check().unwrap();
        for bad in [
            FlythroughSpec {
                frames: 0,
                ..ok.clone()
            },
            FlythroughSpec {
                size: FrameSize::Downscale(0),
                ..ok.clone()
            },
            FlythroughSpec {
                size: FrameSize::Width(0),
                ..ok.clone()
            },
            FlythroughSpec {
                size: FrameSize::Width(MAX_SIDE + 1),
                ..ok.clone()
            },
            FlythroughSpec {
                fps: 0.0,
                ..ok.clone()
            },
            FlythroughSpec {
                fps: f64::NAN,
                ..ok.clone()
            },
            FlythroughSpec {
                fps: 1001.0,
                ..ok.clone()
            },
        ] {
            let e = bad.check().unwrap_err().to_string();
            assert!(e.contains("fly-through"), "{e}");
        }
        // The frame cameras: a width keeps the aspect; a downscale compounds the virtual one.
        let cam = Camera {
            width: 400,
            height: 300,
            fx: 300.0,
            fy: 300.0,
            cx: 200.0,
            cy: 150.0,
            c2w: Default::default(),
            bounds: None,
            image: "v.png".into(),
        };
        let w = FlythroughSpec {
            size: FrameSize::Width(100),
            ..ok.clone()
        }
        .frame_camera(&cam, 2);
        assert_eq!((w.width, w.height), (100, 75));
        assert!((w.fx - 75.0).abs() < 1e-9);
        let d = ok.frame_camera(&cam, 2);
        assert_eq!((d.width, d.height), (100, 75));
    }
}
