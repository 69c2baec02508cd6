//! `extranerf mvs`: plane-sweep stereo depth for a scene's training views, written as depth
//! maps `train --depth-dir` reads, and compared with the COLMAP sparse points.

use std::path::PathBuf;

use anyhow::{bail, Context as _};
use extranerf_gpu::Context;
use extranerf_nerf::data::colmap::read_points3d;
use extranerf_nerf::data::depth::{read_view_depth, sparse_depth, view_depth_paths};
use extranerf_nerf::mvs_depth::{self, MvsDepthSettings};
use extranerf_nerf::run::{write_depth_exr, write_png};

use crate::nerf::SceneArgs;

/// Arguments of `extranerf mvs`.
#[derive(clap::Args, Debug)]
pub struct MvsArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// Match at 1/N of the images' resolution (box-filtered); maps are written at full size.
    #[arg(long, default_value_t = MvsDepthSettings::default().downscale)]
    downscale: u32,
    /// Depth planes, uniform in inverse depth.
    #[arg(long, default_value_t = MvsDepthSettings::default().planes)]
    planes: u32,
    /// Nearest plane in scene units (default: 0.8 x the smallest near bound of the views).
    #[arg(long)]
    near: Option<f32>,
    /// Farthest plane (default: 1.2 x the largest far bound).
    #[arg(long)]
    far: Option<f32>,
    /// NCC window radius ((2r+1)^2 pixels, r <= 3).
    #[arg(long, default_value_t = MvsDepthSettings::default().radius)]
    radius: u32,
    /// Sources averaged per plane (the lowest costs; robust to occlusion).
    #[arg(long, default_value_t = MvsDepthSettings::default().best_k)]
    best_k: u32,
    /// Other views whose depth must agree for a pixel to be kept.
    #[arg(long, default_value_t = MvsDepthSettings::default().min_agree)]
    min_agree: u32,
    /// Agreement: reprojection error in pixels (at the matching resolution).
    #[arg(long, default_value_t = MvsDepthSettings::default().px_tol)]
    px_tol: f32,
    /// Agreement: relative depth difference.
    #[arg(long, default_value_t = MvsDepthSettings::default().rel_tol)]
    rel_tol: f32,
    /// Jacobi sweeps of the colour-guided fill of the pixels kept without depth, in inverse
    /// depth at the matching resolution (0: none); the written maps and --truth-depth's figures
    /// include the filled pixels, the PNGs and the sparse agreement do not.
    #[arg(long, default_value_t = MvsDepthSettings::default().fill)]
    fill: u32,
    /// Exact depth maps to measure against (<image stem>.npy or .exr, view depth in the
    /// capture's units, as `train --depth-dir` reads them; e.g. ../shared/data/synth2/depth):
    /// the kept fraction of pixels with a true depth and the relative errors, in mvs.json.
    #[arg(long, value_name = "DIR")]
    truth_depth: Option<PathBuf>,
    /// Output folder: <image stem>.exr (depth along the viewing axis in the scene's source
    /// units, 0 where none; `extranerf train --depth-dir` reads these), _depth.png,
    /// _conf.png, mvs.json.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

/// Agreement of depths with reference depths (sparse points, or exact maps): relative errors
/// |d - d_ref| / d_ref of the `points` references (named `what` in the JSON) that have a depth.
fn agreement(errors: &mut [f64], points: usize, what: &str) -> serde_json::Value {
    errors.sort_by(f64::total_cmp);
    let n = errors.len();
    let within = |t: f64| errors.iter().filter(|&&e| e < t).count() as f64 / n.max(1) as f64;
    serde_json::json!({
        what: points,
        "with_depth": n,
        "coverage": n as f64 / points.max(1) as f64,
        "median_rel_error": if n > 0 { errors[n / 2] } else { f64::NAN },
        "mean_rel_error": errors.iter().sum::<f64>() / n.max(1) as f64,
        "within_1pct": within(0.01),
        "within_2pct": within(0.02),
        "within_5pct": within(0.05),
        "within_10pct": within(0.10),
    })
}

