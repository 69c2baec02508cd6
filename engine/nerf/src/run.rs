//! A training run on disk: the scene it trains on, the resolved configuration (`config.json`)
//! and the checkpoint (`checkpoint.safetensors`: the flat parameters, Adam's moments and the
//! step), both written atomically so a crash leaves the previous checkpoint intact.

use std::path::{Path, PathBuf};

use glam::DVec3;
use image::ImageEncoder;
use serde::{Deserialize, Serialize};

use crate::data::depth::{read_view_depth, sparse_depth, view_depth_paths};
use crate::data::llff::{load_llff, LlffOptions};
use crate::data::split::{Split, SplitIndices, SplitKind};
use crate::data::transforms::{has_split_files, load_split_transforms, load_transforms};
use crate::data::{colmap, load_image, unorm8, Camera, DataError, Scene};
use crate::model::{ModelConfig, ParamLayout};
use crate::safetensors::{write_atomic, SafeTensors, Tensor};
use crate::trainer::TrainConfig;

/// What can go wrong with a run.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// Scene or checkpoint files.
    #[error(transparent)]
    Data(#[from] DataError),
    /// The device.
    #[error(transparent)]
    Gpu(#[from] extranerf_gpu::GpuError),
    /// A setting that cannot work.
    #[error("{0}")]
    Config(String),
}

/// Result alias of runs.
pub type Result<T, E = RunError> = std::result::Result<T, E>;

/// Which scene and views.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    /// LLFF folder (poses_bounds.npy) or a folder / file with transforms.json.
    pub dir: PathBuf,
    /// Which split.
    pub split: SplitKind,
    /// Training views of the few-shot split.
    pub fewshot_views: usize,
    /// LLFF downsampling factor (images_N).
    pub factor: u32,
    /// Supervise depth with the COLMAP sparse points when `sparse/0/points3D.bin` exists.
    pub sparse_depth: bool,
    /// Dense depth maps (`<image stem>.npy` or `.exr`, view depth in the capture's units) for
    /// every training view; they replace the sparse targets.
    #[serde(default)]
    pub depth_dir: Option<PathBuf>,
}

/// Everything a run was trained with.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Scene.
    pub scene: SceneSpec,
    /// Field.
    pub model: ModelConfig,
    /// Training.
    pub train: TrainConfig,
}

/// A loaded scene with its split.
#[derive(Clone, Debug)]
pub struct LoadedScene {
    /// Cameras.
    pub scene: Scene,
    /// Train / test views.
    pub split: SplitIndices,
}

impl SceneSpec {
    /// The split.
    pub fn split(&self) -> Split {
        self.split.split(self.fewshot_views)
    }

    /// Loads the cameras and applies the split.
    pub fn load(&self) -> Result<LoadedScene> {
        let scene = if self.dir.join("poses_bounds.npy").exists() {
            load_llff(
                &self.dir,
                &LlffOptions {
                    factor: self.factor,
                    ..LlffOptions::default()
                },
            )?
        } else if self.dir.is_file() {
            load_transforms(&self.dir)?
        } else if self.dir.join("transforms.json").exists() {
            load_transforms(&self.dir.join("transforms.json"))?
        } else if has_split_files(&self.dir) {
            load_split_transforms(&self.dir)?
        } else {
            return Err(DataError::Malformed {
                path: self.dir.clone(),
                problem: "not a scene: expected poses_bounds.npy (LLFF), transforms.json or \
                          transforms_train.json (NeRF-synthetic)"
                    .into(),
            }
            .into());
        };
        let split = self.split().apply_to(&scene)?;
        Ok(LoadedScene { scene, split })
    }
}

pub use crate::views::View;

