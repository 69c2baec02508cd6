//! Adam against the f64 reference over several steps of the schedule, on lengths that are not
//! multiples of the vector width, with gradient scaling, weight decay and bad gradients.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_gpu::Buffer;
use extranerf_nerf::field::mlp::MlpMode;
use extranerf_nerf::model::init_params;
use extranerf_nerf::optim::{Adam, AdamConfig};
use extranerf_nerf::reference::adam_step_with;
use extranerf_nerf::renderer::Nerf;
use extranerf_nerf::trainer::Trainer;
use extranerf_nerf::views::TrainData;
use extranerf_prims::reference::Rng;
use extranerf_tests::{assert_no_validation_messages, engine};

#[test]
fn schedule_runs_from_start_to_end() {
    let c = AdamConfig::default();
    assert!((c.lr_at(1) - 1e-2).abs() < 1e-9);
    assert!((c.lr_at(5000) - 3e-4).abs() < 1e-9);
    assert!((c.lr_at(9000) - 3e-4).abs() < 1e-9);
    let mid = c.lr_at(2500) as f64;
    assert!((mid - (1e-2f64 * 3e-4).sqrt()).abs() < 1e-5, "{mid}");
    assert!(Adam::new(&engine().ctx, 4, AdamConfig { beta2: 1.0, ..c }).is_err());
}

fn run(n: usize, weight_decay: f32, grad_scale: f32, seed: u64) {
    let e = engine();
    let cfg = AdamConfig {
        weight_decay,
        decay_steps: 4,
        ..Default::default()
    };
    let adam = Adam::new(&e.ctx, n as u64, cfg).unwrap();
    let mut rng = Rng::new(seed);
    let p0: Vec<f32> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let params = Buffer::from_slice(&e.ctx, "params", &p0).unwrap();
    let (mut p, mut m, mut v) = (
        p0.iter().map(|&x| x as f64).collect::<Vec<_>>(),
        vec![0f64; n],
        vec![0f64; n],
    );
    // Indices with gradients the f32 arithmetic cannot follow exactly (over- or underflowing
    // g^2): checked for being finite and bounded instead of against the f64 values.
    let mut extreme = vec![false; n];
    for step in 1..=4u32 {
        let g: Vec<f32> = (0..n)
            .map(|i| match (i + step as usize) % 97 {
                0 => f32::NAN,
                1 => f32::INFINITY,
                2 => f32::NEG_INFINITY,
                3 => {
                    extreme[i] = true;
                    1e30
                }
                4 => {
                    extreme[i] = true;
                    1e-30
                }
                _ => rng.uniform(-2.0, 2.0),
            })
            .collect();
        let gb = Buffer::from_slice(&e.ctx, "grads", &g).unwrap();
        let mut rec = e.ctx.recorder("adam").unwrap();
        adam.record_step(
            &mut rec,
            params.binding(),
            gb.binding(),
            step,
            grad_scale,
            None,
        )
        .unwrap();
        e.ctx.run(rec).unwrap();
        adam_step_with(&mut p, &mut m, &mut v, &g, &cfg, step, grad_scale as f64);
    }
    let got = params.read().unwrap();
    for i in 0..n {
        assert!(got[i].is_finite(), "param {i} is {}", got[i]);
        if extreme[i] {
            // Bounded: an Adam step moves a parameter by a few learning rates at most.
            assert!(
                (got[i] - p0[i]).abs() <= 4.0 * cfg.lr_start * 3.2,
                "param {i} moved {}",
                got[i] - p0[i]
            );
        } else {
            // f32 update of size ~lr: 1e-5 lr relative error plus the rounding of p.
            let tol = 1e-5 * cfg.lr_start as f64 + 2.0 * f32::EPSILON as f64 * p[i].abs();
            assert!(
                (got[i] as f64 - p[i]).abs() <= tol,
                "param {i}: {} vs {}",
                got[i],
                p[i]
            );
        }
    }
}

#[test]
fn adam_matches_reference() {
    for (n, wd, scale, seed) in [
        (0usize, 0.0, 1.0, 1),
        (1, 0.0, 1.0, 2),
        (1003, 0.0, 0.5, 3),
        (64 * 16 * 3 + 5, 1e-3, 1.0, 4),
    ] {
        run(n, wd, scale, seed);
    }
    assert_no_validation_messages(&engine().ctx);
}

