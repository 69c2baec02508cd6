//! Tables larger than one storage binding, end to end: a context that treats bindings as
//! limited to 600 KiB (`ContextDesc::max_binding_bytes`) splits a 1 MiB hash table in two
//! ranges and updates the parameters range by range. Training steps, the fused render and the
//! visibility of the split model match the same model on the device's own limit.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_gpu::{Context, ContextDesc};
use extranerf_nerf::model::{init_params, ModelConfig};
use extranerf_nerf::render::march::MarchCuts;
use extranerf_nerf::renderer::{March, Nerf};
use extranerf_nerf::trainer::{TrainConfig, Trainer};
use extranerf_nerf::views::{TrainData, View};
use extranerf_prims::Prims;
use extranerf_tests::{assert_no_validation_messages, demo_training_views, desc};

const LIMIT: u64 = 600 << 10;

fn model() -> ModelConfig {
    // 8 hashed levels of 2^14 x 2 floats: 1 MiB of table.
    ModelConfig {
        levels: 8,
        features: 2,
        log2_table: 14,
        min_res: 64,
        max_res: 512,
        density_width: 16,
        density_layers: 1,
        geo_dims: 8,
        color_width: 16,
        color_layers: 2,
        ..ModelConfig::default()
    }
}

fn views() -> Vec<View> {
    demo_training_views("split-tables", &model())
}

/// Trains 30 steps on `ctx`; returns the per-window MSEs, the parameters and a fused render.
fn run(ctx: &Context, views: &[View]) -> (Vec<f64>, Vec<f32>, Vec<f32>, bool) {
    let prims = Prims::new(ctx).unwrap();
    let m = model();
    let cfg = TrainConfig {
        steps: 30,
        decay_steps: 30,
        rays: 64,
        samples: 8,
        ..TrainConfig::default()
    };
    let nerf = Nerf::new(ctx, m.clone(), &init_params(&m, 3), cfg.background).unwrap();
    let split = nerf.field().grid().split().is_some();
    let data = TrainData::new(ctx, views).unwrap();
    let mut t = Trainer::new(ctx, nerf, cfg, 0, None).unwrap();
    let mse: Vec<f64> = (0..3)
        .map(|_| t.run_steps(ctx, &prims, &data, 10).unwrap().mse)
        .collect();
    let (rgb, _, _) = t
        .nerf()
        .render_with(
            ctx,
            &views[0].camera,
            4096,
            8,
            March::Fused(MarchCuts::EXACT),
        )
        .unwrap();
    assert_no_validation_messages(ctx);
    (mse, t.nerf().params().read().unwrap(), rgb, split)
}

#[test]
fn split_tables_train_and_render_like_whole_ones() {
    let views = views();
    let whole = Context::new(&desc()).unwrap();
    let small = Context::new(&ContextDesc {
        max_binding_bytes: Some(LIMIT),
        max_memory_bytes: None,
        ..desc()
    })
    .unwrap();
    assert_eq!(small.info().max_storage_buffer_range, LIMIT);
    let (m0, p0, r0, s0) = run(&whole, &views);
    let (m1, p1, r1, s1) = run(&small, &views);
    assert!(!s0 && s1, "split: whole {s0}, limited {s1}");
    eprintln!("MSE per 10 steps: whole {m0:?}, split {m1:?}");
    for (a, b) in m0.iter().zip(&m1) {
        // The same batches; only the order of atomic additions differs.
        assert!((a - b).abs() <= 1e-3 * a.abs() + 1e-6, "{a} vs {b}");
    }
    assert!(m1[2] < m1[0]);
    let drift = p0
        .iter()
        .zip(&p1)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    let shift = r0
        .iter()
        .zip(&r1)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    eprintln!("largest parameter difference {drift:.3e}, largest render difference {shift:.3e}");
    assert!(p1.iter().all(|v| v.is_finite()) && drift < 1e-3, "{drift}");
    assert!(shift < 1e-3, "{shift}");
}