/// Loads the training views' images and, when asked and available, sparse depth targets in
/// the model's ray space (NDC t for `space == "ndc"`, view depth otherwise).
pub fn training_views(
    spec: &SceneSpec,
    loaded: &LoadedScene,
    model: &ModelConfig,
) -> Result<Vec<View>> {
    let points_path = spec.dir.join("sparse/0/points3D.bin");
    let points = if spec.sparse_depth && points_path.exists() {
        Some(colmap::read_points3d_bin(&points_path)?)
    } else {
        None
    };
    let world = points.as_ref().map(|p| loaded.scene.transform_points(p));
    // View depth in source units -> scene units (the load's uniform scale).
    let scale = loaded.scene.world_from_source.x_axis.truncate().length();
    let mut views = Vec::new();
    for &i in &loaded.split.train {
        let cam = loaded.scene.cameras[i].clone();
        let img = load_image(&cam.image)?;
        if (img.width, img.height) != (cam.width, cam.height) {
            return Err(DataError::Malformed {
                path: cam.image.clone(),
                problem: format!(
                    "image is {}x{} but its camera says {}x{}",
                    img.width, img.height, cam.width, cam.height
                ),
            }
            .into());
        }
        let target = |x: u32, y: u32, depth: f64| -> Option<f32> {
            if model.space != crate::model::Space::Ndc {
                return Some(depth as f32);
            }
            // World point of the pixel centre at that view depth; NDC t = 1 + near / z
            // (near = 1, the camera looks along -z).
            let dir = DVec3::new(
                (x as f64 + 0.5 - cam.cx) / cam.fx,
                -(y as f64 + 0.5 - cam.cy) / cam.fy,
                -1.0,
            );
            let pw = cam.c2w.transform_point3(dir * depth);
            (pw.z < -1.0).then(|| (1.0 + 1.0 / pw.z) as f32)
        };
        let mut d = vec![[0f32; 2]; cam.width as usize * cam.height as usize];
        let depth = if let Some(dir) = &spec.depth_dir {
            let Some(map) = read_view_depth(dir, &cam)? else {
                let [npy, exr] = view_depth_paths(dir, &cam);
                return Err(DataError::Malformed {
                    path: dir.clone(),
                    problem: format!(
                        "no depth map for training view {i}: expected {} or {}",
                        npy.display(),
                        exr.display()
                    ),
                }
                .into());
            };
            for (k, &z) in map.iter().enumerate() {
                if z > 0.0 {
                    let (x, y) = (k as u32 % cam.width, k as u32 / cam.width);
                    if let Some(t) = target(x, y, z as f64 * scale) {
                        d[k] = [t, 1.0];
                    }
                }
            }
            Some(d)
        } else if let (Some(p), Some(w)) = (&points, &world) {
            for s in sparse_depth(&cam, w, p) {
                if let Some(t) = target(s.x, s.y, s.depth) {
                    d[(s.y * cam.width + s.x) as usize] = [t, s.confidence as f32];
                }
            }
            Some(d)
        } else {
            None
        };
        views.push(View::captured(cam, img, depth));
    }
    Ok(views)
}

/// File names inside a run folder.
pub const CONFIG_FILE: &str = "config.json";
/// See [`CONFIG_FILE`].
pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";

/// A checkpoint's contents.
#[derive(Clone, Debug)]
pub struct Checkpoint {
    /// The run's configuration.
    pub config: RunConfig,
    /// Steps done.
    pub step: u32,
    /// Flat parameters.
    pub params: Vec<f32>,
    /// Adam's first and second moments (absent in weights-only files).
    pub moments: Option<(Vec<f32>, Vec<f32>)>,
}

/// Writes `config.json` and the checkpoint into `dir` (created if missing), each atomically.
pub fn save_checkpoint(dir: &Path, ck: &Checkpoint) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| DataError::Io {
        path: dir.to_path_buf(),
        error: e,
    })?;
    let json = serde_json::to_string_pretty(&ck.config)
        .map_err(|e| RunError::Config(format!("cannot serialise the configuration: {e}")))?;
    let mut st = SafeTensors::default();
    let lay = ParamLayout::new(&ck.config.model);
    if ck.params.len() != lay.total {
        return Err(RunError::Config(format!(
            "{} parameters for a layout of {}",
            ck.params.len(),
            lay.total
        )));
    }
    let mut put = |name: &str, v: &[f32]| {
        st.tensors.insert(
            name.into(),
            Tensor {
                shape: vec![v.len()],
                data: v.to_vec(),
            },
        );
    };
    put("params", &ck.params);
    if let Some((m, v)) = &ck.moments {
        put("adam.m", m);
        put("adam.v", v);
    }
    st.metadata.insert("step".into(), ck.step.to_string());
    st.metadata.insert("config".into(), json.clone());
    st.metadata
        .insert("format".into(), "extranerf-basenerf-1".into());
    st.write(&dir.join(CHECKPOINT_FILE))?;
    write_atomic(&dir.join(CONFIG_FILE), json.as_bytes())?;
    Ok(())
}