/// An agreement's median and within-2/5/10% shares, for the summary lines.
fn agreement_line(ag: &serde_json::Value) -> String {
    let pct = |k: &str, or: f64| 100.0 * ag[k].as_f64().unwrap_or(or);
    format!(
        "median error {:.2}%, within 2% / 5% / 10%: {:.1}% / {:.1}% / {:.1}%",
        pct("median_rel_error", f64::NAN),
        pct("within_2pct", 0.0),
        pct("within_5pct", 0.0),
        pct("within_10pct", 0.0)
    )
}

/// `extranerf mvs`.
pub fn mvs(ctx: &Context, a: &MvsArgs) -> anyhow::Result<()> {
    if a.downscale == 0 {
        bail!("--downscale must be at least 1");
    }
    let spec = a.scene.spec();
    let loaded = spec.load()?;
    let views: Vec<usize> = loaded.split.train.clone();
    let full: Vec<_> = views
        .iter()
        .map(|&i| loaded.scene.cameras[i].clone())
        .collect();
    let settings = MvsDepthSettings {
        downscale: a.downscale,
        planes: a.planes,
        near: a.near,
        far: a.far,
        radius: a.radius,
        best_k: a.best_k,
        min_agree: a.min_agree,
        px_tol: a.px_tol,
        rel_tol: a.rel_tol,
        fill: a.fill,
    };
    let (near, far) = settings.range(&full)?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    eprintln!(
        "plane sweep over {} views at 1/{} of {}x{}: {} planes from {near:.3} to {far:.3}, {}x{} windows, best {} sources",
        full.len(),
        a.downscale,
        full.first().map_or(0, |c| c.width),
        full.first().map_or(0, |c| c.height),
        a.planes,
        2 * a.radius + 1,
        2 * a.radius + 1,
        a.best_k
    );
    let scene_depth = mvs_depth::compute(ctx, &full, &settings)?;
    let seconds = scene_depth.seconds;
    let maps = &scene_depth.maps;
    eprintln!(
        "done in {seconds:.1} s ({:.2} s per view)",
        seconds / full.len() as f64
    );
    // Sparse points, when the scene has them.
    let points_path = extranerf_nerf::run::points_path(&a.scene.scene);
    let points = if points_path.exists() {
        Some(read_points3d(&points_path)?)
    } else {
        None
    };
    let world = points.as_ref().map(|p| loaded.scene.transform_points(p));
    // Scene units -> the source's units (what --depth-dir expects).
    let scale = loaded.scene.world_from_source.x_axis.truncate().length();
    let (mut all_kept, mut all_raw, mut all_points) = (Vec::new(), Vec::new(), 0);
    // Against exact depth: relative errors of kept pixels, and pixels with a true depth.
    let (mut truth_errors, mut truth_pixels) = (Vec::new(), 0usize);
    let mut rows = Vec::new();
    for (k, (&vi, m)) in views.iter().zip(maps).enumerate() {
        let c = &full[k];
        let stem = c
            .image
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_else(|| format!("view_{vi:03}"));
        // Nearest-neighbour upsampling to the view's size (the sparse comparison below).
        let at = |map: &[f32], x: u32, y: u32| {
            let sx = (x / a.downscale).min(m.width - 1);
            let sy = (y / a.downscale).min(m.height - 1);
            map[(sy * m.width + sx) as usize]
        };
        let full_depth: Vec<f32> = scene_depth.views[k]
            .depth
            .iter()
            .map(|&d| d / scale as f32)
            .collect();
        write_depth_exr(
            &a.out.join(format!("{stem}.exr")),
            c.width,
            c.height,
            &full_depth,
        )?;
        let inv = |d: f32| {
            if d > 0.0 {
                ((1.0 / d - 1.0 / far) / (1.0 / near - 1.0 / far)).clamp(0.0, 1.0)
            } else {
                0.0
            }
        };
        let vis: Vec<f32> = m.depth.iter().flat_map(|&d| [inv(d); 3]).collect();
        write_png(
            &a.out.join(format!("{stem}_depth.png")),
            m.width,
            m.height,
            &vis,
        )?;
        let conf: Vec<f32> = m.confidence.iter().flat_map(|&v| [v; 3]).collect();
        write_png(
            &a.out.join(format!("{stem}_conf.png")),
            m.width,
            m.height,
            &conf,
        )?;
        let mut row = serde_json::json!({
            "view": vi,
            "image": stem,
            "coverage": m.coverage(),
            "raw_coverage": m.raw_depth.iter().filter(|&&d| d > 0.0).count() as f64 / m.raw_depth.len().max(1) as f64,
        });
        if let (Some(w), Some(p)) = (&world, &points) {
            let samples = sparse_depth(c, w, p);
            let (mut kept, mut raw) = (Vec::new(), Vec::new());
            for s in &samples {
                let d = at(&m.depth, s.x, s.y) as f64;
                if d > 0.0 {
                    kept.push((d - s.depth).abs() / s.depth);
                }
                let d = at(&m.raw_depth, s.x, s.y) as f64;
                if d > 0.0 {
                    raw.push((d - s.depth).abs() / s.depth);
                }
            }
            all_points += samples.len();
            row["sparse_agreement"] = agreement(&mut kept.clone(), samples.len(), "sparse_points");
            row["sparse_agreement_before_consistency"] =
                agreement(&mut raw.clone(), samples.len(), "sparse_points");
            let ag = &row["sparse_agreement"];
            eprintln!(
                "view {vi} ({stem}): {:.1}% of pixels kept; {} sparse points, {:.1}% with depth, median error {:.2}%, {:.1}% within 5%",
                100.0 * m.coverage(),
                samples.len(),
                100.0 * ag["coverage"].as_f64().unwrap_or(0.0),
                100.0 * ag["median_rel_error"].as_f64().unwrap_or(f64::NAN),
                100.0 * ag["within_5pct"].as_f64().unwrap_or(0.0)
            );
            all_kept.extend(kept);
            all_raw.extend(raw);
        } else {
            eprintln!(
                "view {vi} ({stem}): {:.1}% of pixels kept",
                100.0 * m.coverage()
            );
        }
        if let Some(dir) = &a.truth_depth {
            let Some(truth) = read_view_depth(dir, c)? else {
                let [npy, exr] = view_depth_paths(dir, c);
                bail!(
                    "{}: no exact depth for view {vi}: expected {} or {}",
                    dir.display(),
                    npy.display(),
                    exr.display()
                );
            };
            let mut errors = Vec::new();
            let mut with_truth = 0usize;
            for (&d, &t) in full_depth.iter().zip(&truth) {
                if t > 0.0 {
                    with_truth += 1;
                    if d > 0.0 {
                        errors.push(((d - t) / t).abs() as f64);
                    }
                }
            }
            truth_pixels += with_truth;
            truth_errors.extend_from_slice(&errors);
            row["truth_agreement"] = agreement(&mut errors, with_truth, "truth_pixels");
        }
        rows.push(row);
    }
    let mut doc = serde_json::json!({
        "scene": a.scene.scene,
        "split": a.scene.views.kind(&a.scene.scene),
        "factor": a.scene.views.factor,
        "downscale": a.downscale,
        "width": scene_depth.width,
        "height": scene_depth.height,
        "planes": a.planes,
        "near": near,
        "far": far,
        "radius": a.radius,
        "best_k": a.best_k,
        "min_agree": a.min_agree,
        "px_tol": a.px_tol,
        "rel_tol": a.rel_tol,
        "seconds": seconds,
        "device": ctx.info().name,
        "views": rows,
    });
    if points.is_some() {
        doc["sparse_agreement"] = agreement(&mut all_kept, all_points, "sparse_points");
        doc["sparse_agreement_before_consistency"] =
            agreement(&mut all_raw, all_points, "sparse_points");
        let ag = &doc["sparse_agreement"];
        eprintln!(
            "all views: {all_points} sparse points, {:.1}% with a kept depth; {}",
            100.0 * ag["coverage"].as_f64().unwrap_or(0.0),
            agreement_line(ag)
        );
    } else {
        eprintln!(
            "no sparse points ({}): agreement not measured",
            points_path.display()
        );
    }
    if a.truth_depth.is_some() {
        doc["truth_agreement"] = agreement(&mut truth_errors, truth_pixels, "truth_pixels");
        let ag = &doc["truth_agreement"];
        eprintln!(
            "against the exact depth: {:.1}% of {truth_pixels} pixels kept; {}",
            100.0 * ag["coverage"].as_f64().unwrap_or(0.0),
            agreement_line(ag)
        );
    }
    crate::bench::write_json(&a.out.join("mvs.json"), &doc)?;
    eprintln!("wrote {}", a.out.display());
    Ok(())
}
