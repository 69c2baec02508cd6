//! `extranerf visibility` (visibility maps of virtual or held-out views, pseudo-disocclusion
//! masks of the training views) and `extranerf bench visibility`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context as _};
use extranerf_extrapolate::visibility::{
    complete_depth, map_summary, write_map, QuerySettings, RunVisibility,
};
use extranerf_gpu::Context;
use extranerf_nerf::data::Camera;
use extranerf_nerf::render::visibility::{
    mask_all_but, VisibilityMap, VisibilityMeasure, MAX_RANK,
};
use extranerf_nerf::train::ViewSet;

use crate::args::MarchArgs;

/// Where the training cameras' transmittances come from.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum Method {
    /// Transmittance volumes (deep shadow maps).
    Volume,
    /// A march of every segment.
    March,
}

impl Method {
    fn name(self) -> &'static str {
        match self {
            Method::Volume => "volume",
            Method::March => "march",
        }
    }
}

/// What a transmittance is measured against (`VisibilityMeasure`).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Measure {
    /// Over the pixel ray's own transmittance in front of the sample, at most 1.
    Relative,
    /// The transmittance itself (the paper).
    Absolute,
}

impl From<Measure> for VisibilityMeasure {
    fn from(m: Measure) -> VisibilityMeasure {
        match m {
            Measure::Relative => VisibilityMeasure::Relative,
            Measure::Absolute => VisibilityMeasure::Absolute,
        }
    }
}

/// How visibility is computed (shared by `visibility` and `bench visibility`).
#[derive(clap::Args, Debug, Clone)]
pub struct VisArgs {
    /// Samples per camera ray (default: the run's training setting).
    #[arg(long)]
    samples: Option<u32>,
    /// Samples per segment from a ray sample toward a training camera.
    #[arg(long, default_value_t = 32)]
    vis_samples: u32,
    /// Which largest transmittance across the training cameras counts: 2 (the paper) means a
    /// point is visible only when two training views saw it.
    #[arg(long, default_value_t = 2)]
    rank: u32,
    /// Samples whose weight is at most this are not marched toward the cameras (each drops at
    /// most this much visibility; 0: exact).
    #[arg(long, default_value_t = 1e-3)]
    min_weight: f32,
    /// Segments toward a camera stop once their transmittance falls below this, and count as
    /// 0 (0: exact).
    #[arg(long, default_value_t = 1e-3)]
    min_transmittance: f32,
    /// Divide the views' resolution by this (visibility is smooth; 1 = full resolution).
    #[arg(long, default_value_t = 4)]
    downscale: u32,
    /// Occupancy grid cells per axis, built from the field first, so segments skip empty
    /// space (0: no grid).
    #[arg(long, default_value_t = 0)]
    occupancy_res: u32,
    /// volume: look each training camera's transmittance up in a volume built once from its
    /// rays (a deep shadow map; cost independent of the distance to the camera). march: march
    /// every segment toward every camera (the exact definition; about 100x slower on fern,
    /// results/bench_visibility_lavapipe).
    #[arg(long, value_enum, default_value_t = Method::Volume)]
    method: Method,
    /// relative: a camera's transmittance to a sample over the pixel ray's own in front of
    /// it (at most 1), so a surface the field renders as a semi-transparent shell counts as
    /// seen where the cameras saw it. absolute: the transmittance itself (the paper), which
    /// such a shell halves even for the pixel's own camera.
    #[arg(long, value_enum, default_value_t = Measure::Relative)]
    measure: Measure,
    /// Rays across each training camera's transmittance volume (rows follow its aspect).
    #[arg(long, default_value_t = 128)]
    volume_res: u32,
    /// Depth strata of the transmittance volumes.
    #[arg(long, default_value_t = 128)]
    volume_depth: u32,
    /// Pixels per submission.
    #[arg(long, default_value_t = 4096)]
    chunk: u32,
}

