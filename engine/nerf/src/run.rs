//! A training run on disk: the scene it trains on, the resolved configuration (`config.json`)
//! and the checkpoint (`checkpoint.safetensors`: the flat parameters, Adam's moments and the
//! step), both written atomically so a crash leaves the previous checkpoint intact.

use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::data::depth::{read_capture_depth, read_view_depth, sparse_depth, view_depth_paths};
use crate::data::llff::{load_llff, LlffOptions};
use crate::data::split::{Split, SplitIndices, SplitKind};
use crate::data::transforms::{has_split_files, load_split_transforms, load_transforms_at};
use crate::data::{colmap, load_image, Camera, DataError, Scene};
use crate::model::{ModelConfig, ParamLayout};
use crate::mvs_depth::{CacheUse, MvsDepthSettings, ViewDepth};
use crate::safetensors::{write_atomic, SafeTensors, Tensor};
use crate::trainer::TrainConfig;

pub use crate::run_error::{Result, RunError};
pub use crate::write::{
    ray_depth_to_view_depth, write_depth_exr, write_exr_channels, write_png, write_png_rgba,
    write_ray_depth_exr, RAY_DEPTH_CHANNEL,
};

/// Which scene and views.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    /// LLFF folder (poses_bounds.npy), a folder / file with transforms.json, or a COLMAP
    /// capture (`sparse/0/` and `images/`).
    pub dir: PathBuf,
    /// Which split.
    pub split: SplitKind,
    /// Training views of the few-shot split.
    pub fewshot_views: usize,
    /// LLFF downsampling factor (images_N).
    pub factor: u32,
    /// Supervise depth with the COLMAP sparse points when `sparse/0/points3D.bin` (or `.txt`)
    /// exists.
    pub sparse_depth: bool,
    /// Dense depth maps (`<image stem>.npy` or `.exr`, view depth in the capture's units) for
    /// every training view; they replace the sparse targets and the MVS maps.
    #[serde(default)]
    pub depth_dir: Option<PathBuf>,
    /// Dense depth of the training views from the project's plane sweep, with these settings
    /// (cached in the run folder, [`crate::mvs_depth::cached`]); its confidence weights each
    /// pixel's depth loss, and the sparse points (with `sparse_depth`) replace it where they
    /// fall. Absent in runs from before issue 52.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mvs_depth: Option<MvsDepthSettings>,
    /// Dense depth from the files the capture's frames name (nerfstudio's `depth_file_path`,
    /// millimetres); they replace the sparse targets and the MVS maps. Absent in runs from
    /// before it was read.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub capture_depth: bool,
}

/// `train --depth`: where a run's depth targets come from, before it is resolved into a
/// [`SceneSpec`]'s depth fields ([`DepthRequest::resolve`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DepthRequest {
    /// The depth files the capture's frames name (nerfstudio's `depth_file_path`), else the
    /// dense maps the scene ships (`depth/` beside its images), else MVS depth of the
    /// training views plus COLMAP's sparse points where the scene has them, else the sparse
    /// points alone (when the views cannot be matched: no depth bounds, or views of several
    /// sizes).
    Auto,
    /// COLMAP's sparse points (`sparse/0/points3D.bin`) only.
    Sparse,
    /// MVS depth of the training views only.
    Mvs,
    /// No depth target.
    None,
    /// The depth files the capture's frames name (nerfstudio's `depth_file_path`).
    Capture,
    /// Dense maps from this folder (`<image stem>.npy` or `.exr`, view depth in the capture's
    /// units).
    Dir(PathBuf),
}

impl std::str::FromStr for DepthRequest {
    type Err = std::convert::Infallible;

    /// `auto`, `sparse`, `mvs`, `none`, `capture`, or any other text as a folder.
    fn from_str(s: &str) -> std::result::Result<Self, Self::Err> {
        Ok(match s {
            "auto" => DepthRequest::Auto,
            "sparse" => DepthRequest::Sparse,
            "mvs" => DepthRequest::Mvs,
            "none" => DepthRequest::None,
            "capture" => DepthRequest::Capture,
            dir => DepthRequest::Dir(PathBuf::from(dir)),
        })
    }
}