/// Hash decay folded into Adam: the update equals Adam on gradient + 2 lambda V / (size_l F)
/// for the table's floats (levels of several sizes, boundaries inside vec4s, a table that
/// starts and ends off the buffer's ends), and plain Adam elsewhere.
/// With `chunk`, Adam updates that many floats per dispatch (the ranged path of buffers larger
/// than one binding), across the table's start and its level bounds.
#[test]
fn adam_with_folded_hash_decay_matches_reference() {
    for chunk in [None, Some(64), Some(192)] {
        adam_decay_case(chunk);
    }
}

fn adam_decay_case(chunk: Option<u64>) {
    use extranerf_nerf::optim::TableDecay;
    let e = engine();
    let cfg = AdamConfig {
        decay_steps: 3,
        ..Default::default()
    };
    let n = 403usize;
    let (start, floats) = (6usize, 297usize);
    // Levels of 42, 66 and 189 floats (relative offsets 0, 42, 108).
    let sizes = [42u32, 66, 189];
    let mut block = vec![[0u32; 4]; 65];
    let mut off = 0;
    for (l, &s) in sizes.iter().enumerate() {
        block[l] = [off, s, 0, 0];
        off += s;
    }
    block[sizes.len()] = [floats as u32, 1, 0, 0];
    let lambda = 0.37f32;
    let coef = |i: usize| -> f64 {
        if i < start || i >= start + floats {
            return 0.0;
        }
        let t = (i - start) as u32;
        let l = (1..sizes.len())
            .rev()
            .find(|&k| t >= block[k][0])
            .unwrap_or(0);
        2.0 * lambda as f64 / block[l][1] as f64
    };
    let adam = Adam::new(&e.ctx, n as u64, cfg).unwrap();
    let adam = match chunk {
        None => adam,
        Some(c) => adam.with_chunk(c),
    };
    let blk = Buffer::from_slice(&e.ctx, "level block", &block).unwrap();
    let mut rng = Rng::new(17);
    let p0: Vec<f32> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let params = Buffer::from_slice(&e.ctx, "params", &p0).unwrap();
    let mut p: Vec<f64> = p0.iter().map(|&x| x as f64).collect();
    let (mut m, mut v) = (vec![0f64; n], vec![0f64; n]);
    for step in 1..=3u32 {
        let g: Vec<f32> = (0..n).map(|_| rng.uniform(-0.5, 0.5)).collect();
        let gb = Buffer::from_slice(&e.ctx, "grads", &g).unwrap();
        let mut rec = e.ctx.recorder("adam decay").unwrap();
        let decay = TableDecay {
            block: blk.binding(),
            levels: sizes.len() as u32,
            start: start as u64,
            floats: floats as u64,
            lambda,
        };
        adam.record_step(
            &mut rec,
            params.binding(),
            gb.binding(),
            step,
            1.0,
            Some(decay),
        )
        .unwrap();
        e.ctx.run(rec).unwrap();
        // The reference: the decay gradient added to g, at the parameters before the step.
        let g_eff: Vec<f32> = (0..n)
            .map(|i| (g[i] as f64 + coef(i) * p[i]) as f32)
            .collect();
        adam_step_with(&mut p, &mut m, &mut v, &g_eff, &cfg, step, 1.0);
    }
    let got = params.read().unwrap();
    for i in 0..n {
        let tol = 1e-5 * cfg.lr_start as f64 + 2.0 * f32::EPSILON as f64 * p[i].abs();
        assert!(
            (got[i] as f64 - p[i]).abs() <= tol,
            "chunk {chunk:?} param {i} (decay coefficient {}): {} vs {}",
            coef(i),
            got[i],
            p[i]
        );
    }
    // Bad settings are errors.
    let gb = Buffer::from_slice(&e.ctx, "grads", &vec![0f32; n]).unwrap();
    let mut rec = e.ctx.recorder("adam bad").unwrap();
    for (levels, floats, lambda) in [(0u32, 10u64, 0.1f32), (3, 1000, 0.1), (3, 10, f32::NAN)] {
        let d = TableDecay {
            block: blk.binding(),
            levels,
            start: 0,
            floats,
            lambda,
        };
        assert!(adam
            .record_step(&mut rec, params.binding(), gb.binding(), 1, 1.0, Some(d))
            .is_err());
    }
    assert_no_validation_messages(&e.ctx);
}

