//! The `extranerf` command line end to end: `info`, a tiny `bench kernels` run writing JSON,
//! and clear errors for bad arguments.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::process::Command;

fn extranerf(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_extranerf"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn info_names_device_and_driver() {
    let (ok, out, err) = extranerf(&["info"]);
    assert!(ok, "{err}");
    for field in [
        "device",
        "driver",
        "vulkan",
        "heap 0",
        "subgroup size",
        "f32 atomic add",
        "validation",
    ] {
        assert!(out.contains(field), "`{field}` missing from:\n{out}");
    }
    let (ok, out, _) = extranerf(&["info", "--list"]);
    assert!(ok && out.starts_with("0: "), "{out}");
}

#[test]
fn bench_kernels_writes_a_table_and_json() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-{}", std::process::id()));
    let json = dir.join("bench.json");
    let (ok, out, err) = extranerf(&[
        "bench",
        "kernels",
        "--sizes",
        "4096",
        "--repeats",
        "1",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    for row in [
        "copy (vkCmdCopyBuffer, reference)",
        "saxpy",
        "radix sort",
        "scatter-add subgroup, all equal",
        "hash grid fwd",
        "mlp fwd",
        "adam",
    ] {
        assert!(out.contains(row), "row `{row}` missing:\n{out}");
    }
    let text = std::fs::read_to_string(&json).unwrap();
    assert!(
        text.contains("\"ratio_to_copy\"") && text.contains("\"median_ms\""),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn bench_kernels_micro_figures_are_finite_and_positive() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-micro-{}", std::process::id()));
    let json = dir.join("micro.json");
    let (ok, out, err) = extranerf(&[
        "bench",
        "kernels",
        "--sizes",
        "4096",
        "--repeats",
        "1",
        "--only",
        "micro",
        "--micro-lanes",
        "100",
        "--micro-ops",
        "256",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let rows = v["micro"].as_array().unwrap();
    // Every operation issue 61 names, each timed.
    for op in [
        "random read 8 B",
        "random read 16 B",
        "f32 atomic add, distinct addresses",
        "f32 atomic add, 64 lanes per address",
        "FMA, registers",
        "dense 64x64 layer, 4 points/lane",
        "workgroup vec4 read-modify-write",
        "storage vec4 read-modify-write",
    ] {
        assert!(
            rows.iter().any(|r| r["op"] == op) && out.contains(op),
            "`{op}` missing:\n{out}"
        );
    }
    assert_eq!(rows.len(), 19, "{rows:?}");
    for r in rows {
        for key in ["median_ms", "ns_per_op", "ns_per_lane_op"] {
            let x = r[key].as_f64().unwrap();
            assert!(x.is_finite() && x > 0.0, "{key} of {}: {x}", r["op"]);
        }
        assert!(
            r["lanes"] == 100 && r["ops_per_lane"].as_u64().unwrap() >= 256,
            "{r}"
        );
        if let Some(net) = r["net_ns_per_op"].as_f64() {
            assert!(net.is_finite(), "{r}");
        }
    }
    let (ok, _, err) = extranerf(&["bench", "kernels", "--only", "micro", "--micro-ops", "0"]);
    assert!(!ok && err.contains("--micro-ops"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn bad_arguments_are_clear_errors() {
    let (ok, _, err) = extranerf(&["bench", "kernels", "--sizes", "0"]);
    assert!(
        !ok && err.contains("--sizes") && err.contains("outside"),
        "{err}"
    );
    let (ok, _, err) = extranerf(&["--device", "no-such-gpu", "info"]);
    assert!(
        !ok && err.contains("no Vulkan device matches `no-such-gpu`"),
        "{err}"
    );
    let (ok, _, err) = extranerf(&["bench", "kernels", "--repeats", "0"]);
    assert!(!ok && err.contains("--repeats"), "{err}");
    let (ok, _, err) = extranerf(&["train"]);
    assert!(
        !ok && err.contains("--scene") && err.contains("--out"),
        "{err}"
    );
    // Choices are enums that clap checks and lists before any device or file is touched.
    let run = "/no/such/run";
    for (args, bad, choices) in [
        (
            ["train", "--out", run, "--split"],
            "everything",
            ["extrapolation", "fewshot", "all"].as_slice(),
        ),
        (
            ["train", "--out", run, "--precision"],
            "f8",
            &["f32", "f16"],
        ),
        (
            ["train", "--out", run, "--step"],
            "fast",
            &["fused", "standalone"],
        ),
        (
            ["train", "--out", run, "--sampler"],
            "nested",
            &["uniform", "proposal"],
        ),
        (
            ["extrapolate", "--out", run, "--diffusion-backend"],
            "tpu",
            &["auto", "device", "cpu"],
        ),
        (
            ["extrapolate", "--out", run, "--inpainter"],
            "sd",
            &[
                "harmonic",
                "exemplar",
                "hybrid",
                "diffusion",
                "diffusion-base",
            ],
        ),
        (
            ["render", run, "--chunk=64", "--march"],
            "fast",
            &["fused", "standalone"],
        ),
        // Views are parsed with the command line too.
        (
            ["render", run, "--chunk=64", "--views"],
            "0,x",
            &["test", "train", "all", "indices"],
        ),
        (
            ["visibility", run, "--training-masks", "--views"],
            "front",
            &["test", "train", "all", "indices"],
        ),
        (
            ["train", "--out", run, "--eval-views"],
            "1;2",
            &["test", "train", "all", "indices"],
        ),
    ] {
        let mut a = args.to_vec();
        a.push(bad);
        let (ok, _, err) = extranerf(&a);
        assert!(
            !ok && err.contains(bad) && choices.iter().all(|c| err.contains(c)),
            "{a:?}: {err}"
        );
    }
    let (ok, out, err) = extranerf(&["train", "--help"]);
    assert!(
        ok && out.contains("else holdout]")
            && out.contains("fewshot")
            && out.contains("extrapolation"),
        "{out}{err}"
    );
    let dir = std::env::temp_dir().join(format!("extranerf-cli-bad-{}", std::process::id()));
    let out = dir.join("run");
    let (ok, _, err) = extranerf(&[
        "train",
        "--scene",
        "/no/such/scene",
        "--split",
        "extrapolation",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        !ok && err.contains("/no/such/scene") && err.contains("poses_bounds.npy"),
        "{err}"
    );
    let (ok, _, err) = extranerf(&["render", out.to_str().unwrap()]);
    assert!(!ok && err.contains("checkpoint.safetensors"), "{err}");
    let (ok, _, err) = extranerf(&["train", "--resume", "--out", out.to_str().unwrap()]);
    assert!(!ok && err.contains("checkpoint.safetensors"), "{err}");
    // A run's sampler is its own: --resume refuses to change it.
    let (ok, _, err) = extranerf(&[
        "train",
        "--resume",
        "--out",
        out.to_str().unwrap(),
        "--sampler",
        "proposal",
        "--proposal-samples",
        "32",
    ]);
    assert!(
        !ok && err.contains("--sampler") && err.contains("--proposal-samples"),
        "{err}"
    );
    // KID's protocol flags on an extrapolate run are checked before any work.
    let xrun = dir.join("xrun");
    std::fs::create_dir_all(&xrun).unwrap();
    std::fs::write(xrun.join("extrapolate.json"), "{}").unwrap();
    for (flag, value, says) in [
        ("--kid-min-fraction", "1.5", "not a share in [0, 1]"),
        ("--kid-subset-size", "1", "at least 2"),
        ("--kid-subsets", "0", "must be positive"),
    ] {
        let (ok, _, err) = extranerf(&[
            "eval",
            xrun.to_str().unwrap(),
            "--kid-backend",
            "cpu",
            flag,
            value,
        ]);
        assert!(!ok && err.contains(says), "{flag} {value}: {err}");
    }
    // extrapolate --depth: resolved before any work; a reused BaseNeRF keeps its own.
    let fern = fern();
    let xnew = dir.join("xnew");
    let (ok, _, err) = extranerf(&[
        "extrapolate",
        "--scene",
        fern.to_str().unwrap(),
        "--split",
        "extrapolation",
        "--out",
        xnew.to_str().unwrap(),
        "--depth",
        "/no/such/depth",
    ]);
    assert!(!ok && err.contains("/no/such/depth"), "{err}");
    assert!(!xnew.exists(), "a run folder was left behind");
    let (ok, _, err) = extranerf(&[
        "extrapolate",
        "--base",
        xrun.to_str().unwrap(),
        "--out",
        xnew.to_str().unwrap(),
        "--depth",
        "mvs",
    ]);
    assert!(!ok && err.contains("cannot be used with"), "{err}");
    // A bad GPU wait limit is refused before any work, naming the variable.
    let out = Command::new(env!("CARGO_BIN_EXE_extranerf"))
        .arg("info")
        .env("EXTRANERF_GPU_TIMEOUT_S", "ten")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("EXTRANERF_GPU_TIMEOUT_S is `ten`"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(dir);
}

fn fern() -> std::path::PathBuf {
    extranerf_tests::shared_data().join("llff/fern")
}

/// train -> checkpoint -> resume -> render -> eval through the real binary, on fern with a
/// tiny model and a handful of steps.
#[test]
fn train_resume_render_eval_on_fern() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-train-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let run = dir.join("run");
    let run_s = run.to_str().unwrap();
    let scene = fern();
    let tiny = [
        "--levels",
        "4",
        "--log2-table",
        "12",
        "--max-res",
        "128",
        "--width",
        "16",
        "--rays",
        "64",
        "--samples",
        "8",
    ];
    let mut args = vec![
        "train",
        "--scene",
        scene.to_str().unwrap(),
        "--split",
        "extrapolation",
        "--out",
        run_s,
    ];
    args.extend([
        "--steps",
        "6",
        "--log-every",
        "3",
        "--checkpoint-every",
        "3",
    ]);
    args.extend(tiny);
    let (ok, _, err) = extranerf(&args);
    assert!(ok, "{err}");
    assert!(
        err.contains("step     6/6")
            && err.contains("samples/s")
            && err.contains("training step: fused kernel")
            && err.contains("sampler: proposal, the default")
            && err.contains("at 32 strata per ray; the 8 samples per ray drawn"),
        "{err}"
    );
    // --depth auto (the default) on fern: MVS depth of the six training views, computed once
    // into RUN/depth_mvs, with the COLMAP points where they fall.
    assert!(
        err.contains("depth auto: MVS depth (1/2 resolution, 64 planes) and COLMAP sparse points")
            && err.contains("cached in"),
        "{err}"
    );
    assert!(run.join("depth_mvs/key.json").exists());
    for f in ["config.json", "checkpoint.safetensors", "progress.jsonl"] {
        assert!(run.join(f).exists(), "{f} missing");
    }
    // Gradient scaling is refused in NDC, and a Huber loss without a positive threshold.
    for (flags, want) in [
        (&["--grad-scaling"][..], "NDC"),
        (&["--rgb-loss", "huber", "--huber-delta", "0"][..], "Huber"),
    ] {
        let bad = dir.join("bad");
        let mut a = vec![
            "train",
            "--scene",
            scene.to_str().unwrap(),
            "--split",
            "extrapolation",
        ];
        a.extend(["--out", bad.to_str().unwrap(), "--steps", "2"]);
        a.extend(tiny);
        a.extend(flags);
        let (ok, _, err) = extranerf(&a);
        assert!(!ok && err.contains(want), "{flags:?}: {err}");
        let _ = std::fs::remove_dir_all(&bad);
    }
    // A second plain train into the same folder is refused; --resume extends it.
    let (ok, _, err) = extranerf(&args);
    assert!(!ok && err.contains("--resume"), "{err}");
    let (ok, _, err) = extranerf(&["train", "--resume", "--out", run_s, "--rays", "9"]);
    assert!(!ok && err.contains("drop --rays"), "{err}");
    let (ok, _, err) = extranerf(&["train", "--resume", "--out", run_s, "--depth", "none"]);
    assert!(!ok && err.contains("drop --depth"), "{err}");
    // --step may change on resume: the standalone chain continues the fused run.
    let (ok, _, err) = extranerf(&[
        "train",
        "--resume",
        "--out",
        run_s,
        "--steps",
        "9",
        "--step",
        "standalone",
    ]);
    assert!(
        ok && err.contains("resuming")
            && err.contains("step     9/9")
            && err.contains("training step: standalone kernels")
            && err.contains("maps reused from"),
        "{err}"
    );
    let progress = std::fs::read_to_string(run.join("progress.jsonl")).unwrap();
    assert_eq!(progress.lines().count(), 3, "{progress}");
    // Render one training view: PNG + EXR of the right size.
    let (ok, _, err) = extranerf(&["render", run_s, "--views", "2", "--samples", "4"]);
    assert!(ok, "{err}");
    let png = image::open(run.join("render/train_002.png")).unwrap();
    assert_eq!((png.width(), png.height()), (504, 378));
    let scene = extranerf_nerf::data::llff::load_llff(&scene, &Default::default()).unwrap();
    // The render's depth is the field's ray-space depth (channel T), which `--depth-dir`'s
    // reader refuses by name.
    let exr_path = run.join("render/train_002.exr");
    let e = extranerf_nerf::data::depth::read_depth_exr(&exr_path, &scene.cameras[2])
        .unwrap_err()
        .to_string();
    assert!(e.contains("channel T"), "{e}");
    let img = exr::prelude::read_first_flat_layer_from_file(&exr_path).unwrap();
    let ch = &img.layer_data.channel_data.list[0];
    assert_eq!(ch.name.to_string(), "T");
    assert_eq!(
        (img.layer_data.size.width(), img.layer_data.size.height()),
        (504, 378)
    );
    let depth: Vec<f32> = match &ch.sample_data {
        exr::prelude::FlatSamples::F32(v) => v.clone(),
        o => panic!("depth samples of another type: {o:?}"),
    };
    // NDC t of the expected depth: inside (0, 1] wherever the field has density.
    assert!(depth.iter().all(|d| (0.0..=1.0).contains(d)));
    assert!(depth.iter().any(|&d| d > 0.0));
    // The standalone kernels give the same image as the fused march (default path) up to f32
    // summation order and PNG rounding.
    let alt = run.join("render_standalone");
    let (ok, _, err) = extranerf(&[
        "render",
        run_s,
        "--views",
        "2",
        "--samples",
        "4",
        "--march",
        "standalone",
        "--out",
        alt.to_str().unwrap(),
    ]);
    assert!(ok && err.contains("standalone march"), "{err}");
    let a = png.to_rgb8();
    let b = image::open(alt.join("train_002.png")).unwrap().to_rgb8();
    let worst = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&p, &q)| (p as i32 - q as i32).abs())
        .max()
        .unwrap();
    assert!(
        worst <= 1,
        "fused and standalone renders differ by {worst}/255"
    );
    // The run samples with the proposal sampler (the default), which takes no occupancy grid:
    // asking for one is refused, saying why.
    let (ok, _, err) = extranerf(&[
        "render",
        run_s,
        "--views",
        "2",
        "--samples",
        "4",
        "--occupancy-res",
        "16",
        "--out",
        alt.to_str().unwrap(),
    ]);
    assert!(
        !ok && err.contains("proposal sampler") && err.contains("occupancy"),
        "{err}"
    );
    let (ok, _, err) = extranerf(&["render", run_s, "--min-weight", "2"]);
    assert!(!ok && err.contains("--min-weight 2"), "{err}");
    let (ok, _, err) = extranerf(&["render", run_s, "--views", "99"]);
    assert!(!ok && err.contains("view 99"), "{err}");
    // Along a named path: the frames at the width asked for, the time said before they start,
    // and the path as rendered, which renders again to the same frames.
    let path_out = run.join("sweep");
    let (ok, _, err) = extranerf(&[
        "render",
        run_s,
        "--path",
        "sweep",
        "--frames",
        "3",
        "--width",
        "48",
        "--samples",
        "4",
        "--fps",
        "12",
        "--depth-video",
        "--visibility-video",
        "--out",
        path_out.to_str().unwrap(),
    ]);
    assert!(
        ok && err.contains("3 frames of 48x36")
            && err.contains("to render")
            && err.contains("path.mp4, depth.mp4, visibility.mp4"),
        "{err}"
    );
    // The video decodes to the frames, at their size and rate; the depth video beside it.
    let video = extranerf_nerf::video::read_video(&path_out.join("path.mp4")).unwrap();
    assert_eq!((video.width, video.height, video.frames.len()), (48, 36, 3));
    assert!((video.fps - 12.0).abs() < 1e-9, "{} fps", video.fps);
    let png = image::open(path_out.join("frame_0001.png"))
        .unwrap()
        .to_rgb8();
    let mean_err = png
        .as_raw()
        .iter()
        .zip(&video.frames[1])
        .map(|(&a, &b)| (a as f64 - b as f64).abs())
        .sum::<f64>()
        / png.as_raw().len() as f64;
    assert!(
        mean_err < 8.0,
        "video frame 1 is off its PNG by {mean_err}/255 on average"
    );
    let depth = extranerf_nerf::video::read_video(&path_out.join("depth.mp4")).unwrap();
    assert_eq!(depth.frames.len(), 3);
    // The visibility video: grey, and the sweep's middle frame, inside the rig, mostly seen
    // by the training cameras.
    let vis = extranerf_nerf::video::read_video(&path_out.join("visibility.mp4")).unwrap();
    assert_eq!((vis.width, vis.height, vis.frames.len()), (48, 36, 3));
    let mean = |f: &[u8]| f.iter().map(|&v| v as f64).sum::<f64>() / f.len() as f64;
    let seen = mean(&vis.frames[1]);
    eprintln!("visibility video: mean {seen:.1}/255 in the middle frame");
    assert!(
        seen > 128.0,
        "the middle frame is seen at {seen:.1}/255 on average"
    );
    let chroma = vis.frames[1]
        .chunks_exact(3)
        .map(|p| (p[0] as i32 - p[2] as i32).abs())
        .max()
        .unwrap();
    assert!(chroma <= 8, "the visibility video is not grey: {chroma}");
    let frame = |dir: &std::path::Path, k: usize| {
        image::open(dir.join(format!("frame_{k:04}.png")))
            .unwrap()
            .to_rgb8()
    };
    assert_eq!(frame(&path_out, 2).dimensions(), (48, 36));
    let again = run.join("sweep_again");
    let (ok, _, err) = extranerf(&[
        "render",
        run_s,
        "--path",
        path_out.join("camera_path.json").to_str().unwrap(),
        "--samples",
        "4",
        "--out",
        again.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    for k in 0..3 {
        assert_eq!(frame(&path_out, k), frame(&again, k), "frame {k}");
    }
    let (ok, _, err) = extranerf(&["render", run_s, "--path", "line:0,40"]);
    assert!(!ok && err.contains("views 0 to 19"), "{err}");
    // Evaluate one held-out view with AlexNet LPIPS.
    let lpips = fern().join("../../../models/lpips");
    let (ok, out, err) = extranerf(&[
        "eval",
        run_s,
        "--views",
        "0",
        "--samples",
        "4",
        "--lpips-nets",
        "alex",
        "--lpips",
        lpips.to_str().unwrap(),
        "--save-images",
    ]);
    assert!(ok, "{err}");
    assert!(out.contains("test: PSNR"), "{out}");
    let m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("metrics.json")).unwrap()).unwrap();
    // Where the rendered points lie, per view and pooled over the role's views: shares of
    // the pixels outside NDC's unit cube (the grid box before) and outside the model's box,
    // which holds every point a sample can be at (an expected depth lies in the range).
    let v0 = &m["views"][0];
    let unit = v0["outside_unit_cube"].as_f64().unwrap();
    assert_eq!(v0["outside_grid_box"].as_f64(), Some(0.0), "{v0}");
    assert!((0.0..1.0).contains(&unit), "{v0}");
    let pooled = &m["unit_cube"]["test"];
    assert!(
        (pooled["outside_fraction"].as_f64().unwrap() - unit).abs() < 1e-9,
        "{m}"
    );
    let psnr = m["test"]["psnr"].as_f64().unwrap();
    let lp = m["test"]["lpips_alex"].as_f64().unwrap();
    let ssim = m["test"]["ssim"].as_f64().unwrap();
    // The reported PSNR is that of the render it saved against the photo (up to the PNG's 8-bit
    // rounding), a 6-step field is far from the photo, and the other metrics are in range (LPIPS is not bounded by 1: 1.03 here).
    let load = |p: &std::path::Path| extranerf_nerf::data::load_image(p).unwrap().rgb;
    let saved = load(&run.join("eval/test_000.png"));
    let photo = load(&fern().join("images_8/image000.png"));
    let again = extranerf_nerf::metrics::psnr(&saved, &photo).unwrap();
    assert!(
        (psnr - again).abs() < 0.05,
        "reported {psnr} dB, saved render {again} dB"
    );
    assert!(
        psnr > 6.0 && psnr < 20.0 && lp > 0.2 && lp < 2.0 && ssim > 0.0 && ssim < 0.8,
        "{m}"
    );
    assert_eq!(m["render"]["march"], "fused", "{m}");
    assert_eq!(
        m["depth"], "MVS depth (1/2 resolution, 64 planes) and COLMAP sparse points",
        "{m}"
    );
    assert!(
        m["views"][0]["render_seconds"].as_f64().unwrap() > 0.0,
        "{m}"
    );
    // Visibility masks named as the images: view 0 is scored over its left half (white) and
    // its right half; a mask of another size is an error naming it.
    let masks = dir.join("masks");
    std::fs::create_dir_all(&masks).unwrap();
    let mask = image::GrayImage::from_fn(504, 378, |x, _| {
        image::Luma([if x < 252 { 255 } else { 0 }])
    });
    mask.save(masks.join("image000.png")).unwrap();
    let eval_masked = |out: &str| {
        extranerf(&[
            "eval",
            run_s,
            "--views",
            "0",
            "--samples",
            "4",
            "--lpips-nets",
            "alex",
            "--lpips",
            lpips.to_str().unwrap(),
            "--visibility-masks",
            masks.to_str().unwrap(),
            "--out",
            out,
        ])
    };
    let masked_json = dir.join("masked.json");
    let (ok, _, err) = eval_masked(masked_json.to_str().unwrap());
    assert!(ok, "{err}");
    let mm: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&masked_json).unwrap()).unwrap();
    let v = &mm["views"][0];
    assert_eq!(v["visible_fraction"].as_f64(), Some(0.5), "{v}");
    // The halves' mean squared errors average to the whole view's.
    let mse = |db: f64| 10f64.powf(-db / 10.0);
    let (a, b) = (
        v["psnr_visible"].as_f64().unwrap(),
        v["psnr_not_visible"].as_f64().unwrap(),
    );
    assert!(
        ((mse(a) + mse(b)) / 2.0 / mse(psnr) - 1.0).abs() < 1e-6,
        "{v}"
    );
    assert_eq!(mm["test"]["psnr_visible"].as_f64(), Some(a), "{mm}");
    image::GrayImage::new(10, 10)
        .save(masks.join("image000.png"))
        .unwrap();
    let (ok, _, err) = eval_masked(masked_json.to_str().unwrap());
    assert!(
        !ok && err.contains("image000.png") && err.contains("10x10 mask"),
        "{err}"
    );
    // Visibility of a held-out view and of virtual cameras, and the training views' masks.
    let cams = dir.join("outward.json");
    let (ok, _, err) = extranerf(&[
        "cameras",
        "--scene",
        fern().to_str().unwrap(),
        "--split",
        "extrapolation",
        "--count",
        "2",
        "--out",
        cams.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let small = [
        "--downscale",
        "16",
        "--samples",
        "4",
        "--vis-samples",
        "4",
        "--volume-res",
        "16",
        "--volume-depth",
        "8",
    ];
    let mut args = vec![
        "visibility",
        run_s,
        "--views",
        "0",
        "--cameras",
        cams.to_str().unwrap(),
        "--training-masks",
        "--complete-depth",
        "30",
    ];
    args.extend(small);
    let (ok, _, err) = extranerf(&args);
    assert!(ok && err.contains("transmittance volumes"), "{err}");
    let vis = run.join("visibility");
    for f in [
        "test_000_vis.png",
        "test_000_vis.exr",
        "test_000_mask.png",
        "virtual_001_vis.png",
        "trainmask_002_mask.png",
        "test_000_depth.exr",
        "test_000_view_depth.exr",
        "virtual_001_depth_completed.exr",
        "visibility.json",
    ] {
        assert!(vis.join(f).exists(), "{f} missing");
    }
    let png = image::open(vis.join("test_000_vis.png")).unwrap();
    assert_eq!((png.width(), png.height()), (31, 23));
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(vis.join("visibility.json")).unwrap()).unwrap();
    let views = v["views"].as_array().unwrap();
    assert_eq!(views.len(), 1 + 2 + 6, "{v}");
    for row in views.iter().filter(|r| r["kind"] != "training-mask") {
        let dc = &row["depth_completion"];
        assert!(
            dc["iterations"] == 30 && dc["mean_abs_change"].as_f64().unwrap().is_finite(),
            "{row}"
        );
    }
    for row in views {
        let mean = row["mean_visibility"].as_f64().unwrap();
        let opacity = row["mean_opacity"].as_f64().unwrap();
        assert!((0.0..=opacity + 1e-6).contains(&mean), "{row}");
    }
    // The exact march on one view; then the benchmark at a tiny size.
    let mut args = vec!["visibility", run_s, "--views", "0", "--method", "march"];
    args.extend(small);
    let (ok, _, err) = extranerf(&args);
    assert!(ok && err.contains("samples per segment"), "{err}");
    let mut args = vec!["bench", "visibility", run_s];
    args.extend(small);
    let (ok, out, err) = extranerf(&args);
    assert!(ok, "{err}");
    assert!(
        out.contains("march         6") && out.contains("volume        6"),
        "{out}"
    );
    let (ok, _, err) = extranerf(&["visibility", run_s, "--views", "0", "--rank", "9"]);
    assert!(!ok && err.contains("rank 9"), "{err}");
    let (ok, _, err) = extranerf(&["visibility", run_s]);
    assert!(!ok && err.contains("--cameras"), "{err}");
    let (ok, _, err) = extranerf(&[
        "visibility",
        run_s,
        "--cameras",
        dir.join("missing.json").to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("missing.json"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
}

/// The views `eval` scored as held out in `run/metrics.json`.
fn scored_test_views(run: &std::path::Path) -> Vec<u64> {
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    m["views"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|v| v["role"] == "test")
        .map(|v| v["view"].as_u64().unwrap())
        .collect()
}

/// A COLMAP capture (a text model in `sparse/0`, its images in `images/`) trains with one
/// command: by default every 8th view is held out and the others train; `--split all` trains on
/// every view and `eval` says there is no held-out view; a benchmark split the capture is too
/// small for says what to pass; `export` writes it again as a COLMAP capture that trains.
#[test]
fn a_colmap_capture_trains_on_its_views() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-colmap-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let cap = dir.join("capture");
    let model = extranerf_tests::colmap_model(&extranerf_tests::colmap_rig(9));
    extranerf_tests::write_colmap_capture(
        &cap,
        &model,
        extranerf_nerf::data::colmap::ModelFormat::Text,
    );
    let cap_s = cap.to_str().unwrap();
    let train = |run: &str, split: &[&str]| {
        let run = dir.join(run);
        let mut args = vec![
            "train", "--scene", cap_s, "--factor", "1", "--steps", "4", "--depth", "sparse",
            "--out",
        ];
        args.push(run.to_str().unwrap());
        args.extend(split);
        let (ok, _, err) = extranerf(&args);
        (ok, err, run)
    };
    let (ok, err, run) = train("default", &[]);
    assert!(ok, "{err}");
    let cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("config.json")).unwrap()).unwrap();
    assert_eq!(cfg["scene"]["split"], "holdout", "{cfg}");
    // (AlexNet's LPIPS needs 31 pixels a side; these views are 32x24.)
    let lpips = extranerf_tests::shared_data().join("../models/lpips");
    let eval = |run: &std::path::Path| {
        extranerf(&[
            "eval",
            run.to_str().unwrap(),
            "--lpips-nets",
            "vgg",
            "--lpips",
            lpips.to_str().unwrap(),
        ])
    };
    let (ok, out, err) = eval(&run);
    assert!(ok && out.contains("test: PSNR"), "{out}{err}");
    assert_eq!(scored_test_views(&run), [0, 8]);
    let (ok, err, run) = train("all", &["--split", "all"]);
    assert!(ok, "{err}");
    let (ok, out, err) = eval(&run);
    assert!(
        ok && out.contains("no held-out view") && out.contains("all split"),
        "{out}{err}"
    );
    let (ok, err, _) = train("benchmark", &["--split", "extrapolation"]);
    assert!(
        !ok && err.contains("needs at least 14 views, the scene has 9")
            && err.contains("--split all"),
        "{err}"
    );
    // `export` writes it again as a COLMAP capture in binary, which trains; never over a
    // folder that holds something.
    let copy = dir.join("exported");
    let export = || {
        extranerf(&[
            "export",
            "--scene",
            cap_s,
            "--factor",
            "1",
            "--format",
            "binary",
            "--out",
            copy.to_str().unwrap(),
        ])
    };
    let (ok, _, err) = export();
    assert!(
        ok && err.contains("9 views") && err.contains("--factor 1"),
        "{err}"
    );
    assert!(copy.join("sparse/0/images.bin").is_file());
    let (ok, _, err) = extranerf(&[
        "train",
        "--scene",
        copy.to_str().unwrap(),
        "--factor",
        "1",
        "--steps",
        "4",
        "--depth",
        "sparse",
        "--out",
        dir.join("from_export").to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let (ok, _, err) = export();
    assert!(!ok && err.contains("not empty"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Run folders written by commit fc82428, before each stage recorded its serde spec
/// (`tests/fixtures/old_runs`, their manifests): resumed with the commands that made them,
/// every stage is found done and skipped and the manifest is left as it was; a setting a stage
/// declares free to change on resume changes nothing; one that forces a rerun is refused,
/// naming the field as the old record holds it (the defaults the old layout left out
/// included).
#[test]
fn old_run_folders_resume() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-old-runs-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let fixtures =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/old_runs");
    // The manifests name the scene `demo/scene`, relative to where they were made.
    let run = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_extranerf"))
            .current_dir(&dir)
            .args(args)
            .output()
            .unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (ok, err) = run(&[
        "demo",
        "--out",
        "demo",
        "--width",
        "32",
        "--stop-after",
        "scene",
    ]);
    assert!(ok, "{err}");
    let common = [
        "extrapolate",
        "--scene",
        "demo/scene",
        "--split",
        "extrapolation",
        "--factor",
        "1",
        "--base-budget",
        "8",
        "--virtual",
        "2",
        "--virtual-downscale",
        "1",
        "--rounds",
        "1",
        "--steps-per-round",
        "10",
        "--flythrough",
        "2",
        "--stage3-rounds",
        "1",
        "--stage3-steps-per-round",
        "5",
        "--resume",
    ];
    let diffusion = [
        "--data-rounds",
        "1",
        "--data-steps-per-round",
        "5",
        "--fresh-checkpoints",
        "5",
        "--enhancer-channels",
        "8,16",
        "--enhancer-steps",
        "4",
        "--enhancer-batch",
        "2",
        "--enhancer-crop",
        "16",
        "--stage3-ddim-steps",
        "2",
    ];
    let unsharp = [
        "--stage3-enhancer",
        "unsharp",
        "--stage3-anchor",
        "2",
        "--threshold",
        "0.4",
        "--inpainter",
        "exemplar",
    ];
    type Case<'a> = (
        &'a str,
        &'a [&'a str],
        &'a [&'a str],
        &'a [&'a str],
        &'a [&'a str],
        &'a str,
    );
    let cases: [Case; 2] = [
        (
            "fc82428_diffusion",
            &diffusion,
            &["--stage3-gate", "off"],
            // Where the enhancer trains may change.
            &["--diffusion-backend", "cpu"],
            // Checking the enhancer: the old record left the gate out when it was off.
            &["--stage3-gate", "check"],
            "stage3-harmonic.enhance.diffusion.gate: \"off\" -> \"check\"",
        ),
        (
            "fc82428_unsharp",
            &unsharp,
            &[],
            // (No stage of this run has a model: nothing records it.)
            &["--diffusion-backend", "cpu"],
            &["--stage3-unsharp-amount", "0.7"],
            "stage3-exemplar.enhance.unsharp.amount: 0.5 -> 0.699999988079071",
        ),
    ];
    for (name, flags, keep, free, rerun, says) in cases {
        let out = dir.join(name);
        std::fs::create_dir_all(&out).unwrap();
        let manifest = out.join("extrapolate.json");
        std::fs::copy(fixtures.join(name).join("extrapolate.json"), &manifest).unwrap();
        let before = std::fs::read(&manifest).unwrap();
        let stages: Vec<String> = serde_json::from_slice::<serde_json::Value>(&before).unwrap()
            ["stages"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["name"].as_str().unwrap().to_string())
            .collect();
        assert!(stages.len() >= 7, "{name}: {stages:?}");
        // Those builds wrote each field's fly-through frames (beside a GIF, gone since): the
        // video stage that came after them reads those frames, made here as they were left.
        let old: serde_json::Value = serde_json::from_slice(&before).unwrap();
        let mut fields = Vec::new();
        for s in old["stages"].as_array().unwrap() {
            let Some(field) = s["name"].as_str().unwrap().strip_prefix("flythrough-") else {
                continue;
            };
            let r = &s["report"];
            let (w, h) = (r["width"].as_u64().unwrap(), r["height"].as_u64().unwrap());
            let folder = out.join("flythrough").join(field);
            std::fs::create_dir_all(&folder).unwrap();
            for k in 0..r["frames"].as_u64().unwrap() {
                image::RgbImage::from_pixel(w as u32, h as u32, image::Rgb([40, 90, 160]))
                    .save(folder.join(format!("frame_{k:03}.png")))
                    .unwrap();
            }
            fields.push(field.to_string());
        }
        assert_eq!(fields.len(), 3, "{name}: {stages:?}");
        let mut after: Option<Vec<u8>> = None;
        for extra in [&[][..], free] {
            let args: Vec<&str> = common
                .iter()
                .chain(flags)
                .chain(keep)
                .chain(extra)
                .copied()
                .chain(["--out", name])
                .collect();
            let (ok, err) = run(&args);
            assert!(ok, "{name} {extra:?}: {err}");
            for s in &stages {
                assert!(
                    err.contains(&format!("stage {s}: done, skipped")),
                    "{name} {extra:?}: {s} not skipped:\n{err}"
                );
            }
            // The first resume adds the video of the old frames, and leaves the old records
            // as they were; the second runs nothing.
            let now = std::fs::read(&manifest).unwrap();
            match &after {
                None => {
                    let m: serde_json::Value = serde_json::from_slice(&now).unwrap();
                    let recs = m["stages"].as_array().unwrap();
                    assert_eq!(
                        &recs[..stages.len()],
                        &old["stages"].as_array().unwrap()[..]
                    );
                    let video = &recs[stages.len()];
                    assert_eq!(video["name"], "flythrough-video", "{name}");
                    assert_eq!(video["report"]["frames"], 2, "{name}");
                    let v = extranerf_nerf::video::read_video(
                        &out.join("flythrough").join("flythrough.mp4"),
                    )
                    .unwrap();
                    assert_eq!((v.frames.len(), v.width), (2, 3 * 16 + 2 * 2), "{name}");
                    after = Some(now);
                }
                Some(a) => {
                    assert!(
                        err.contains("stage flythrough-video: done, skipped"),
                        "{err}"
                    );
                    assert_eq!(&now, a, "{name}");
                }
            }
        }
        let args: Vec<&str> = common
            .iter()
            .chain(flags)
            .chain(rerun)
            .copied()
            .chain(["--out", name])
            .collect();
        let (ok, err) = run(&args);
        assert!(!ok && err.contains(says), "{name} {rerun:?}: {err}");
        assert!(err.contains("--redo"), "{err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The demo end to end at a small size through the command line: ExtraNeRF's stages, the
/// table (stage 2's PSNR over the exactly known not-visible pixels recomputed here from the
/// saved renders), the report and the picture; a second run replaces the first; a foreign
/// folder is refused; `--stop-after scene` writes only the scene.
#[test]
fn demo_runs_extranerf_and_replaces_its_own_output() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-demo-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = dir.join("demo");
    let args = [
        "demo",
        "--out",
        out.to_str().unwrap(),
        "--width",
        "48",
        "--steps",
        "30",
        "--rounds",
        "1",
        "--steps-per-round",
        "10",
        "--stage3-rounds",
        "1",
        "--stage3-steps-per-round",
        "10",
        "--flythrough",
        "2",
    ];
    let (ok, out_text, err) = extranerf(&args);
    assert!(ok, "{err}");
    assert!(out_text.contains("PSNR not visible (exact)"), "{out_text}");
    assert!(err.contains("basenerf    30/30"), "{err}");
    let run = out.join("extranerf");
    assert!(
        err.contains(&format!("Open {}", run.join("report.html").display())),
        "{err}"
    );
    let t: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("eval.json")).unwrap()).unwrap();
    let names: Vec<&str> = t["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["variant"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["base", "stage2-harmonic", "stage3-harmonic"], "{t}");
    assert_eq!(
        t["truth_masks"]["views"],
        serde_json::json!([6, 7, 8, 9, 10, 11, 12, 13])
    );
    // Stage 2's figure over the truly unseen pixels: a number, and the one the saved renders
    // give against the photos over the scene's exact masks (up to the PNGs' 8-bit rounding).
    let reported = t["rows"][1]["psnr_not_visible_exact"].as_f64().unwrap();
    let load = |p: &std::path::Path| extranerf_nerf::data::load_image(p).unwrap().rgb;
    let mut psnrs = Vec::new();
    for k in 6..14 {
        let render = load(&run.join(format!("stage2-harmonic/test_{k:03}.png")));
        let truth = load(&out.join(format!("scene/images/view_{k:02}.png")));
        let seen = load(&out.join(format!("scene/gt_visibility/view_{k:02}.png")));
        let (mut se, mut n) = (0.0f64, 0usize);
        for p in 0..seen.len() / 3 {
            if seen[3 * p] < 0.5 {
                for c in 0..3 {
                    se += (render[3 * p + c] as f64 - truth[3 * p + c] as f64).powi(2);
                }
                n += 3;
            }
        }
        if n > 0 {
            psnrs.push(-10.0 * (se / n as f64).log10());
        }
    }
    assert!(
        !psnrs.is_empty(),
        "no view outside the rig has unseen pixels"
    );
    let again = psnrs.iter().sum::<f64>() / psnrs.len() as f64;
    assert!(
        reported.is_finite() && (reported - again).abs() < 0.05,
        "reported {reported} dB, saved renders {again} dB"
    );
    let report = std::fs::read_to_string(run.join("report.html")).unwrap();
    for k in 6..14 {
        assert!(report.contains(&format!("<h3>view {k}</h3>")), "view {k}");
    }
    assert!(report.contains("BaseNeRF") && report.contains("stage3-harmonic"));
    assert!(report.contains("PSNR not visible (exact)"));
    // The picture: 8 views, two to a row, each as photo, BaseNeRF and final field.
    let pic = image::open(run.join("outside_views.png")).unwrap();
    assert_eq!(
        (pic.width(), pic.height()),
        (6 * 48 + 5 * 4, 4 * 36 + 3 * 4)
    );
    let (ok, _, err) = extranerf(&args);
    assert!(ok, "second demo into its own folder: {err}");
    let foreign = dir.join("foreign");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("precious.txt"), b"x").unwrap();
    let (ok, _, err) = extranerf(&["demo", "--out", foreign.to_str().unwrap()]);
    assert!(!ok && err.contains("not made by"), "{err}");
    assert!(foreign.join("precious.txt").exists());
    // Only the scene: the folder the demo made before now holds nothing else.
    let (ok, _, err) = extranerf(&[
        "demo",
        "--out",
        out.to_str().unwrap(),
        "--width",
        "48",
        "--stop-after",
        "scene",
    ]);
    assert!(ok, "{err}");
    assert!(out.join("scene/poses_bounds.npy").exists());
    assert_eq!(
        std::fs::read_dir(out.join("scene/gt_visibility"))
            .unwrap()
            .count(),
        8
    );
    assert!(!out.join("basenerf").exists() && !run.exists());
    let _ = std::fs::remove_dir_all(dir);
}

/// `extranerf cameras` writes a transforms.json the loader reads back; bad flags are errors.
#[test]
fn cameras_writes_transforms_json() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-cameras-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("virtual.json");
    let fern = fern();
    let (ok, _, err) = extranerf(&[
        "cameras",
        "--scene",
        fern.to_str().unwrap(),
        "--split",
        "extrapolation",
        "--trajectory",
        "spiral",
        "--count",
        "5",
        "--range",
        "2",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok && err.contains("5 Spiral cameras"), "{err}");
    let scene = extranerf_nerf::data::transforms::load_transforms(&out).unwrap();
    assert_eq!(scene.cameras.len(), 5);
    assert_eq!(scene.cameras[0].width, 504);
    let (ok, _, err) = extranerf(&[
        "cameras",
        "--scene",
        fern.to_str().unwrap(),
        "--split",
        "extrapolation",
        "--trajectory",
        "zoom",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        !ok && err.contains("use outward, spiral or rotate"),
        "{err}"
    );
    let (ok, _, err) = extranerf(&[
        "cameras",
        "--scene",
        fern.to_str().unwrap(),
        "--split",
        "extrapolation",
        "--range=-1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("range -1"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
}

/// The NeRF-synthetic protocol end to end on the generated turntable scene: `turntable`
/// writes the split files, `train` defaults to the given split, keeps random backgrounds for
/// the RGBA images and renders over white, prints its device memory, and `eval` scores the
/// test split's views over white, saying the split, resolution and background.
#[test]
fn nerf_synthetic_protocol_runs_through_eval() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-turntable-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (scene, run) = (dir.join("scene"), dir.join("run"));
    let (s, r) = (scene.to_str().unwrap(), run.to_str().unwrap());
    let (ok, _, err) = extranerf(&[
        "turntable",
        "--out",
        s,
        "--size",
        "32",
        "--train",
        "8",
        "--test",
        "2",
    ]);
    assert!(ok, "{err}");
    assert!(scene.join("transforms_test.json").exists() && scene.join("test/r_1.png").exists());
    // A second time into the same folder is refused.
    let (ok, _, err) = extranerf(&["turntable", "--out", s]);
    assert!(!ok && err.contains("not empty"), "{err}");
    let (ok, _, err) = extranerf(&["train", "--scene", s, "--out", r, "--steps", "30"]);
    assert!(ok, "{err}");
    assert!(
        err.contains("has alpha") && err.contains("over white"),
        "the background choice is said: {err}"
    );
    assert!(
        err.contains("device memory: 8192 training pixels of 8 views"),
        "memory at start: {err}"
    );
    let cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("config.json")).unwrap()).unwrap();
    assert_eq!(cfg["scene"]["split"], "given");
    assert_eq!(
        cfg["train"]["background"],
        serde_json::json!([1.0, 1.0, 1.0])
    );
    assert_eq!(cfg["train"]["random_background"], true);
    let lpips = fern().join("../../../models/lpips");
    let (ok, out, err) = extranerf(&[
        "eval",
        r,
        "--lpips-nets",
        "alex",
        "--lpips",
        lpips.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(
        out.contains("test: PSNR")
            && out.contains("given split, 32x32, background [1.0, 1.0, 1.0]"),
        "{out}"
    );
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(m["split"], "given");
    assert_eq!(m["resolution"], "32x32");
    assert_eq!(
        scored_test_views(&run),
        vec![8, 9],
        "the test file's views are scored"
    );
    assert!(m["test"]["psnr"].as_f64().unwrap().is_finite());
    assert!(m["test"]["lpips_alex"].as_f64().unwrap().is_finite());
    let _ = std::fs::remove_dir_all(dir);
}

/// `extranerf mvs` on fern at a small size: depth maps `train --depth-dir` accepts, and the
/// agreement with the sparse points in mvs.json.
#[test]
fn mvs_writes_depth_maps_training_reads() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-mvs-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = dir.join("mvs");
    let scene = fern();
    // `mvs` at a coarse setting into `out`, measured against `truth` when given.
    let mvs = |out: &std::path::Path, truth: Option<&std::path::Path>| {
        let mut args = vec![
            "mvs",
            "--scene",
            scene.to_str().unwrap(),
            "--split",
            "extrapolation",
            "--downscale",
            "8",
            "--planes",
            "16",
            "--radius",
            "1",
            "--out",
            out.to_str().unwrap(),
        ];
        if let Some(t) = truth {
            args.extend(["--truth-depth", t.to_str().unwrap()]);
        }
        extranerf(&args)
    };
    let (ok, _, err) = mvs(&out, None);
    assert!(ok && err.contains("sparse points"), "{err}");
    for f in [
        "image002.exr",
        "image002_depth.png",
        "image017_conf.png",
        "mvs.json",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("mvs.json")).unwrap()).unwrap();
    assert_eq!(m["views"].as_array().unwrap().len(), 6, "{m}");
    let ag = &m["sparse_agreement"];
    assert!(
        ag["sparse_points"].as_u64().unwrap() > 40000 && ag["with_depth"].as_u64().unwrap() > 100,
        "{ag}"
    );
    let med = ag["median_rel_error"].as_f64().unwrap();
    assert!(med.is_finite() && med > 0.0 && med < 0.5, "{ag}");
    // Its own maps as the exact depth: every pixel with a depth kept, without error.
    let (ok, _, err) = mvs(&dir.join("again"), Some(&out));
    assert!(ok && err.contains("against the exact depth"), "{err}");
    let again: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("again/mvs.json")).unwrap()).unwrap();
    let t = &again["truth_agreement"];
    assert!(
        t["truth_pixels"].as_u64().unwrap() > 0
            && t["coverage"].as_f64() == Some(1.0)
            && t["median_rel_error"].as_f64() == Some(0.0),
        "{t}"
    );
    // A folder without the maps: an error naming the folder and the view.
    let none = dir.join("no-depth");
    std::fs::create_dir_all(&none).unwrap();
    let (ok, _, err) = mvs(&dir.join("again2"), Some(&none));
    assert!(
        !ok && err.contains("no exact depth for view") && err.contains("no-depth"),
        "{err}"
    );
    // The maps are dense depth supervision for training.
    let tiny = [
        "--steps",
        "2",
        "--levels",
        "2",
        "--log2-table",
        "10",
        "--width",
        "16",
        "--rays",
        "32",
        "--samples",
        "4",
    ];
    let run = dir.join("run");
    let mut args = vec![
        "train",
        "--scene",
        scene.to_str().unwrap(),
        "--split",
        "extrapolation",
    ];
    args.extend([
        "--out",
        run.to_str().unwrap(),
        "--depth-dir",
        out.to_str().unwrap(),
    ]);
    args.extend(tiny);
    let (ok, _, err) = extranerf(&args);
    assert!(
        ok && err.contains("step     2/2") && err.contains("depth: dense maps from"),
        "{err}"
    );
    // The other --depth choices: none trains with no target, sparse with the COLMAP points
    // only; the run folder records the choice. A folder that is not there, or --depth with
    // --depth-dir, is refused before any work.
    for (depth, says, sparse) in [
        ("none", "depth: none", false),
        ("sparse", "depth: COLMAP sparse points", true),
    ] {
        let run = dir.join(format!("run-{depth}"));
        let mut args = vec![
            "train",
            "--scene",
            scene.to_str().unwrap(),
            "--split",
            "extrapolation",
        ];
        args.extend(["--out", run.to_str().unwrap(), "--depth", depth]);
        args.extend(tiny);
        let (ok, _, err) = extranerf(&args);
        assert!(
            ok && err.contains(says) && err.contains("step     2/2"),
            "{err}"
        );
        assert_eq!(err.contains(" 0 depth targets"), !sparse, "{depth}: {err}");
        let cfg: serde_json::Value =
            serde_json::from_slice(&std::fs::read(run.join("config.json")).unwrap()).unwrap();
        let sc = &cfg["scene"];
        assert!(
            sc["sparse_depth"] == sparse
                && sc["depth_dir"].is_null()
                && sc.get("mvs_depth").is_none(),
            "{cfg}"
        );
        assert!(!run.join("depth_mvs").exists());
    }
    for (flags, says) in [
        (vec!["--depth", "/no/such/depth"], "/no/such/depth"),
        (
            vec!["--depth", "none", "--mvs-fill", "10"],
            "--mvs-fill applies to MVS depth",
        ),
        (
            vec!["--depth", "mvs", "--depth-dir", out.to_str().unwrap()],
            "cannot be used with",
        ),
    ] {
        let run = dir.join("run-bad");
        let mut args = vec![
            "train",
            "--scene",
            scene.to_str().unwrap(),
            "--split",
            "extrapolation",
        ];
        args.extend(["--out", run.to_str().unwrap()]);
        args.extend(flags.iter().copied());
        args.extend(tiny);
        let (ok, _, err) = extranerf(&args);
        assert!(!ok && err.contains(says), "{flags:?}: {err}");
        assert!(!run.join("checkpoint.safetensors").exists());
    }
    let (ok, _, err) = extranerf(&[
        "mvs",
        "--scene",
        scene.to_str().unwrap(),
        "--split",
        "extrapolation",
        "--radius",
        "4",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("radius"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
}

/// `train --auto` prints its choices; `--budget` fits the steps to a measured probe; `bench
/// tradeoff` writes its CSV, JSON and plot.
#[test]
fn auto_config_budget_and_tradeoff_on_fern() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-auto-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let scene = fern();
    let scene_s = scene.to_str().unwrap();
    let run = dir.join("auto");
    let (ok, _, err) = extranerf(&[
        "train",
        "--scene",
        scene_s,
        "--split",
        "extrapolation",
        "--auto",
        "--steps",
        "2",
        "--rays",
        "32",
        "--samples",
        "4",
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(
        err.contains("auto-config:")
            && err.contains("finest resolution 687")
            && err.contains("512 over NDC's unit cube")
            && err.contains("grid box: centre")
            && err.contains("samples: NDC t 0.085 to 0.852")
            && err.contains("space: NDC"),
        "{err}"
    );
    let cfg: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("config.json")).unwrap()).unwrap();
    // Fern's box has half side 1.341: 512 cells across the unit cube become 687.
    assert_eq!(cfg["model"]["max_res"], 687, "{cfg}");
    let radius = cfg["model"]["radius"].as_f64().unwrap();
    assert!((radius - 1.341).abs() < 1e-3, "{cfg}");
    let run = dir.join("budget");
    let (ok, _, err) = extranerf(&[
        "train",
        "--scene",
        scene_s,
        "--split",
        "extrapolation",
        "--budget",
        "2",
        "--rays",
        "32",
        "--samples",
        "4",
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(ok && err.contains("budget 2 s: measured"), "{err}");
    let cfg: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("config.json")).unwrap()).unwrap();
    let steps = cfg["train"]["steps"].as_u64().unwrap();
    assert!((1..=5000).contains(&steps), "{cfg}");
    let (ok, _, err) = extranerf(&[
        "train",
        "--scene",
        scene_s,
        "--split",
        "extrapolation",
        "--budget=-1",
        "--out",
        dir.join("bad").to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("--budget"), "{err}");
    let out = dir.join("tradeoff");
    let (ok, stdout, err) = extranerf(&[
        "bench",
        "tradeoff",
        "--scene",
        scene_s,
        "--steps",
        "4",
        "--rays",
        "32",
        "--samples",
        "4",
        "--eval-downscale",
        "16",
        "--points",
        "base,auto",
        "--lpips",
        fern().join("../../../models/lpips").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(
        stdout.contains("frontier") && stdout.contains("auto-config"),
        "{stdout}"
    );
    let csv = std::fs::read_to_string(out.join("tradeoff.csv")).unwrap();
    assert_eq!(csv.lines().count(), 3, "{csv}");
    let svg = std::fs::read_to_string(out.join("tradeoff.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("auto"), "{svg}");
    let (ok, _, err) = extranerf(&[
        "bench",
        "tradeoff",
        "--scene",
        scene_s,
        "--points",
        "nope",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("nope"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// A 32x24 mask (another size than the demo's views).
fn small_mask_for_enhance(dir: &std::path::Path) -> std::path::PathBuf {
    let p = dir.join("small_enhance_mask.png");
    write_mask_png(&p, 32, 24, (0, 0, 4, 4));
    p
}

fn write_mask_png(path: &std::path::Path, w: u32, h: u32, hole: (u32, u32, u32, u32)) {
    let (x0, y0, hw, hh) = hole;
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        let on = x >= x0 && x < x0 + hw && y >= y0 && y < y0 + hh;
        image::Rgb(if on { [255, 255, 255] } else { [0, 0, 0] })
    });
    img.save(path).unwrap();
}

/// The diffusion commands end to end on the demo scene at a tiny size: a scene prior trained
/// and scored against the fills, inpainting with it, LoRA fine-tuning with a pseudo mask and
/// inpainting with the adapters, a latent model from `init`, the bench, and clear errors.
#[test]
fn diffusion_prior_inpaint_finetune_init_and_bench() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-diffusion-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let scene = dir.join("scene");
    extranerf_nerf::demo::write_demo_scene(&scene, 64, 48).unwrap();
    let lpips = extranerf_tests::shared_data().join("../models/lpips");
    let prior = dir.join("prior");
    let s = |p: &std::path::Path| p.to_str().unwrap().to_string();
    // The benchmark split these tests were written for (the demo scene's 6-camera rig).
    let common = [
        "--split",
        "extrapolation",
        "--factor",
        "1",
        "--downscale",
        "1",
        "--diffusion-backend",
        "cpu",
    ];
    let mut args: Vec<String> = [
        "diffusion",
        "prior",
        "--scene",
        &s(&scene),
        "--out",
        &s(&prior),
        "--steps",
        "6",
        "--batch",
        "2",
        "--crop",
        "32",
        "--channels",
        "16,32",
        "--holes",
        "1",
        "--hole-size",
        "8",
        "--eval-steps",
        "2",
        "--lpips",
        &s(&lpips),
    ]
    .iter()
    .map(|v| v.to_string())
    .collect();
    args.extend(common.iter().map(|v| v.to_string()));
    let argv: Vec<&str> = args.iter().map(String::as_str).collect();
    let (ok, out, err) = extranerf(&argv);
    assert!(ok, "{err}");
    assert!(err.contains("trained here from scratch"), "{err}");
    assert!(err.contains("prior step     6/6"), "{err}");
    for m in [
        "mean colour",
        "harmonic fill",
        "edge-aware fill",
        "scene prior (from noise)",
        "scene prior (refining harmonic)",
    ] {
        assert!(out.contains(m), "{m} missing:\n{out}");
    }
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(prior.join("prior_eval.json")).unwrap()).unwrap();
    assert_eq!(report["holes_per_view"], 1, "{report}");
    for set in [
        "training views, held-out regions",
        "test views (never trained on)",
    ] {
        for m in [
            "mean colour",
            "scene prior (from noise)",
            "scene prior (refining harmonic)",
        ] {
            let r = &report["mean"][set][m];
            assert!(r["psnr_in_mask"].as_f64().unwrap().is_finite(), "{set} {m}");
            assert!(r["lpips_hole_crop"].as_f64().unwrap() >= 0.0, "{set} {m}");
        }
    }
    assert_eq!(
        report["mean"]["test views (never trained on)"]["mean colour"]["regions"],
        8
    );
    let curve = std::fs::read_to_string(prior.join("loss.csv")).unwrap();
    assert!(curve.starts_with("step,loss\n6,"), "{curve}");
    assert!(prior.join("loss.svg").is_file());
    assert!(prior
        .join("model/unet/diffusion_pytorch_model.safetensors")
        .is_file());
    assert_eq!(std::fs::read_dir(prior.join("eval")).unwrap().count(), 14);
    assert!(prior.join("model/prior_holes.json").is_file());
    // Training again into the same --out is refused: the model is kept.
    let (ok, _, err) = extranerf(&argv);
    assert!(!ok && err.contains("already holds a prior"), "{err}");
    // Scoring the saved prior again without training gives the same figures.
    // Scores the prior `model` into `out` without training.
    let score = |model: &std::path::Path, out: &std::path::Path| {
        extranerf(&[
            "diffusion",
            "prior",
            "--scene",
            &s(&scene),
            "--out",
            &s(out),
            "--model",
            &s(model),
            "--holes",
            "1",
            "--hole-size",
            "8",
            "--eval-steps",
            "2",
            "--lpips",
            &s(&lpips),
            "--split",
            "extrapolation",
            "--factor",
            "1",
            "--downscale",
            "1",
            "--diffusion-backend",
            "cpu",
        ])
    };
    let again = dir.join("again");
    let (ok, _, err) = score(&prior.join("model"), &again);
    assert!(ok, "{err}");
    let r2: serde_json::Value =
        serde_json::from_slice(&std::fs::read(again.join("prior_eval.json")).unwrap()).unwrap();
    assert_eq!(r2["mean"], report["mean"]);
    // A prior whose held-out regions name a view this split lacks, or lie outside it, is
    // refused naming its prior_holes.json (it was an index panic).
    let foreign = dir.join("foreign");
    copy_dir(&prior.join("model"), &foreign);
    let holes_path = foreign.join("prior_holes.json");
    let holes: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&holes_path).unwrap()).unwrap();
    for (field, value, want) in [("view", 99, "99"), ("x", 1000, "does not lie inside")] {
        let mut h = holes.clone();
        h[0][field] = value.into();
        std::fs::write(&holes_path, serde_json::to_vec(&h).unwrap()).unwrap();
        let (ok, _, err) = score(&foreign, &dir.join("foreign-eval"));
        assert!(
            !ok && err.contains("prior_holes.json")
                && err.contains(want)
                && !err.contains("panicked"),
            "{field}: {err}"
        );
    }

    // Inpainting with the prior keeps the known pixels.
    let view = scene.join("images/view_00.png");
    let mask = dir.join("mask.png");
    write_mask_png(&mask, 64, 48, (20, 12, 16, 12));
    let result = dir.join("inpainted.png");
    let (ok, out, err) = extranerf(&[
        "diffusion",
        "inpaint",
        "--model",
        &s(&prior.join("model")),
        "--image",
        &s(&view),
        "--mask",
        &s(&mask),
        "--out",
        &s(&result),
        "--steps",
        "2",
        "--diffusion-backend",
        "cpu",
    ]);
    assert!(ok, "{err}");
    assert!(out.contains("DDIM steps"), "{out}");
    let a = image::open(&view).unwrap().to_rgb8();
    let b = image::open(&result).unwrap().to_rgb8();
    assert_eq!(b.dimensions(), (64, 48));
    for (x, y, p) in a.enumerate_pixels() {
        let inside = (20..36).contains(&x) && (12..24).contains(&y);
        if !inside {
            let q = b.get_pixel(x, y);
            for c in 0..3 {
                assert!((p[c] as i32 - q[c] as i32).abs() <= 1, "({x}, {y}) changed");
            }
        }
    }

    // LoRA fine-tuning with a pseudo-disocclusion mask named as `visibility` writes them.
    let masks = dir.join("masks");
    std::fs::create_dir_all(&masks).unwrap();
    write_mask_png(&masks.join("trainmask_000_mask.png"), 32, 24, (4, 4, 8, 8));
    let tuned = dir.join("lora");
    let mut args: Vec<String> = [
        "diffusion",
        "finetune",
        "--model",
        &s(&prior.join("model")),
        "--scene",
        &s(&scene),
        "--masks",
        &s(&masks),
        "--out",
        &s(&tuned),
        "--steps",
        "3",
        "--batch",
        "2",
        "--crop",
        "32",
        "--rank",
        "2",
        "--convs",
    ]
    .iter()
    .map(|v| v.to_string())
    .collect();
    args.extend(common.iter().map(|v| v.to_string()));
    let argv: Vec<&str> = args.iter().map(String::as_str).collect();
    let (ok, _, err) = extranerf(&argv);
    assert!(ok, "{err}");
    assert!(err.contains("1 with pseudo-disocclusion masks"), "{err}");
    assert!(err.contains("finetune step     3/3"), "{err}");
    assert!(err.contains("32x24 resampled to the view's 64x48"), "{err}");
    // Existing output is never replaced, and a mask of another shape is refused.
    let (ok, _, err) = extranerf(&argv);
    assert!(!ok && err.contains("already holds LoRA adapters"), "{err}");
    let odd = dir.join("masks-odd");
    std::fs::create_dir_all(&odd).unwrap();
    write_mask_png(&odd.join("trainmask_000_mask.png"), 32, 32, (4, 4, 8, 8));
    let mut odd_args = args.clone();
    let at = odd_args.iter().position(|a| a == "--masks").unwrap();
    odd_args[at + 1] = s(&odd);
    let at = odd_args.iter().position(|a| a == "--out").unwrap();
    odd_args[at + 1] = s(&dir.join("lora-odd"));
    let argv_odd: Vec<&str> = odd_args.iter().map(String::as_str).collect();
    let (ok, _, err) = extranerf(&argv_odd);
    assert!(
        !ok && err.contains("trainmask_000_mask.png")
            && err.contains("32x32")
            && err.contains("aspect"),
        "{err}"
    );
    for f in [
        "pytorch_lora_weights.safetensors",
        "adapter_config.json",
        "loss.csv",
        "loss.svg",
    ] {
        assert!(tuned.join(f).is_file(), "{f}");
    }
    let (ok, _, err) = extranerf(&[
        "diffusion",
        "inpaint",
        "--model",
        &s(&prior.join("model")),
        "--lora",
        &s(&tuned),
        "--image",
        &s(&view),
        "--mask",
        &s(&mask),
        "--out",
        &s(&dir.join("tuned.png")),
        "--steps",
        "2",
        "--diffusion-backend",
        "cpu",
    ]);
    assert!(ok, "{err}");
    assert!(err.contains("LoRA adapters from"), "{err}");
    assert!(err.contains("conditioning tokens from"), "{err}");
    // The adapters and tokens change the result (same seed, same noise).
    let base = image::open(&result).unwrap().to_rgb8();
    let tuned_img = image::open(dir.join("tuned.png")).unwrap().to_rgb8();
    assert_ne!(base.as_raw(), tuned_img.as_raw(), "LoRA had no effect");

    // A latent (VAE) model from init, with guidance.
    let tiny = dir.join("tiny");
    let (ok, out, err) = extranerf(&["diffusion", "init", "--config", "tiny", "--out", &s(&tiny)]);
    assert!(ok && out.contains("randomly initialised"), "{err}");
    let (ok, _, err) = extranerf(&["diffusion", "init", "--config", "tiny", "--out", &s(&tiny)]);
    assert!(!ok && err.contains("already holds a model"), "{err}");
    let (ok, _, err) = extranerf(&[
        "diffusion",
        "inpaint",
        "--model",
        &s(&tiny),
        "--image",
        &s(&view),
        "--mask",
        &s(&mask),
        "--out",
        &s(&dir.join("tiny.png")),
        "--steps",
        "2",
        "--strength",
        "0.6",
        "--guidance",
        "2.5",
        "--diffusion-backend",
        "cpu",
    ]);
    assert!(ok, "{err}");

    // Enhancement: an inpainting model is refused; an enhancer (two steps on the view paired
    // with itself) enhances the whole view, mask or not.
    let enhanced = dir.join("enhanced.png");
    let enhance = |model: &std::path::Path, extra: &[&str]| {
        let mut args = vec![
            "diffusion".to_string(),
            "enhance".into(),
            "--model".into(),
            s(model),
            "--image".into(),
            s(&view),
            "--out".into(),
            s(&enhanced),
            "--steps".into(),
            "2".into(),
            "--diffusion-backend".into(),
            "cpu".into(),
        ];
        args.extend(extra.iter().map(|a| a.to_string()));
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        extranerf(&args)
    };
    let (ok, _, err) = enhance(&tiny, &[]);
    assert!(!ok && err.contains("not an enhancer"), "{err}");
    let photo = image::open(&view).unwrap().to_rgb8();
    let (w, h) = photo.dimensions();
    let rgb: Vec<f32> = photo.as_raw().iter().map(|&v| v as f32 / 255.0).collect();
    let mut pair = extranerf_diffusion::train::TrainImage::new(w as usize, h as usize, rgb.clone());
    pair.guides = vec![extranerf_diffusion::train::Guide {
        rgb,
        mask: vec![0.0; (w * h) as usize],
    }];
    let enhancer_dir = dir.join("enhancer");
    extranerf_diffusion::enhancer::train_enhancer(
        &[pair],
        &extranerf_diffusion::enhancer::EnhancerSpec {
            channels: vec![8, 16],
            steps: 2,
            batch: 1,
            crop: 16,
            ..Default::default()
        },
        &enhancer_dir,
        &burn::tensor::Device::flex(),
        &mut |_| {},
    )
    .unwrap();
    let (ok, out, err) = enhance(&enhancer_dir, &["--mask", &s(&mask)]);
    assert!(ok && out.contains("mean absolute change"), "{err}");
    assert_eq!(
        image::open(&enhanced).unwrap().to_rgb8().dimensions(),
        (w, h)
    );
    let (ok, _, err) = enhance(&enhancer_dir, &["--strength", "0"]);
    assert!(!ok && err.contains("--strength 0"), "{err}");
    let (ok, _, err) = enhance(
        &enhancer_dir,
        &["--mask", &s(&small_mask_for_enhance(&dir))],
    );
    assert!(!ok && err.contains("is 32x24"), "{err}");

    // Clear errors.
    let (ok, _, err) = extranerf(&[
        "diffusion",
        "inpaint",
        "--model",
        &s(&dir.join("none")),
        "--image",
        &s(&view),
        "--mask",
        &s(&mask),
        "--out",
        &s(&result),
    ]);
    assert!(!ok && err.contains("model_index.json"), "{err}");
    let small = dir.join("small.png");
    write_mask_png(&small, 32, 24, (0, 0, 4, 4));
    let (ok, _, err) = extranerf(&[
        "diffusion",
        "inpaint",
        "--model",
        &s(&prior.join("model")),
        "--image",
        &s(&view),
        "--mask",
        &s(&small),
        "--out",
        &s(&result),
        "--diffusion-backend",
        "cpu",
    ]);
    assert!(
        !ok && err.contains("small.png") && err.contains("32x24"),
        "{err}"
    );
    let (ok, _, err) = extranerf(&[
        "diffusion",
        "prior",
        "--scene",
        &s(&scene),
        "--out",
        &s(&dir.join("p2")),
        "--crop",
        "33",
        "--channels",
        "16,32",
        "--factor",
        "1",
        "--downscale",
        "1",
        "--diffusion-backend",
        "cpu",
        "--lpips",
        &s(&lpips),
    ]);
    assert!(!ok && err.contains("--crop 33"), "{err}");
    let (ok, _, err) = extranerf(&[
        "diffusion",
        "prior",
        "--scene",
        &s(&scene),
        "--out",
        &s(&dir.join("p3")),
        "--holes",
        "0",
    ]);
    assert!(!ok && err.contains("--holes"), "{err}");
    let (ok, _, err) = extranerf(&[
        "diffusion",
        "inpaint",
        "--model",
        &s(&prior.join("model")),
        "--image",
        &s(&view),
        "--mask",
        &s(&mask),
        "--out",
        &s(&result),
        "--strength",
        "1.5",
    ]);
    assert!(!ok && err.contains("--strength 1.5"), "{err}");
    let (ok, _, err) = extranerf(&["diffusion", "init", "--config", "huge", "--out", "x"]);
    assert!(!ok && err.contains("huge"), "{err}");

    // The bench, CPU backend, tiny configuration.
    let json = dir.join("bench.json");
    let (ok, out, err) = extranerf(&[
        "bench",
        "diffusion",
        "--backends",
        "cpu",
        "--tiny-only",
        "--iters",
        "1",
        "--json",
        &s(&json),
    ]);
    assert!(ok, "{err}");
    assert!(
        out.contains("forward+backward") && out.contains("SD-1.5 inpainting"),
        "{out}"
    );
    let j: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(j["rows"].as_array().unwrap().len(), 3);
    let _ = std::fs::remove_dir_all(dir);
}

/// Resource faults: no Vulkan driver, a driver whose library is missing, and device memory
/// exhausted (forced with --max-memory) are clear errors with a non-zero exit status, and leave
/// no run folder behind.
#[test]
fn resource_faults_are_clear_errors() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-faults-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let bogus = dir.join("bogus_icd.json");
    std::fs::write(
        &bogus,
        r#"{"file_format_version": "1.0.0", "ICD": {"library_path": "/nonexistent/libvulkan_bogus.so", "api_version": "1.3.0"}}"#,
    )
    .unwrap();
    for icd in [dir.join("no_such_icd.json"), bogus] {
        let out = Command::new(env!("CARGO_BIN_EXE_extranerf"))
            .arg("info")
            .env("VK_DRIVER_FILES", &icd)
            .env("VK_ICD_FILENAMES", &icd)
            .env("EXTRANERF_VALIDATION", "off")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.code() == Some(1)
                && err.contains("Vulkan driver")
                && !err.contains("panicked"),
            "{}: {err}",
            icd.display()
        );
    }
    let scene = dir.join("scene");
    extranerf_nerf::demo::write_demo_scene(&scene, 48, 36).unwrap();
    let run = dir.join("run");
    let train = |mib: &str| {
        extranerf(&[
            "--max-memory",
            mib,
            "train",
            "--scene",
            scene.to_str().unwrap(),
            "--split",
            "extrapolation",
            "--factor",
            "1",
            "--steps",
            "2",
            "--out",
            run.to_str().unwrap(),
        ])
    };
    let (ok, _, err) = train("4");
    assert!(
        !ok && err.contains("out of device memory while allocating") && !err.contains("panicked"),
        "{err}"
    );
    assert!(!run.exists(), "a run folder was left behind");
    // With enough memory the same run trains.
    let (ok, _, err) = train("512");
    assert!(ok, "{err}");
    assert!(run.join("checkpoint.safetensors").is_file());
    let _ = std::fs::remove_dir_all(dir);
}

/// The last step logged in a run's progress.jsonl (0 when none).
fn last_logged_step(run: &std::path::Path) -> u32 {
    std::fs::read_to_string(run.join("progress.jsonl"))
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| v["step"].as_u64())
        .max()
        .unwrap_or(0) as u32
}

/// Whether `dir` holds the temporary file of an atomic write of `name` (one in progress, or
/// left by a killed process).
fn writing_file(dir: &std::path::Path, name: &str) -> bool {
    let prefix = format!(".{name}.tmp");
    std::fs::read_dir(dir)
        .map(|r| {
            r.filter_map(Result::ok)
                .any(|e| e.file_name().to_string_lossy().starts_with(&prefix))
        })
        .unwrap_or(false)
}

/// Runs the program with `args` (stderr to `log` when given), with
/// `EXTRANERF_CRASH_TEST_PAUSE=pause` when given, and kills it with SIGKILL once `ready()`
/// holds; fails if it ends first.
fn spawn_and_kill(
    args: &[String],
    pause: Option<&str>,
    log: Option<&std::path::Path>,
    ready: &dyn Fn() -> bool,
) {
    use std::process::Stdio;
    use std::time::{Duration, Instant};
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_extranerf"));
    cmd.args(args).stdout(Stdio::null());
    match log {
        Some(l) => cmd.stderr(std::fs::File::create(l).unwrap()),
        None => cmd.stderr(Stdio::null()),
    };
    if let Some(p) = pause {
        cmd.env("EXTRANERF_CRASH_TEST_PAUSE", p);
    }
    let mut child = cmd.spawn().unwrap();
    let t = Instant::now();
    while !ready() {
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run ended before it could be killed"
        );
        assert!(t.elapsed() < Duration::from_secs(300), "timed out");
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
}

/// A fresh scratch folder `extranerf-cli-TAG-PID` holding the demo scene at `w` x `h` in
/// `scene/`: (the folder, the scene).
fn scratch_with_demo_scene(tag: &str, w: u32, h: u32) -> (std::path::PathBuf, std::path::PathBuf) {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let scene = dir.join("scene");
    extranerf_nerf::demo::write_demo_scene(&scene, w, h).unwrap();
    (dir, scene)
}

/// Crash safety of `extrapolate` (issue 60): one run folder killed with SIGKILL at each
/// boundary (held there by EXTRANERF_CRASH_TEST_PAUSE where a file marks it), and one whose
/// write fails as a full disk does (EXTRANERF_CRASH_TEST_FULL_DISK); each resumes with
/// `--resume`, losing at most the round it was in, cleans what the killed writes left, and
/// ends at a stage-3 field within the bounds of `train`'s kill test of the uninterrupted
/// run's. While a run holds its folder, a second one into it is refused naming the holder.
#[test]
fn extrapolate_survives_sigkill_at_every_boundary() {
    let (dir, scene) = scratch_with_demo_scene("xkill", 32, 24);
    // The BaseNeRF they share, with uniform strata (see train_survives_sigkill_and_resumes).
    let base = dir.join("base");
    let (ok, _, err) = extranerf(&[
        "train",
        "--scene",
        scene.to_str().unwrap(),
        "--split",
        "extrapolation",
        "--factor",
        "1",
        "--steps",
        "200",
        "--levels",
        "8",
        "--log2-table",
        "14",
        "--rays",
        "256",
        "--samples",
        "32",
        "--sampler",
        "uniform",
        "--seed",
        "5",
        "--out",
        base.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let args = |out: &std::path::Path| -> Vec<String> {
        [
            "extrapolate",
            "--base",
            base.to_str().unwrap(),
            "--virtual",
            "2",
            "--virtual-downscale",
            "1",
            "--rounds",
            "3",
            "--steps-per-round",
            "20",
            "--inpainter",
            "harmonic",
            "--flythrough",
            "2",
            "--stage3-rounds",
            "2",
            "--stage3-steps-per-round",
            "10",
            "--stage3-gate",
            "off",
            "--data-rounds",
            "2",
            "--data-steps-per-round",
            "5",
            "--fresh-checkpoints",
            "5",
            "--enhancer-channels",
            "8,16",
            "--enhancer-steps",
            "60",
            "--enhancer-batch",
            "2",
            "--enhancer-crop",
            "16",
            "--stage3-ddim-steps",
            "2",
            "--out",
            out.to_str().unwrap(),
        ]
        .map(String::from)
        .to_vec()
    };
    let run = |a: Vec<String>| -> String {
        let argv: Vec<&str> = a.iter().map(String::as_str).collect();
        let (ok, _, err) = extranerf(&argv);
        assert!(ok, "{err}");
        err
    };
    let resume = |out: &std::path::Path| -> String {
        let mut a = args(out);
        a.push("--resume".into());
        let err = run(a);
        let mut left = Vec::new();
        let mut todo = vec![out.to_path_buf()];
        while let Some(d) = todo.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                let n = p.file_name().unwrap().to_string_lossy().into_owned();
                if p.is_dir() {
                    todo.push(p);
                } else if n.contains(".tmp") || n.ends_with(".partial") {
                    left.push(p);
                }
            }
        }
        assert!(left.is_empty(), "left after the resume: {left:?}");
        err
    };
    let straight = dir.join("straight");
    run(args(&straight));
    let params = |d: &std::path::Path| {
        extranerf_nerf::run::load_checkpoint(&d.join("stage3-harmonic"))
            .unwrap()
            .params
    };
    let p0 = params(&straight);
    let norm = |v: &[f32]| v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    let close = |d: &std::path::Path| {
        let p = params(d);
        let diff: Vec<f32> = p0.iter().zip(&p).map(|(a, b)| a - b).collect();
        let r = norm(&diff) / norm(&p0);
        eprintln!(
            "{}: the stage-3 field differs by {:.2}% (relative L2)",
            d.display(),
            100.0 * r
        );
        assert!(
            r < 0.04,
            "{}: the stage-3 field differs by {:.2}%",
            d.display(),
            100.0 * r
        );
    };
    let files = |d: &std::path::Path, pred: &dyn Fn(&str) -> bool| {
        std::fs::read_dir(d)
            .map(|r| {
                r.filter_map(Result::ok)
                    .any(|e| pred(&e.file_name().to_string_lossy()))
            })
            .unwrap_or(false)
    };

    // Inside stage 2's second round, as it writes the round's fills.
    let a = dir.join("in-round");
    let s2 = a.join("stage2-harmonic");
    spawn_and_kill(&args(&a), Some("virtual_001.png:3000"), None, &|| {
        s2.join("round.json").is_file() && writing_file(&s2.join("round_01"), "virtual_001.png")
    });
    let err = resume(&a);
    assert!(
        err.contains("stage2-harmonic: resuming after round 1"),
        "{err}"
    );
    assert!(err.contains("removed 1 temporary file(s)"), "{err}");
    close(&a);

    // Between round 2's checkpoint and its record; meanwhile a second run into the folder
    // is refused, naming the first.
    let b = dir.join("between");
    let s2 = b.join("stage2-harmonic");
    spawn_and_kill(&args(&b), Some("round.json:4000"), None, &|| {
        if !(s2.join("round.json").is_file() && writing_file(&s2, "round.json")) {
            return false;
        }
        let mut second = args(&b);
        second.push("--resume".into());
        let argv: Vec<&str> = second.iter().map(String::as_str).collect();
        let (ok, _, err) = extranerf(&argv);
        assert!(
            !ok && err.contains("in use by process") && err.contains("extrapolate"),
            "{err}"
        );
        true
    });
    let err = resume(&b);
    assert!(
        err.contains("round 2's checkpoint was saved but not its record")
            && err.contains("resuming after round 2"),
        "{err}"
    );
    close(&b);

    // Inside a stage-3 data round: its first round's renders begun.
    let c = dir.join("in-data");
    let data = c.join("stage3-data");
    spawn_and_kill(&args(&c), None, None, &|| {
        files(&data, &|n| n.ends_with("_view000_inpainted_0.png"))
    });
    assert!(
        !data.join("triplets.safetensors").exists(),
        "the data stage ended first"
    );
    let err = resume(&c);
    assert!(err.contains("stage visibility: done, skipped"), "{err}");
    assert!(
        err.contains("stage stage2-harmonic: done, skipped"),
        "{err}"
    );
    close(&c);

    // Inside the enhancer's training, as it writes its first training state.
    let d = dir.join("in-enhancer");
    let state = d.join("stage3-enhancer").join("train_state");
    spawn_and_kill(&args(&d), Some("state.json:3000"), None, &|| {
        writing_file(&state, "state.json")
    });
    let err = resume(&d);
    assert!(err.contains("stage stage3-data: done, skipped"), "{err}");
    close(&d);

    // A full disk as stage 2 records its first round: a clear error naming the file; the
    // resume starts the round again.
    let e = dir.join("full-disk");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_extranerf"));
    let out = cmd
        .args(args(&e))
        .env("EXTRANERF_CRASH_TEST_FULL_DISK", "round.json")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("round.json") && err.contains("No space left"),
        "{err}"
    );
    assert!(!e.join("stage2-harmonic").join("round.json").exists());
    let err = resume(&e);
    assert!(!err.contains("resuming after round"), "{err}");
    close(&e);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Resume and redo cannot mix runs (issue 59), each finding through the command line:
/// - a round whose checkpoint was written but not its record (killed in between, held there by
///   EXTRANERF_CRASH_TEST_PAUSE) resumes after that round, not before it;
/// - `--redo base` reruns the visibility and stage 2 that read it, and `--redo visibility`
///   with another threshold reruns stage 2;
/// - a folder whose `base` was trained on another scene is refused; `--base` is known by its
///   checkpoint's hash (a copy may take its place; another run reruns what reads it);
/// - the scene is known by its cameras' and images' hash: an image changed in place is refused.
#[test]
fn extrapolate_resume_and_redo_cannot_mix_runs() {
    let (dir, scene) = scratch_with_demo_scene("mix", 32, 24);
    let scene_s = scene.to_str().unwrap();
    let common = |out: &std::path::Path| -> Vec<String> {
        [
            "extrapolate",
            "--split",
            "extrapolation",
            "--factor",
            "1",
            "--virtual",
            "2",
            "--virtual-downscale",
            "1",
            "--rounds",
            "3",
            "--steps-per-round",
            "10",
            "--inpainter",
            "harmonic",
            "--flythrough",
            "0",
            "--no-stage3",
            "--out",
            out.to_str().unwrap(),
        ]
        .map(String::from)
        .to_vec()
    };
    let run = |args: &[String]| {
        let argv: Vec<&str> = args.iter().map(String::as_str).collect();
        let (ok, _, err) = extranerf(&argv);
        (ok, err)
    };
    let with = |base: Vec<String>, extra: &[&str]| -> Vec<String> {
        base.into_iter()
            .chain(extra.iter().map(|s| s.to_string()))
            .collect()
    };
    let own =
        |out: &std::path::Path| with(common(out), &["--scene", scene_s, "--base-budget", "6"]);

    // Killed between round 2's checkpoint and its record.
    let r = dir.join("r");
    let stage = r.join("stage2-harmonic");
    spawn_and_kill(&own(&r), Some("round.json:3000"), None, &|| {
        stage.join("round.json").is_file() && writing_file(&stage, "round.json")
    });
    let round = std::fs::read_to_string(stage.join("round.json")).unwrap();
    assert!(round.contains("\"rounds_done\":1"), "{round}");
    let (ok, err) = run(&with(own(&r), &["--resume"]));
    assert!(ok, "{err}");
    assert!(
        err.contains("round 2's checkpoint was saved but not its record")
            && err.contains("resuming after round 2")
            && err.contains("stage2-harmonic round 3/3")
            && !err.contains("stage2-harmonic round 2/3"),
        "{err}"
    );
    assert_eq!(
        extranerf_nerf::run::load_checkpoint(&stage).unwrap().step,
        30
    );

    // --redo base: what reads the BaseNeRF runs again.
    let (ok, err) = run(&with(own(&r), &["--resume", "--redo", "base"]));
    assert!(ok, "{err}");
    for s in [
        "stage visibility: runs again after base",
        "stage stage2-harmonic: runs again after base, visibility",
    ] {
        assert!(err.contains(s), "{s}:\n{err}");
    }
    // --redo visibility with another threshold: stage 2 runs again on the new masks.
    let (ok, err) = run(&with(
        own(&r),
        &["--resume", "--redo", "visibility", "--threshold", "0.3"],
    ));
    assert!(ok, "{err}");
    assert!(err.contains("stage base: done, skipped"), "{err}");
    assert!(
        err.contains("stage stage2-harmonic: runs again after visibility"),
        "{err}"
    );
    // And with nothing changed, nothing runs.
    let (ok, err) = run(&with(own(&r), &["--resume", "--threshold", "0.3"]));
    assert!(ok, "{err}");
    for s in ["base", "visibility", "stage2-harmonic"] {
        assert!(
            err.contains(&format!("stage {s}: done, skipped")),
            "{s}:\n{err}"
        );
    }

    // A folder whose base/ holds a BaseNeRF of another split of the scene.
    let train = |out: &std::path::Path, seed: &str, split: &str| {
        let (ok, _, err) = extranerf(&[
            "train",
            "--scene",
            scene_s,
            "--split",
            split,
            "--factor",
            "1",
            "--steps",
            "30",
            "--levels",
            "8",
            "--log2-table",
            "14",
            "--rays",
            "256",
            "--seed",
            seed,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(ok, "{err}");
    };
    let foreign = dir.join("foreign");
    train(&foreign.join("base"), "1", "holdout");
    let (ok, err) = run(&own(&foreign));
    assert!(
        !ok && err.contains("holds a BaseNeRF of another scene or split") && err.contains("split"),
        "{err}"
    );

    // --base by its checkpoint: a copy takes its place; another run reruns what reads it.
    let p = dir.join("p");
    train(&p, "1", "extrapolation");
    let reused = dir.join("reused");
    let (ok, err) = run(&with(common(&reused), &["--base", p.to_str().unwrap()]));
    assert!(ok, "{err}");
    let copy = dir.join("p-copy");
    std::fs::create_dir_all(&copy).unwrap();
    for e in std::fs::read_dir(&p).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_file() {
            std::fs::copy(e.path(), copy.join(e.file_name())).unwrap();
        }
    }
    let (ok, err) = run(&with(
        common(&reused),
        &["--resume", "--base", copy.to_str().unwrap()],
    ));
    assert!(ok, "{err}");
    for s in ["base", "visibility", "stage2-harmonic"] {
        assert!(
            err.contains(&format!("stage {s}: done, skipped")),
            "{s}:\n{err}"
        );
    }
    let other = dir.join("p-other");
    train(&other, "2", "extrapolation");
    let (ok, err) = run(&with(
        common(&reused),
        &["--resume", "--base", other.to_str().unwrap()],
    ));
    assert!(ok, "{err}");
    assert!(
        err.contains("stage base: its output changed since this run recorded it")
            && err.contains("stage visibility: runs again after base")
            && err.contains("stage stage2-harmonic: runs again after base, visibility"),
        "{err}"
    );

    // An image of the scene changed in place.
    let img = scene.join("images").join("view_00.png");
    let mut px = image::open(&img).unwrap().to_rgb8();
    px.put_pixel(0, 0, image::Rgb([255, 0, 255]));
    px.save(&img).unwrap();
    let (ok, err) = run(&with(
        common(&reused),
        &["--resume", "--base", other.to_str().unwrap()],
    ));
    assert!(
        !ok && err.contains("the cameras or images of the scene") && err.contains("changed"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Crash safety of `train`: a run killed with SIGKILL during training, and one killed while it
/// writes a checkpoint (between the synced temporary file and the rename, held open there by
/// the EXTRANERF_CRASH_TEST_PAUSE hook), resume with --resume from their last checkpoint,
/// losing at most one checkpoint interval, and end where an uninterrupted run with the same
/// seed ends (the same batches; float-atomic gradient sums make runs agree closely, not bit
/// for bit).
#[test]
fn train_survives_sigkill_and_resumes() {
    let (dir, scene) = scratch_with_demo_scene("kill", 48, 36);
    let (steps, every) = (120u32, 20u32);
    let args = |out: &std::path::Path| -> Vec<String> {
        [
            "train",
            "--scene",
            scene.to_str().unwrap(),
            "--split",
            "extrapolation",
            "--factor",
            "1",
            "--out",
            out.to_str().unwrap(),
            "--steps",
            &steps.to_string(),
            "--checkpoint-every",
            &every.to_string(),
            "--log-every",
            "5",
            "--levels",
            "8",
            "--log2-table",
            "14",
            "--rays",
            "512",
            "--samples",
            "32",
            "--seed",
            "11",
            // Uniform strata: with the proposal sampler (the default) two uninterrupted runs of
            // the same seed already differ by about 16% (the resampled positions amplify the
            // float-atomic summation order; the training PSNR agrees), which would hide a lost
            // checkpoint from the comparison below.
            "--sampler",
            "uniform",
        ]
        .map(String::from)
        .to_vec()
    };
    let run = |a: &[String]| {
        let argv: Vec<&str> = a.iter().map(String::as_str).collect();
        let (ok, _, err) = extranerf(&argv);
        assert!(ok, "{err}");
        err
    };
    // Kills the run in `out` once `ready` says so; returns the last step it logged.
    let kill_when = |out: &std::path::Path, pause: Option<&str>, ready: &dyn Fn() -> bool| {
        spawn_and_kill(&args(out), pause, None, ready);
        last_logged_step(out)
    };
    let resume = |out: &std::path::Path, killed_at: u32| {
        let ck = extranerf_nerf::run::load_checkpoint(out).unwrap();
        assert!(
            ck.step + every >= killed_at && ck.step < killed_at,
            "killed at step {killed_at}, the checkpoint holds step {}",
            ck.step
        );
        let err = run(&[
            "train".into(),
            "--resume".into(),
            "--out".into(),
            out.to_str().unwrap().into(),
        ]);
        assert!(
            err.contains(&format!("resuming {} at step {}", out.display(), ck.step)),
            "{err}"
        );
    };

    let straight = dir.join("straight");
    run(&args(&straight));
    // Killed during training, a little past the second checkpoint.
    let killed = dir.join("killed");
    let at = kill_when(&killed, None, &|| {
        last_logged_step(&killed) >= 2 * every + 5
    });
    let killed_ck = extranerf_nerf::run::load_checkpoint(&killed).unwrap().step;
    resume(&killed, at);
    // Killed while writing the third checkpoint: the second stays intact.
    let mid = dir.join("mid-write");
    let tmp = |d: &std::path::Path| writing_file(d, "checkpoint.safetensors");
    let at = kill_when(&mid, Some("checkpoint.safetensors:2000"), &|| {
        last_logged_step(&mid) >= 3 * every && tmp(&mid)
    });
    assert_eq!(at, 3 * every);
    assert_eq!(
        extranerf_nerf::run::load_checkpoint(&mid).unwrap().step,
        2 * every
    );
    resume(&mid, at);

    // All three end at the last step, with parameters and training PSNR that agree.
    let end = |d: &std::path::Path| {
        let ck = extranerf_nerf::run::load_checkpoint(d).unwrap();
        assert_eq!(ck.step, steps);
        let last = std::fs::read_to_string(d.join("progress.jsonl"))
            .unwrap()
            .lines()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
            .find(|v| v["step"].as_u64() == Some(steps as u64))
            .unwrap();
        (ck.params, last["psnr"].as_f64().unwrap())
    };
    let (p0, psnr0) = end(&straight);
    // Each step is logged once, in order, as in the uninterrupted run: a resume cuts the log
    // back to its checkpoint before training again.
    let logged = |d: &std::path::Path| -> Vec<u64> {
        std::fs::read_to_string(d.join("progress.jsonl"))
            .unwrap()
            .lines()
            .map(|l| {
                serde_json::from_str::<serde_json::Value>(l).unwrap()["step"]
                    .as_u64()
                    .unwrap()
            })
            .collect()
    };
    let want = logged(&straight);
    assert_eq!(want.len(), (steps / 5) as usize);
    // (The resume logs at `train`'s default interval from its checkpoint on.)
    for (d, ck) in [(&killed, killed_ck), (&mid, 2 * every)] {
        let got = logged(d);
        let upto: Vec<u64> = want.iter().copied().filter(|&s| s <= ck as u64).collect();
        assert_eq!(got[..upto.len()], upto[..], "{}: {got:?}", d.display());
        assert!(
            got.windows(2).all(|w| w[0] < w[1]),
            "{}: {got:?}",
            d.display()
        );
        assert_eq!(got.last(), Some(&(steps as u64)), "{}", d.display());
    }
    // A fresh run into the folder of one killed before its first checkpoint (while writing
    // it) starts its own log.
    let early = dir.join("early");
    let at = kill_when(&early, Some("checkpoint.safetensors:2000"), &|| tmp(&early));
    assert_eq!(at, every);
    assert!(extranerf_nerf::run::load_checkpoint(&early).is_err());
    run(&args(&early));
    assert_eq!(logged(&early), want);
    let norm = |v: &[f32]| v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    let rel = |p: &[f32]| {
        let d: Vec<f32> = p0.iter().zip(p).map(|(a, b)| a - b).collect();
        norm(&d) / norm(&p0)
    };
    for d in [&killed, &mid] {
        let (p, psnr) = end(d);
        let r = rel(&p);
        eprintln!(
            "{}: training PSNR {psnr:.3} dB vs {psnr0:.3} uninterrupted; parameters differ by {:.2}% (relative L2)",
            d.display(),
            100.0 * r
        );
        assert!((psnr - psnr0).abs() < 0.2, "{psnr} vs {psnr0}");
        assert!(r < 0.04, "parameters differ by {:.2}%", 100.0 * r);
    }
    let _ = std::fs::remove_dir_all(dir);
}

/// Crash safety of `diffusion prior` and `diffusion finetune`: runs killed with SIGKILL during
/// training, and (prior) while the training state is written (between the synced temporary
/// file and the rename), resume with --resume from their last saved step, losing at most one
/// --checkpoint-every interval, and end bit for bit where uninterrupted runs end (the same
/// loss curve and weights: the CPU backend's training is deterministic).
#[test]
fn diffusion_training_survives_sigkill_and_resumes() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-dkill-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let scene = dir.join("scene");
    extranerf_nerf::demo::write_demo_scene(&scene, 64, 48).unwrap();
    let lpips = extranerf_tests::shared_data().join("../models/lpips");
    let s = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let (steps, every) = (60u64, 20u64);
    let common = [
        "--scene".to_string(),
        s(&scene),
        "--split".into(),
        "extrapolation".into(),
        "--steps".into(),
        steps.to_string(),
        "--checkpoint-every".into(),
        every.to_string(),
        "--log-every".into(),
        "1".into(),
        "--batch".into(),
        "2".into(),
        "--crop".into(),
        "32".into(),
        "--factor".into(),
        "1".into(),
        "--downscale".into(),
        "1".into(),
        "--diffusion-backend".into(),
        "cpu".into(),
        "--seed".into(),
        "3".into(),
    ];
    let prior_args = |out: &std::path::Path| -> Vec<String> {
        let mut a: Vec<String> = [
            "diffusion",
            "prior",
            "--out",
            &s(out),
            "--channels",
            "16,32",
            "--holes",
            "1",
            "--hole-size",
            "8",
            "--eval-steps",
            "2",
            "--refine-steps",
            "2",
            "--lpips",
            &s(&lpips),
        ]
        .iter()
        .map(|v| v.to_string())
        .collect();
        a.extend(common.iter().cloned());
        a
    };
    let base = dir.join("straight-prior").join("model");
    let finetune_args = |out: &std::path::Path| -> Vec<String> {
        let mut a: Vec<String> = [
            "diffusion",
            "finetune",
            "--model",
            &s(&base),
            "--out",
            &s(out),
            "--rank",
            "2",
        ]
        .iter()
        .map(|v| v.to_string())
        .collect();
        a.extend(common.iter().cloned());
        a
    };
    let run = |a: &[String]| {
        let argv: Vec<&str> = a.iter().map(String::as_str).collect();
        let (ok, _, err) = extranerf(&argv);
        assert!(ok, "{err}");
        err
    };
    // The last step a log reports, and the step the saved state holds.
    let logged = |log: &std::path::Path| -> u64 {
        std::fs::read_to_string(log)
            .unwrap_or_default()
            .lines()
            .filter_map(|l| {
                let rest = l.split(" step ").nth(1)?;
                rest.trim_start().split('/').next()?.parse::<u64>().ok()
            })
            .max()
            .unwrap_or(0)
    };
    let saved = |out: &std::path::Path| -> Option<u64> {
        let text = std::fs::read_to_string(out.join("train_state").join("state.json")).ok()?;
        serde_json::from_str::<serde_json::Value>(&text).ok()?["step"].as_u64()
    };
    let writing = |out: &std::path::Path| writing_file(&out.join("train_state"), "state.json");
    // Resumes `out` (killed at step `killed_at`) with the same arguments and --resume.
    let resume = |args: &[String], out: &std::path::Path, killed_at: u64| {
        let at = saved(out).expect("no saved state");
        assert!(
            at + every >= killed_at && at < killed_at,
            "killed at step {killed_at}, the state holds step {at}"
        );
        let mut a = args.to_vec();
        a.push("--resume".into());
        let err = run(&a);
        assert!(
            err.contains(&format!("resuming {} at step {at}", out.display())),
            "{err}"
        );
        // Nothing of the killed write is left behind.
        assert!(!writing(out));
    };
    // The same file content; for safetensors the same tensors (the header's metadata order
    // varies).
    let same = |a: &std::path::Path, b: &std::path::Path, file: &str| {
        let equal = if file.ends_with(".safetensors") {
            let read = |p: std::path::PathBuf| {
                extranerf_nerf::safetensors::SafeTensors::read(&p)
                    .unwrap()
                    .tensors
                    .into_iter()
                    .map(|(k, t)| (k, t.shape, t.data))
                    .collect::<Vec<_>>()
            };
            read(a.join(file)) == read(b.join(file))
        } else {
            std::fs::read(a.join(file)).unwrap() == std::fs::read(b.join(file)).unwrap()
        };
        assert!(
            equal,
            "{file} of {} differs from the uninterrupted run's",
            b.display()
        );
    };

    let straight = dir.join("straight-prior");
    run(&prior_args(&straight));
    // Killed during training, a little past the second save.
    let killed = dir.join("killed-prior");
    let log = dir.join("killed-prior.log");
    spawn_and_kill(&prior_args(&killed), None, Some(&log), &|| {
        saved(&killed) == Some(2 * every) && logged(&log) >= 2 * every + 3
    });
    resume(&prior_args(&killed), &killed, logged(&log));
    // Killed while the third save writes state.json: the second stays in force.
    let mid = dir.join("mid-write-prior");
    let log = dir.join("mid-write-prior.log");
    spawn_and_kill(
        &prior_args(&mid),
        Some("state.json:2000"),
        Some(&log),
        &|| saved(&mid) == Some(2 * every) && writing(&mid) && logged(&log) >= 3 * every,
    );
    assert_eq!(logged(&log), 3 * every);
    assert_eq!(saved(&mid), Some(2 * every));
    resume(&prior_args(&mid), &mid, 3 * every);
    for d in [&killed, &mid] {
        same(&straight, d, "loss.csv");
        same(
            &straight,
            d,
            "model/unet/diffusion_pytorch_model.safetensors",
        );
        same(&straight, d, "model/prior_holes.json");
    }
    // A finished run is not replaced without --resume, and --resume past its steps is refused.
    let argv = prior_args(&straight);
    let (ok, _, err) = extranerf(&argv.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!ok && err.contains("already holds a prior"), "{err}");

    // LoRA fine-tuning of that prior, killed during training.
    let tuned = dir.join("straight-lora");
    run(&finetune_args(&tuned));
    let killed = dir.join("killed-lora");
    let log = dir.join("killed-lora.log");
    spawn_and_kill(&finetune_args(&killed), None, Some(&log), &|| {
        saved(&killed) == Some(every) && logged(&log) >= every + 3
    });
    resume(&finetune_args(&killed), &killed, logged(&log));
    same(&tuned, &killed, "loss.csv");
    same(&tuned, &killed, "pytorch_lora_weights.safetensors");
    // Another rank is another training: refused, naming it.
    let mut other = finetune_args(&killed);
    let at = other.iter().position(|a| a == "--rank").unwrap();
    other[at + 1] = "3".into();
    other.push("--resume".into());
    let (ok, _, err) = extranerf(&other.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!ok && err.contains("rank: 2 when saved, 3 now"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
}
