//! Adam against the f64 reference over several steps of the schedule, on lengths that are not
//! multiples of the vector width, with gradient scaling, weight decay and bad gradients.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_gpu::Buffer;
use extranerf_nerf::optim::{Adam, AdamConfig};
use extranerf_nerf::reference::adam_step_with;
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
