//! Numerical stability at the ends the other suites do not reach: learning rates at both ends,
//! coincident training cameras (training, visibility, stereo), and settings that cannot work
//! giving a clear error.
//!
//! The rest of the stability suite lives beside the kernels it checks: densities 0 to 1e8 and
//! step sizes to 1e-7 in render.rs (compositing, distortion); coordinates to 1e30 under
//! contraction in field.rs; axis-parallel rays in render.rs, march.rs, train.rs and
//! visibility.rs; all-black and all-white images in train.rs; gradients of 1e30 and 1e-30 in
//! optim.rs; opaque and empty fields in march.rs and visibility.rs; the f16 table's overflow,
//! underflow and NaN, and the f16 MLP record under output gradients scaled by 1e-9 and 1e6, in
//! field.rs. Training with the f16 table and with the occupancy grid is
//! checked here.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_nerf::model::{init_params, ModelConfig};
use extranerf_nerf::mvs::{Mvs, MvsConfig};
use extranerf_nerf::render::visibility::{
    AnalyticField, Density, Shape, Visibility, VisibilityConfig,
};
use extranerf_nerf::renderer::Nerf;
use extranerf_nerf::trainer::{TrainConfig, Trainer};
use extranerf_nerf::views::{TrainData, View};
use extranerf_tests::{assert_no_validation_messages, demo_training_views, engine, tiny_model};

fn demo_views(name: &str) -> Vec<View> {
    demo_training_views(name, &tiny_model())
}

/// Trains `steps` steps and returns (first window MSE, last window MSE, parameters).
fn train(views: &[View], cfg: TrainConfig) -> (f64, f64, Vec<f32>, Vec<f32>) {
    train_model(views, cfg, tiny_model())
}

fn train_model(
    views: &[View],
    cfg: TrainConfig,
    model: ModelConfig,
) -> (f64, f64, Vec<f32>, Vec<f32>) {
    let e = engine();
    let ctx = &e.ctx;
    let p0 = init_params(&model, 2);
    let nerf = Nerf::new(ctx, model, &p0, cfg.background).unwrap();
    let data = TrainData::new(ctx, views).unwrap();
    let half = cfg.steps / 2;
    let mut t = Trainer::new(ctx, nerf, cfg, 0, None).unwrap();
    let first = t.run_steps(ctx, &e.prims, &data, half).unwrap();
    let last = t.run_steps(ctx, &e.prims, &data, half).unwrap();
    assert!(
        first.loss.is_finite() && last.loss.is_finite(),
        "{first:?} {last:?}"
    );
    let (m, v) = t.moments().unwrap();
    assert!(m.iter().chain(&v).all(|x| x.is_finite()));
    (first.mse, last.mse, p0, t.nerf().params().read().unwrap())
}

