//! Fuzzing of every parser of user files, with proptest: each target starts from a corpus of
//! valid files (real ones from ../shared/data where they exist, otherwise written by the
//! engine's own writers), mutates them (bit flips, overwritten bytes, interesting integers,
//! truncations, insertions, deletions; for JSON also structural edits of the parsed tree) and
//! feeds the result to the loader a user's file reaches. Each input must give a value or an
//! error that names the file: never a panic. The run is bounded by the number of inputs per
//! target, `EXTRANERF_FUZZ_CASES` (default 256; CI runs the default), and each target prints
//! how many inputs it ran, how many the loader accepted and how many it refused. The inputs are
//! the same on every run unless `EXTRANERF_FUZZ_RANDOM` is set (`tools/fuzz.sh` sets it).
//!
//! Not fuzzed here: COLMAP `images.bin` (nothing in the engine reads it) and `prior_holes.json`
//! (read only by the command line; its regions are checked against the views in
//! `bin/tests/cli.rs`).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use serde_json::Value;

use extranerf_nerf::data::Camera;
use extranerf_tests::{scratch_dir, shared_data};

/// Inputs per target.
fn cases() -> u32 {
    std::env::var("EXTRANERF_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(256)
}

/// One edit of a byte string; positions are taken modulo its length.
#[derive(Clone, Debug)]
enum Edit {
    Flip(usize, u8),
    Set(usize, u8),
    /// A little-endian integer of 1, 2, 4 or 8 bytes.
    Int(usize, u64, u8),
    Truncate(usize),
    Insert(usize, Vec<u8>),
    Delete(usize, usize),
}

/// Integers that break size arithmetic.
const INTERESTING: [u64; 12] = [
    0,
    1,
    0x7f,
    0xff,
    0xffff,
    0x7fff_ffff,
    0x8000_0000,
    0xffff_ffff,
    0x1_0000_0000,
    0x7fff_ffff_ffff_ffff,
    0x8000_0000_0000_0000,
    u64::MAX,
];

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<usize>(), 0u8..8).prop_map(|(p, b)| Edit::Flip(p, b)),
        (any::<usize>(), any::<u8>()).prop_map(|(p, v)| Edit::Set(p, v)),
        (
            any::<usize>(),
            prop_oneof![prop::sample::select(INTERESTING.to_vec()), any::<u64>()],
            prop::sample::select(vec![1u8, 2, 4, 8])
        )
            .prop_map(|(p, v, w)| Edit::Int(p, v, w)),
        any::<usize>().prop_map(Edit::Truncate),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(p, b)| Edit::Insert(p, b)),
        (any::<usize>(), 1usize..64).prop_map(|(p, n)| Edit::Delete(p, n)),
    ]
}

fn apply(seed: &[u8], edits: &[Edit]) -> Vec<u8> {
    let mut b = seed.to_vec();
    for e in edits {
        let n = b.len().max(1);
        match e {
            Edit::Flip(p, bit) => {
                if let Some(x) = b.get_mut(p % n) {
                    *x ^= 1 << bit;
                }
            }
            Edit::Set(p, v) => {
                if let Some(x) = b.get_mut(p % n) {
                    *x = *v;
                }
            }
            Edit::Int(p, v, w) => {
                let at = p % n;
                for (k, byte) in v.to_le_bytes().iter().take(*w as usize).enumerate() {
                    if let Some(x) = b.get_mut(at + k) {
                        *x = *byte;
                    }
                }
            }
            Edit::Truncate(p) => b.truncate(p % n),
            Edit::Insert(p, bytes) => {
                let at = p % (b.len() + 1);
                b.splice(at..at, bytes.iter().copied());
            }
            Edit::Delete(p, k) => {
                let at = p % n;
                let end = (at + k).min(b.len());
                if at < end {
                    b.drain(at..end);
                }
            }
        }
    }
    b
}

