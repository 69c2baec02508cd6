//! The ExtraNeRF pipeline (`extranerf extrapolate`) on the demo scene at a small size: every
//! stage runs, the visible region stays close to the BaseNeRF while the masked one changes,
//! a resumed run (at a stage boundary, or after a crash inside stage 2) ends where an
//! uninterrupted one does, and run folders made from another scene or other settings are
//! refused; stage 3 (the enhancer's data, the enhancer, the enhancement loop) likewise.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::path::Path;

use extranerf_diffusion::device::Backend;
use extranerf_diffusion::enhancer::EnhancerSpec;
use extranerf_extrapolate::inpaint::Fill;
use extranerf_extrapolate::inpaint::InpainterKind;
use extranerf_extrapolate::manifest::Manifest;
use extranerf_extrapolate::rounds::Stage2Spec;
use extranerf_extrapolate::run::{extrapolate, Options};
use extranerf_extrapolate::stage::VirtualSpec;
use extranerf_extrapolate::stage3::{
    check_triplets, collector_views, EnhancerCheck, Stage3Enhancer, Stage3Gate, Stage3Spec,
    Triplets, CHECK_FILE,
};
use extranerf_extrapolate::stages::{BaseSpec, FlythroughSpec, FrameSize};
use extranerf_extrapolate::visibility::VisSettings;
use extranerf_extrapolate::ExtrapolateError;
use extranerf_nerf::cameras::Trajectory;
use extranerf_nerf::data::load_image;
use extranerf_nerf::data::split::SplitKind;
use extranerf_nerf::image_ops::unsharp;
use extranerf_nerf::model::{ModelConfig, ProposalConfig, Sampler};
use extranerf_nerf::run::training_views;
use extranerf_nerf::run::{load_checkpoint, RunConfig};
use extranerf_nerf::train::{train_loop, Progress, Reporter, TrainRun, Unit};
use extranerf_nerf::trainer::TrainConfig;
use extranerf_nerf::views::ViewKind;
use extranerf_tests::{assert_no_validation_messages, demo_scene_spec, engine, scratch_dir};
use rusty_fork::rusty_fork_test;

/// Keeps the notes; panics at the `panic_at`-th training progress of the stage named
/// `crash_in` (default stage 2's: a crash).
#[derive(Default)]
struct Record {
    notes: Vec<String>,
    stage2_steps: usize,
    panic_at: Option<usize>,
    crash_in: Option<&'static str>,
    stage: String,
}

impl Reporter for Record {
    fn note(&mut self, line: &str) {
        self.notes.push(line.to_string());
    }

    fn progress(&mut self, p: &Progress) {
        let crash_in = self.crash_in.unwrap_or("stage2");
        if self.stage.starts_with(crash_in) && p.unit == Unit::Steps {
            self.stage2_steps += 1;
            if Some(self.stage2_steps) == self.panic_at {
                panic!("simulated crash inside {crash_in}");
            }
        }
    }

    fn stage(&mut self, name: &str) {
        self.stage = name.to_string();
    }
}

impl Record {
    /// Every one of `want` is part of a note.
    fn assert_notes(&self, want: &[&str]) {
        for note in want {
            assert!(
                self.notes.iter().any(|n| n.contains(note)),
                "{note}: {:?}",
                self.notes
            );
        }
    }
}

/// Runs `o` with a simulated crash inside stage3-harmonic's second round, and checks that the
/// run in `run` kept its first.
fn crash_in_stage3_round_two(ctx: &extranerf_gpu::Context, o: &Options, run: &Path) {
    let crash = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let mut rec = Record {
            panic_at: Some(2),
            crash_in: Some("stage3-harmonic"),
            ..Record::default()
        };
        let _ = extrapolate(ctx, o, &mut rec);
    }));
    assert!(crash.is_err(), "the simulated crash did not happen");
    let state = std::fs::read_to_string(run.join("stage3-harmonic/round.json")).unwrap();
    assert!(state.contains("\"rounds_done\":1"), "{state}");
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
            size: FrameSize::Downscale(2),
            fps: 12.0,
        },
        stage3: None,
        resume: false,
        redo: Vec::new(),
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

/// The demo scene at 48x36 in `dir/scene` and a small BaseNeRF of it in `dir/base`.
/// The pixels of held-out view `view` that its stored visibility map (`RUN/visibility/maps`
/// in `st`) leaves out of the inpainting mask, at the default settings.
fn seen_pixels(st: &extranerf_nerf::safetensors::SafeTensors, view: usize) -> Vec<bool> {
    let map = extranerf_extrapolate::visibility::load_map(
        st,
        Path::new("maps"),
        &format!("test_{view:03}"),
    )
    .unwrap();
    VisSettings::default()
        .mask(&map)
        .iter()
        .map(|&m| m < 0.5)
        .collect()
}

fn small_base(
    ctx: &extranerf_gpu::Context,
    dir: &Path,
) -> (std::path::PathBuf, std::path::PathBuf) {
    small_base_sampled(ctx, dir, Sampler::Uniform)
}

/// [`small_base`] with the rays sampled by `sampler`.
fn small_base_sampled(
    ctx: &extranerf_gpu::Context,
    dir: &Path,
    sampler: Sampler,
) -> (std::path::PathBuf, std::path::PathBuf) {
    small_base_of(ctx, dir, sampler, SplitKind::Extrapolation)
}