/// Arguments of `extranerf visibility`.
#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("which").required(true).multiple(true).args(["cameras", "views", "training_masks"])))]
pub struct VisibilityArgs {
    /// Run folder written by `extranerf train`.
    run: PathBuf,
    /// Views to test, as a transforms.json in the run's world frame (`extranerf cameras`
    /// writes one).
    #[arg(long, value_name = "FILE")]
    cameras: Option<PathBuf>,
    /// The run's own views instead (or as well): test, train, all (every view of the scene),
    /// or indices such as 0,4.
    #[arg(long)]
    views: Option<ViewSet>,
    /// Also write pseudo-disocclusion masks for every training view: the view tested against
    /// the other training views (for fine-tuning the inpainting model).
    #[arg(long)]
    training_masks: bool,
    /// Rank for the training masks (0: the number of other views, at most 8, so a pixel is
    /// disoccluded when any other view missed it).
    #[arg(long, default_value_t = 0)]
    mask_rank: u32,
    /// Pixels with visibility below this are masked (to be inpainted). Visibility is at most the
    /// pixel's opacity: what the field does not fill counts as unseen.
    #[arg(long, default_value_t = 0.5)]
    threshold: f32,
    /// Also complete each view's depth where the training views did not see it: Jacobi
    /// iterations of the colour-guided fill (`depth_completion`) from the rendered depth of
    /// the visible pixels, guided by the rendered colour (the inpainting stage will supply
    /// inpainted colour instead). Writes NAME_depth.exr and NAME_depth_completed.exr (the
    /// field's ray-space depth, NDC t for forward-facing scenes, in channel T, which
    /// `train --depth-dir` refuses) and NAME_view_depth.exr (the completed depth as view depth
    /// in the capture's units, channel Z, what `--depth-dir` reads). 0: off.
    #[arg(long, default_value_t = 0, value_name = "ITERATIONS")]
    complete_depth: u32,
    /// Colour difference at which a neighbour's weight in the depth fill falls to 1/e.
    #[arg(long, default_value_t = 0.1)]
    depth_sigma: f32,
    /// Output folder (default RUN/visibility).
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    vis: VisArgs,
}

/// Loads the run for visibility queries, with the occupancy grid `a` asks for.
fn load(ctx: &Context, run: &Path, a: &VisArgs) -> anyhow::Result<RunVisibility> {
    let mut l = RunVisibility::load(ctx, run)?;
    let march = MarchArgs {
        occupancy_res: a.occupancy_res,
        ..MarchArgs::default()
    };
    if let Some(occ) = march.occupancy(&l.base.ck.config.model)? {
        if let Some(b) = l.build_occupancy(ctx, occ, march.occupancy_passes)? {
            eprintln!(
                "occupancy grid {}^3: {} of {} cells occupied ({:.1}%), built in {:.1} s",
                b.res,
                b.stats.occupied,
                b.stats.cells,
                100.0 * b.stats.occupied as f64 / b.stats.cells as f64,
                b.seconds
            );
        }
    }
    Ok(l)
}

impl VisArgs {
    fn query(&self) -> QuerySettings {
        QuerySettings {
            samples: self.samples,
            vis_samples: self.vis_samples,
            min_weight: self.min_weight,
            min_transmittance: self.min_transmittance,
            measure: self.measure.into(),
        }
    }
}

/// Builds the transmittance volumes and prints their size; returns the seconds.
fn build_volume(
    ctx: &Context,
    l: &mut RunVisibility,
    train: &[Camera],
    a: &VisArgs,
) -> anyhow::Result<f64> {
    let s = l.build_volume(ctx, train, a.volume_res, a.volume_depth)?;
    if let Some(vol) = l.volume() {
        let [w, h, d] = vol.size();
        eprintln!(
            "transmittance volumes: {} cameras x {w}x{h} rays x {d} strata ({:.1} MiB), built in {s:.1} s",
            train.len(),
            vol.bytes() as f64 / (1 << 20) as f64
        );
    }
    Ok(s)
}