/// Values that break JSON consumers.
fn json_value() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        prop::sample::select(vec![
            0.0f64,
            -1.0,
            1.0,
            0.5,
            1e-300,
            1e300,
            -1e300,
            4294967296.0,
            1e19,
            -0.0,
            3.0,
        ])
        .prop_map(|v| serde_json::json!(v)),
        prop::sample::select(vec![0i64, -1, 1, 2, 7, i64::MIN, i64::MAX, 65536])
            .prop_map(|v| serde_json::json!(v)),
        Just(serde_json::json!(u64::MAX)),
        "[a-z_.]{0,12}".prop_map(Value::String),
        Just(serde_json::json!([])),
        Just(serde_json::json!({})),
        Just(serde_json::json!([
            [1, 0, 0, 0],
            [0, 1, 0, 0],
            [0, 0, 1, 0]
        ])),
    ]
}

/// Replaces the node that `pick` selects (a walk down the tree) by `v`, or removes it from its
/// object or array when `remove`.
fn edit_json(root: &mut Value, mut pick: u64, v: Value, remove: bool) {
    let mut node = root;
    loop {
        let n = match node {
            Value::Object(m) => m.len(),
            Value::Array(a) => a.len(),
            _ => 0,
        };
        let stop = n == 0 || pick.is_multiple_of(4);
        pick /= 4;
        if stop {
            *node = v;
            return;
        }
        let k = (pick % n as u64) as usize;
        pick /= n as u64 + 1;
        let last = pick == 0;
        match node {
            Value::Object(m) => {
                let key = m.keys().nth(k).cloned().unwrap_or_default();
                if remove && last {
                    m.remove(&key);
                    return;
                }
                node = m.get_mut(&key).unwrap();
            }
            Value::Array(a) => {
                if remove && last {
                    a.remove(k);
                    return;
                }
                node = &mut a[k];
            }
            _ => unreachable!(),
        }
    }
}

/// What one input is: byte edits of a seed, or (for JSON seeds) structural edits.
#[derive(Clone, Debug)]
enum Input {
    Bytes(usize, Vec<Edit>),
    Json(usize, Vec<(u64, Value, bool)>),
}

fn input(seeds: usize, json: bool) -> BoxedStrategy<Input> {
    let bytes =
        (0..seeds, prop::collection::vec(edit(), 0..6)).prop_map(|(i, e)| Input::Bytes(i, e));
    if json {
        prop_oneof![
            bytes,
            (
                0..seeds,
                prop::collection::vec((any::<u64>(), json_value(), any::<bool>()), 1..5)
            )
                .prop_map(|(i, e)| Input::Json(i, e)),
        ]
        .boxed()
    } else {
        bytes.boxed()
    }
}

fn realise(corpus: &[Vec<u8>], input: &Input) -> Vec<u8> {
    match input {
        Input::Bytes(i, e) => apply(&corpus[*i], e),
        Input::Json(i, e) => {
            let mut v: Value = serde_json::from_slice(&corpus[*i]).unwrap();
            for (pick, value, remove) in e {
                edit_json(&mut v, *pick, value.clone(), *remove);
            }
            serde_json::to_vec(&v).unwrap()
        }
    }
}