/// The folder of dense depth maps a scene ships: `depth/` in its folder (beside a
/// transforms.json given as a file).
pub fn shipped_depth_dir(scene_dir: &Path) -> PathBuf {
    let root = if scene_dir.is_file() {
        scene_dir.parent().unwrap_or(Path::new("."))
    } else {
        scene_dir
    };
    root.join("depth")
}

/// COLMAP's sparse points of a scene (`sparse/0/points3D.bin` or `.txt`; a path that does not
/// exist where the scene has none).
pub fn points_path(scene_dir: &Path) -> PathBuf {
    crate::data::colmap_scene::model_dir(scene_dir)
        .and_then(|d| colmap::points_file(&d))
        .unwrap_or_else(|| scene_dir.join("sparse/0/points3D.bin"))
}

/// Why the training views of `loaded` cannot be matched by the plane sweep, if they cannot.
pub fn mvs_unavailable(loaded: &LoadedScene, settings: &MvsDepthSettings) -> Option<String> {
    let cams = loaded.train_cameras();
    if !(2..=crate::mvs::MAX_VIEWS).contains(&cams.len()) {
        return Some(format!(
            "{} training view(s): it matches 2 to {}",
            cams.len(),
            crate::mvs::MAX_VIEWS
        ));
    }
    if cams
        .iter()
        .any(|c| (c.width, c.height) != (cams[0].width, cams[0].height))
    {
        return Some("the training views are not all one size".into());
    }
    settings.range(&cams).err().map(|e| e.to_string())
}

impl DepthRequest {
    /// Sets `spec`'s depth fields for this request, MVS depth with `settings`, and says what
    /// was chosen (and, for `auto`, why). `sparse` needs the scene's sparse points; `mvs` needs
    /// views the sweep can match.
    pub fn resolve(
        &self,
        spec: &mut SceneSpec,
        loaded: &LoadedScene,
        settings: MvsDepthSettings,
    ) -> Result<String> {
        let has_points = points_path(&spec.dir).exists();
        spec.sparse_depth = false;
        spec.depth_dir = None;
        spec.mvs_depth = None;
        spec.capture_depth = false;
        let capture = !loaded.scene.depth_files.is_empty();
        match self {
            DepthRequest::None => {}
            DepthRequest::Capture => {
                if !capture {
                    return Err(DataError::Malformed {
                        path: spec.dir.clone(),
                        problem: "--depth capture: the scene's frames name no depth file \
                                  (depth_file_path)"
                            .into(),
                    }
                    .into());
                }
                spec.capture_depth = true;
            }
            DepthRequest::Sparse => {
                if !has_points {
                    return Err(DataError::Malformed {
                        path: points_path(&spec.dir),
                        problem: "--depth sparse: the scene has no COLMAP sparse points".into(),
                    }
                    .into());
                }
                spec.sparse_depth = true;
            }
            DepthRequest::Mvs => {
                if let Some(why) = mvs_unavailable(loaded, &settings) {
                    return Err(RunError::Config(format!(
                        "--depth mvs on {}: {why}",
                        spec.dir.display()
                    )));
                }
                spec.mvs_depth = Some(settings);
            }
            DepthRequest::Dir(d) => {
                if !d.is_dir() {
                    return Err(DataError::Malformed {
                        path: d.clone(),
                        problem:
                            "--depth: not a folder of depth maps, nor auto, sparse, mvs or none"
                                .into(),
                    }
                    .into());
                }
                spec.depth_dir = Some(d.clone());
            }
            DepthRequest::Auto => {
                let shipped = shipped_depth_dir(&spec.dir);
                if capture {
                    spec.capture_depth = true;
                } else if shipped.is_dir() {
                    spec.depth_dir = Some(shipped);
                } else {
                    spec.sparse_depth = has_points;
                    match mvs_unavailable(loaded, &settings) {
                        None => spec.mvs_depth = Some(settings),
                        Some(why) => {
                            return Ok(format!(
                                "depth auto: {} (no MVS depth: {why})",
                                spec.depth_label()
                            ))
                        }
                    }
                }
                return Ok(format!("depth auto: {}", spec.depth_label()));
            }
        }
        Ok(format!("depth: {}", spec.depth_label()))
    }
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
    /// Where the run's depth targets come from, in words (reports and `eval`).
    pub fn depth_label(&self) -> String {
        let points = self.sparse_depth && points_path(&self.dir).exists();
        let mvs = |s: &MvsDepthSettings| {
            let fill = if s.fill > 0 {
                format!(", holes filled by {} sweeps", s.fill)
            } else {
                String::new()
            };
            format!(
                "MVS depth (1/{} resolution, {} planes{fill})",
                s.downscale, s.planes
            )
        };
        if self.capture_depth {
            return "the capture's depth files (depth_file_path, millimetres)".into();
        }
        match (&self.depth_dir, &self.mvs_depth, points) {
            (Some(d), _, _) => format!("dense maps from {}", d.display()),
            (None, Some(s), true) => format!("{} and COLMAP sparse points", mvs(s)),
            (None, Some(s), false) => mvs(s),
            (None, None, true) => "COLMAP sparse points".into(),
            (None, None, false) => "none".into(),
        }
    }

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
            load_transforms_at(&self.dir, self.factor)?
        } else if self.dir.join("transforms.json").exists() {
            load_transforms_at(&self.dir.join("transforms.json"), self.factor)?
        } else if has_split_files(&self.dir) {
            load_split_transforms(&self.dir)?
        } else if crate::data::colmap_scene::model_dir(&self.dir).is_some() {
            crate::data::colmap_scene::load_colmap(&self.dir, self.factor)?
        } else {
            return Err(DataError::Malformed {
                path: self.dir.clone(),
                problem: "not a scene: expected poses_bounds.npy (LLFF), transforms.json, \
                          transforms_train.json (NeRF-synthetic) or a COLMAP model \
                          (sparse/0/cameras.bin or .txt, with images/)"
                    .into(),
            }
            .into());
        };
        let split = self.split().apply_to(&scene)?;
        Ok(LoadedScene { scene, split })
    }
}