/// A mask (a bit per vec4, `table.div_ceil(128)` words) with the vec4s `on` set.
fn mask_of(table: usize, on: impl Fn(usize) -> bool) -> Vec<u32> {
    let mut w = vec![0u32; table.div_ceil(128)];
    for q in 0..table.div_ceil(4) {
        if on(q) {
            w[q / 32] |= 1 << (q % 32);
        }
    }
    w
}

/// The sparse Adam against the f64 reference over several steps: a table of 517 floats (its
/// last vec4 partial) updated only where the mask is set, the gap to the dense rest left
/// alone, the rest dense; with and without hash decay. After each step the table's gradient
/// is zero and the mask empty; entries never touched keep their parameters and moments.
#[test]
fn sparse_adam_matches_the_reference() {
    use extranerf_nerf::optim::{SparseTable, TableDecay};
    use extranerf_nerf::reference::adam_step_sparse;
    let e = engine();
    let cfg = AdamConfig {
        decay_steps: 4,
        ..Default::default()
    };
    let (table, rest, n) = (517usize, 576usize, 803usize);
    for lambda in [0.0f32, 0.37] {
        let block: Vec<[u32; 4]> = (0..65)
            .map(|l| match l {
                0 => [0, 200, 0, 0],
                1 => [200, table as u32 - 200, 0, 0],
                2 => [table as u32, 1, 0, 0],
                _ => [0; 4],
            })
            .collect();
        let coef = |i: usize| -> f64 {
            if i >= table {
                0.0
            } else if i < 200 {
                2.0 * lambda as f64 / 200.0
            } else {
                2.0 * lambda as f64 / (table - 200) as f64
            }
        };
        let blk = Buffer::from_slice(&e.ctx, "level block", &block).unwrap();
        let adam = Adam::new(&e.ctx, n as u64, cfg).unwrap();
        let mut rng = Rng::new(23);
        let p0: Vec<f32> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let params = Buffer::from_slice(&e.ctx, "params", &p0).unwrap();
        let mut p: Vec<f64> = p0.iter().map(|&x| x as f64).collect();
        let (mut m, mut v) = (vec![0f64; n], vec![0f64; n]);
        // vec4 3 is never touched; vec4 0 always; the partial last vec4 (129) at steps 2 and 4.
        for step in 1..=4u32 {
            let on = |q: usize| {
                q == 0 || (q == 129 && step % 2 == 0) || (q != 3 && (q * 7 + step as usize) % 5 < 2)
            };
            let mask = mask_of(table, on);
            let g: Vec<f32> = (0..n)
                .map(|i| {
                    // Untouched table vec4s have no gradient; touched ones have zero
                    // components at times (every 11th float).
                    if (i < table && !on(i / 4)) || i % 11 == 0 {
                        0.0
                    } else {
                        rng.uniform(-0.5, 0.5)
                    }
                })
                .collect();
            let gb = Buffer::from_slice(&e.ctx, "grads", &g).unwrap();
            let mb = Buffer::from_slice(&e.ctx, "mask", &mask).unwrap();
            let mut rec = e.ctx.recorder("sparse adam").unwrap();
            let decay = (lambda > 0.0).then(|| TableDecay {
                block: blk.binding(),
                levels: 2,
                start: 0,
                floats: table as u64,
                lambda,
            });
            adam.record_step_sparse(
                &mut rec,
                params.binding(),
                gb.binding(),
                step,
                1.0,
                decay,
                SparseTable {
                    floats: table as u64,
                    touched: mb.binding(),
                    rest: rest as u64,
                },
            )
            .unwrap();
            e.ctx.run(rec).unwrap();
            let g_eff: Vec<f32> = (0..n)
                .map(|i| (g[i] as f64 + coef(i) * p[i]) as f32)
                .collect();
            adam_step_sparse(
                &mut p, &mut m, &mut v, &g_eff, &mask, table, rest, &cfg, step, 1.0,
            );
            // The table's gradient consumed and the mask cleared; the rest's gradient kept.
            let (g_after, m_after) = (gb.read().unwrap(), mb.read().unwrap());
            assert!(m_after.iter().all(|&w| w == 0), "mask left: {m_after:?}");
            for i in 0..n {
                let want = if i < table { 0.0 } else { g[i] };
                assert_eq!(g_after[i], want, "lambda {lambda} step {step} gradient {i}");
            }
        }
        let got = params.read().unwrap();
        let (gm, gv) = adam.moments().unwrap();
        for i in 0..n {
            let tol = 1e-5 * cfg.lr_start as f64 + 2.0 * f32::EPSILON as f64 * p[i].abs();
            assert!(
                (got[i] as f64 - p[i]).abs() <= tol,
                "lambda {lambda} param {i}: {} vs {}",
                got[i],
                p[i]
            );
            assert!(
                (gm[i] as f64 - m[i]).abs() <= 1e-6 + 1e-5 * m[i].abs(),
                "m {i}"
            );
            assert!(
                (gv[i] as f64 - v[i]).abs() <= 1e-7 + 1e-5 * v[i].abs(),
                "v {i}"
            );
        }
        // Never touched (vec4 3) and the gap: exactly as they started, moments zero.
        for i in (12..16).chain(table..rest) {
            assert_eq!(got[i], p0[i], "float {i} moved");
            assert_eq!((gm[i], gv[i]), (0.0, 0.0), "float {i} has moments");
        }
    }
    assert_no_validation_messages(&e.ctx);
}