/// `cam` at 1/`factor` of its resolution (same field of view).
fn downscaled(cam: &Camera, factor: u32) -> anyhow::Result<Camera> {
    if factor == 0 {
        bail!("--downscale must be at least 1");
    }
    Ok(cam.downscaled(factor))
}

/// `extranerf visibility`.
pub fn visibility(ctx: &Context, a: &VisibilityArgs) -> anyhow::Result<()> {
    let out = a.out.clone().unwrap_or_else(|| a.run.join("visibility"));
    if !(0.0..=1.0).contains(&a.threshold) {
        bail!("--threshold {}: use a value in [0, 1]", a.threshold);
    }
    let mut l = load(ctx, &a.run, &a.vis)?;
    let train = l.train_cameras()?;
    let cfg = l.config(&a.vis.query(), a.vis.rank)?;
    let volume = a.vis.method == Method::Volume;
    let build_seconds = if volume {
        Some(build_volume(ctx, &mut l, &train, &a.vis)?)
    } else {
        None
    };
    let mut views: Vec<(String, &'static str, Camera)> = Vec::new();
    if let Some(file) = &a.cameras {
        let scene = extranerf_nerf::data::transforms::load_transforms(file)
            .with_context(|| format!("--cameras {}", file.display()))?;
        for (i, c) in scene.cameras.into_iter().enumerate() {
            views.push((format!("virtual_{i:03}"), "virtual", c));
        }
    }
    if let Some(set) = &a.views {
        let split = &l.base.loaded.split;
        let n = l.base.loaded.scene.cameras.len();
        // `all` here is every view of the scene, also those in neither half of the split.
        let idx = match set {
            ViewSet::All => (0..n).collect(),
            set => set.indices(split, n, "--views")?,
        };
        for i in idx {
            let kind = if split.train.contains(&i) {
                "train"
            } else if split.test.contains(&i) {
                "test"
            } else {
                "other"
            };
            views.push((
                format!("{kind}_{i:03}"),
                kind,
                l.base.loaded.scene.cameras[i].clone(),
            ));
        }
    }
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    eprintln!(
        "visibility against {} training views (rank {}, {} samples per ray, {}, downscale {})",
        train.len(),
        cfg.rank,
        cfg.samples,
        if volume {
            format!(
                "transmittance volumes {}x{}",
                a.vis.volume_res, a.vis.volume_depth
            )
        } else {
            format!("{} samples per segment", cfg.vis_samples)
        },
        a.vis.downscale
    );
    let mut rows = Vec::new();
    let all = mask_all_but(train.len(), None);
    for (name, kind, cam) in &views {
        let cam = downscaled(cam, a.vis.downscale)?;
        let t = Instant::now();
        let m = l.map(ctx, &cam, &train, all, &cfg, volume, a.vis.chunk)?;
        let s = t.elapsed().as_secs_f64();
        write_map(&out, name, &m, a.threshold)?;
        eprintln!(
            "{name}: {}x{}, mean visibility {:.3} (opacity {:.3}; {:.1}% of the rendered content seen), {:.1}% masked, {s:.1} s",
            m.width,
            m.height,
            m.mean(),
            m.mean_opacity(),
            100.0 * m.visible_fraction(),
            100.0 * m.masked_fraction(a.threshold)
        );
        let mut row = map_summary(name, kind, &m, s, a.threshold);
        if a.complete_depth > 0 {
            let t = Instant::now();
            let samples = a.vis.samples.unwrap_or(l.base.ck.config.train.samples);
            let done = complete_depth(
                ctx,
                &l.base,
                &cam,
                &m,
                a.threshold,
                a.depth_sigma,
                a.complete_depth,
                samples,
                a.vis.chunk,
            )?;
            done.write(&out, name, &cam)?;
            row["depth_completion"] = serde_json::json!({
                "iterations": a.complete_depth,
                "sigma": a.depth_sigma,
                "mean_abs_change": done.mean_abs_change,
                "seconds": t.elapsed().as_secs_f64(),
            });
        }
        rows.push(row);
    }
    if a.training_masks {
        if train.len() < 2 {
            bail!("training masks need at least two training views");
        }
        let others = train.len() as u32 - 1;
        let rank = if a.mask_rank == 0 {
            others.min(MAX_RANK)
        } else if a.mask_rank > others {
            bail!(
                "--mask-rank {}: each training view has {others} others to be seen by",
                a.mask_rank
            );
        } else {
            a.mask_rank
        };
        let mcfg = l.config(&a.vis.query(), rank)?;
        for (k, &i) in l.base.loaded.split.train.iter().enumerate() {
            let cam = downscaled(&train[k], a.vis.downscale)?;
            let t = Instant::now();
            let m = l.map(
                ctx,
                &cam,
                &train,
                mask_all_but(train.len(), Some(k)),
                &mcfg,
                volume,
                a.vis.chunk,
            )?;
            let s = t.elapsed().as_secs_f64();
            let name = format!("trainmask_{i:03}");
            write_map(&out, &name, &m, a.threshold)?;
            eprintln!(
                "training view {i} against the other {}: {:.1}% disoccluded (rank {rank}), {s:.1} s",
                train.len() - 1,
                100.0 * m.masked_fraction(a.threshold)
            );
            rows.push(map_summary(&name, "training-mask", &m, s, a.threshold));
        }
    }
    let doc = serde_json::json!({
        "run": a.run,
        "training_views": l.base.loaded.split.train,
        "settings": {
            "rank": cfg.rank,
            "mask_rank": a.mask_rank,
            "samples": cfg.samples,
            "vis_samples": cfg.vis_samples,
            "min_weight": cfg.min_weight,
            "min_transmittance": cfg.min_transmittance,
            "downscale": a.vis.downscale,
            "method": a.vis.method.name(),
            "measure": cfg.measure,
            "volume_res": a.vis.volume_res,
            "volume_depth": a.vis.volume_depth,
            "volume_build_seconds": build_seconds,
            "occupancy_res": a.vis.occupancy_res,
            "threshold": a.threshold,
        },
        "device": ctx.info().name,
        "views": rows,
    });
    crate::bench::write_json(&out.join("visibility.json"), &doc)?;
    eprintln!("wrote {}", out.display());
    Ok(())
}

/// Arguments of `extranerf bench visibility`.
#[derive(clap::Args, Debug)]
pub struct BenchVisibilityArgs {
    /// Run folder written by `extranerf train`.
    run: PathBuf,
    /// The view to test (default: the run's first held-out view).
    #[arg(long)]
    view: Option<usize>,
    /// Timed repeats per setting (the median counts).
    #[arg(long, default_value_t = 1)]
    repeats: u32,
    /// Also write the table as JSON.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    #[command(flatten)]
    vis: VisArgs,
}

/// `extranerf bench visibility`: cost per pixel against the number of training views, for the
/// exact segment march and for transmittance volumes (with the volumes' build cost and their
/// difference from the march).
pub fn bench_visibility(ctx: &Context, a: &BenchVisibilityArgs) -> anyhow::Result<()> {
    let mut l = load(ctx, &a.run, &a.vis)?;
    let train = l.train_cameras()?;
    let view = a
        .view
        .or_else(|| l.base.loaded.split.test.first().copied())
        .unwrap_or(0);
    let Some(cam) = l.base.loaded.scene.cameras.get(view) else {
        bail!(
            "--view {view}: the scene has {} views",
            l.base.loaded.scene.cameras.len()
        );
    };
    let cam = downscaled(cam, a.vis.downscale)?;
    let px = cam.width as f64 * cam.height as f64;
    let repeats = a.repeats.max(1);
    // The volumes' build, timed (the first build also creates the pipeline).
    build_volume(ctx, &mut l, &train, &a.vis)?;
    let mut builds = Vec::new();
    for _ in 0..repeats {
        builds.push(build_volume(ctx, &mut l, &train, &a.vis)? * 1e3);
    }
    builds.sort_by(f64::total_cmp);
    let build_ms = builds[builds.len() / 2];
    let [vw, vh, vd] = l.volume().map(|v| v.size()).unwrap_or([0; 3]);
    println!("device: {}", ctx.info().name);
    println!(
        "view {view} at {}x{}, {} samples per ray; march: {} samples per segment, cuts {} / {}; volumes: {vw}x{vh}x{vd} per camera, built for all {} cameras in {build_ms:.1} ms",
        cam.width,
        cam.height,
        a.vis.samples.unwrap_or(l.base.ck.config.train.samples),
        a.vis.vis_samples,
        a.vis.min_weight,
        a.vis.min_transmittance,
        train.len()
    );
    println!(
        "{:<7} {:>7} {:>5} {:>10} {:>10} {:>12} {:>9} {:>8} {:>10}",
        "method",
        "cameras",
        "rank",
        "ms/view",
        "us/pixel",
        "evals/pixel",
        "x ray",
        "mean vis",
        "|d| march"
    );
    let mut rows = Vec::new();
    let mut base_ms = None;
    // n = 0: the camera ray alone (no camera selected), the reference cost.
    for n in 0..=train.len() {
        let rank = if n >= 2 { a.vis.rank.min(n as u32) } else { 1 };
        let cfg = l.config(&a.vis.query(), rank)?;
        let mask = mask_all_but(n, None);
        let mut exact: Option<VisibilityMap> = None;
        for method in ["march", "volume"] {
            if n == 0 && method == "volume" {
                continue;
            }
            let volume = method == "volume";
            // The first run warms the pipeline; then the timed repeats.
            let mut m = l.map(ctx, &cam, &train, mask, &cfg, volume, a.vis.chunk)?;
            let mut times = Vec::new();
            for _ in 0..repeats {
                let t = Instant::now();
                m = l.map(ctx, &cam, &train, mask, &cfg, volume, a.vis.chunk)?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
            times.sort_by(f64::total_cmp);
            let ms = times[times.len() / 2];
            let base = *base_ms.get_or_insert(ms);
            let evals = m.evals.iter().map(|&e| e as f64).sum::<f64>() / px;
            let diff = exact.as_ref().map(|e| {
                e.visibility
                    .iter()
                    .zip(&m.visibility)
                    .map(|(x, y)| (x - y).abs() as f64)
                    .sum::<f64>()
                    / px
            });
            println!(
                "{method:<7} {n:>7} {rank:>5} {ms:>10.1} {:>10.2} {evals:>12.1} {:>9.2} {:>8.3} {:>10}",
                ms * 1e3 / px,
                ms / base,
                m.mean(),
                diff.map(|d| format!("{d:.4}")).unwrap_or_else(|| "-".into())
            );
            rows.push(serde_json::json!({
                "method": method,
                "cameras": n,
                "rank": rank,
                "ms_per_view": ms,
                "us_per_pixel": ms * 1e3 / px,
                "evals_per_pixel": evals,
                "ratio_to_camera_ray_only": ms / base,
                "mean_visibility": m.mean(),
                "mean_abs_diff_from_march": diff,
            }));
            if !volume {
                exact = Some(m);
            }
        }
    }
    if let Some(path) = &a.json {
        let doc = serde_json::json!({
            "device": ctx.info().name,
            "run": a.run,
            "view": view,
            "width": cam.width,
            "height": cam.height,
            "vis_samples": a.vis.vis_samples,
            "min_weight": a.vis.min_weight,
            "min_transmittance": a.vis.min_transmittance,
            "volume": {"size": [vw, vh, vd], "cameras": train.len(), "build_ms": build_ms},
            "repeats": repeats,
            "rows": rows,
        });
        crate::bench::write_json(path, &doc)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}
