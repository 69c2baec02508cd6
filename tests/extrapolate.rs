//! The ExtraNeRF pipeline (`extranerf extrapolate`) on the demo scene at a small size: every
//! stage runs, the visible region stays close to the BaseNeRF while the masked one changes,
//! a resumed run (at a stage boundary, or after a crash inside stage 2) ends where an
//! uninterrupted one does, and run folders made from another scene or other settings are
//! refused.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::path::Path;

use extranerf_extrapolate::driver::{train_loop, Progress, Reporter, TrainRun, Unit};
use extranerf_extrapolate::inpaint::InpainterKind;
use extranerf_extrapolate::manifest::Manifest;
use extranerf_extrapolate::pipeline::{
    extrapolate, BaseSpec, FlythroughSpec, Options, Stage2Spec, VirtualSpec,
};
use extranerf_extrapolate::visibility::VisSettings;
use extranerf_nerf::cameras::Trajectory;
use extranerf_nerf::data::load_image;
use extranerf_nerf::model::ModelConfig;
use extranerf_nerf::run::{load_checkpoint, RunConfig, SceneSpec};
use extranerf_nerf::trainer::TrainConfig;
use extranerf_tests::{assert_no_validation_messages, engine, scratch_dir};

/// Keeps the notes; panics at the `panic_at`-th training progress of stage 2 (a crash).
#[derive(Default)]
struct Record {
    notes: Vec<String>,
    stage2_steps: usize,
    panic_at: Option<usize>,
    stage: String,
}

impl Reporter for Record {
    fn note(&mut self, line: &str) {
        self.notes.push(line.to_string());
    }

    fn progress(&mut self, p: &Progress) {
        if self.stage.starts_with("stage2") && p.unit == Unit::Steps {
            self.stage2_steps += 1;
            if Some(self.stage2_steps) == self.panic_at {
                panic!("simulated crash inside stage 2");
            }
        }
    }

    fn stage(&mut self, name: &str) {
        self.stage = name.to_string();
    }
}

fn scene(dir: &Path) -> SceneSpec {
    SceneSpec {
        dir: dir.to_path_buf(),
        split: extranerf_nerf::data::split::SplitKind::Extrapolation,
        fewshot_views: 3,
        factor: 1,
        sparse_depth: false,
        depth_dir: None,
    }
}

fn options(out: &Path, base: &Path) -> Options {
    Options {
        out: out.to_path_buf(),
        scene: None,
        base: BaseSpec {
            from: Some(base.to_path_buf()),
            budget: 60.0,
        },
        virt: VirtualSpec {
            trajectory: Trajectory::Spiral,
            count: 3,
            range: 1.5,
            downscale: 1,
        },
        vis: VisSettings {
            volume_res: 32,
            volume_depth: 32,
            ..VisSettings::default()
        },
        stage2: Stage2Spec {
            rounds: 2,
            steps_per_round: 50,
            ..Stage2Spec::default()
        },
        inpainters: vec![InpainterKind::Harmonic],
        diffusion: None,
        flythrough: FlythroughSpec {
            frames: 3,
            downscale: 2,
            delay_ms: 100,
        },
        resume: false,
    }
}

/// Mean PSNR between two runs' stage-2 renders of the held-out views. The training step sums
/// hash-table gradients with float atomics, whose order varies, so two runs of the same
/// settings agree closely but not bit for bit.
fn agreement(a: &Path, b: &Path, views: &[usize]) -> f64 {
    let mut sum = 0.0;
    for &i in views {
        let f = format!("stage2-harmonic/test_{i:03}.png");
        let (x, y) = (
            load_image(&a.join(&f)).unwrap(),
            load_image(&b.join(&f)).unwrap(),
        );
        sum += psnr_where(&x.rgb, &y.rgb, &vec![true; x.rgb.len() / 3]);
    }
    sum / views.len() as f64
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dst = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dst);
        } else {
            std::fs::copy(e.path(), dst).unwrap();
        }
    }
}

/// PSNR between two images over the pixels where `keep` holds.
fn psnr_where(a: &[f32], b: &[f32], keep: &[bool]) -> f64 {
    let (mut se, mut n) = (0f64, 0usize);
    for (i, &k) in keep.iter().enumerate() {
        if k {
            for c in 0..3 {
                se += (a[3 * i + c] as f64 - b[3 * i + c] as f64).powi(2);
            }
            n += 3;
        }
    }
    -10.0 * (se / n.max(1) as f64).max(1e-12).log10()
}