/// Reads a run folder's checkpoint (the configuration comes from the checkpoint's own
/// metadata, so the pair can never disagree).
pub fn load_checkpoint(dir: &Path) -> Result<Checkpoint> {
    let path = dir.join(CHECKPOINT_FILE);
    if !path.exists() {
        return Err(DataError::Malformed {
            path: dir.to_path_buf(),
            problem: format!(
                "no {CHECKPOINT_FILE}: not a run folder, or training has not saved yet"
            ),
        }
        .into());
    }
    let st = SafeTensors::read(&path)?;
    let bad = |p: String| {
        RunError::Data(DataError::Malformed {
            path: path.clone(),
            problem: p,
        })
    };
    let json = st
        .metadata
        .get("config")
        .ok_or_else(|| bad("no config in the metadata".into()))?;
    let config: RunConfig =
        serde_json::from_str(json).map_err(|e| bad(format!("config in the metadata: {e}")))?;
    config
        .model
        .validate()
        .map_err(|e| bad(format!("model configuration: {e}")))?;
    let step = st
        .metadata
        .get("step")
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| bad("no step in the metadata".into()))?;
    let total = ParamLayout::new(&config.model).total;
    let params = st.get("params", &[total], &path)?.data.clone();
    if params.iter().any(|v| !v.is_finite()) {
        return Err(bad("parameters contain NaN or infinity".into()));
    }
    let moments = match (st.tensors.get("adam.m"), st.tensors.get("adam.v")) {
        (Some(_), Some(_)) => Some((
            st.get("adam.m", &[total], &path)?.data.clone(),
            st.get("adam.v", &[total], &path)?.data.clone(),
        )),
        _ => None,
    };
    Ok(Checkpoint {
        config,
        step,
        params,
        moments,
    })
}

/// Writes an RGB f32 image (values clamped to [0, 1]) as an 8-bit PNG, atomically.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[f32]) -> Result<()> {
    if rgb.len() != width as usize * height as usize * 3 {
        return Err(RunError::Config(format!(
            "{}: {} values for a {width}x{height} RGB image",
            path.display(),
            rgb.len()
        )));
    }
    let bytes: Vec<u8> = rgb.iter().map(|&v| unorm8(v)).collect();
    write_png_bytes(path, width, height, &bytes, image::ExtendedColorType::Rgb8)
}

/// Encodes 8-bit pixels as PNG and writes them atomically.
fn write_png_bytes(
    path: &Path,
    width: u32,
    height: u32,
    bytes: &[u8],
    colour: image::ExtendedColorType,
) -> Result<()> {
    let mut png = Vec::new();
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(bytes, width, height, colour)
        .map_err(|e| RunError::Config(format!("{}: cannot encode PNG: {e}", path.display())))?;
    write_atomic(path, &png)?;
    Ok(())
}

/// Writes a straight-alpha RGBA image (colour and alpha clamped to [0, 1]) as an 8-bit PNG,
/// atomically.
pub fn write_png_rgba(
    path: &Path,
    width: u32,
    height: u32,
    rgb: &[f32],
    alpha: &[f32],
) -> Result<()> {
    let px = width as usize * height as usize;
    if rgb.len() != px * 3 || alpha.len() != px {
        return Err(RunError::Config(format!(
            "{}: {} colour and {} alpha values for a {width}x{height} RGBA image",
            path.display(),
            rgb.len(),
            alpha.len()
        )));
    }
    let bytes: Vec<u8> = rgb
        .chunks_exact(3)
        .zip(alpha)
        .flat_map(|(c, &a)| [unorm8(c[0]), unorm8(c[1]), unorm8(c[2]), unorm8(a)])
        .collect();
    write_png_bytes(path, width, height, &bytes, image::ExtendedColorType::Rgba8)
}

/// Writes a view-depth map in the capture's units (what `train --depth-dir` reads) as a
/// single-channel f32 OpenEXR file (channel `Z`).
pub fn write_depth_exr(path: &Path, width: u32, height: u32, depth: &[f32]) -> Result<()> {
    write_exr_channels(path, width, height, &[("Z", depth)])
}

pub use crate::data::depth::RAY_DEPTH_CHANNEL;

/// Writes a field's ray-space depth (renders, visibility) as a single-channel f32 OpenEXR
/// file (channel [`RAY_DEPTH_CHANNEL`]).
pub fn write_ray_depth_exr(path: &Path, width: u32, height: u32, depth: &[f32]) -> Result<()> {
    write_exr_channels(path, width, height, &[(RAY_DEPTH_CHANNEL, depth)])
}

