//! `extranerf demo`: ExtraNeRF end to end on the procedural demo scene
//! ([`extranerf_nerf::demo`]: six rig cameras, eight views outside the rig whose photos and
//! exact visibility the generator knows). The scene is ray traced, a BaseNeRF trained on the
//! rig, then the pipeline runs as `extranerf extrapolate` would with no diffusion weights: the
//! visibility of virtual views beyond the rig, stage 2 with the default inpainter and stage 3
//! with the unsharp-mask enhancer (the learned enhancer trains for minutes), the fly-through;
//! last the comparison table over the outside views (whole image, the estimated not-visible
//! mask, and the exact visible and not-visible pixels), `report.html` and a picture of the
//! outside views (photo, BaseNeRF, final field).
//!
//! The output folder holds `scene/`, `basenerf/` (the BaseNeRF's run), `extranerf/` (the
//! extrapolate run: `report.html`, `eval.md`, `eval.json`, `outside_views.png`) and
//! `demo.json` (settings and seconds per part). A folder the
//! demo made is replaced whole by the next demo into it; any other folder is refused.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::error::{create_dir, ExtrapolateError, Result};
use extranerf_gpu::Context;
use extranerf_nerf::cameras::Trajectory;
use extranerf_nerf::data::load_image;
use extranerf_nerf::data::split::SplitKind;
use extranerf_nerf::demo::{write_demo_scene, GT_VISIBILITY_DIR, RIG_VIEWS, RING_VIEWS};
use extranerf_nerf::metrics::Lpips;
use extranerf_nerf::model::ModelConfig;
use extranerf_nerf::run::{write_png, RunConfig, SceneSpec};
use extranerf_nerf::trainer::TrainConfig;

use crate::eval::{compare, write_table, Table};
use crate::inpaint::InpainterKind;
use crate::manifest::Manifest;
use crate::rounds::Stage2Spec;
use crate::run::{extrapolate, Options};
use crate::stage::VirtualSpec;
use crate::stage3::{Stage3Enhancer, Stage3Spec};
use crate::stages::{BaseSpec, FlythroughSpec};
use crate::visibility::VisSettings;
use extranerf_nerf::train::{train_loop, Reporter, TrainRun, ViewSet};

/// The file that marks a folder as one the demo made (and may replace).
pub const DEMO_FOLDER_MARKER: &str = ".extranerf-demo";

/// What the demo does after the BaseNeRF.
#[derive(Clone, Debug, PartialEq)]
pub struct DemoSpec {
    /// Output folder.
    pub out: PathBuf,
    /// Width of the generated views (height 3/4 of it).
    pub width: u32,
    /// BaseNeRF training steps.
    pub base_steps: u32,
    /// Stage 2 (its inpainter: [`InpainterKind::Harmonic`], `extrapolate`'s default).
    pub stage2: Stage2Spec,
    /// Stage 3 rounds and steps per round (the unsharp-mask enhancer); None: no stage 3.
    pub stage3: Option<(u32, u32)>,
    /// Divide the views' resolution by this for the virtual views and visibility maps.
    pub virtual_downscale: u32,
    /// Fly-through frames (0: none).
    pub flythrough: u32,
    /// Folder of the LPIPS weights (scored where `lpips_alex_v0.1.safetensors` loads).
    pub lpips: PathBuf,
    /// Where to stop.
    pub stop_after: DemoStop,
}

/// How far the demo goes.
#[derive(clap::ValueEnum, Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DemoStop {
    /// Only write the scene (for tools that train on it themselves).
    Scene,
    /// The scene and the BaseNeRF (for tools that run `extrapolate` on it themselves).
    Basenerf,
    /// Everything: the pipeline, the table, the report.
    #[default]
    Extranerf,
}

impl DemoSpec {
    /// The default stage 3: rounds and steps per round.
    pub const DEFAULT_STAGE3: (u32, u32) = (2, 150);
}

impl Default for DemoSpec {
    fn default() -> Self {
        DemoSpec {
            out: PathBuf::from("runs/demo"),
            width: 192,
            base_steps: 1200,
            stage2: Stage2Spec {
                rounds: 4,
                steps_per_round: 200,
                ..Stage2Spec::default()
            },
            stage3: Some(Self::DEFAULT_STAGE3),
            virtual_downscale: 2,
            flythrough: FlythroughSpec::default().frames,
            lpips: extranerf_nerf::train::default_lpips_dir(),
            stop_after: DemoStop::default(),
        }
    }
}

/// What the demo made and measured.
#[derive(Debug)]
pub struct DemoOutcome {
    /// The generated scene.
    pub scene: PathBuf,
    /// The BaseNeRF's run folder.
    pub basenerf: PathBuf,
    /// The extrapolate run folder.
    pub run: PathBuf,
    /// The comparison table (None when the demo stopped before the pipeline).
    pub table: Option<Table>,
    /// `report.html` and the picture of the outside views.
    pub report: Option<PathBuf>,
    pub picture: Option<PathBuf>,
    /// Wall seconds of each part: scene, BaseNeRF, then the pipeline's stages, evaluation.
    pub seconds: Vec<(String, f64)>,
}