#[test]
fn the_pipeline_runs_resumes_and_refuses_other_scenes_and_settings() {
    let e = engine();
    let ctx = &e.ctx;
    let dir = scratch_dir("extrapolate");
    let scene_dir = dir.join("scene");
    extranerf_nerf::demo::write_demo_scene(&scene_dir, 48, 36).unwrap();
    // A small BaseNeRF.
    let base = dir.join("base");
    let cfg = RunConfig {
        scene: scene(&scene_dir),
        model: ModelConfig {
            levels: 6,
            log2_table: 12,
            max_res: 128,
            ..ModelConfig::default()
        },
        train: TrainConfig {
            steps: 300,
            decay_steps: 300,
            samples: 16,
            ..TrainConfig::default()
        },
    };
    let run = TrainRun {
        out: base.clone(),
        start: 0,
        log_every: 50,
        checkpoint_every: 300,
        eval_every: 0,
        eval_views: extranerf_extrapolate::driver::ViewSet::Test,
        budget: None,
    };
    train_loop(ctx, &cfg, &run, None, None, &mut Record::default()).unwrap();

    // The whole pipeline.
    let a = dir.join("a");
    let mut rec = Record::default();
    let m = extrapolate(ctx, &options(&a, &base), &mut rec).unwrap();
    let names: Vec<&str> = m.stages.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "base",
            "visibility",
            "stage2-harmonic",
            "flythrough-base",
            "flythrough-stage2-harmonic"
        ]
    );
    assert!(m.stages.iter().all(|s| s.done));
    for f in [
        "visibility/maps.safetensors",
        "visibility/virtual.json",
        "visibility/virtual_002_mask.png",
        "stage2-harmonic/round_01/virtual_002.png",
        "stage2-harmonic/checkpoint.safetensors",
        "flythrough/base/frame_002.png",
        "flythrough/stage2-harmonic/frame_000.png",
    ] {
        assert!(a.join(f).exists(), "{f} missing");
    }
    // The fly-through: one looping animation per field, frames at half the virtual size, and
    // the variant's differs from the BaseNeRF's.
    let gif = |name: &str| {
        use image::AnimationDecoder;
        let f = std::fs::File::open(a.join(format!("flythrough/{name}.gif"))).unwrap();
        image::codecs::gif::GifDecoder::new(std::io::BufReader::new(f))
            .unwrap()
            .into_frames()
            .collect_frames()
            .unwrap()
    };
    let (fb, fs) = (gif("base"), gif("stage2-harmonic"));
    assert_eq!(fb.len(), 3);
    assert_eq!(fs.len(), 3);
    assert_eq!(fb[0].buffer().dimensions(), (24, 18));
    assert_ne!(fb[2].buffer().as_raw(), fs[2].buffer().as_raw());
    // The masks against the demo's exact visibility.
    let vis: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(a.join("visibility/visibility.json")).unwrap(),
    )
    .unwrap();
    let iou = vis["exact_mean"]["iou"].as_f64().unwrap();
    let acc = vis["exact_mean"]["accuracy"].as_f64().unwrap();
    eprintln!("masks against the exact visibility: IoU {iou:.3}, accuracy {acc:.3}");
    assert!(
        (0.0..=1.0).contains(&iou) && acc > 0.65,
        "IoU {iou}, accuracy {acc}"
    );

    // The held-out views: where the training cameras saw, stage 2 stays close to the
    // BaseNeRF's render; inside the mask it changes more.
    let loaded = scene(&scene_dir).load().unwrap();
    let st = extranerf_nerf::safetensors::SafeTensors::read(&a.join("visibility/maps.safetensors"))
        .unwrap();
    let (mut vis_psnr, mut mask_psnr) = (Vec::new(), Vec::new());
    for &i in &loaded.split.test {
        let b = load_image(&a.join(format!("visibility/test_{i:03}_base.png"))).unwrap();
        let s = load_image(&a.join(format!("stage2-harmonic/test_{i:03}.png"))).unwrap();
        let map = extranerf_extrapolate::pipeline::load_map(
            &st,
            Path::new("maps"),
            &format!("test_{i:03}"),
        )
        .unwrap();
        let mask = VisSettings::default().mask(&map);
        let seen: Vec<bool> = mask.iter().map(|&m| m < 0.5).collect();
        let unseen: Vec<bool> = seen.iter().map(|&v| !v).collect();
        vis_psnr.push(psnr_where(&s.rgb, &b.rgb, &seen));
        if unseen.iter().any(|&u| u) {
            mask_psnr.push(psnr_where(&s.rgb, &b.rgb, &unseen));
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (pv, pm) = (mean(&vis_psnr), mean(&mask_psnr));
    eprintln!("stage 2 against the BaseNeRF: visible {pv:.2} dB, masked {pm:.2} dB");
    assert!(
        pv > 24.0,
        "the visible region moved: {pv:.2} dB from the BaseNeRF"
    );
    assert!(
        pm < pv,
        "the masked region ({pm:.2} dB) should change more than the visible"
    );

    // Resume at the stage-2 boundary: the same result.
    let b = dir.join("b");
    copy_dir(&a, &b);
    let mut man = Manifest::load(&b).unwrap().unwrap();
    man.stages.retain(|s| s.name != "stage2-harmonic");
    man.save(&b).unwrap();
    std::fs::remove_dir_all(b.join("stage2-harmonic")).unwrap();
    let o = Options {
        resume: true,
        ..options(&b, &base)
    };
    let mut rec = Record::default();
    extrapolate(ctx, &o, &mut rec).unwrap();
    assert!(rec
        .notes
        .iter()
        .any(|n| n.contains("visibility: done, skipped")));
    let same = agreement(&a, &b, &loaded.split.test);
    eprintln!("resumed at the boundary: {same:.2} dB from the uninterrupted run");
    assert!(
        same > 35.0,
        "resumed at the boundary: {same:.2} dB from the uninterrupted run"
    );

    // A crash inside stage 2's second round: the resumed run keeps round 1 and ends the same.
    let c = dir.join("c");
    copy_dir(&b, &c);
    let mut man = Manifest::load(&c).unwrap().unwrap();
    man.stages.retain(|s| s.name != "stage2-harmonic");
    man.save(&c).unwrap();
    std::fs::remove_dir_all(c.join("stage2-harmonic")).unwrap();
    let crash = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let mut rec = Record {
            panic_at: Some(3),
            ..Record::default()
        };
        let o = Options {
            resume: true,
            ..options(&c, &base)
        };
        let _ = extrapolate(ctx, &o, &mut rec);
    }));
    assert!(crash.is_err(), "the simulated crash did not happen");
    let state = std::fs::read_to_string(c.join("stage2-harmonic/round.json")).unwrap();
    assert!(state.contains("\"rounds_done\":1"), "{state}");
    let mut rec = Record::default();
    let o = Options {
        resume: true,
        ..options(&c, &base)
    };
    extrapolate(ctx, &o, &mut rec).unwrap();
    assert!(
        rec.notes
            .iter()
            .any(|n| n.contains("resuming after round 1")),
        "{:?}",
        rec.notes
    );
    assert_eq!(
        load_checkpoint(&c.join("stage2-harmonic")).unwrap().step,
        100
    );
    let same = agreement(&a, &c, &loaded.split.test);
    eprintln!("resumed after a crash: {same:.2} dB from the uninterrupted run");
    assert!(
        same > 35.0,
        "resumed after a crash: {same:.2} dB from the uninterrupted run"
    );

    // Refusals: an existing run without --resume; another scene; other stage settings.
    let err = |o: Options| -> String {
        format!(
            "{:#}",
            extrapolate(ctx, &o, &mut Record::default()).unwrap_err()
        )
    };
    let e1 = err(options(&a, &base));
    assert!(e1.contains("already holds an extrapolate run"), "{e1}");
    let other = dir.join("other");
    extranerf_nerf::demo::write_demo_scene(&other, 32, 24).unwrap();
    let e2 = err(Options {
        resume: true,
        scene: Some(scene(&other)),
        base: BaseSpec {
            from: None,
            budget: 60.0,
        },
        ..options(&a, &base)
    });
    assert!(e2.contains("another scene"), "{e2}");
    let mut o = options(&a, &base);
    o.resume = true;
    o.stage2.rounds = 3;
    let e3 = err(o);
    assert!(e3.contains("stage2-harmonic.loop.rounds: 2 -> 3"), "{e3}");
    let mut o = options(&a, &base);
    o.resume = true;
    o.vis.threshold = 0.7;
    let e4 = err(o);
    assert!(e4.contains("visibility.settings.threshold"), "{e4}");

    // `eval` on the run: a row per variant.
    let t = extranerf_extrapolate::eval::compare(&a, None).unwrap();
    let rows: Vec<&str> = t.rows.iter().map(|r| r.variant.as_str()).collect();
    assert_eq!(rows, ["base", "stage2-harmonic"]);
    assert!(t
        .rows
        .iter()
        .all(|r| r.psnr.is_finite() && r.psnr_visible.is_some()));
    assert_no_validation_messages(ctx);
    let _ = std::fs::remove_dir_all(&dir);
}