/// A ray-space depth map of `cam` (NDC t when `ndc`) as view depth in the capture's units
/// (`world_scale`: the scene's `world_from_source` scale); 0 where there is no world point.
pub fn ray_depth_to_view_depth(
    cam: &Camera,
    depth: &[f32],
    ndc: bool,
    world_scale: f64,
) -> Vec<f32> {
    depth
        .iter()
        .enumerate()
        .map(|(i, &t)| {
            let (x, y) = (
                (i as u32 % cam.width) as f64 + 0.5,
                (i as u32 / cam.width) as f64 + 0.5,
            );
            match cam.ray_point(x, y, t as f64, ndc) {
                Some(p) => {
                    let z = cam.project(p).2;
                    if z > 0.0 && z.is_finite() {
                        (z / world_scale) as f32
                    } else {
                        0.0
                    }
                }
                None => 0.0,
            }
        })
        .collect()
}

/// Writes named f32 channels of one image as an OpenEXR file, atomically.
pub fn write_exr_channels(
    path: &Path,
    width: u32,
    height: u32,
    channels: &[(&str, &[f32])],
) -> Result<()> {
    use exr::prelude::*;
    let mut list = SmallVec::new();
    for (name, data) in channels {
        if data.len() != width as usize * height as usize {
            return Err(RunError::Config(format!(
                "{}: {} values in channel {name} for {width}x{height}",
                path.display(),
                data.len()
            )));
        }
        list.push(AnyChannel::new(*name, FlatSamples::F32(data.to_vec())));
    }
    let layer = Layer::new(
        (width as usize, height as usize),
        LayerAttributes::named("image"),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(list),
    );
    // Encoded in memory, then written like every other output (synced temp file + rename).
    let mut bytes = Vec::new();
    exr::image::Image::from_layer(layer)
        .write()
        .to_buffered(std::io::Cursor::new(&mut bytes))
        .map_err(|e| RunError::Config(format!("{}: cannot encode EXR: {e}", path.display())))?;
    write_atomic(path, &bytes)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::encodings::Contraction;
    use crate::model::{Precision, Space};
    use crate::trainer::RgbLossKind;

    fn config() -> RunConfig {
        RunConfig {
            scene: SceneSpec {
                dir: "scene".into(),
                split: SplitKind::FewShot,
                fewshot_views: 3,
                factor: 8,
                sparse_depth: true,
                depth_dir: None,
            },
            model: ModelConfig {
                space: Space::World,
                contraction: Contraction::LInf,
                precision: Precision::F16,
                ..ModelConfig::default()
            },
            train: TrainConfig {
                rgb_loss: RgbLossKind::Huber,
                ..TrainConfig::default()
            },
        }
    }

    /// The choices are enums in code and the same lower-case names on disk as when they were
    /// strings, so run folders written before keep loading.
    #[test]
    fn choices_keep_their_names_on_disk() {
        let json = serde_json::to_value(config()).unwrap();
        assert_eq!(json["scene"]["split"], "fewshot");
        assert_eq!(json["model"]["space"], "world");
        assert_eq!(json["model"]["contraction"], "linf");
        assert_eq!(json["model"]["precision"], "f16");
        assert_eq!(json["train"]["rgb_loss"], "huber");
        let back: RunConfig = serde_json::from_value(json.clone()).unwrap();
        assert_eq!(back, config());
        // A config from before `precision` existed reads as f32.
        let mut old = json;
        old["model"].as_object_mut().unwrap().remove("precision");
        let back: RunConfig = serde_json::from_value(old.clone()).unwrap();
        assert_eq!(back.model.precision, Precision::F32);
        // A value that names no choice is refused, naming the choices.
        old["model"]["space"] = "spherical".into();
        let e = serde_json::from_value::<RunConfig>(old)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("spherical") && e.contains("ndc") && e.contains("world"),
            "{e}"
        );
    }

    #[test]
    fn split_kinds_map_to_splits() {
        let mut spec = config().scene;
        assert_eq!(spec.split(), Split::FewShot(3));
        spec.split = SplitKind::Extrapolation;
        assert_eq!(spec.split(), Split::Extrapolation);
        spec.split = SplitKind::All;
        assert_eq!(spec.split(), Split::All);
        spec.split = SplitKind::Given;
        assert_eq!(spec.split(), Split::Given);
        for k in [
            SplitKind::Extrapolation,
            SplitKind::FewShot,
            SplitKind::All,
            SplitKind::Given,
        ] {
            assert_eq!(serde_json::to_value(k).unwrap(), k.name());
        }
    }
}
