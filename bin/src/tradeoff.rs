//! `extranerf bench tradeoff`: what each speed knob costs in quality. Trains one model per
//! sweep point on a scene (one knob changed from a base at a time, plus the auto-config's
//! choice), scores the held-out views, and writes CSV, JSON and an SVG plot of quality against
//! training time with the Pareto frontier marked.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context as _};
use extranerf_gpu::Context;
use extranerf_nerf::data::load_image;
use extranerf_nerf::data::split::SplitKind;
use extranerf_nerf::image_ops::downscale_rgb;
use extranerf_nerf::metrics::{psnr, ssim, Lpips};
use extranerf_nerf::model::Precision;
use extranerf_nerf::render::march::MarchCuts;
use extranerf_nerf::renderer::March;
use extranerf_nerf::run::{RunConfig, SceneSpec};
use extranerf_nerf::trainer::TrainConfig;
use extranerf_prims::Prims;

/// Arguments of `extranerf bench tradeoff`.
#[derive(clap::Args, Debug)]
pub struct TradeoffArgs {
    /// Scene: an LLFF folder or a transforms.json scene.
    #[arg(long, value_name = "DIR")]
    scene: PathBuf,
    /// Split (extrapolation, fewshot, all).
    #[arg(long, value_enum, default_value_t = SplitKind::Extrapolation)]
    split: SplitKind,
    /// LLFF downsampling factor.
    #[arg(long, default_value_t = 8)]
    factor: u32,
    /// Steps of the base point (the steps points scale it).
    #[arg(long, default_value_t = 800)]
    steps: u32,
    /// Rays per step of the base point.
    #[arg(long, default_value_t = 128)]
    rays: u32,
    /// Samples per ray of the base point.
    #[arg(long, default_value_t = 32)]
    samples: u32,
    /// log2 table size of the base point.
    #[arg(long, default_value_t = 17)]
    log2_table: u32,
    /// Sweep points to run (comma-separated names; see the table this prints with --list).
    #[arg(long, value_delimiter = ',')]
    points: Option<Vec<String>>,
    /// Print the sweep points and exit.
    #[arg(long)]
    list: bool,
    /// Score the held-out views at 1/N resolution (1: full).
    #[arg(long, default_value_t = 2)]
    eval_downscale: u32,
    /// Folder with lpips_alex_v0.1.safetensors (default: $EXTRANERF_MODELS/lpips, else
    /// ../shared/models/lpips).
    #[arg(long)]
    lpips: Option<PathBuf>,
    /// Output folder: tradeoff.csv, tradeoff.json, tradeoff.svg.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Keep the points already in OUT/tradeoff.json and add these (a point of the same name is
    /// replaced).
    #[arg(long)]
    append: bool,
}

/// One sweep point: a name, what it changes, and the change.
struct Point {
    name: &'static str,
    knob: &'static str,
    apply: fn(&mut RunConfig),
}

fn points() -> Vec<Point> {
    fn steps(c: &mut RunConfig, f: f64) {
        let s = ((c.train.steps as f64 * f) as u32).max(1);
        c.train.steps = s;
        c.train.decay_steps = s;
    }
    vec![
        Point {
            name: "base",
            knob: "base",
            apply: |_| {},
        },
        Point {
            name: "table14",
            knob: "table size T",
            apply: |c| c.model.log2_table = 14,
        },
        Point {
            name: "table19",
            knob: "table size T",
            apply: |c| c.model.log2_table = 19,
        },
        Point {
            name: "levels8",
            knob: "levels L",
            apply: |c| c.model.levels = 8,
        },
        Point {
            name: "features4",
            knob: "features F",
            apply: |c| c.model.features = 4,
        },
        Point {
            name: "maxres512",
            knob: "finest resolution",
            apply: |c| c.model.max_res = 512,
        },
        Point {
            name: "samples16",
            knob: "samples per ray",
            apply: |c| c.train.samples = 16,
        },
        Point {
            name: "samples64",
            knob: "samples per ray",
            apply: |c| c.train.samples = 64,
        },
        Point {
            name: "rays64",
            knob: "batch (rays)",
            apply: |c| c.train.rays = 64,
        },
        Point {
            name: "rays256",
            knob: "batch (rays)",
            apply: |c| c.train.rays = 256,
        },
        Point {
            name: "steps0.5x",
            knob: "steps",
            apply: |c| steps(c, 0.5),
        },
        Point {
            name: "steps2x",
            knob: "steps",
            apply: |c| steps(c, 2.0),
        },
        Point {
            name: "occ32",
            knob: "occupancy resolution",
            apply: |c| c.train.occupancy_res = 32,
        },
        Point {
            name: "occ64",
            knob: "occupancy resolution",
            apply: |c| c.train.occupancy_res = 64,
        },
        Point {
            name: "occ64x2",
            knob: "occupancy cascades",
            apply: |c| {
                c.train.occupancy_res = 64;
                c.train.occupancy_cascades = 2;
            },
        },
        Point {
            name: "occ64s16",
            knob: "occupancy + samples",
            apply: |c| {
                c.train.occupancy_res = 64;
                c.train.samples = 16;
            },
        },
        Point {
            name: "f16",
            knob: "precision",
            apply: |c| c.model.precision = Precision::F16,
        },
        Point {
            name: "auto",
            knob: "auto-config",
            apply: |_| {},
        },
    ]
}