#[test]
fn learning_rates_at_both_ends_stay_finite() {
    let views = demo_views("stability-lr");
    let base = TrainConfig {
        steps: 30,
        decay_steps: 30,
        rays: 64,
        samples: 8,
        ..TrainConfig::default()
    };
    // Tiny: the parameters barely move (Adam's step is about the learning rate).
    let (_, _, p0, p) = train(
        &views,
        TrainConfig {
            lr_start: 1e-12,
            lr_end: 1e-12,
            ..base.clone()
        },
    );
    let moved = p0
        .iter()
        .zip(&p)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(moved <= 1e-9, "parameters moved by {moved}");
    // Huge: Adam bounds each step, so parameters stay finite even when the fit is poor. By
    // Cauchy-Schwarz, |m_hat / sqrt(v_hat)| at step t is at most
    // (1 - b1) / sqrt(1 - b2) * sqrt((1 - r^t) / (1 - r)) * sqrt(1 - b2^t) / (1 - b1^t) with
    // r = b1^2 / b2: exactly 1 at the first step, about 2.3 at most later (b1 0.9, b2 0.99).
    // Each step is checked against it, and the first must move some parameter by the whole
    // learning rate (Adam's first step is lr * g / |g|).
    let adam = extranerf_nerf::optim::AdamConfig::default();
    let (b1, b2) = (adam.beta1 as f64, adam.beta2 as f64);
    let bound = |t: i32| {
        let r = b1 * b1 / b2;
        (1.0 - b1) / (1.0 - b2).sqrt()
            * ((1.0 - r.powi(t)) / (1.0 - r)).sqrt()
            * (1.0 - b2.powi(t)).sqrt()
            / (1.0 - b1.powi(t))
    };
    assert!((bound(1) - 1.0).abs() < 1e-12 && bound(30) < 2.4);
    let e = engine();
    for lr in [1.0f32, 100.0] {
        let cfg = TrainConfig {
            lr_start: lr,
            lr_end: lr,
            ..base.clone()
        };
        let p0 = init_params(&tiny_model(), 2);
        let nerf = Nerf::new(&e.ctx, tiny_model(), &p0, cfg.background).unwrap();
        let data = TrainData::new(&e.ctx, &views).unwrap();
        let mut t = Trainer::new(&e.ctx, nerf, cfg.clone(), 0, None).unwrap();
        let mut prev = p0;
        for step in 1..=cfg.steps as i32 {
            let st = t.run_steps(&e.ctx, &e.prims, &data, 1).unwrap();
            let p = t.nerf().params().read().unwrap();
            assert!(
                st.loss.is_finite() && p.iter().all(|v| v.is_finite()),
                "lr {lr} step {step}"
            );
            let moved = p
                .iter()
                .zip(&prev)
                .map(|(a, b)| (a - b).abs() as f64)
                .fold(0.0, f64::max);
            let most = lr as f64 * bound(step);
            assert!(
                moved <= most * (1.0 + 1e-4),
                "lr {lr} step {step}: a parameter moved {moved}, Adam allows {most}"
            );
            if step == 1 {
                assert!(
                    moved >= lr as f64 * (1.0 - 1e-4),
                    "lr {lr}: the first step moved at most {moved}"
                );
            }
            prev = p;
        }
    }
    // Settings that cannot work are refused with the reason.
    for (a, b) in [(0.0f32, 1e-3), (1e-2, f32::NAN), (-1.0, 1e-3)] {
        let c = TrainConfig {
            lr_start: a,
            lr_end: b,
            ..base.clone()
        };
        let e = c.validate().unwrap_err();
        assert!(e.to_string().contains("learning rates"), "{e}");
    }
    assert_no_validation_messages(&engine().ctx);
}

#[test]
fn coincident_cameras_train_and_give_finite_visibility_and_stereo() {
    let ctx = &engine().ctx;
    // Training on two copies of every view (coincident cameras) still fits.
    let views = demo_views("stability-coincident");
    let twice: Vec<View> = views.iter().chain(&views).cloned().collect();
    let cfg = TrainConfig {
        steps: 40,
        decay_steps: 40,
        rays: 64,
        samples: 8,
        ..TrainConfig::default()
    };
    let (first, last, _, p) = train(&twice, cfg);
    assert!(last < first, "{first} -> {last}");
    assert!(p.iter().all(|v| v.is_finite()));

    // Visibility with two coincident cameras: rank 2 sees what rank 1 with one camera sees.
    let field = AnalyticField::new(
        ctx,
        &[Shape::Box {
            min: [-5.0, -5.0, -4.0],
            max: [5.0, 5.0, -3.5],
            sigma: 30.0,
            soft: 0.05,
        }],
        false,
        0.5,
        8.0,
    )
    .unwrap();
    let cam = views[0].camera.clone();
    let v = Visibility::new(ctx).unwrap();
    let d = Density::Analytic(&field);
    let cfg = |rank| VisibilityConfig {
        samples: 32,
        vis_samples: 16,
        rank,
        ..VisibilityConfig::default()
    };
    let pair = [cam.clone(), cam.clone()];
    let two = v
        .map(ctx, &d, &cam, &pair, 0b11, &cfg(2), None, 256)
        .unwrap();
    let one = v
        .map(ctx, &d, &cam, &pair[..1], 0b1, &cfg(1), None, 256)
        .unwrap();
    for (a, b) in two.visibility.iter().zip(&one.visibility) {
        assert!(a.is_finite() && (a - b).abs() < 1e-6, "{a} vs {b}");
    }
    assert!(two.mean() > 0.5, "{}", two.mean());

    // Stereo with a zero baseline between two views: every plane warps alike; no NaN.
    let grey: Vec<Vec<f32>> = views
        .iter()
        .take(2)
        .map(|v| extranerf_nerf::image_ops::grey(&v.image.rgb))
        .collect();
    let cams = vec![views[0].camera.clone(), views[0].camera.clone()];
    let grey = vec![grey[0].clone(), grey[0].clone()];
    let out = Mvs::new(ctx)
        .unwrap()
        .run(
            ctx,
            &cams,
            &grey,
            &MvsConfig {
                min_agree: 1,
                ..MvsConfig::new(0.5, 8.0)
            },
        )
        .unwrap();
    for m in &out {
        assert!(m
            .raw_depth
            .iter()
            .chain(&m.raw_confidence)
            .chain(&m.depth)
            .all(|x| x.is_finite() && *x >= 0.0));
    }
    assert_no_validation_messages(ctx);
}