/// Where the mask holds every vec4, the sparse update is the dense one, bit for bit (same
/// arithmetic), with hash decay; a table larger than the mask, or a rest before the table's
/// end, is an error.
#[test]
fn sparse_adam_equals_dense_where_every_entry_is_touched() {
    use extranerf_nerf::optim::{SparseTable, TableDecay};
    let e = engine();
    let cfg = AdamConfig::default();
    let (table, n) = (640usize, 832usize);
    let block: Vec<[u32; 4]> = (0..65)
        .map(|l| match l {
            0 => [0, table as u32, 0, 0],
            1 => [table as u32, 1, 0, 0],
            _ => [0; 4],
        })
        .collect();
    let blk = Buffer::from_slice(&e.ctx, "level block", &block).unwrap();
    let mut rng = Rng::new(5);
    let p0: Vec<f32> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let (dense, sparse) = (
        Adam::new(&e.ctx, n as u64, cfg).unwrap(),
        Adam::new(&e.ctx, n as u64, cfg).unwrap(),
    );
    let (pd, ps) = (
        Buffer::from_slice(&e.ctx, "dense params", &p0).unwrap(),
        Buffer::from_slice(&e.ctx, "sparse params", &p0).unwrap(),
    );
    let decay = || TableDecay {
        block: blk.binding(),
        levels: 1,
        start: 0,
        floats: table as u64,
        lambda: 0.2,
    };
    for step in 1..=3u32 {
        let g: Vec<f32> = (0..n).map(|_| rng.uniform(-0.5, 0.5)).collect();
        let (gd, gs) = (
            Buffer::from_slice(&e.ctx, "grads d", &g).unwrap(),
            Buffer::from_slice(&e.ctx, "grads s", &g).unwrap(),
        );
        let mask = Buffer::from_slice(&e.ctx, "mask", &mask_of(table, |_| true)).unwrap();
        let mut rec = e.ctx.recorder("dense and sparse").unwrap();
        dense
            .record_step(
                &mut rec,
                pd.binding(),
                gd.binding(),
                step,
                1.0,
                Some(decay()),
            )
            .unwrap();
        sparse
            .record_step_sparse(
                &mut rec,
                ps.binding(),
                gs.binding(),
                step,
                1.0,
                Some(decay()),
                SparseTable {
                    floats: table as u64,
                    touched: mask.binding(),
                    rest: table as u64,
                },
            )
            .unwrap();
        e.ctx.run(rec).unwrap();
    }
    assert_eq!(pd.read().unwrap(), ps.read().unwrap());
    assert_eq!(dense.moments().unwrap(), sparse.moments().unwrap());
    let gb = Buffer::from_slice(&e.ctx, "grads", &vec![0f32; n]).unwrap();
    let small = Buffer::from_slice(&e.ctx, "small mask", &[0u32; 2]).unwrap();
    let full = gb_mask(&e.ctx, table);
    let mut rec = e.ctx.recorder("bad").unwrap();
    for (touched, rest) in [(&small, table), (&full, table - 4)] {
        let err = sparse
            .record_step_sparse(
                &mut rec,
                ps.binding(),
                gb.binding(),
                4,
                1.0,
                None,
                SparseTable {
                    floats: table as u64,
                    touched: touched.binding(),
                    rest: rest as u64,
                },
            )
            .unwrap_err()
            .to_string();
        assert!(err.contains("mask") || err.contains("dense from"), "{err}");
    }
    assert_no_validation_messages(&e.ctx);
}