/// Runs `target` on `cases` mutated inputs of `corpus`: `check` writes or parses the bytes
/// and returns Ok(true) when the loader accepted them, Ok(false) when it refused them with an
/// error naming the file, Err when the error does not. Panics fail the test with the input.
fn fuzz(
    target: &str,
    corpus: Vec<Vec<u8>>,
    json: bool,
    cases: u32,
    check: impl Fn(&[u8]) -> Result<bool, String>,
) {
    assert!(!corpus.is_empty());
    if json {
        for c in &corpus {
            serde_json::from_slice::<Value>(c).unwrap();
        }
    }
    // The seeds themselves load.
    for (i, c) in corpus.iter().enumerate() {
        assert_eq!(check(c), Ok(true), "{target}: seed {i} does not load");
    }
    let (accepted, refused) = (AtomicUsize::new(0), AtomicUsize::new(0));
    let config = Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    };
    // The suite's inputs are the same on every run, so its outcome is reproducible;
    // EXTRANERF_FUZZ_RANDOM=1 (tools/fuzz.sh) draws fresh ones.
    let mut runner = if std::env::var_os("EXTRANERF_FUZZ_RANDOM").is_some() {
        TestRunner::new(config)
    } else {
        TestRunner::new_with_rng(
            config,
            proptest::test_runner::TestRng::deterministic_rng(
                proptest::test_runner::RngAlgorithm::ChaCha,
            ),
        )
    };
    let result = runner.run(&input(corpus.len(), json), |inp| {
        let bytes = realise(&corpus, &inp);
        match check(&bytes) {
            Ok(true) => accepted.fetch_add(1, Ordering::Relaxed),
            Ok(false) => refused.fetch_add(1, Ordering::Relaxed),
            Err(e) => return Err(TestCaseError::fail(e)),
        };
        Ok(())
    });
    let (a, r) = (accepted.into_inner(), refused.into_inner());
    eprintln!(
        "fuzz {target}: {} inputs ({a} accepted, {r} refused), {} seeds",
        a + r,
        corpus.len()
    );
    if let Err(e) = result {
        panic!("fuzz {target}: {e}");
    }
}

/// Ok(true) for a value, Ok(false) for an error naming `name`, Err otherwise.
fn named<T, E: std::fmt::Display>(r: Result<T, E>, name: &str) -> Result<bool, String> {
    match r {
        Ok(_) => Ok(true),
        Err(e) => {
            let msg = format!("{e:#}");
            if msg.contains(name) {
                Ok(false)
            } else {
                Err(format!("error does not name {name}: {msg}"))
            }
        }
    }
}

/// [`fuzz`] for a loader that reads a file: each input is written to `path`, `load` runs, and an
/// error must name the file.
fn fuzz_file<T, E: std::fmt::Display>(
    target: &str,
    path: &Path,
    corpus: Vec<Vec<u8>>,
    json: bool,
    load: impl Fn(&Path) -> Result<T, E>,
) {
    let name = path.file_name().unwrap().to_string_lossy().into_owned();
    fuzz(target, corpus, json, cases(), |b| {
        write(path, b);
        named(load(path), &name)
    });
}

fn fern() -> PathBuf {
    shared_data().join("llff/fern")
}