#[test]
fn training_with_the_f16_table_tracks_f32() {
    let views = demo_views("stability-f16");
    let cfg = TrainConfig {
        steps: 60,
        decay_steps: 60,
        rays: 64,
        samples: 8,
        ..TrainConfig::default()
    };
    let (f0, f1, _, p32) = train_model(&views, cfg.clone(), tiny_model());
    let half = ModelConfig {
        precision: extranerf_nerf::model::Precision::F16,
        ..tiny_model()
    };
    let (h0, h1, _, p16) = train_model(&views, cfg, half);
    assert!(h1 < h0, "f16: {h0} -> {h1}");
    assert!(p16.iter().all(|v| v.is_finite()));
    // The same batches and start: the f16 run ends near the f32 one.
    assert!(
        (h1 - f1).abs() <= 0.25 * f1 + 1e-4,
        "final MSE f16 {h1} vs f32 {f1} (started {h0} vs {f0})"
    );
    let drift = p32
        .iter()
        .zip(&p16)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    eprintln!("f16 vs f32 after 60 steps: final MSE {h1:.5} vs {f1:.5}, largest parameter difference {drift:.3e}");
    let bad = ModelConfig {
        precision: extranerf_nerf::model::Precision::F16,
        features: 4,
        ..tiny_model()
    };
    assert!(bad.validate().unwrap_err().to_string().contains("f16"));
}

/// Training with the occupancy grid (empty space skipped after a short warm-up) learns like
/// training without it, stays finite, and the grid marks part of the demo scene empty. The
/// field starts at a density near 1 everywhere, which 120 steps do not carve below the default
/// 1% opacity, so this run asks for 10% (a density threshold of 0.84 at 8 samples per unit).
/// It trains against a black background: with the random one (the default) these 120 steps
/// first raise the density everywhere, so that every cell of the grid is occupied.
#[test]
fn training_with_the_occupancy_grid_tracks_plain_sampling() {
    let views = demo_views("occupancy-train");
    let cfg = TrainConfig {
        steps: 120,
        decay_steps: 120,
        rays: 64,
        samples: 8,
        random_background: false,
        ..TrainConfig::default()
    };
    let (f0, f1, _, _) = train(&views, cfg.clone());
    let occ = TrainConfig {
        occupancy_res: 16,
        occupancy_every: 8,
        occupancy_warmup: 40,
        occupancy_probes: 64,
        occupancy_opacity: 0.1,
        ..cfg.clone()
    };
    let e = engine();
    let ctx = &e.ctx;
    let model = tiny_model();
    let nerf = Nerf::new(ctx, model.clone(), &init_params(&model, 2), occ.background).unwrap();
    let data = TrainData::new(ctx, &views).unwrap();
    let mut t = Trainer::new(ctx, nerf, occ, 0, None).unwrap();
    let first = t.run_steps(ctx, &e.prims, &data, 60).unwrap();
    let last = t.run_steps(ctx, &e.prims, &data, 60).unwrap();
    let frac = t.occupied_fraction().unwrap().unwrap();

    eprintln!(
        "occupancy training: MSE {:.5} -> {:.5} (plain {f0:.5} -> {f1:.5}), {:.1}% of cells occupied",
        first.mse,
        last.mse,
        100.0 * frac
    );
    assert!(last.loss.is_finite() && last.mse < first.mse);
    assert!(t
        .nerf()
        .params()
        .read()
        .unwrap()
        .iter()
        .all(|v| v.is_finite()));
    // A sixth of the cells is skipped where the field is still thin: a little slower to fit.
    assert!(last.mse <= 1.25 * f1 + 1e-4, "{} vs plain {f1}", last.mse);
    assert!(frac > 0.0 && frac < 1.0, "{frac}");
    // Settings the grid cannot take are refused.
    let bad = TrainConfig {
        occupancy_res: 16,
        occupancy_probes: 0,
        ..cfg
    };
    assert!(bad.validate().unwrap_err().to_string().contains("probes"));
    assert_no_validation_messages(ctx);
}