/// One measured point.
struct Row {
    name: String,
    knob: String,
    cfg: RunConfig,
    train_s: f64,
    samples_per_s: f64,
    psnr: f64,
    ssim: f64,
    lpips: f64,
    device_mib: f64,
    failed: Option<String>,
}

/// Indices of the points no other point beats in both training time and PSNR.
fn pareto(rows: &[Row]) -> Vec<usize> {
    let ok: Vec<usize> = (0..rows.len())
        .filter(|&i| rows[i].failed.is_none() && rows[i].psnr.is_finite())
        .collect();
    ok.iter()
        .copied()
        .filter(|&i| {
            !ok.iter().any(|&j| {
                j != i
                    && rows[j].train_s <= rows[i].train_s
                    && rows[j].psnr >= rows[i].psnr
                    && (rows[j].train_s < rows[i].train_s || rows[j].psnr > rows[i].psnr)
            })
        })
        .collect()
}

fn svg(rows: &[Row], front: &[usize], title: &str) -> String {
    let ok: Vec<&Row> = rows.iter().filter(|r| r.failed.is_none()).collect();
    let (w, h, m) = (760.0, 480.0, 70.0);
    let tmax = ok.iter().map(|r| r.train_s).fold(1.0, f64::max) * 1.1;
    let (pmin, pmax) = ok
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), r| {
            (a.min(r.psnr), b.max(r.psnr))
        });
    let (pmin, pmax) = if pmin.is_finite() {
        (pmin - 0.5, pmax + 0.5)
    } else {
        (0.0, 1.0)
    };
    let x = |t: f64| m + (t / tmax) * (w - 2.0 * m);
    let y = |p: f64| h - m - (p - pmin) / (pmax - pmin) * (h - 2.0 * m);
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(s, r#"<rect width="{w}" height="{h}" fill="white"/>"#);
    let _ = writeln!(
        s,
        r#"<text x="{}" y="24" text-anchor="middle" font-size="15">{title}</text>"#,
        w / 2.0
    );
    // Axes and ticks.
    let _ = writeln!(
        s,
        r#"<line x1="{m}" y1="{}" x2="{}" y2="{}" stroke="black"/><line x1="{m}" y1="{m}" x2="{m}" y2="{}" stroke="black"/>"#,
        h - m,
        w - m,
        h - m,
        h - m
    );
    for k in 0..=5 {
        let t = tmax * k as f64 / 5.0;
        let _ = writeln!(
            s,
            r#"<text x="{:.1}" y="{}" text-anchor="middle">{t:.0}</text>"#,
            x(t),
            h - m + 18.0
        );
        let p = pmin + (pmax - pmin) * k as f64 / 5.0;
        let _ = writeln!(
            s,
            r#"<text x="{}" y="{:.1}" text-anchor="end">{p:.1}</text>"#,
            m - 6.0,
            y(p) + 4.0
        );
    }
    let _ = writeln!(
        s,
        r#"<text x="{}" y="{}" text-anchor="middle">training time (s)</text>"#,
        w / 2.0,
        h - 20.0
    );
    let _ = writeln!(
        s,
        r#"<text x="18" y="{}" text-anchor="middle" transform="rotate(-90 18 {})">test PSNR (dB)</text>"#,
        h / 2.0,
        h / 2.0
    );
    // The frontier as a step line, then the points.
    let mut f: Vec<&Row> = front.iter().map(|&i| &rows[i]).collect();
    f.sort_by(|a, b| a.train_s.total_cmp(&b.train_s));
    let pts: Vec<String> = f
        .iter()
        .map(|r| format!("{:.1},{:.1}", x(r.train_s), y(r.psnr)))
        .collect();
    let _ = writeln!(
        s,
        r#"<polyline points="{}" fill="none" stroke="crimson" stroke-width="1.5"/>"#,
        pts.join(" ")
    );
    for (i, r) in rows.iter().enumerate() {
        if r.failed.is_some() {
            continue;
        }
        let on = front.contains(&i);
        let colour = if r.name == "auto" {
            "royalblue"
        } else if on {
            "crimson"
        } else {
            "grey"
        };
        let _ = writeln!(
            s,
            r#"<circle cx="{:.1}" cy="{:.1}" r="5" fill="{colour}"/><text x="{:.1}" y="{:.1}">{}</text>"#,
            x(r.train_s),
            y(r.psnr),
            x(r.train_s) + 7.0,
            y(r.psnr) - 6.0,
            r.name
        );
    }
    let _ = writeln!(
        s,
        r#"<text x="{}" y="{}" text-anchor="end" fill="crimson">red: Pareto frontier; blue: auto-config</text>"#,
        w - m,
        m - 12.0
    );
    s.push_str("</svg>\n");
    s
}