impl LoadedScene {
    /// The training views' cameras, in the split's order.
    pub fn train_cameras(&self) -> Vec<Camera> {
        self.split
            .train
            .iter()
            .map(|&i| self.scene.cameras[i].clone())
            .collect()
    }
}

pub use crate::views::View;

/// Loads the training views' images and their depth targets in the model's ray space (NDC t
/// for `space == "ndc"`, view depth otherwise): the dense maps of `depth_dir`, else the COLMAP
/// sparse points (with `sparse_depth`, where the scene has them). A spec with MVS depth needs
/// its maps: use [`training_views_in`].
pub fn training_views(
    spec: &SceneSpec,
    loaded: &LoadedScene,
    model: &ModelConfig,
) -> Result<Vec<View>> {
    if spec.mvs_depth.is_some() && spec.depth_dir.is_none() {
        return Err(RunError::Config(format!(
            "{}: this run's depth comes from multi-view stereo, which needs the device and the \
             run folder that caches it (training_views_in)",
            spec.dir.display()
        )));
    }
    training_views_from(spec, loaded, model, None)
}

/// [`training_views`] for any spec: MVS depth (when the spec asks for it) is read from
/// `run_dir`'s cache, or computed on `ctx` and cached there. Also says whether the cache was
/// used (`None` when the spec has no MVS depth).
pub fn training_views_in(
    ctx: &extranerf_gpu::Context,
    spec: &SceneSpec,
    loaded: &LoadedScene,
    model: &ModelConfig,
    run_dir: &Path,
) -> Result<(Vec<View>, Option<CacheUse>)> {
    let (maps, used) = match (&spec.mvs_depth, &spec.depth_dir) {
        (Some(settings), None) => {
            let cams = loaded.train_cameras();
            let (maps, used) = crate::mvs_depth::cached(ctx, &spec.dir, &cams, settings, run_dir)?;
            (Some(maps), Some(used))
        }
        _ => (None, None),
    };
    Ok((
        training_views_from(spec, loaded, model, maps.as_deref())?,
        used,
    ))
}