/// The BaseNeRF's settings: a small model (8 levels, a 2^15 table, 32-wide MLPs) and batch
/// (512 rays of 24 samples), which stages 2 and 3 keep.
pub fn base_config(scene: &Path, steps: u32) -> RunConfig {
    RunConfig {
        scene: SceneSpec {
            dir: scene.to_path_buf(),
            split: SplitKind::Extrapolation,
            fewshot_views: 3,
            factor: 1,
            sparse_depth: false,
            depth_dir: None,
            mvs_depth: None,
            capture_depth: false,
        },
        model: ModelConfig {
            levels: 8,
            log2_table: 15,
            max_res: 512,
            density_width: 32,
            color_width: 32,
            ..Default::default()
        },
        train: TrainConfig {
            steps,
            decay_steps: steps,
            rays: 512,
            samples: 24,
            ..TrainConfig::default()
        },
    }
}

/// Empties `out` if the demo made it (refusing any other non-empty folder) and marks it.
fn claim(out: &Path) -> Result<()> {
    let marker = out.join(DEMO_FOLDER_MARKER);
    if out.exists() {
        let mut entries = std::fs::read_dir(out)
            .map_err(|e| ExtrapolateError::io("reading", out, e))?
            .peekable();
        if entries.peek().is_some() {
            if !marker.exists() {
                return Err(ExtrapolateError::usage(format!(
                    "{} exists and was not made by `extranerf demo`; pass another --out",
                    out.display()
                )));
            }
            for e in entries {
                let p = e
                    .map_err(|e| ExtrapolateError::io("reading", out, e))?
                    .path();
                let removed = if p.is_dir() {
                    std::fs::remove_dir_all(&p)
                } else {
                    std::fs::remove_file(&p)
                };
                removed.map_err(|e| ExtrapolateError::io("removing the previous demo's", &p, e))?;
            }
        }
    }
    create_dir(out)?;
    extranerf_gpu::files::write_atomic(
        &marker,
        b"made by extranerf demo; the next demo into this folder replaces all of it\n",
    )
    .map_err(|e| ExtrapolateError::io("writing", &marker, e))?;
    Ok(())
}

/// Runs the demo (progress and notes go to `rep`).
pub fn demo(ctx: &Context, spec: &DemoSpec, rep: &mut dyn Reporter) -> Result<DemoOutcome> {
    if spec.width < 32 {
        return Err(ExtrapolateError::usage(format!(
            "--width {}: use at least 32 pixels",
            spec.width
        )));
    }
    let t0 = Instant::now();
    claim(&spec.out)?;
    let scene = spec.out.join("scene");
    let base = spec.out.join("basenerf");
    let run = spec.out.join("extranerf");
    let height = spec.width * 3 / 4;
    let mut seconds = Vec::new();
    let t = Instant::now();
    rep.stage("scene");
    rep.note(&format!(
        "ray tracing the procedural scene ({RIG_VIEWS} rig views + {RING_VIEWS} views outside the rig, {}x{height}) into {}",
        spec.width,
        scene.display()
    ));
    write_demo_scene(&scene, spec.width, height)?;
    seconds.push(("scene".to_string(), t.elapsed().as_secs_f64()));
    let mut outcome = DemoOutcome {
        scene: scene.clone(),
        basenerf: base.clone(),
        run: run.clone(),
        table: None,
        report: None,
        picture: None,
        seconds,
    };
    if spec.stop_after == DemoStop::Scene {
        return Ok(outcome);
    }
    let t = Instant::now();
    rep.stage("basenerf");
    let cfg = base_config(&scene, spec.base_steps);
    train_loop(
        ctx,
        &cfg,
        &TrainRun {
            out: base.clone(),
            start: 0,
            log_every: 25,
            checkpoint_every: spec.base_steps.max(1),
            eval_every: 0,
            eval_views: ViewSet::Test,
            budget: None,
        },
        None,
        None,
        rep,
    )?;
    outcome
        .seconds
        .push(("basenerf".to_string(), t.elapsed().as_secs_f64()));
    if spec.stop_after == DemoStop::Basenerf {
        return Ok(outcome);
    }
    let o = Options {
        out: run.clone(),
        scene: None,
        base: BaseSpec {
            from: Some(base),
            budget: 0.0,
        },
        // `extrapolate`'s defaults.
        virt: VirtualSpec {
            trajectory: Trajectory::Spiral,
            count: 8,
            range: 1.5,
            downscale: spec.virtual_downscale,
        },
        vis: VisSettings::default(),
        stage2: spec.stage2.clone(),
        inpainters: vec![InpainterKind::Harmonic],
        diffusion: None,
        stage3: spec.stage3.map(|(rounds, steps_per_round)| Stage3Spec {
            rounds,
            steps_per_round,
            enhance: Stage3Enhancer::Unsharp,
            ..Stage3Spec::default()
        }),
        flythrough: FlythroughSpec {
            frames: spec.flythrough,
            ..FlythroughSpec::default()
        },
        resume: false,
        redo: Vec::new(),
    };
    let m = extrapolate(ctx, &o, rep)?;
    for s in &m.stages {
        outcome.seconds.push((s.name.clone(), s.seconds));
    }
    let t = Instant::now();
    rep.stage("eval");
    let lpips = match Lpips::load(
        &spec.lpips.join("lpips_alex_v0.1.safetensors"),
        extranerf_nerf::metrics::LpipsNet::Alex,
    ) {
        Ok(l) => Some(l),
        Err(e) => {
            rep.note(&format!(
                "no LPIPS in the table: {e} (set EXTRANERF_MODELS to a folder with lpips/)"
            ));
            None
        }
    };
    let table = compare(
        &run,
        lpips.as_ref(),
        None,
        Some(&scene.join(GT_VISIBILITY_DIR)),
        rep,
    )?;
    outcome.report = Some(write_table(&run, &table)?);
    outcome.picture = Some(outside_views_picture(&run)?);
    outcome
        .seconds
        .push(("eval".to_string(), t.elapsed().as_secs_f64()));
    outcome.table = Some(table);
    // What ran and how long each part took, for tools that record the demo.
    let summary = serde_json::json!({
        "width": spec.width,
        "height": height,
        "base_steps": spec.base_steps,
        "stage2": {"rounds": spec.stage2.rounds, "steps_per_round": spec.stage2.steps_per_round},
        "stage3": spec.stage3.map(|(r, s)| serde_json::json!({"rounds": r, "steps_per_round": s})),
        "virtual_downscale": spec.virtual_downscale,
        "device": ctx.info().name,
        "seconds": outcome.seconds.iter().map(|(n, s)| serde_json::json!({"part": n, "seconds": s})).collect::<Vec<_>>(),
        "total_seconds": t0.elapsed().as_secs_f64(),
    });
    crate::error::write_json(&spec.out.join(SUMMARY_FILE), &summary)?;
    Ok(outcome)
}

