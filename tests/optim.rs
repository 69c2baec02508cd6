//! Adam against the f64 reference over several steps of the schedule, on lengths that are not
//! multiples of the vector width, with gradient scaling, weight decay and bad gradients.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_gpu::Buffer;
use extranerf_nerf::optim::{Adam, AdamConfig};
use extranerf_nerf::reference::adam_step;
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
        adam.record_step(&mut rec, params.binding(), gb.binding(), step, grad_scale)
            .unwrap();
        e.ctx.run(rec).unwrap();
        adam_step(
            &mut p,
            &mut m,
            &mut v,
            &g,
            cfg.lr_at(step) as f64,
            cfg.beta1 as f64,
            cfg.beta2 as f64,
            cfg.eps as f64,
            step,
            grad_scale as f64,
            weight_decay as f64,
        );
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