fn gb_mask(ctx: &extranerf_gpu::Context, table: usize) -> Buffer<u32> {
    Buffer::from_slice(ctx, "mask", &vec![0u32; table.div_ceil(128)]).unwrap()
}

/// An entry skipped for k steps (k = 1, 7, 1000) stands still meanwhile (parameter and moments)
/// and then takes the update of its step with the step's learning rate and bias corrections,
/// as the f64 reference of the rule; with hash decay on and off. The whole run is one
/// submission: each step fills the gradients and the mask, then the sparse update.
#[test]
fn sparse_adam_skipped_entries_follow_the_rule() {
    use extranerf_nerf::optim::{SparseTable, TableDecay};
    use extranerf_nerf::reference::adam_step_sparse;
    let e = engine();
    let (table, n) = (128usize, 192usize);
    // vec4 0 (floats 0..4) every step; vec4 16 (floats 64..68) at step 1 and step k + 2.
    for k in [1u32, 7, 1000] {
        for lambda in [0.0f32, 0.5] {
            let cfg = AdamConfig {
                decay_steps: k + 2,
                ..Default::default()
            };
            let block: Vec<[u32; 4]> = (0..65)
                .map(|l| match l {
                    0 => [0, table as u32, 0, 0],
                    1 => [table as u32, 1, 0, 0],
                    _ => [0; 4],
                })
                .collect();
            let blk = Buffer::from_slice(&e.ctx, "level block", &block).unwrap();
            let adam = Adam::new(&e.ctx, n as u64, cfg).unwrap();
            let p0: Vec<f32> = (0..n).map(|i| 0.01 * (i as f32 - 90.0)).collect();
            let params = Buffer::from_slice(&e.ctx, "params", &p0).unwrap();
            let grads = Buffer::from_slice(&e.ctx, "grads", &vec![0f32; n]).unwrap();
            let mask = Buffer::from_slice(&e.ctx, "mask", &[0u32]).unwrap();
            let touched_at = |s: u32| s == 1 || s == k + 2;
            let (ga, gb, gr) = (0.25f32, -0.5f32, 0.125f32);
            let mut p: Vec<f64> = p0.iter().map(|&x| x as f64).collect();
            let (mut m, mut v) = (vec![0f64; n], vec![0f64; n]);
            let mut mid = None;
            let mut rec = e.ctx.recorder("skipped").unwrap();
            for s in 1..=k + 2 {
                let word = 1u32 | if touched_at(s) { 1 << 16 } else { 0 };
                rec.fill_words(grads.binding().sub(0, 16).unwrap(), 4, ga.to_bits())
                    .unwrap();
                if touched_at(s) {
                    rec.fill_words(grads.binding().sub(256, 16).unwrap(), 4, gb.to_bits())
                        .unwrap();
                }
                rec.fill_words(grads.binding().sub(512, 256).unwrap(), 64, gr.to_bits())
                    .unwrap();
                rec.fill_words(mask.binding(), 1, word).unwrap();
                adam.record_step_sparse(
                    &mut rec,
                    params.binding(),
                    grads.binding(),
                    s,
                    1.0,
                    (lambda > 0.0).then(|| TableDecay {
                        block: blk.binding(),
                        levels: 1,
                        start: 0,
                        floats: table as u64,
                        lambda,
                    }),
                    SparseTable {
                        floats: table as u64,
                        touched: mask.binding(),
                        rest: table as u64,
                    },
                )
                .unwrap();
                let g: Vec<f32> = (0..n)
                    .map(|i| {
                        let raw = match i {
                            0..4 => ga,
                            64..68 if touched_at(s) => gb,
                            128.. => gr,
                            _ => 0.0,
                        };
                        let c = if i < table {
                            2.0 * lambda as f64 / table as f64
                        } else {
                            0.0
                        };
                        (raw as f64 + c * p[i]) as f32
                    })
                    .collect();
                adam_step_sparse(
                    &mut p,
                    &mut m,
                    &mut v,
                    &g,
                    &[word],
                    table,
                    table,
                    &cfg,
                    s,
                    1.0,
                );
                if s == k + 1 {
                    // Just before the second touch: the skipped entry as step 1 left it.
                    e.ctx
                        .run(std::mem::replace(
                            &mut rec,
                            e.ctx.recorder("skipped, part 2").unwrap(),
                        ))
                        .unwrap();
                    mid = Some((params.read().unwrap(), adam.moments().unwrap(), p.clone()));
                }
            }
            e.ctx.run(rec).unwrap();
            let (mid_p, (mid_m, mid_v), ref_mid) = mid.unwrap();
            for i in 64..68 {
                assert!(
                    (mid_p[i] as f64 - ref_mid[i]).abs() < 1e-6,
                    "k {k}: {}",
                    mid_p[i]
                );
                assert!(mid_m[i] != 0.0 && mid_v[i] != 0.0);
            }
            let got = params.read().unwrap();
            for i in 0..n {
                let tol = 1e-5 * cfg.lr_start as f64 * (k as f64).sqrt().max(1.0)
                    + 4.0 * f32::EPSILON as f64 * p[i].abs();
                assert!(
                    (got[i] as f64 - p[i]).abs() <= tol,
                    "k {k} lambda {lambda} param {i}: {} vs {}",
                    got[i],
                    p[i]
                );
            }
            // Untouched table floats: never moved.
            assert_eq!(&got[4..64], &p0[4..64]);
        }
    }
    assert_no_validation_messages(&e.ctx);
}