/// The demo's summary in its output folder: settings, device, seconds per part and in all.
pub const SUMMARY_FILE: &str = "demo.json";

/// The picture's file name in the run folder.
pub const PICTURE_FILE: &str = "outside_views.png";

/// `RUN/outside_views.png`: for every held-out view the photo, the BaseNeRF's render and the
/// final field's, side by side, two views to a row, with white gaps.
pub fn outside_views_picture(run: &Path) -> Result<PathBuf> {
    let Some(m) = Manifest::load(run)? else {
        return Err(ExtrapolateError::incomplete(run, "no extrapolate manifest"));
    };
    let loaded = m.scene.load()?;
    let fin = crate::eval::report::final_field(&m)
        .ok_or_else(|| ExtrapolateError::incomplete(run, "no stage-2 or stage-3 field"))?;
    let views = &loaded.split.test;
    let Some(first) = views.first() else {
        return Err(ExtrapolateError::incomplete(run, "no held-out views"));
    };
    let (w, h) = (
        loaded.scene.cameras[*first].width,
        loaded.scene.cameras[*first].height,
    );
    const GAP: u32 = 4;
    let per_row = 2u32;
    let rows = (views.len() as u32).div_ceil(per_row);
    let cols = 3 * per_row;
    let (pw, ph) = (cols * w + (cols - 1) * GAP, rows * h + (rows - 1) * GAP);
    let mut pic = vec![1f32; (pw * ph * 3) as usize];
    for (k, &i) in views.iter().enumerate() {
        let cam = &loaded.scene.cameras[i];
        let paths = [
            cam.image.clone(),
            run.join("visibility").join(format!("test_{i:03}_base.png")),
            run.join(&fin).join(format!("test_{i:03}.png")),
        ];
        let (row, slot) = (k as u32 / per_row, k as u32 % per_row);
        for (c, p) in paths.iter().enumerate() {
            let img = load_image(p)?;
            if (img.width, img.height) != (w, h) {
                return Err(ExtrapolateError::malformed(
                    p,
                    format!(
                        "{}x{}, not the {w}x{h} of the other views",
                        img.width, img.height
                    ),
                ));
            }
            let (x0, y0) = ((3 * slot + c as u32) * (w + GAP), row * (h + GAP));
            for y in 0..h as usize {
                let src = 3 * y * w as usize;
                let dst = 3 * ((y0 as usize + y) * pw as usize + x0 as usize);
                pic[dst..dst + 3 * w as usize].copy_from_slice(&img.rgb[src..src + 3 * w as usize]);
            }
        }
    }
    let path = run.join(PICTURE_FILE);
    write_png(&path, pw, ph, &pic)?;
    Ok(path)
}