fn write(path: &Path, bytes: &[u8]) {
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn npy_files() {
    let small = scratch_dir("fuzz-npy-seed").join("small.npy");
    extranerf_nerf::data::npy::write_npy_f64(&small, &[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
        .unwrap();
    let corpus = vec![
        std::fs::read(fern().join("poses_bounds.npy")).unwrap(),
        std::fs::read(small).unwrap(),
    ];
    fuzz("npy", corpus, false, cases(), |b| {
        named(
            extranerf_nerf::data::npy::parse_npy(b, Path::new("poses_bounds.npy")),
            "poses_bounds.npy",
        )
    });
}

/// A two-view LLFF folder `name` (two small images) and its poses: fern's first two, sized
/// for 16x12 images.
fn llff_folder(name: &str) -> (PathBuf, Vec<f64>) {
    let dir = scratch_dir(name);
    let images = dir.join("images");
    std::fs::create_dir_all(&images).unwrap();
    for i in 0..2 {
        image::RgbImage::from_pixel(16, 12, image::Rgb([40, 90, 200]))
            .save(images.join(format!("im{i}.png")))
            .unwrap();
    }
    let raw = extranerf_nerf::data::npy::read_npy(&fern().join("poses_bounds.npy")).unwrap();
    let mut rows = raw.data[..34].to_vec();
    for r in 0..2 {
        // Height, width and focal of the full-size capture.
        rows[r * 17 + 4] = 12.0;
        rows[r * 17 + 9] = 16.0;
        rows[r * 17 + 14] = 14.0;
    }
    (dir, rows)
}

#[test]
fn llff_poses_bounds() {
    let (dir, rows) = llff_folder("fuzz-llff");
    let seed = dir.join("seed.npy");
    extranerf_nerf::data::npy::write_npy_f64(&seed, &[2, 17], &rows).unwrap();
    let corpus = vec![std::fs::read(&seed).unwrap()];
    let opts = extranerf_nerf::data::llff::LlffOptions {
        factor: 1,
        ..Default::default()
    };
    fuzz("poses_bounds.npy (LLFF)", corpus, false, cases(), |b| {
        write(&dir.join("poses_bounds.npy"), b);
        let r = extranerf_nerf::data::llff::load_llff(&dir, &opts);
        if let Ok(s) = &r {
            for c in &s.cameras {
                let ok = c.c2w.is_finite()
                    && c.fx > 0.0
                    && c.fy > 0.0
                    && c.bounds.is_none_or(|(n, f)| n.is_finite() && f.is_finite());
                if !ok {
                    return Err(format!("accepted a camera that cannot work: {c:?}"));
                }
            }
        }
        named(r, "poses_bounds.npy")
    });
}

#[test]
fn transforms_json() {
    let dir = scratch_dir("fuzz-transforms");
    image::RgbImage::from_pixel(8, 6, image::Rgb([1, 2, 3]))
        .save(dir.join("a.png"))
        .unwrap();
    let frame = |x: f64| {
        serde_json::json!({
            "file_path": "a.png",
            "transform_matrix": [[1.0, 0.0, 0.0, x], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]],
        })
    };
    let corpus = vec![
        serde_json::to_vec(&serde_json::json!({"camera_angle_x": 0.7, "frames": [frame(0.0), frame(0.5)]})).unwrap(),
        serde_json::to_vec(&serde_json::json!({"fl_x": 9.0, "fl_y": 9.5, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "k1": 0.0, "frames": [frame(1.0)]})).unwrap(),
    ];
    let path = dir.join("transforms.json");
    fuzz("transforms.json", corpus, true, cases(), |b| {
        write(&path, b);
        let r = extranerf_nerf::data::transforms::load_transforms(&path);
        if let Ok(s) = &r {
            for c in &s.cameras {
                let ok = c.c2w.is_finite() && c.fx > 0.0 && c.fy > 0.0 && c.width > 0;
                if !ok {
                    return Err(format!("accepted a camera that cannot work: {c:?}"));
                }
            }
        }
        // The error names the file, or the image a frame points to (a mutated `file_path`
        // may point anywhere).
        match named(r, "transforms.json") {
            Err(e) if e.contains(".png") || e.contains(dir.to_str().unwrap()) => Ok(false),
            other => other,
        }
    });
}

#[test]
fn colmap_binaries() {
    let dir = scratch_dir("fuzz-colmap");
    let sparse = fern().join("sparse/0");
    let cams = dir.join("cameras.bin");
    fuzz_file(
        "cameras.bin",
        &cams,
        vec![std::fs::read(sparse.join("cameras.bin")).unwrap()],
        false,
        extranerf_nerf::data::colmap::read_cameras_bin,
    );
    // fern's points3D.bin is large; its first 40 points make the seed.
    let all =
        extranerf_nerf::data::colmap::read_points3d_bin(&sparse.join("points3D.bin")).unwrap();
    let full = std::fs::read(sparse.join("points3D.bin")).unwrap();
    let mut at = 8;
    for _ in 0..40.min(all.len()) {
        // id, xyz, rgb, error, track length, track (image id, point2D idx) pairs
        let track = u64::from_le_bytes(full[at + 43..at + 51].try_into().unwrap()) as usize;
        at += 51 + 8 * track;
    }
    let mut seed = (40u64.min(all.len() as u64)).to_le_bytes().to_vec();
    seed.extend_from_slice(&full[8..at]);
    let pts = dir.join("points3D.bin");
    fuzz_file(
        "points3D.bin",
        &pts,
        vec![seed],
        false,
        extranerf_nerf::data::colmap::read_points3d_bin,
    );
}

#[test]
fn images() {
    let dir = scratch_dir("fuzz-images");
    let mut png = Vec::new();
    let img = image::RgbImage::from_fn(24, 16, |x, y| image::Rgb([x as u8 * 9, y as u8 * 13, 77]));
    image::DynamicImage::ImageRgb8(img.clone())
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    let mut jpg = Vec::new();
    image::DynamicImage::ImageRgb8(img)
        .write_to(
            &mut std::io::Cursor::new(&mut jpg),
            image::ImageFormat::Jpeg,
        )
        .unwrap();
    for (name, seed) in [("image.png", png), ("image.jpg", jpg)] {
        fuzz_file(
            name,
            &dir.join(name),
            vec![seed],
            false,
            extranerf_nerf::data::load_image,
        );
    }
}

#[test]
fn depth_maps() {
    let dir = scratch_dir("fuzz-depth");
    let cam = Camera {
        c2w: glam::DMat4::IDENTITY,
        width: 8,
        height: 6,
        fx: 8.0,
        fy: 8.0,
        cx: 4.0,
        cy: 3.0,
        bounds: None,
        image: dir.join("a.png"),
    };
    let depth: Vec<f32> = (0..48).map(|i| 1.0 + i as f32 * 0.1).collect();
    let seed_exr = dir.join("seed.exr");
    extranerf_nerf::run::write_depth_exr(&seed_exr, 8, 6, &depth).unwrap();
    let seed_npy = dir.join("seed.npy");
    let d64: Vec<f64> = depth.iter().map(|&v| v as f64).collect();
    extranerf_nerf::data::npy::write_npy_f64(&seed_npy, &[6, 8], &d64).unwrap();
    fuzz_file(
        "depth .exr",
        &dir.join("depth.exr"),
        vec![std::fs::read(&seed_exr).unwrap()],
        false,
        |p| extranerf_nerf::data::depth::read_depth_exr(p, &cam),
    );
    fuzz_file(
        "depth .npy",
        &dir.join("depth.npy"),
        vec![std::fs::read(&seed_npy).unwrap()],
        false,
        |p| extranerf_nerf::data::depth::read_depth_npy(p, &cam),
    );
}

/// A small run folder's checkpoint (the safetensors container with the run's config in its
/// metadata), fuzzed as bytes and through structural edits of that config.
#[test]
fn checkpoints_and_run_configs() {
    use extranerf_nerf::model::{init_params, ModelConfig};
    use extranerf_nerf::run::{load_checkpoint, save_checkpoint, Checkpoint, RunConfig, SceneSpec};
    use extranerf_nerf::safetensors::SafeTensors;
    let dir = scratch_dir("fuzz-checkpoint");
    let model = ModelConfig {
        levels: 2,
        log2_table: 6,
        max_res: 32,
        min_res: 4,
        density_width: 8,
        color_width: 8,
        geo_dims: 4,
        ..ModelConfig::default()
    };
    let config = RunConfig {
        scene: SceneSpec {
            dir: "scene".into(),
            split: extranerf_nerf::data::split::SplitKind::Extrapolation,
            fewshot_views: 3,
            factor: 8,
            sparse_depth: true,
            depth_dir: None,
            mvs_depth: None,
            capture_depth: false,
        },
        train: Default::default(),
        model: model.clone(),
    };
    let params = init_params(&model, 1);
    save_checkpoint(
        &dir,
        &Checkpoint {
            config: config.clone(),
            step: 7,
            params: params.clone(),
            moments: None,
        },
    )
    .unwrap();
    let file = dir.join("checkpoint.safetensors");
    let seed = std::fs::read(&file).unwrap();
    fuzz_file(
        "checkpoint.safetensors",
        &file,
        vec![seed.clone()],
        false,
        |_| load_checkpoint(&dir),
    );
    // The config inside the metadata, edited as JSON.
    let st = SafeTensors::parse(&seed, &file).unwrap();
    let json = st.metadata["config"].clone().into_bytes();
    fuzz(
        "run config (checkpoint metadata)",
        vec![json],
        true,
        cases(),
        |b| {
            let mut st = st.clone();
            st.metadata
                .insert("config".into(), String::from_utf8_lossy(b).into_owned());
            write(&file, &st.to_bytes());
            named(load_checkpoint(&dir), "checkpoint.safetensors")
        },
    );
}

#[test]
fn safetensors_files() {
    use extranerf_nerf::safetensors::{SafeTensors, Tensor};
    let mut st = SafeTensors::default();
    st.tensors.insert(
        "a".into(),
        Tensor {
            shape: vec![2, 3],
            data: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
        },
    );
    st.tensors.insert(
        "b.c".into(),
        Tensor {
            shape: vec![1],
            data: vec![-1.0],
        },
    );
    st.metadata.insert("step".into(), "3".into());
    fuzz("safetensors", vec![st.to_bytes()], false, cases(), |b| {
        named(
            SafeTensors::parse(b, Path::new("w.safetensors")),
            "w.safetensors",
        )
    });
}

/// diffusers folders: the U-Net, VAE and scheduler configs, LoRA's adapter_config.json, and the
/// U-Net weights of a tiny folder loaded whole.
#[test]
fn diffusers_folders() {
    use extranerf_diffusion::config::{UNetConfig, VaeConfig};
    use extranerf_diffusion::lora::LoraConfig;
    use extranerf_diffusion::scheduler::SchedulerConfig;
    let dir = scratch_dir("fuzz-diffusers");
    let p = dir.join("config.json");
    UNetConfig::tiny_inpainting().save(&p).unwrap();
    let unet = std::fs::read(&p).unwrap();
    fuzz_file(
        "unet/config.json",
        &p,
        vec![unet],
        true,
        UNetConfig::from_file,
    );
    VaeConfig::tiny().save(&p).unwrap();
    let vae = std::fs::read(&p).unwrap();
    fuzz_file("vae/config.json", &p, vec![vae], true, VaeConfig::from_file);
    let s = dir.join("scheduler_config.json");
    SchedulerConfig::default().save(&s).unwrap();
    let sched = std::fs::read(&s).unwrap();
    fuzz_file(
        "scheduler_config.json",
        &s,
        vec![sched],
        true,
        SchedulerConfig::from_file,
    );
    let a = dir.join("adapter_config.json");
    let lora = serde_json::to_vec(&LoraConfig {
        r: 4,
        lora_alpha: 4.0,
        target_modules: vec!["to_q".into(), "to_k".into(), "conv1".into()],
        peft_type: "LORA".into(),
    })
    .unwrap();
    fuzz_file(
        "adapter_config.json",
        &a,
        vec![lora],
        true,
        LoraConfig::from_file,
    );
    // Whole-model loads cost more: a tenth of the inputs.
    let model = dir.join("model");
    let dev = burn::tensor::Device::flex();
    extranerf_diffusion::pipeline::Pipeline::new(
        UNetConfig::tiny_inpainting(),
        Some(VaeConfig::tiny()),
        SchedulerConfig::default(),
        2,
        &dev,
    )
    .unwrap()
    .save(&model)
    .unwrap();
    let w = model.join("unet/diffusion_pytorch_model.safetensors");
    let weights = std::fs::read(&w).unwrap();
    fuzz(
        "unet weights (.safetensors)",
        vec![weights],
        false,
        (cases() / 10).max(8),
        |b| {
            write(&w, b);
            named(
                extranerf_diffusion::pipeline::Pipeline::load(&model, &dev, ""),
                "model",
            )
        },
    );
}

/// The resumable training state of `diffusion prior` and `diffusion finetune`: `state.json`,
/// and the burnpack parameter and optimiser files, read through a resume (a tenth of the
/// inputs: each builds a model).
#[test]
fn diffusion_training_state() {
    use extranerf_diffusion::inpaint::{Codec, PixelCodec};
    use extranerf_diffusion::scheduler::{Schedule, SchedulerConfig};
    use extranerf_diffusion::text::LearnedTokens;
    use extranerf_diffusion::train::{self, Augment, TrainImage, TrainSettings, Trainable};
    use extranerf_diffusion::train_state::{self, Checkpointing, STATE_FILE};
    use extranerf_diffusion::unet::UNet2DConditionModel;
    let dir = scratch_dir("fuzz-train-state");
    let dev = burn::tensor::Device::flex().autodiff();
    let cfg = extranerf_tests::tiny_pixel_unet_config();
    let schedule = Schedule::new(&SchedulerConfig::default()).unwrap();
    let images = vec![TrainImage::new(8, 8, vec![0.5; 3 * 64])];
    let aug = Augment {
        crop: 8,
        ..Augment::default()
    };
    let settings = TrainSettings {
        steps: 1,
        batch: 1,
        log_every: 1,
        ..TrainSettings::default()
    };
    let run = |resume: bool| {
        let model = Trainable {
            unet: UNet2DConditionModel::new(&cfg, &dev).unwrap(),
            tokens: LearnedTokens::new(2, 8, &dev),
        };
        let ck = Checkpointing {
            dir: dir.clone(),
            every: 1,
            resume,
            identity: Value::Null,
        };
        train::train(
            model,
            &Codec::Pixels(PixelCodec),
            &schedule,
            &images,
            &aug,
            &settings,
            &dev,
            Some(&ck),
            &mut |_| {},
        )
        .map(|_| ())
    };
    run(false).unwrap();
    let state = dir.join(STATE_FILE);
    let saved = train_state::peek(&dir).unwrap().unwrap();
    fuzz_file(
        "train_state/state.json",
        &state,
        vec![std::fs::read(&state).unwrap()],
        true,
        |p| train_state::peek(p.parent().unwrap()),
    );
    let text = serde_json::to_vec_pretty(&saved).unwrap();
    write(&state, &text);
    for file in [&saved.model, &saved.adamw_unet] {
        let p = dir.join(file);
        let good = std::fs::read(&p).unwrap();
        fuzz(
            &format!("train_state/{file}"),
            vec![good.clone()],
            false,
            (cases() / 10).max(8),
            |b| {
                write(&p, b);
                named(run(true), file)
            },
        );
        write(&p, &good);
    }
}

/// Inputs the fuzzer found that once broke a loader, kept as fixed regressions.
#[test]
fn regressions_found_by_fuzzing() {
    // poses_bounds.npy whose nearest bound is a denormal: the scene's normalisation scale was
    // infinite and every pose NaN, accepted silently.
    let (dir, mut rows) = llff_folder("fuzz-regress-llff");
    rows[15] = 5e-324;
    extranerf_nerf::data::npy::write_npy_f64(&dir.join("poses_bounds.npy"), &[2, 17], &rows)
        .unwrap();
    let opts = extranerf_nerf::data::llff::LlffOptions {
        factor: 1,
        ..Default::default()
    };
    let e = extranerf_nerf::data::llff::load_llff(&dir, &opts)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("poses_bounds.npy") && e.contains("normalise"),
        "{e}"
    );
    // scheduler_config.json with num_train_timesteps = 2^64 - 1: a capacity-overflow panic.
    let p = scratch_dir("fuzz-regress-sched").join("scheduler_config.json");
    let mut v =
        serde_json::to_value(extranerf_diffusion::scheduler::SchedulerConfig::default()).unwrap();
    v["num_train_timesteps"] = serde_json::json!(u64::MAX);
    write(&p, &serde_json::to_vec(&v).unwrap());
    let e = extranerf_diffusion::scheduler::SchedulerConfig::from_file(&p)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("scheduler_config.json") && e.contains("num_train_timesteps"),
        "{e}"
    );
}