/// The tiny model and the demo scene's training views for it, in scratch folder `name`.
fn tiny_scene(name: &str) -> (extranerf_nerf::model::ModelConfig, TrainData) {
    let model = extranerf_tests::tiny_model();
    let views = extranerf_tests::demo_training_views(name, &model);
    let data = TrainData::new(&engine().ctx, &views).unwrap();
    (model, data)
}

fn sparse_config(mlp: MlpMode) -> extranerf_nerf::trainer::TrainConfig {
    extranerf_nerf::trainer::TrainConfig {
        rays: 64,
        samples: 8,
        steps: 20,
        decay_steps: 20,
        adam: extranerf_nerf::optim::AdamMode::Sparse,
        mlp,
        ..Default::default()
    }
}

/// The fused step (scalar MLPs, and cooperative-matrix ones where the device has them) sets the
/// touched bit of exactly the table's vec4s it adds a gradient to, and a sparse step then moves
/// exactly those, and the MLPs, as the f64 reference of the rule does from that gradient
/// (no hash decay here), leaving the mask empty. The standalone chain is refused.
#[test]
fn the_fused_step_marks_what_it_reaches_and_sparse_adam_moves_only_that() {
    use extranerf_nerf::reference::adam_step_sparse;
    let e = engine();
    let ctx = &e.ctx;
    let (model, data) = tiny_scene("sparse_adam_marks");
    let mut modes = vec![MlpMode::Scalar];
    if extranerf_tests::coop_tile_or_skip(ctx).is_some() {
        modes.push(MlpMode::Coop);
    }
    for mlp in modes {
        let cfg = extranerf_nerf::trainer::TrainConfig {
            hash_decay_lambda: 0.0,
            ..sparse_config(mlp)
        };
        let p0 = init_params(&model, 3);
        let nerf = Nerf::new(ctx, model.clone(), &p0, cfg.background).unwrap();
        let lay = *nerf.field().layout();
        let mut t = Trainer::new(ctx, nerf, cfg.clone(), 0, None).unwrap();
        let (g, _) = t.gradient(ctx, &e.prims, &data).unwrap();
        let mask = t.touched_mask().unwrap().unwrap();
        let table = lay.table.1;
        let mut reached = 0;
        for q in 0..table.div_ceil(4) {
            let nonzero = (4 * q..(4 * q + 4).min(table)).any(|i| g[i] != 0.0);
            let bit = mask[q / 32] >> (q % 32) & 1 == 1;
            assert_eq!(
                nonzero, bit,
                "{mlp:?}: vec4 {q} gradient {nonzero}, bit {bit}"
            );
            reached += nonzero as usize;
        }
        assert!(
            reached > 10 && reached < table / 4,
            "{mlp:?}: {reached} of {} vec4s reached",
            table / 4
        );
        // One update from the same batch (gradient() draws the batch of the next step).
        t.run_steps(ctx, &e.prims, &data, 1).unwrap();
        assert!(t.touched_mask().unwrap().unwrap().iter().all(|&w| w == 0));
        let got = t.nerf().params().read().unwrap();
        let mut p: Vec<f64> = p0.iter().map(|&x| x as f64).collect();
        let (mut m, mut v) = (vec![0f64; p.len()], vec![0f64; p.len()]);
        adam_step_sparse(
            &mut p,
            &mut m,
            &mut v,
            &g,
            &mask,
            table,
            lay.density.0,
            &cfg.adam(),
            1,
            1.0,
        );
        for i in (0..table).chain(lay.density.0..p.len()) {
            let tol = 1e-5 * cfg.lr_start as f64 + 2.0 * f32::EPSILON as f64 * p[i].abs();
            assert!(
                (got[i] as f64 - p[i]).abs() <= tol,
                "{mlp:?} param {i}: {} vs {} (from {})",
                got[i],
                p[i],
                p0[i]
            );
        }
    }
    // The standalone chain writes no mask: refused, naming why.
    let nerf = Nerf::new(ctx, model.clone(), &init_params(&model, 3), [0.0; 3]).unwrap();
    let cfg = extranerf_nerf::trainer::TrainConfig {
        fused_step: false,
        ..sparse_config(MlpMode::Scalar)
    };
    let err = Trainer::new(ctx, nerf, cfg, 0, None)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("--adam sparse") && err.contains("standalone"),
        "{err}"
    );
    assert_no_validation_messages(ctx);
}