/// `extranerf bench tradeoff`.
pub fn tradeoff(ctx: &Context, a: &TradeoffArgs) -> anyhow::Result<()> {
    let all = points();
    if a.list {
        for p in &all {
            println!("{:<12} {}", p.name, p.knob);
        }
        return Ok(());
    }
    let chosen: Vec<&Point> = match &a.points {
        None => all.iter().collect(),
        Some(names) => names
            .iter()
            .map(|n| {
                all.iter()
                    .find(|p| p.name == n.as_str())
                    .ok_or_else(|| anyhow::anyhow!("--points: no point `{n}` (see --list)"))
            })
            .collect::<anyhow::Result<_>>()?,
    };
    if a.eval_downscale == 0 || a.steps == 0 {
        bail!("--eval-downscale and --steps must be positive");
    }
    let spec = SceneSpec {
        dir: a.scene.clone(),
        split: a.split,
        fewshot_views: 3,
        factor: a.factor,
        sparse_depth: true,
        depth_dir: None,
        mvs_depth: None,
        capture_depth: false,
    };
    let loaded = spec.load()?;
    let lpips = extranerf_nerf::train::lpips_alex(a.lpips.as_deref())?;
    // Held-out views and their ground truth at the scoring resolution, loaded once.
    let mut tests = Vec::new();
    for &i in &loaded.split.test {
        let cam = &loaded.scene.cameras[i];
        let img = load_image(&cam.image)?;
        let (rgb, w, h) = downscale_rgb(&img.rgb, img.width, img.height, a.eval_downscale)
            .with_context(|| cam.image.display().to_string())?;
        tests.push((cam.downscaled(a.eval_downscale), rgb, w, h));
    }
    if tests.is_empty() {
        bail!(
            "the {} split of {} holds no held-out views to score",
            a.split,
            a.scene.display()
        );
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let prims = Prims::new(ctx)?;
    let mut rows: Vec<Row> = if a.append {
        previous_rows(a, &spec)?
            .into_iter()
            .filter(|r| !chosen.iter().any(|p| p.name == r.name))
            .collect()
    } else {
        Vec::new()
    };
    for p in chosen {
        let mut model = extranerf_nerf::autoconfig::model_for_scene(&loaded.scene);
        model.log2_table = a.log2_table;
        let train = TrainConfig {
            steps: a.steps,
            decay_steps: a.steps,
            rays: a.rays,
            samples: a.samples,
            ..TrainConfig::default()
        };
        let mut cfg = RunConfig {
            scene: spec.clone(),
            model,
            train,
        };
        if p.name == "auto" {
            cfg.model =
                extranerf_nerf::autoconfig::auto_model(&loaded.scene, &loaded.split.train).model;
        }
        (p.apply)(&mut cfg);
        eprintln!(
            "[{}] {}: L{} F{} T2^{} N..{} {} | {} rays x {} samples, {} steps, occupancy {}",
            p.name,
            p.knob,
            cfg.model.levels,
            cfg.model.features,
            cfg.model.log2_table,
            cfg.model.max_res,
            cfg.model.precision,
            cfg.train.rays,
            cfg.train.samples,
            cfg.train.steps,
            match cfg.train.occupancy_res {
                0 => "off".to_string(),
                r => match cfg.train.occupancy_cascades {
                    0 => format!("{r}^3, cascades from the bounds"),
                    c => format!("{r}^3 x {c} cascades"),
                },
            }
        );
        let row = match run_point(ctx, &prims, &cfg, &loaded, &tests, &lpips, &a.out) {
            Ok((train_s, sps, ps, ss, lp, mib)) => Row {
                name: p.name.into(),
                knob: p.knob.into(),
                cfg,
                train_s,
                samples_per_s: sps,
                psnr: ps,
                ssim: ss,
                lpips: lp,
                device_mib: mib,
                failed: None,
            },
            Err(e) => Row {
                name: p.name.into(),
                knob: p.knob.into(),
                cfg,
                train_s: f64::NAN,
                samples_per_s: f64::NAN,
                psnr: f64::NAN,
                ssim: f64::NAN,
                lpips: f64::NAN,
                device_mib: f64::NAN,
                failed: Some(format!("{e:#}")),
            },
        };
        match &row.failed {
            None => eprintln!(
                "[{}] train {:.1} s ({:.3e} samples/s), test PSNR {:.2} SSIM {:.4} LPIPS {:.4}, {:.0} MiB on the device",
                row.name, row.train_s, row.samples_per_s, row.psnr, row.ssim, row.lpips, row.device_mib
            ),
            Some(e) => eprintln!("[{}] failed: {e}", row.name),
        }
        rows.push(row);
        write_outputs(a, &rows)?;
    }
    let front = pareto(&rows);
    println!(
        "{:<11} {:<18} {:>9} {:>11} {:>7} {:>7} {:>7} {:>8}  frontier",
        "point", "knob", "train s", "samples/s", "PSNR", "SSIM", "LPIPS", "MiB"
    );
    for (i, r) in rows.iter().enumerate() {
        println!(
            "{:<11} {:<18} {:>9.1} {:>11.3e} {:>7.2} {:>7.4} {:>7.4} {:>8.0}  {}",
            r.name,
            r.knob,
            r.train_s,
            r.samples_per_s,
            r.psnr,
            r.ssim,
            r.lpips,
            r.device_mib,
            if front.contains(&i) { "yes" } else { "" }
        );
    }
    println!("wrote {}", a.out.display());
    Ok(())
}

/// The points of an earlier run in OUT/tradeoff.json.
fn previous_rows(a: &TradeoffArgs, spec: &SceneSpec) -> anyhow::Result<Vec<Row>> {
    let path = a.out.join("tradeoff.json");
    let text =
        std::fs::read(&path).with_context(|| format!("--append: reading {}", path.display()))?;
    let doc: serde_json::Value = serde_json::from_slice(&text)
        .with_context(|| format!("--append: {} is not JSON", path.display()))?;
    let Some(points) = doc["points"].as_array() else {
        bail!("--append: {} has no `points` array", path.display());
    };
    let num = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    points
        .iter()
        .map(|p| {
            let bad = || anyhow::anyhow!("--append: a point in {} is malformed", path.display());
            Ok(Row {
                name: p["point"].as_str().ok_or_else(bad)?.into(),
                knob: p["knob"].as_str().ok_or_else(bad)?.into(),
                cfg: RunConfig {
                    scene: spec.clone(),
                    model: serde_json::from_value(p["model"].clone()).map_err(|_| bad())?,
                    train: serde_json::from_value(p["train"].clone()).map_err(|_| bad())?,
                },
                train_s: num(&p["train_s"]),
                samples_per_s: num(&p["samples_per_s"]),
                psnr: num(&p["psnr"]),
                ssim: num(&p["ssim"]),
                lpips: num(&p["lpips_alex"]),
                device_mib: num(&p["device_mib"]),
                failed: p["failed"].as_str().map(String::from),
            })
        })
        .collect()
}

/// Trains one point (MVS depth, if its scene asked for it, cached in `out`) and scores it: (train seconds, samples/s, PSNR, SSIM, LPIPS, device MiB).
/// Device memory is the allocator's live bytes, sampled after the trainer is set up and after
/// each held-out render (the training step allocates nothing per step).
fn run_point(
    ctx: &Context,
    prims: &Prims,
    cfg: &RunConfig,
    loaded: &extranerf_nerf::run::LoadedScene,
    tests: &[(extranerf_nerf::data::Camera, Vec<f32>, u32, u32)],
    lpips: &Lpips,
    out: &std::path::Path,
) -> anyhow::Result<(f64, f64, f64, f64, f64, f64)> {
    let (mut trainer, data) = extranerf_nerf::train::fresh_trainer(ctx, cfg, loaded, out)?;
    let mut peak = ctx.allocated_bytes()?.0;
    let t = Instant::now();
    while trainer.step() < cfg.train.steps {
        let n = 64.min(cfg.train.steps - trainer.step());
        let s = trainer.run_steps(ctx, prims, &data, n)?;
        if !(s.loss.is_finite() && s.mse.is_finite()) {
            bail!("the loss became {} at step {}", s.loss, trainer.step());
        }
    }
    let train_s = t.elapsed().as_secs_f64();
    let sps = cfg.train.steps as f64 * trainer.samples_per_step() as f64 / train_s;
    if let Some(f) = trainer.occupied_fraction()? {
        eprintln!(
            "  training occupancy grid: {:.1}% of cells occupied at the end",
            100.0 * f
        );
    }
    let (mut p, mut q, mut l) = (0.0, 0.0, 0.0);
    for (cam, truth, w, h) in tests {
        let (rgb, _, _) = trainer.nerf().render_with(
            ctx,
            cam,
            8192,
            cfg.train.samples,
            March::Fused(MarchCuts::EXACT),
        )?;
        peak = peak.max(ctx.allocated_bytes()?.0);
        p += psnr(&rgb, truth)?;
        q += ssim(&rgb, truth, *w, *h)?;
        l += lpips.distance(&rgb, truth, *w, *h)?;
    }
    let n = tests.len().max(1) as f64;
    Ok((
        train_s,
        sps,
        p / n,
        q / n,
        l / n,
        peak as f64 / (1 << 20) as f64,
    ))
}

fn write_outputs(a: &TradeoffArgs, rows: &[Row]) -> anyhow::Result<()> {
    let front = pareto(rows);
    let mut csv = String::from(
        "point,knob,levels,features,log2_table,max_res,rays,samples,steps,precision,occupancy_res,occupancy_cascades,train_s,samples_per_s,psnr,ssim,lpips_alex,device_mib,pareto,failed\n",
    );
    for (i, r) in rows.iter().enumerate() {
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{},{},{},{},{:.2},{:.4e},{:.4},{:.5},{:.5},{:.1},{},{}",
            r.name,
            r.knob,
            r.cfg.model.levels,
            r.cfg.model.features,
            r.cfg.model.log2_table,
            r.cfg.model.max_res,
            r.cfg.train.rays,
            r.cfg.train.samples,
            r.cfg.train.steps,
            r.cfg.model.precision,
            r.cfg.train.occupancy_res,
            r.cfg.train.occupancy_cascades,
            r.train_s,
            r.samples_per_s,
            r.psnr,
            r.ssim,
            r.lpips,
            r.device_mib,
            front.contains(&i),
            r.failed.clone().unwrap_or_default().replace(',', ";")
        );
    }
    let csv_path = a.out.join("tradeoff.csv");
    extranerf_gpu::files::write_atomic(&csv_path, csv.as_bytes())
        .with_context(|| format!("writing {}", csv_path.display()))?;
    let json: Vec<serde_json::Value> = rows
        .iter()
        .enumerate()
        .map(|(i, r)| {
            serde_json::json!({
                "point": r.name, "knob": r.knob, "model": r.cfg.model, "train": r.cfg.train,
                "precision": r.cfg.model.precision, "train_s": r.train_s, "samples_per_s": r.samples_per_s,
                "psnr": r.psnr, "ssim": r.ssim, "lpips_alex": r.lpips, "device_mib": r.device_mib,
                "pareto": front.contains(&i), "failed": r.failed,
            })
        })
        .collect();
    crate::bench::write_json(
        &a.out.join("tradeoff.json"),
        &serde_json::json!({
            "scene": a.scene, "split": a.split, "factor": a.factor,
            "eval_downscale": a.eval_downscale, "points": json,
        }),
    )?;
    let name: String = a
        .scene
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
        .chars()
        .filter(|c| c.is_alphanumeric() || matches!(c, '_' | '-' | '.' | ' '))
        .collect();
    let title = format!("{name}: test PSNR against training time");
    let svg_path = a.out.join("tradeoff.svg");
    extranerf_gpu::files::write_atomic(&svg_path, svg(rows, &front, &title).as_bytes())
        .with_context(|| format!("writing {}", svg_path.display()))?;
    Ok(())
}