/// [`small_base_sampled`] trained on the demo scene's views of `split`.
fn small_base_of(
    ctx: &extranerf_gpu::Context,
    dir: &Path,
    sampler: Sampler,
    split: SplitKind,
) -> (std::path::PathBuf, std::path::PathBuf) {
    let scene_dir = dir.join("scene");
    extranerf_nerf::demo::write_demo_scene(&scene_dir, 48, 36).unwrap();
    // A small BaseNeRF.
    let base = dir.join("base");
    let cfg = RunConfig {
        scene: extranerf_nerf::run::SceneSpec {
            split,
            ..demo_scene_spec(scene_dir.to_path_buf())
        },
        model: ModelConfig {
            levels: 6,
            log2_table: 12,
            max_res: 128,
            sampler,
            ..ModelConfig::default()
        },
        train: TrainConfig {
            steps: 300,
            decay_steps: 300,
            // The batch this test's thresholds were set with (the default is now 1024).
            rays: 256,
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
        eval_views: extranerf_nerf::train::ViewSet::Test,
        budget: None,
    };
    train_loop(ctx, &cfg, &run, None, None, &mut Record::default()).unwrap();
    (scene_dir, base)
}

#[test]
fn the_pipeline_runs_resumes_and_refuses_other_scenes_and_settings() {
    let e = engine();
    let ctx = &e.ctx;
    let dir = scratch_dir("extrapolate");
    let (scene_dir, base) = small_base(ctx, &dir);

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
            "flythrough-stage2-harmonic",
            "flythrough-video"
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
    // The fly-through: each field's frames at half the virtual size, the variant's unlike the
    // BaseNeRF's, and the video of the two side by side under their labels, at its rate.
    let frame = |name: &str, k: usize| {
        image::open(a.join(format!("flythrough/{name}/frame_{k:03}.png")))
            .unwrap()
            .to_rgb8()
    };
    let (fb, fs) = (frame("base", 2), frame("stage2-harmonic", 2));
    assert_eq!(fb.dimensions(), (24, 18));
    assert_ne!(fb.as_raw(), fs.as_raw());
    let video = extranerf_nerf::video::read_video(&a.join("flythrough/flythrough.mp4")).unwrap();
    let layout = extranerf_extrapolate::montage::Layout::new(2, 24, 18).unwrap();
    assert_eq!((video.width, video.height), layout.size());
    assert_eq!(video.frames.len(), 3);
    assert!((video.fps - 12.0).abs() < 1e-9, "{} fps", video.fps);
    for (t, name) in ["base", "stage2-harmonic"].iter().enumerate() {
        let (x0, y0) = layout.origin(t);
        for k in 0..3 {
            let png = frame(name, k);
            // The frame's mean error against the video's tile shifted by (dx, dy).
            let err = |dx: i32, dy: i32| {
                let mut e = 0.0;
                for y in 1..17u32 {
                    for x in 1..23u32 {
                        let vx = (x0 + x) as i32 + dx;
                        let vy = (y0 + layout.band + y) as i32 + dy;
                        let o = ((vy as u32 * video.width + vx as u32) * 3) as usize;
                        for c in 0..3 {
                            let v = video.frames[k][o + c] as f64;
                            e += (v - png.get_pixel(x, y)[c] as f64).abs();
                        }
                    }
                }
                e / (22.0 * 16.0 * 3.0)
            };
            let here = err(0, 0);
            eprintln!("{name} frame {k}: {here:.2}/255 from its PNG in the video");
            assert!(here < 16.0, "{name} frame {k}: {here}/255 from its PNG");
            for (dx, dy) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
                assert!(
                    here < err(dx, dy),
                    "{name} frame {k} fits the video better shifted by ({dx}, {dy})"
                );
            }
        }
        // Its label: light pixels in the band above it.
        let lit = (0..layout.band)
            .flat_map(|y| (0..24).map(move |x| (x, y)))
            .filter(|&(x, y)| {
                video.frames[0][(((y0 + y) * video.width + x0 + x) * 3) as usize] > 128
            })
            .count();
        assert!(lit > 5, "{name}'s label: {lit} light pixels");
    }
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
    let loaded = demo_scene_spec(scene_dir.to_path_buf()).load().unwrap();
    let st = extranerf_nerf::safetensors::SafeTensors::read(&a.join("visibility/maps.safetensors"))
        .unwrap();
    let (mut vis_psnr, mut mask_psnr) = (Vec::new(), Vec::new());
    for &i in &loaded.split.test {
        let b = load_image(&a.join(format!("visibility/test_{i:03}_base.png"))).unwrap();
        let s = load_image(&a.join(format!("stage2-harmonic/test_{i:03}.png"))).unwrap();
        let seen = seen_pixels(&st, i);
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

    // Stage 2 redone (`--redo`) on a copy of the finished run: its old rounds are discarded,
    // not resumed, the fly-through that reads it runs again, and the result is the same.
    let b = dir.join("b");
    copy_dir(&a, &b);
    // A frame the fly-through to redo made earlier goes with it.
    let stale = b.join("flythrough/stage2-harmonic/frame_099.png");
    std::fs::copy(b.join("flythrough/stage2-harmonic/frame_000.png"), &stale).unwrap();
    let o = Options {
        resume: true,
        redo: vec!["stage2-harmonic".into()],
        ..options(&b, &base)
    };
    let mut rec = Record::default();
    extrapolate(ctx, &o, &mut rec).unwrap();
    let has = |s: &str| rec.notes.iter().any(|n| n.contains(s));
    assert!(has("visibility: done, skipped"), "{:?}", rec.notes);
    assert!(
        has("stage stage2-harmonic: redone (--redo)"),
        "{:?}",
        rec.notes
    );
    assert!(
        has("stage flythrough-stage2-harmonic: runs again after stage2-harmonic"),
        "{:?}",
        rec.notes
    );
    assert!(
        has("stage flythrough-video: runs again after flythrough-stage2-harmonic"),
        "{:?}",
        rec.notes
    );
    assert!(!has("resuming after round"), "{:?}", rec.notes);
    assert!(has("flythrough-base: done, skipped"), "{:?}", rec.notes);
    assert!(
        !stale.exists(),
        "the redone fly-through kept an earlier frame"
    );
    assert!(b.join("flythrough/stage2-harmonic/frame_002.png").is_file());
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
        scene: Some(demo_scene_spec(other.to_path_buf())),
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
    let t =
        extranerf_extrapolate::eval::compare(&a, None, None, None, &mut Record::default()).unwrap();
    let rows: Vec<&str> = t.rows.iter().map(|r| r.variant.as_str()).collect();
    assert_eq!(rows, ["base", "stage2-harmonic"]);
    assert!(t
        .rows
        .iter()
        .all(|r| r.psnr.is_finite() && r.psnr_visible.is_some()));
    assert!(t.truth_masks.is_none() && t.rows[0].psnr_not_visible_exact.is_none());
    // With the scene's exact visibility: both regions scored for every variant, the masks'
    // share as the generator's own visibility gives it.
    let gt = scene_dir.join(extranerf_nerf::demo::GT_VISIBILITY_DIR);
    let t = extranerf_extrapolate::eval::compare(&a, None, None, Some(&gt), &mut Record::default())
        .unwrap();
    let m = t.truth_masks.as_ref().unwrap();
    assert_eq!(m.views, (6..14).collect::<Vec<_>>());
    let unseen: f64 = (6..14)
        .map(|i| {
            let s = extranerf_nerf::demo::demo_seen(i, 48, 36, 2);
            s.iter().filter(|&&v| !v).count() as f64 / s.len() as f64
        })
        .sum::<f64>()
        / 8.0;
    assert!(
        (m.not_visible_fraction - unseen).abs() < 1e-9,
        "{m:?} against {unseen}"
    );
    assert!(unseen > 0.01 && unseen < 0.99, "{unseen}");
    assert!(t
        .rows
        .iter()
        .all(|r| r.psnr_not_visible_exact.is_some_and(f64::is_finite)
            && r.psnr_visible_exact.is_some_and(f64::is_finite)));
    assert!(t.markdown().contains("PSNR not visible (exact)"));
    // KID over no subsets: the metric refuses it.
    let net = extranerf_extrapolate::eval::inception::Inception::load(
        &extranerf_tests::inception_weights(),
        &burn::tensor::Device::flex(),
    )
    .unwrap();
    let kid = extranerf_extrapolate::eval::KidEval {
        net: &net,
        spec: extranerf_extrapolate::eval::KidSpec {
            crops: 4,
            crop_size: 8,
            subsets: 0,
            ..Default::default()
        },
    };
    let e =
        extranerf_extrapolate::eval::compare(&a, None, Some(&kid), None, &mut Record::default())
            .unwrap_err();
    assert!(matches!(e, ExtrapolateError::Metrics(_)), "{e:?}");
    // A folder that is missing, or holds no mask of a held-out view, or a mask of the wrong
    // size: clear errors naming it.
    let e = |d: &Path| {
        format!(
            "{:#}",
            extranerf_extrapolate::eval::compare(&a, None, None, Some(d), &mut Record::default())
                .unwrap_err()
        )
    };
    let missing = dir.join("no-such-masks");
    assert!(e(&missing).contains("no such folder"), "{}", e(&missing));
    let empty = dir.join("empty-masks");
    std::fs::create_dir_all(&empty).unwrap();
    assert!(e(&empty).contains("view_06.png"), "{}", e(&empty));
    extranerf_nerf::run::write_png(&empty.join("view_06.png"), 8, 8, &[1.0; 8 * 8 * 3]).unwrap();
    assert!(
        e(&empty).contains("a 8x8 mask for a 48x36 view"),
        "{}",
        e(&empty)
    );
    assert_no_validation_messages(ctx);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Every variant of [`ExtrapolateError`] reached through the public API, so that a caller can
/// tell a bad setting from a run folder that refused to resume, and a failed stage (and which
/// one) from the scene, the device, training, an inpainter or a model. (`Metrics` is reached
/// on a finished run in the pipeline's test above.)
#[test]
fn each_error_variant_is_reached_through_the_public_api() {
    let e = engine();
    let ctx = &e.ctx;
    let dir = scratch_dir("extrapolate-errors");
    let (scene_dir, base) = small_base(ctx, &dir);
    let fail = |o: &Options| extrapolate(ctx, o, &mut Record::default()).unwrap_err();
    let in_stage = |e: &ExtrapolateError, name: &str| {
        assert_eq!(e.stage(), Some(name), "{e}");
        assert!(e.to_string().starts_with(&format!("stage {name}: ")), "{e}");
    };

    // A setting that cannot work.
    let mut o = options(&dir.join("usage"), &base);
    o.inpainters.clear();
    let e = fail(&o);
    assert!(matches!(e, ExtrapolateError::Usage(_)), "{e:?}");
    assert!(e.to_string().contains("--inpainter"), "{e}");

    // A folder that holds a run, without --resume; --resume where there is none.
    let held = dir.join("held");
    std::fs::create_dir_all(&held).unwrap();
    Manifest::new(load_checkpoint(&base).unwrap().config.scene)
        .save(&held)
        .unwrap();
    let e = fail(&options(&held, &base));
    assert!(
        matches!(&e, ExtrapolateError::Resume { dir, .. } if dir == &held),
        "{e:?}"
    );
    // A run folder another process writes: its lock names the holder.
    let busy = dir.join("busy");
    let lock = extranerf_gpu::files::RunLock::acquire(&busy).unwrap();
    let e = fail(&options(&busy, &base));
    assert!(
        matches!(&e, ExtrapolateError::Locked { dir, .. } if dir == &busy),
        "{e:?}"
    );
    assert!(
        e.to_string()
            .contains(&format!("in use by process {}", std::process::id())),
        "{e}"
    );
    drop(lock);
    let e = fail(&Options {
        resume: true,
        ..options(&dir.join("nothing"), &base)
    });
    assert!(matches!(e, ExtrapolateError::Resume { .. }), "{e:?}");
    assert!(e.to_string().contains("drop --resume"), "{e}");

    // A run folder that cannot be made: a file stands where it would be.
    std::fs::write(dir.join("file"), b"x").unwrap();
    let e = fail(&options(&dir.join("file").join("run"), &base));
    assert!(
        matches!(
            &e,
            ExtrapolateError::Io {
                what: "creating",
                ..
            }
        ),
        "{e:?}"
    );

    // A manifest that is not one.
    let bad = dir.join("bad");
    std::fs::create_dir_all(&bad).unwrap();
    std::fs::write(Manifest::path(&bad), b"{\"stages\": 3}").unwrap();
    let e = Manifest::load(&bad).unwrap_err();
    assert!(
        matches!(&e, ExtrapolateError::Malformed { path, .. } if path == &Manifest::path(&bad)),
        "{e:?}"
    );

    // `eval` on a folder that holds no run.
    let e = extranerf_extrapolate::eval::compare(&dir, None, None, None, &mut Record::default())
        .unwrap_err();
    assert!(matches!(e, ExtrapolateError::Incomplete { .. }), "{e:?}");

    // A scene that is not there: refused before any stage (its cameras and images identify
    // the run), and no run folder is left.
    let fresh = |out: &str, scene: &Path, budget: f64| Options {
        scene: Some(demo_scene_spec(scene.to_path_buf())),
        base: BaseSpec { from: None, budget },
        ..options(&dir.join(out), &base)
    };
    let e = fail(&fresh("no-scene", &dir.join("no-such-scene"), 60.0));
    assert_eq!(e.stage(), None, "{e}");
    assert!(matches!(e, ExtrapolateError::Run(_)), "{e:?}");
    assert!(!Manifest::path(&dir.join("no-scene")).exists());
    // A budget the training refuses.
    let e = fail(&fresh("no-budget", &scene_dir, 0.0));
    in_stage(&e, "base");
    assert!(matches!(e.cause(), ExtrapolateError::Train(_)), "{e:?}");

    // Transmittance volumes past what a device buffer holds.
    let mut o = options(&dir.join("volume"), &base);
    o.vis.volume_res = 100_000;
    let e = fail(&o);
    in_stage(&e, "visibility");
    assert!(matches!(e.cause(), ExtrapolateError::Gpu(_)), "{e:?}");

    // Every pixel of the virtual views to inpaint: the harmonic fill has nothing to start from.
    let mut o = options(&dir.join("whole-mask"), &base);
    o.vis.threshold = 1.0;
    o.vis.min_opacity = 1.0;
    let e = fail(&o);
    in_stage(&e, "stage2-harmonic");
    let ExtrapolateError::Stage { error, .. } = &e else {
        panic!("{e:?}");
    };
    assert!(
        matches!(&**error, ExtrapolateError::View { view, .. } if view == "virtual view 0, round 0"),
        "{e:?}"
    );
    assert!(matches!(e.cause(), ExtrapolateError::Inpaint(_)), "{e:?}");

    // A learning rate that blows the field up.
    let mut o = options(&dir.join("diverged"), &base);
    o.stage2.lr = 1e30;
    let e = fail(&o);
    in_stage(&e, "stage2-harmonic");
    assert!(
        matches!(e.cause(), ExtrapolateError::Diverged { dir: d, .. } if d == &dir.join("diverged/stage2-harmonic")),
        "{e:?}"
    );

    // Stage 3's training data in a file that is not a tensor file.
    let data = dir.join("triplets");
    std::fs::create_dir_all(&data).unwrap();
    std::fs::write(
        data.join(extranerf_extrapolate::stage3::TRIPLETS_FILE),
        b"not",
    )
    .unwrap();
    let e = Triplets::load(&data).unwrap_err();
    assert!(matches!(e, ExtrapolateError::Data(_)), "{e:?}");

    // A diffusion model that is not there.
    let spec = extranerf_extrapolate::inpaint::DiffusionSpec {
        model: dir.join("no-such-model"),
        lora: None,
        steps: 2,
        backend: Backend::Cpu,
    };
    let e = extranerf_extrapolate::inpaint::build_inpainter(
        ctx,
        InpainterKind::DiffusionBase,
        Some(&spec),
        &mut Record::default(),
    )
    .err()
    .unwrap();
    assert!(matches!(e, ExtrapolateError::Diffusion(_)), "{e:?}");
    assert!(e.to_string().contains("no-such-model"), "{e}");
    assert_no_validation_messages(ctx);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The pipeline on a BaseNeRF trained with the proposal sampler: the visibility maps and every
/// render take its samples, stage 2 trains with it (its checkpoint keeps it), the masks agree
/// with the demo's exact visibility and the visible region stays close to the BaseNeRF as on
/// uniform strata.
#[test]
fn the_pipeline_runs_on_a_proposal_base() {
    let e = engine();
    let ctx = &e.ctx;
    let dir = scratch_dir("extrapolate-proposal");
    let sampler = Sampler::Proposal(ProposalConfig {
        samples: 32,
        levels: 4,
        log2_table: 12,
        min_res: 8,
        max_res: 64,
        ..ProposalConfig::default()
    });
    let (scene_dir, base) = small_base_sampled(ctx, &dir, sampler.clone());
    let a = dir.join("a");
    let m = extrapolate(ctx, &options(&a, &base), &mut Record::default()).unwrap();
    assert!(m.stages.iter().all(|s| s.done));
    assert_eq!(
        load_checkpoint(&a.join("stage2-harmonic"))
            .unwrap()
            .config
            .model
            .sampler,
        sampler
    );
    let vis: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(a.join("visibility/visibility.json")).unwrap(),
    )
    .unwrap();
    let acc = vis["exact_mean"]["accuracy"].as_f64().unwrap();
    eprintln!("proposal base: masks against the exact visibility, accuracy {acc:.3}");
    assert!(acc > 0.65, "accuracy {acc}");
    let loaded = demo_scene_spec(scene_dir.to_path_buf()).load().unwrap();
    let st = extranerf_nerf::safetensors::SafeTensors::read(&a.join("visibility/maps.safetensors"))
        .unwrap();
    let mut vis_psnr = 0.0;
    for &i in &loaded.split.test {
        let b = load_image(&a.join(format!("visibility/test_{i:03}_base.png"))).unwrap();
        let s = load_image(&a.join(format!("stage2-harmonic/test_{i:03}.png"))).unwrap();
        let seen = seen_pixels(&st, i);
        vis_psnr += psnr_where(&s.rgb, &b.rgb, &seen) / loaded.split.test.len() as f64;
    }
    eprintln!("proposal base: stage 2 against the BaseNeRF in the visible region {vis_psnr:.2} dB");
    assert!(
        vis_psnr > 24.0,
        "the visible region moved: {vis_psnr:.2} dB"
    );
    assert_no_validation_messages(ctx);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A run whose split holds no view out (`--split all`): the visibility stage and every variant
/// render the training views (`train_NNN`), `eval` scores them saying that none is held out,
/// and the report shows them beside their photos.
#[test]
fn a_run_that_holds_no_view_out_shows_and_scores_its_training_views() {
    use extranerf_extrapolate::eval::{compare, report::write_report};
    let e = engine();
    let ctx = &e.ctx;
    let dir = scratch_dir("extrapolate-split-all");
    let (scene_dir, base) = small_base_of(ctx, &dir, Sampler::Uniform, SplitKind::All);
    let run = dir.join("run");
    let m = extrapolate(ctx, &options(&run, &base), &mut Record::default()).unwrap();
    assert!(m.stages.iter().all(|s| s.done));
    let loaded = extranerf_nerf::run::SceneSpec {
        split: SplitKind::All,
        ..demo_scene_spec(scene_dir)
    }
    .load()
    .unwrap();
    assert!(loaded.split.test.is_empty());
    let views = loaded.split.train.clone();
    assert!(views.len() >= 6, "{views:?}");
    for &i in &views {
        for f in [
            format!("visibility/train_{i:03}_base.png"),
            format!("visibility/train_{i:03}_mask.png"),
            format!("stage2-harmonic/train_{i:03}.png"),
        ] {
            assert!(run.join(&f).is_file(), "{f} missing");
        }
    }
    let names: Vec<String> = std::fs::read_dir(run.join("stage2-harmonic"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(!names.iter().any(|n| n.starts_with("test_")), "{names:?}");
    let t = compare(&run, None, None, None, &mut Record::default()).unwrap();
    assert!(!t.held_out);
    assert_eq!(t.views, views);
    assert_eq!(t.rows.len(), 2, "base and stage2-harmonic");
    for r in &t.rows {
        // A field fitted to these very views renders them well above chance.
        assert!(
            r.psnr.is_finite() && r.psnr > 15.0,
            "{}: {}",
            r.variant,
            r.psnr
        );
    }
    assert!(
        t.notes.iter().any(|n| n.contains("No held-out view")),
        "{:?}",
        t.notes
    );
    let html = std::fs::read_to_string(write_report(&run, Some(&t)).unwrap()).unwrap();
    assert!(html.contains("<h2>Training views</h2>") && !html.contains("Held-out views"));
    assert_eq!(html.matches("<h3>view ").count(), views.len());
    assert!(
        !html.contains("missing</div>"),
        "a render is missing from the report"
    );
    assert_no_validation_messages(ctx);
    let _ = std::fs::remove_dir_all(&dir);
}

fn stage3_spec() -> Stage3Spec {
    Stage3Spec {
        data_rounds: 2,
        data_steps_per_round: 25,
        base_checkpoints: vec![30],
        enhancer: EnhancerSpec {
            channels: vec![8, 16],
            steps: 60,
            batch: 4,
            crop: 16,
            lr: 3e-3,
            ..EnhancerSpec::default()
        },
        rounds: 2,
        steps_per_round: 25,
        ddim_steps: 3,
        backend: Backend::Cpu,
        // The loop itself is under test here; the gate has its own part below.
        gate: Stage3Gate::Off,
        ..Stage3Spec::default()
    }
}

/// Stage 3 on the demo scene at a small size: the data collector's supervision (the
/// inpainter's fill inside each training view's pseudo mask, the photo outside), its triplets
/// written and reloaded, the enhancer trained on them, the stage-3 loop run, resumed after a
/// crash inside it with the data and the enhancer reused, the visible region kept close to
/// stage 2's, and `eval`'s rows.
fn stage_three_enhances_resumes_and_keeps_the_visible_region_in_this_process() {
    let e = engine();
    let ctx = &e.ctx;
    let dir = scratch_dir("extrapolate_stage3");
    let (scene_dir, base) = small_base(ctx, &dir);
    let opts = |out: &Path| Options {
        stage3: Some(stage3_spec()),
        flythrough: FlythroughSpec {
            frames: 2,
            size: FrameSize::Width(30),
            fps: 10.0,
        },
        ..options(out, &base)
    };
    let a = dir.join("a");
    let m = extrapolate(ctx, &opts(&a), &mut Record::default()).unwrap();
    let names: Vec<&str> = m.stages.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "base",
            "visibility",
            "stage2-harmonic",
            "stage3-data",
            "stage3-enhancer",
            "stage3-harmonic",
            "flythrough-base",
            "flythrough-stage2-harmonic",
            "flythrough-stage3-harmonic",
            "flythrough-video"
        ]
    );
    for f in [
        "stage3-data/triplets.safetensors",
        "stage3-data/pseudo_mask_000.png",
        "stage3-enhancer/enhancer.json",
        "stage3-enhancer/model/model_index.json",
        "stage3-harmonic/round_01/virtual_002.png",
        "stage3-harmonic/checkpoint.safetensors",
        "flythrough/stage3-harmonic/frame_001.png",
        "flythrough/flythrough.mp4",
    ] {
        assert!(a.join(f).exists(), "{f} missing");
    }

    // The triplets: per training view a fresh field's, the BaseNeRF's and one per data round,
    // the masks of the inpainting-supervised ones the view's pseudo mask; they reload as saved.
    let loaded = demo_scene_spec(scene_dir.to_path_buf()).load().unwrap();
    let views = loaded.split.train.len();
    let tr = Triplets::load(&a.join("stage3-data")).unwrap();
    assert_eq!(tr.photos.len(), views);
    assert_eq!(tr.entries.len(), views * 4);
    let sources: Vec<&str> = tr.entries.iter().map(|e| e.source.as_str()).collect();
    for s in ["fresh@30", "base", "inpainted@0", "inpainted@1"] {
        assert_eq!(sources.iter().filter(|&&x| x == s).count(), views, "{s}");
    }
    for (e, (_, mask)) in tr.entries.iter().zip(&tr.renders) {
        if e.source.starts_with("inpainted") {
            assert_eq!(mask, &tr.masks[e.slot], "{}", e.key);
        } else {
            assert!(mask.iter().all(|&m| m == 0.0), "{}", e.key);
        }
    }
    let masked = tr.masks.iter().flatten().filter(|&&m| m >= 0.5).count();
    let total = tr.masks.iter().map(Vec::len).sum::<usize>();
    eprintln!(
        "pseudo masks: {:.1}% of the training views",
        100.0 * masked as f64 / total as f64
    );
    assert!(masked > 0 && masked < total, "{masked} of {total}");
    let copy = dir.join("triplets_copy");
    std::fs::create_dir_all(&copy).unwrap();
    tr.save(&copy).unwrap();
    let again = Triplets::load(&copy).unwrap();
    assert_eq!(again.entries, tr.entries);
    assert_eq!(again.renders, tr.renders);
    assert_eq!(again.photos, tr.photos);

    // An enhancer trained on the triplets of every training view but the first lowers the
    // LPIPS of an under-fitted render of that view against its photo by at least 10%.
    let held = Triplets {
        photos: tr.photos.clone(),
        entries: tr.entries.iter().filter(|e| e.slot != 0).cloned().collect(),
        renders: tr
            .entries
            .iter()
            .zip(&tr.renders)
            .filter(|(e, _)| e.slot != 0)
            .map(|(_, r)| r.clone())
            .collect(),
        ..tr.clone()
    };
    let images: Vec<_> = held
        .train_images()
        .into_iter()
        .filter(|im| !im.guides.is_empty())
        .collect();
    let edir = dir.join("enhancer_held_out");
    let spec = EnhancerSpec {
        channels: vec![16, 32],
        steps: 200,
        batch: 8,
        crop: 24,
        lr: 5e-3,
        max_strength: 0.3,
        ..EnhancerSpec::default()
    };
    let dev = burn::tensor::Device::flex();
    extranerf_diffusion::enhancer::train_enhancer(&images, &spec, &edir, &dev, &mut |_| {})
        .unwrap();
    let pipe = extranerf_diffusion::enhancer::load(&edir, &dev).unwrap();
    let lp = extranerf_nerf::train::lpips_alex(Some(
        &extranerf_tests::shared_data().join("../models/lpips"),
    ))
    .unwrap();
    let (tw, th) = (tr.width, tr.height);
    let score = |source: &str| {
        let k = tr
            .entries
            .iter()
            .position(|e| e.slot == 0 && e.source == source)
            .unwrap();
        let enhanced = pipe
            .model
            .enhance_image(
                &tr.renders[k].0,
                None,
                tw,
                th,
                0,
                &extranerf_diffusion::inpaint::SampleSettings {
                    strength: 0.3,
                    steps: 6,
                    guidance: 1.0,
                    keep_known: false,
                },
                &dev,
            )
            .unwrap();
        let d = |img: &[f32]| {
            lp.distance(img, &tr.photos[0], tw as u32, th as u32)
                .unwrap()
        };
        let (before, after) = (d(&tr.renders[k].0), d(&enhanced.rgb));
        eprintln!(
            "held-out training view 0, {source} render: LPIPS-alex {before:.4}, enhanced {after:.4}"
        );
        (before, after)
    };
    // The under-fitted field's blur is what it learns to undo. (The BaseNeRF itself fits this
    // training view to LPIPS 0.02, closer than the small enhancer's own noise: not asserted.)
    let (before, after) = score("fresh@30");
    assert!(after < 0.9 * before, "LPIPS {before:.4} -> {after:.4}");
    score("base");

    // The collector's supervision of one view: inside the pseudo mask the photo weighs 0 and
    // the fill weighs w(t); outside the photo keeps its weight and the fill weighs 0.
    let cfg = load_checkpoint(&base).unwrap().config;
    let captured = training_views(&cfg.scene, &loaded, &cfg.model).unwrap();
    let v = &captured[0];
    let (w, h) = (v.camera.width as usize, v.camera.height as usize);
    let mask = tr.masks[0].clone();
    assert_eq!(
        mask.len(),
        w * h,
        "downscale 1: the masks are at the views' size"
    );
    let fill = Fill {
        rgb: vec![0.25; w * h * 3],
        depth: vec![0.5; w * h],
    };
    let (photo, virt) = collector_views(v, &mask, &v.camera, &fill, &mask, 0.8);
    let (pw, vw) = (photo.weight.unwrap(), virt.weight.unwrap());
    let vd = virt.depth.unwrap();
    for i in 0..w * h {
        let inside = mask[i] >= 0.5;
        assert_eq!(pw[i], if inside { 0.0 } else { 1.0 }, "photo weight {i}");
        assert_eq!(vw[i], if inside { 0.8 } else { 0.0 }, "fill weight {i}");
        assert_eq!(vd[i][1], if inside { 1.0 } else { 0.0 }, "fill depth {i}");
    }
    assert_eq!(photo.image.rgb, v.image.rgb);
    assert_eq!(virt.image.rgb, fill.rgb);
    assert_eq!(virt.kind, ViewKind::Virtual);

    // The visible region of the held-out views stays within the previous issue's bound of
    // stage 2's render.
    let st = extranerf_nerf::safetensors::SafeTensors::read(&a.join("visibility/maps.safetensors"))
        .unwrap();
    let mut vis_psnr = Vec::new();
    for &i in &loaded.split.test {
        let s2 = load_image(&a.join(format!("stage2-harmonic/test_{i:03}.png"))).unwrap();
        let s3 = load_image(&a.join(format!("stage3-harmonic/test_{i:03}.png"))).unwrap();
        let seen = seen_pixels(&st, i);
        vis_psnr.push(psnr_where(&s3.rgb, &s2.rgb, &seen));
    }
    let pv = vis_psnr.iter().sum::<f64>() / vis_psnr.len() as f64;
    eprintln!("stage 3 against stage 2: visible {pv:.2} dB");
    assert!(pv > 24.0, "stage 3 moved the visible region: {pv:.2} dB");

    // A crash inside stage 3's second round: the resumed run reuses the data and the enhancer,
    // keeps round 1, and ends close to the uninterrupted run.
    let c = dir.join("c");
    copy_dir(&a, &c);
    let mut man = Manifest::load(&c).unwrap().unwrap();
    man.stages
        .retain(|s| s.name != "stage3-harmonic" && s.name != "flythrough-stage3-harmonic");
    man.save(&c).unwrap();
    std::fs::remove_dir_all(c.join("stage3-harmonic")).unwrap();
    let o = Options {
        resume: true,
        ..opts(&c)
    };
    crash_in_stage3_round_two(ctx, &o, &c);
    let mut rec = Record::default();
    let o = Options {
        resume: true,
        ..opts(&c)
    };
    extrapolate(ctx, &o, &mut rec).unwrap();
    rec.assert_notes(&[
        "stage stage3-data: done, skipped",
        "stage stage3-enhancer: done, skipped",
        "stage3-harmonic: resuming after round 1",
    ]);
    let mut sum = 0.0;
    for &i in &loaded.split.test {
        let f = format!("stage3-harmonic/test_{i:03}.png");
        let (x, y) = (
            load_image(&a.join(&f)).unwrap(),
            load_image(&c.join(&f)).unwrap(),
        );
        sum += psnr_where(&x.rgb, &y.rgb, &vec![true; x.rgb.len() / 3]);
    }
    let same = sum / loaded.split.test.len() as f64;
    eprintln!("stage 3 resumed after a crash: {same:.2} dB from the uninterrupted run");
    assert!(
        same > 30.0,
        "resumed stage 3: {same:.2} dB from the uninterrupted run"
    );

    // Other stage-3 settings are refused on resume.
    let mut o = opts(&a);
    o.resume = true;
    o.stage3.as_mut().unwrap().enhancer.steps = 61;
    let err = format!(
        "{:#}",
        extrapolate(ctx, &o, &mut Record::default()).unwrap_err()
    );
    assert!(
        err.contains("stage3-enhancer.enhancer.steps: 60 -> 61"),
        "{err}"
    );
    // So are the loop's colour anchoring, smoothing, L1 core and seen-pixel weight, which a run
    // records only when they are not the defaults; out-of-range values are refused before
    // anything runs.
    for (anchor, smooth, core, visible, want) in [
        (3, 0, 0.0, 1.0, "anchor_radius"),
        (0, 2, 0.0, 1.0, "smooth_radius"),
        (0, 0, 0.1, 1.0, "l1_core"),
        (0, 0, 0.0, 0.0, "visible_weight"),
        (
            0,
            0,
            0.0,
            1.5,
            "--stage3-visible-weight 1.5: use a value in [0, 1]",
        ),
        (
            0,
            65,
            0.0,
            1.0,
            "--stage3-smooth 65: use a radius of at most 64 pixels",
        ),
        (
            0,
            0,
            -0.1,
            1.0,
            "--stage3-l1-core -0.1: use a colour error in [0, 1]",
        ),
    ] {
        let mut o = opts(&a);
        o.resume = true;
        let s3 = o.stage3.as_mut().unwrap();
        s3.anchor_radius = anchor;
        s3.smooth_radius = smooth;
        s3.l1_core = core;
        s3.visible_weight = visible;
        let err = format!(
            "{:#}",
            extrapolate(ctx, &o, &mut Record::default()).unwrap_err()
        );
        assert!(err.contains(want), "{err}");
    }

    // `eval`: stage 3's field is a row of its own, with both KID protocols (small crops: the
    // demo views are small).
    let net = extranerf_extrapolate::eval::inception::Inception::load(
        &extranerf_tests::inception_weights(),
        &burn::tensor::Device::flex(),
    )
    .unwrap();
    let spec = extranerf_extrapolate::eval::KidSpec {
        crops: 8,
        crop_size: 8,
        min_fraction: 0.25,
        subsets: 20,
        subset_size: 4,
        ..Default::default()
    };
    let kid = extranerf_extrapolate::eval::KidEval { net: &net, spec };
    let t =
        extranerf_extrapolate::eval::compare(&a, None, Some(&kid), None, &mut Record::default())
            .unwrap();
    let rows: Vec<&str> = t.rows.iter().map(|r| r.variant.as_str()).collect();
    assert_eq!(rows, ["base", "stage2-harmonic", "stage3-harmonic"]);
    // No stage was skipped; the table says what depth the BaseNeRF trained with.
    assert_eq!(t.notes, ["BaseNeRF depth targets: none"]);
    let report = t.kid.as_ref().unwrap();
    assert_eq!(report.crops_per_view.iter().sum::<usize>(), 8);
    assert_eq!(report.patch_subset_size, Some(4));
    for r in &t.rows {
        let (k, p) = (r.kid.unwrap(), r.kid_patch.unwrap());
        eprintln!(
            "{}: KID {k:.5} +- {:.5}, patch KID {p:.5} +- {:.5}",
            r.variant,
            r.kid_std.unwrap(),
            r.kid_patch_std.unwrap()
        );
        assert!(k.is_finite() && p.is_finite());
    }
    assert!(t.markdown().contains("patch KID"));

    // The report: self-contained (every image inlined, nothing fetched), the stages, the table,
    // five images per held-out view and the fly-through video of the three fields.
    let page = extranerf_extrapolate::eval::report::write_report(&a, Some(&t)).unwrap();
    let html = std::fs::read_to_string(&page).unwrap();
    for want in [
        "stage3-enhancer",
        "<td>stage3-harmonic</td>",
        "LPIPS-alex",
        "patch KID",
        "Fly-through",
    ] {
        assert!(html.contains(want), "{want} missing from the report");
    }
    assert!(!html.contains("http:") && !html.contains("https:") && !html.contains("file:"));
    assert!(!html.contains("missing</div>"), "an image is missing");
    let images = html.matches("<img ").count();
    let inlined = html.matches("src=\"data:image/").count();
    assert_eq!(images, inlined);
    assert_eq!(images, 5 * loaded.split.test.len());
    assert_eq!(html.matches("<video ").count(), 1);
    assert_eq!(html.matches("src=\"data:video/mp4;base64,").count(), 1);

    // The gate (--stage3-gate check), on a copy with stage 3 redone: the check enhances one
    // triplet per training view (the sources in turn) and scores it against the photo (the
    // renders' PSNR is recomputed here); the stage ran or was skipped as the check says. The
    // check is then forged to the other verdict and the stage redone, so that both outcomes
    // are tested whichever the small enhancer earns.
    let g = dir.join("g");
    copy_dir(&a, &g);
    let gated = |redo: &str, enhancer_steps: usize| {
        let mut o = opts(&g);
        o.resume = true;
        o.redo = vec![redo.into()];
        let s3 = o.stage3.as_mut().unwrap();
        s3.enhancer.steps = enhancer_steps;
        s3.gate = Stage3Gate::Check;
        s3.lpips = Some(extranerf_tests::shared_data().join("../models/lpips"));
        let mut rec = Record::default();
        extrapolate(ctx, &o, &mut rec).unwrap();
        let m = Manifest::load(&g).unwrap().unwrap();
        let report = m
            .stages
            .iter()
            .find(|s| s.name == "stage3-harmonic")
            .unwrap()
            .report
            .clone();
        (report, rec.notes)
    };
    let check_path = g.join("stage3-enhancer").join(CHECK_FILE);
    let read_check = || -> EnhancerCheck {
        serde_json::from_str(&std::fs::read_to_string(&check_path).unwrap()).unwrap()
    };
    let outcome = |report: &serde_json::Value, notes: &[String], check: &EnhancerCheck| {
        assert_eq!(report["check"], serde_json::to_value(check).unwrap());
        let stage3 = g.join("stage3-harmonic");
        let t = extranerf_extrapolate::eval::compare(&g, None, None, None, &mut Record::default())
            .unwrap();
        let row = |v: &str| t.rows.iter().find(|r| r.variant == v).unwrap().psnr;
        if check.helps() {
            assert!(report["skipped"].is_null(), "{report}");
            assert_eq!(report["rounds"].as_array().unwrap().len(), 2);
            assert!(stage3.join("round_01").is_dir());
            assert_eq!(t.notes, ["BaseNeRF depth targets: none"]);
        } else {
            let why = report["skipped"].as_str().unwrap();
            assert!(
                why.contains("worse") && why.contains("--stage3-gate off"),
                "{why}"
            );
            assert!(notes.iter().any(|n| n.contains(why)), "{notes:?}");
            assert!(!stage3.join("round_00").exists());
            // The stage-2 field and its renders, byte for byte; the fly-through made from it.
            let same = |f: &str| {
                std::fs::read(stage3.join(f)).unwrap()
                    == std::fs::read(g.join("stage2-harmonic").join(f)).unwrap()
            };
            assert!(same(extranerf_nerf::run::CHECKPOINT_FILE));
            for &i in &loaded.split.test {
                assert!(same(&format!("test_{i:03}.png")), "test view {i}");
            }
            assert!(g.join("flythrough/stage3-harmonic/frame_001.png").is_file());
            assert_eq!(row("stage3-harmonic"), row("stage2-harmonic"));
            assert_eq!(
                t.notes,
                [
                    "BaseNeRF depth targets: none".to_string(),
                    format!("stage3-harmonic: {why}")
                ]
            );
            assert!(t.markdown().contains(why));
        }
    };
    let (report, notes) = gated("stage3-harmonic", 60);
    let check = read_check();
    eprintln!("enhancer check: {}", check.describe());
    let picks = check_triplets(&tr);
    assert_eq!(picks.len(), views);
    for (v, &k) in picks.iter().enumerate() {
        let e = &tr.entries[k];
        assert_eq!(e.slot, v);
        let mine: Vec<&str> = tr
            .entries
            .iter()
            .filter(|x| x.slot == v)
            .map(|x| x.source.as_str())
            .collect();
        assert_eq!(e.source, mine[v % mine.len()]);
        assert_eq!(check.triplets[v], e.key);
    }
    let want = picks
        .iter()
        .map(|&k| {
            extranerf_nerf::metrics::psnr(&tr.renders[k].0, &tr.photos[tr.entries[k].slot]).unwrap()
        })
        .sum::<f64>()
        / views as f64;
    assert!(
        (check.psnr_render - want).abs() < 1e-9,
        "{} {want}",
        check.psnr_render
    );
    let (lr, le) = (check.lpips_render.unwrap(), check.lpips_enhanced.unwrap());
    assert!(lr.is_finite() && le.is_finite() && check.psnr_enhanced.is_finite());
    assert_eq!(check.helps(), le < lr);
    outcome(&report, &notes, &check);
    let forged = EnhancerCheck {
        lpips_enhanced: Some(if check.helps() { lr + 0.1 } else { 0.5 * lr }),
        ..check.clone()
    };
    assert_ne!(forged.helps(), check.helps());
    std::fs::write(&check_path, serde_json::to_string(&forged).unwrap()).unwrap();
    let (report, notes) = gated("stage3-harmonic", 60);
    assert_eq!(
        read_check(),
        forged,
        "a check with the same settings is reused"
    );
    outcome(&report, &notes, &forged);
    // A check file that does not read is made again, not an error.
    std::fs::write(&check_path, "{ not json").unwrap();
    let (report, _) = gated("stage3-harmonic", 60);
    assert_eq!(report["check"], serde_json::to_value(read_check()).unwrap());

    // A stage resumed after its first round does not judge again, even with its check gone:
    // it passed when it started (a skipped stage writes no rounds).
    let passing = EnhancerCheck {
        lpips_enhanced: Some(0.5 * lr),
        ..check.clone()
    };
    std::fs::write(&check_path, serde_json::to_string(&passing).unwrap()).unwrap();
    let gated_opts = |redo: Vec<String>| {
        let mut o = opts(&g);
        o.resume = true;
        o.redo = redo;
        let s3 = o.stage3.as_mut().unwrap();
        s3.gate = Stage3Gate::Check;
        s3.lpips = Some(extranerf_tests::shared_data().join("../models/lpips"));
        o
    };
    crash_in_stage3_round_two(ctx, &gated_opts(vec!["stage3-harmonic".into()]), &g);
    std::fs::remove_file(&check_path).unwrap();
    let mut rec = Record::default();
    extrapolate(ctx, &gated_opts(Vec::new()), &mut rec).unwrap();
    rec.assert_notes(&[
        "stage3-harmonic: resuming, the enhancer check passed when it started",
        "stage3-harmonic: resuming after round 1",
    ]);
    assert!(!check_path.exists(), "a resumed stage judged again");
    assert!(g.join("stage3-harmonic/round_01").is_dir());

    // A new enhancer is checked again: the forged check, made with the same settings, is
    // dropped with the enhancer it judged.
    std::fs::write(&check_path, serde_json::to_string(&forged).unwrap()).unwrap();
    let (report, _) = gated("stage3-enhancer", 2);
    let again = read_check();
    assert_ne!(again, forged, "a stale check survived");
    assert_eq!(report["check"], serde_json::to_value(&again).unwrap());

    // --stage3-enhancer unsharp: no data or enhancer stage in the plan, no check, and each
    // virtual view's target is the unsharp mask of its render (to the PNGs' 8 bits).
    let mut o = opts(&g);
    o.resume = true;
    o.redo = vec!["stage3-harmonic".into()];
    let s3 = o.stage3.as_mut().unwrap();
    s3.enhance = Stage3Enhancer::Unsharp;
    s3.gate = Stage3Gate::Check;
    let mut rec = Record::default();
    extrapolate(ctx, &o, &mut rec).unwrap();
    assert!(
        !rec.notes
            .iter()
            .any(|n| n.contains("stage3-data") || n.contains("stage3-enhancer")),
        "{:?}",
        rec.notes
    );
    assert!(rec
        .notes
        .iter()
        .any(|n| n.contains("unsharp mask, amount 0.5 radius 1")));
    let m = Manifest::load(&g).unwrap().unwrap();
    let st = m
        .stages
        .iter()
        .find(|s| s.name == "stage3-harmonic")
        .unwrap();
    assert!(st.report["check"].is_null() && st.report["skipped"].is_null());
    // The record holds the enhancer as one choice, with its settings and no gate.
    assert_eq!(
        st.config["enhance"],
        serde_json::json!({"unsharp": {"amount": 0.5, "radius": 1}})
    );
    assert!(st.config["gate"].is_null());
    for round in ["round_00", "round_01"] {
        let d = g.join("stage3-harmonic").join(round);
        let r = load_image(&d.join("virtual_000_render.png")).unwrap();
        let t = load_image(&d.join("virtual_000.png")).unwrap();
        let want = unsharp(&r.rgb, r.width as usize, r.height as usize, 0.5, 1);
        let worst = want
            .iter()
            .zip(&t.rgb)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst < 0.01, "{round}: {worst}");
        let changed = r.rgb.iter().zip(&t.rgb).filter(|(a, b)| a != b).count();
        assert!(changed > 0, "{round}: the target is the render");
    }

    assert_no_validation_messages(ctx);
    let _ = std::fs::remove_dir_all(&dir);
}

rusty_fork_test! {
    /// In a process of its own (rusty-fork): stage 3 trains an enhancer from burn's process-global
    /// random generator, which a test drawing from it at the same time would change.
    #[test]
    fn stage_three_enhances_resumes_and_keeps_the_visible_region() {
        stage_three_enhances_resumes_and_keeps_the_visible_region_in_this_process();
    }
}