/// The training views with depth from `depth_dir`, else from `mvs` (one map per training view,
/// view depth in scene units; the confidence is each pixel's weight) with the sparse points
/// (when the spec asks for them) in place of the maps where they fall.
pub fn training_views_from(
    spec: &SceneSpec,
    loaded: &LoadedScene,
    model: &ModelConfig,
    mvs: Option<&[ViewDepth]>,
) -> Result<Vec<View>> {
    if let Some(m) = mvs {
        if m.len() != loaded.split.train.len() {
            return Err(RunError::Config(format!(
                "{} MVS depth maps for {} training views",
                m.len(),
                loaded.split.train.len()
            )));
        }
    }
    let points_path = points_path(&spec.dir);
    let points = if spec.sparse_depth && points_path.exists() {
        Some(colmap::read_points3d(&points_path)?)
    } else {
        None
    };
    let world = points.as_ref().map(|p| loaded.scene.transform_points(p));
    // View depth in source units -> scene units (the load's uniform scale).
    let scale = loaded.scene.world_from_source.x_axis.truncate().length();
    let mut views = Vec::new();
    for (k, &i) in loaded.split.train.iter().enumerate() {
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
        let dense = if spec.capture_depth {
            let Some(file) = loaded.scene.depth_files.get(i) else {
                return Err(DataError::Malformed {
                    path: spec.dir.clone(),
                    problem: format!(
                        "the run reads the capture's depth files, but view {i} names none \
                         (depth_file_path)"
                    ),
                }
                .into());
            };
            // In the units of the frames' poses, which the transforms loader keeps as the
            // scene's (its `world_from_source` scale is COLMAP's to theirs, not theirs to the
            // scene's).
            Some((read_capture_depth(file, &cam)?, 1.0))
        } else if let Some(dir) = &spec.depth_dir {
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
            Some((map, scale))
        } else {
            None
        };
        let depth = if let Some((map, scale)) = dense {
            for (k, &z) in map.iter().enumerate() {
                if z > 0.0 {
                    let (x, y) = (k as u32 % cam.width, k as u32 / cam.width);
                    if let Some(t) = target(x, y, z as f64 * scale) {
                        d[k] = [t, 1.0];
                    }
                }
            }
            Some(d)
        } else if mvs.is_some() || points.is_some() {
            if let Some(m) = mvs.map(|m| &m[k]) {
                if (m.width, m.height) != (cam.width, cam.height) {
                    return Err(RunError::Config(format!(
                        "the MVS depth of training view {i} is {}x{}, the view {}x{}",
                        m.width, m.height, cam.width, cam.height
                    )));
                }
                for (p, (&z, &c)) in m.depth.iter().zip(&m.confidence).enumerate() {
                    if z > 0.0 && c > 0.0 {
                        let (x, y) = (p as u32 % cam.width, p as u32 / cam.width);
                        if let Some(t) = target(x, y, z as f64) {
                            d[p] = [t, c.min(1.0)];
                        }
                    }
                }
            }
            // The sparse points replace the MVS depth where they fall.
            if let (Some(p), Some(w)) = (&points, &world) {
                for s in sparse_depth(&cam, w, p) {
                    if let Some(t) = target(s.x, s.y, s.depth) {
                        d[(s.y * cam.width + s.x) as usize] = [t, s.confidence as f32];
                    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::encodings::Contraction;
    use crate::model::{Precision, ProposalConfig, Sampler, Space};
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
                mvs_depth: None,
                capture_depth: false,
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
        // A config from before the proposal sampler (no `sampler`) reads as uniform and writes
        // no `sampler`; the proposal sampler's settings round-trip.
        assert!(old["model"].get("sampler").is_none());
        assert_eq!(back.model.sampler, Sampler::Uniform);
        let mut with = config();
        with.model.sampler = Sampler::Proposal(ProposalConfig::default());
        let json = serde_json::to_value(&with).unwrap();
        assert_eq!(json["model"]["sampler"]["proposal"]["samples"], 32);
        let back: RunConfig = serde_json::from_value(json).unwrap();
        assert_eq!(back, with);
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