/// Sparse training resumed from its parameters and moments after k steps ends bit for bit where
/// an uninterrupted run ends (the mask is empty and the table's gradient zero between steps,
/// so nothing else needs saving).
#[test]
fn sparse_training_resumes_where_it_stopped() {
    let e = engine();
    let ctx = &e.ctx;
    let (model, data) = tiny_scene("sparse_adam_resume");
    let cfg = sparse_config(MlpMode::Scalar);
    let p0 = init_params(&model, 4);
    let whole = {
        let nerf = Nerf::new(ctx, model.clone(), &p0, cfg.background).unwrap();
        let mut t = Trainer::new(ctx, nerf, cfg.clone(), 0, None).unwrap();
        t.run_steps(ctx, &e.prims, &data, 10).unwrap();
        t.run_steps(ctx, &e.prims, &data, 10).unwrap();
        t.nerf().params().read().unwrap()
    };
    let (half, moments) = {
        let nerf = Nerf::new(ctx, model.clone(), &p0, cfg.background).unwrap();
        let mut t = Trainer::new(ctx, nerf, cfg.clone(), 0, None).unwrap();
        t.run_steps(ctx, &e.prims, &data, 10).unwrap();
        (t.nerf().params().read().unwrap(), t.moments().unwrap())
    };
    let nerf = Nerf::new(ctx, model, &half, cfg.background).unwrap();
    let mut t = Trainer::new(ctx, nerf, cfg, 10, Some((&moments.0, &moments.1))).unwrap();
    t.run_steps(ctx, &e.prims, &data, 10).unwrap();
    assert_eq!(t.nerf().params().read().unwrap(), whole);
    assert_no_validation_messages(ctx);
}
