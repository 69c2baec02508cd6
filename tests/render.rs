//! Compositing (forward, backward) and the distortion loss against the f64 reference, on
//! random rays and at the extremes: densities from 0 to 1e8, intervals down to 1e-7, empty and
//! opaque rays.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_gpu::{Buffer, GpuError};
use extranerf_nerf::reference::{composite_backward, composite_forward, distortion};
use extranerf_nerf::render::composite::{Background, Compositor, RayGrads, Samples};
use extranerf_prims::reference::Rng;
use extranerf_tests::{assert_no_validation_messages, engine};

struct Batch {
    rays: Vec<[u32; 2]>,
    sigma: Vec<f32>,
    rgb: Vec<[f32; 4]>,
    t_dt: Vec<[f32; 2]>,
    s_ds: Vec<[f32; 2]>,
}

fn log_uniform(rng: &mut Rng, lo: f32, hi: f32) -> f32 {
    (rng.uniform(lo.ln(), hi.ln())).exp()
}

/// Random rays plus hand-made extremes at the front of the batch.
fn batch(rng: &mut Rng, n_rays: usize) -> Batch {
    let mut b = Batch {
        rays: vec![],
        sigma: vec![],
        rgb: vec![],
        t_dt: vec![],
        s_ds: vec![],
    };
    let push_ray = |b: &mut Batch, samples: &[(f32, f32)], rng: &mut Rng| {
        b.rays.push([b.sigma.len() as u32, samples.len() as u32]);
        let mut t = rng.uniform(0.2, 3.0);
        for (i, &(sigma, dt)) in samples.iter().enumerate() {
            b.sigma.push(sigma);
            b.rgb.push([
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
                0.0,
            ]);
            b.t_dt.push([t + 0.5 * dt, dt]);
            let s = (i as f32 + 0.5) / samples.len() as f32;
            b.s_ds.push([s, 1.0 / samples.len() as f32]);
            t += dt;
        }
    };
    push_ray(&mut b, &[], rng); // empty
    push_ray(&mut b, &[(0.0, 0.1); 50], rng); // empty space
    push_ray(&mut b, &[(1e8, 0.01), (1e8, 0.01), (3.0, 0.01)], rng); // opaque at once
    push_ray(&mut b, &[(1.0, 1e-7); 100], rng); // tiny steps
    push_ray(&mut b, &[(1e8, 1e-7); 20], rng); // huge density, tiny steps
    push_ray(&mut b, &[(5.0, 0.0), (5.0, 0.2), (0.0, 0.0)], rng); // zero-length intervals
    while b.rays.len() < n_rays {
        let count = rng.below(160) as usize;
        let samples: Vec<(f32, f32)> = (0..count)
            .map(|_| {
                let sigma = match rng.below(10) {
                    0 => 0.0,
                    1 => 1e8,
                    _ => log_uniform(rng, 1e-4, 1e4),
                };
                (sigma, log_uniform(rng, 1e-7, 0.05))
            })
            .collect();
        push_ray(&mut b, &samples, rng);
    }
    b
}

#[test]
fn composite_and_distortion_match_reference() {
    let e = engine();
    let comp = Compositor::new(&e.ctx).unwrap();
    let mut rng = Rng::new(21);
    let b = batch(&mut rng, 400);
    let (nr, ns) = (b.rays.len(), b.sigma.len());
    let bg = [0.1f32, 0.5, 0.9];
    let d_rgba: Vec<[f32; 4]> = (0..nr)
        .map(|_| {
            [
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
            ]
        })
        .collect();
    let d_depth: Vec<f32> = (0..nr).map(|_| rng.uniform(-0.1, 0.1)).collect();
    let lambda = 0.01f32;

    let flat = |v: &[[f32; 2]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    let rays = Buffer::from_slice(
        &e.ctx,
        "rays",
        &b.rays.iter().flatten().copied().collect::<Vec<u32>>(),
    )
    .unwrap();
    let sigma = Buffer::from_slice(&e.ctx, "sigma", &b.sigma).unwrap();
    let rgb = Buffer::from_slice(
        &e.ctx,
        "rgb",
        &b.rgb.iter().flatten().copied().collect::<Vec<f32>>(),
    )
    .unwrap();
    let t_dt = Buffer::from_slice(&e.ctx, "t_dt", &flat(&b.t_dt)).unwrap();
    let s_ds = Buffer::from_slice(&e.ctx, "s_ds", &flat(&b.s_ds)).unwrap();
    let out_rgba = Buffer::<f32>::new(&e.ctx, "out rgba", 4 * nr).unwrap();
    let out_depth = Buffer::<f32>::new(&e.ctx, "out depth", nr).unwrap();
    let loss = Buffer::<f32>::new(&e.ctx, "loss", nr).unwrap();
    let d_weight = Buffer::<f32>::new(&e.ctx, "d_weight", ns).unwrap();
    let g_rgba = Buffer::from_slice(
        &e.ctx,
        "d_rgba",
        &d_rgba.iter().flatten().copied().collect::<Vec<f32>>(),
    )
    .unwrap();
    let g_depth = Buffer::from_slice(&e.ctx, "d_depth", &d_depth).unwrap();
    let d_sigma = Buffer::<f32>::new(&e.ctx, "d_sigma", ns).unwrap();
    let d_rgb = Buffer::<f32>::new(&e.ctx, "d_rgb", 4 * ns).unwrap();
    let s = Samples {
        rays: rays.binding(),
        sigma: sigma.binding(),
        rgb: rgb.binding(),
        t_dt: t_dt.binding(),
        n_rays: nr as u64,
        n_samples: ns as u64,
    };
    // A fixed background, then a random one per ray (the reference's ray_background).
    for background in [Background::Fixed(bg), Background::Random(0x5eed_1234)] {
        let mut rec = e.ctx.recorder("composite").unwrap();
        comp.forward(
            &mut rec,
            &s,
            background,
            out_rgba.binding(),
            out_depth.binding(),
        )
        .unwrap();
        comp.distortion(
            &mut rec,
            &s,
            s_ds.binding(),
            lambda,
            loss.binding(),
            d_weight.binding(),
        )
        .unwrap();
        // Gradient scaling on: rays start at t in [0.2, 3], so samples below t = 1 are scaled.
        let g = RayGrads {
            d_rgba: g_rgba.binding(),
            d_depth: g_depth.binding(),
            d_weight: d_weight.binding(),
            grad_scaling: true,
        };
        comp.backward(
            &mut rec,
            &s,
            background,
            &g,
            d_sigma.binding(),
            d_rgb.binding(),
        )
        .unwrap();
        e.ctx.run(rec).unwrap();

        let (rgba, depth, loss, dw) = (
            out_rgba.read().unwrap(),
            out_depth.read().unwrap(),
            loss.read().unwrap(),
            d_weight.read().unwrap(),
        );
        let (ds, drgb) = (d_sigma.read().unwrap(), d_rgb.read().unwrap());
        for (r, &[first, count]) in b.rays.iter().enumerate() {
            let bg = background.colour(r as u32);
            let range = first as usize..(first + count) as usize;
            let (sg, col, tdt, sds) = (
                &b.sigma[range.clone()],
                &b.rgb[range.clone()],
                &b.t_dt[range.clone()],
                &b.s_ds[range.clone()],
            );
            let want = composite_forward(sg, col, tdt, bg);
            let t_max = tdt.last().map_or(1.0, |v| v[0] as f64);
            // Stated tolerances: 5e-5 on colour and opacity (f32 transmittance over up to 160
            // samples), 5e-5 of the farthest sample on depth.
            for k in 0..4 {
                assert!(
                    (rgba[4 * r + k] as f64 - want[k]).abs() <= 5e-5,
                    "ray {r} channel {k}: {} vs {}",
                    rgba[4 * r + k],
                    want[k]
                );
            }
            assert!(
                (depth[r] as f64 - want[4]).abs() <= 5e-5 * t_max,
                "ray {r} depth: {} vs {}",
                depth[r],
                want[4]
            );
            let (l, gw) = distortion(sg, tdt, sds, lambda);
            assert!(
                (loss[r] as f64 - l).abs() <= 1e-4 * lambda as f64,
                "ray {r} distortion: {} vs {l}",
                loss[r]
            );
            for (i, &g) in gw.iter().enumerate() {
                assert!(
                    (dw[first as usize + i] as f64 - g).abs() <= 1e-4 * lambda as f64,
                    "ray {r} sample {i} dL/dw: {} vs {g}",
                    dw[first as usize + i]
                );
            }
            let dw_f32: Vec<f32> = dw[range.clone()].to_vec();
            let (want_ds, want_drgb) =
                composite_backward(sg, col, tdt, bg, d_rgba[r], d_depth[r], &dw_f32, true);
            // |dL/dx| <= 2 max|u| + |background term|; 1e-4 of that bound, times dt.
            let u_max = (0..sg.len())
                .map(|i| {
                    (0..3)
                        .map(|c| (col[i][c] * d_rgba[r][c]).abs())
                        .sum::<f32>()
                        + (tdt[i][0] * d_depth[r]).abs()
                        + d_rgba[r][3].abs()
                        + dw_f32[i].abs()
                })
                .fold(0.0f32, f32::max) as f64;
            let bound = 2.0 * u_max
                + (0..3)
                    .map(|c| (bg[c] * d_rgba[r][c]).abs() as f64)
                    .sum::<f64>();
            for i in 0..sg.len() {
                let s = first as usize + i;
                let tol = 1e-4 * bound * tdt[i][1] as f64 + 1e-12;
                assert!(
                    ds[s].is_finite() && (ds[s] as f64 - want_ds[i]).abs() <= tol,
                    "ray {r} sample {i} dL/dsigma: {} vs {} (tol {tol})",
                    ds[s],
                    want_ds[i]
                );
                for c in 0..3 {
                    assert!(
                        (drgb[4 * s + c] as f64 - want_drgb[i][c]).abs() <= 5e-5,
                        "ray {r} sample {i} dL/drgb"
                    );
                }
            }
        }
        // The extremes at the front: empty ray shows the background; opaque ray shows its first
        // sample; no NaN anywhere.
        let bg = background.colour(0);
        assert_eq!(&rgba[0..4], &[bg[0], bg[1], bg[2], 0.0]);
        assert!((rgba[4 * 2 + 3] - 1.0).abs() < 1e-6);
        for c in 0..3 {
            assert!((rgba[4 * 2 + c] - b.rgb[b.rays[2][0] as usize][c]).abs() < 1e-6);
        }
        assert!(rgba
            .iter()
            .chain(&depth)
            .chain(&ds)
            .chain(&drgb)
            .chain(&dw)
            .all(|v| v.is_finite()));
        if let Background::Random(_) = background {
            // The per-ray colours differ and lie in [0, 1).
            let (c0, c1) = (background.colour(0), background.colour(1));
            assert_ne!(c0, c1);
            assert!(c0.iter().chain(&c1).all(|v| (0.0..1.0).contains(v)));
        }
    }
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn rays_match_reference_on_fern_in_world_and_ndc() {
    use extranerf_nerf::data::llff::{load_llff, LlffOptions};
    use extranerf_nerf::reference::{camera_ray, ndc_ray};
    use extranerf_nerf::render::rays::{gpu_camera, RayGen, RaySpace};
    let e = engine();
    let gen = RayGen::new(&e.ctx).unwrap();
    let mut scene = load_llff(
        &extranerf_tests::shared_data().join("llff/fern"),
        &LlffOptions::default(),
    )
    .unwrap();
    // A camera looking along +x: its central ray is parallel to NDC's near plane.
    let mut side = scene.cameras[0].clone();
    side.c2w = glam::DMat4::from_rotation_y(-std::f64::consts::FRAC_PI_2);
    scene.cameras.push(side);
    let cams: Vec<_> = scene.cameras.iter().map(gpu_camera).collect();
    let nc = cams.len() as u32;
    let mut rng = Rng::new(41);
    let mut pix: Vec<[u32; 2]> = Vec::new();
    for (c, cam) in scene.cameras.iter().enumerate() {
        let (w, h) = (cam.width, cam.height);
        for p in [0, w - 1, (h - 1) * w, h * w - 1, (h / 2) * w + w / 2] {
            pix.push([c as u32, p]);
        }
        for _ in 0..50 {
            pix.push([c as u32, rng.below(w * h)]);
        }
    }
    pix.push([nc + 3, 0]); // no such camera
    pix.push([0, 504 * 378]); // past the last pixel
    let n = pix.len();
    let cb = Buffer::from_slice(&e.ctx, "cameras", &cams).unwrap();
    let pb = Buffer::from_slice(
        &e.ctx,
        "pixels",
        &pix.iter().flatten().copied().collect::<Vec<u32>>(),
    )
    .unwrap();
    let ob = Buffer::<f32>::new(&e.ctx, "origins", 4 * n).unwrap();
    let db = Buffer::<f32>::new(&e.ctx, "directions", 4 * n).unwrap();
    for space in [RaySpace::World, RaySpace::Ndc { near: 1.0 }] {
        let mut rec = e.ctx.recorder("rays").unwrap();
        gen.generate(
            &mut rec,
            cb.binding(),
            nc,
            pb.binding(),
            ob.binding(),
            db.binding(),
            n as u64,
            space,
        )
        .unwrap();
        e.ctx.run(rec).unwrap();
        let (o, d) = (ob.read().unwrap(), db.read().unwrap());
        assert!(
            o.iter().chain(&d).all(|v| v.is_finite()),
            "{space:?}: non-finite ray"
        );
        for (i, &[c, p]) in pix.iter().enumerate() {
            let (go, gd) = (
                [o[4 * i] as f64, o[4 * i + 1] as f64, o[4 * i + 2] as f64],
                [d[4 * i] as f64, d[4 * i + 1] as f64, d[4 * i + 2] as f64],
            );
            if c >= nc || p >= scene.cameras[c as usize].width * scene.cameras[c as usize].height {
                assert_eq!(
                    (go, gd),
                    ([0.0; 3], [0.0; 3]),
                    "invalid index must give a zero ray"
                );
                continue;
            }
            let cam = &scene.cameras[c as usize];
            let px = [(p % cam.width) as f64 + 0.5, (p / cam.width) as f64 + 0.5];
            let (wo, wd) = camera_ray(cam, px);
            let (wo, wd) = match space {
                RaySpace::World => (wo, wd),
                RaySpace::Ndc { near } => ndc_ray(cam, wo, wd, near as f64),
            };
            // The side camera's central ray sits on the 1e-12 nudge: its NDC values are huge
            // and only checked for being finite.
            if (c + 1 == nc) && matches!(space, RaySpace::Ndc { .. }) {
                continue;
            }
            for k in 0..3 {
                let tol = 1e-5 * (1.0 + wo[k].abs());
                assert!(
                    (go[k] - wo[k]).abs() <= tol,
                    "{space:?} camera {c} pixel {p} origin {k}: {} vs {}",
                    go[k],
                    wo[k]
                );
                let tol = 1e-5 * (1.0 + wd[k].abs());
                assert!(
                    (gd[k] - wd[k]).abs() <= tol,
                    "{space:?} camera {c} pixel {p} direction {k}: {} vs {}",
                    gd[k],
                    wd[k]
                );
            }
            match space {
                // Independent check of the convention: the point at depth 5 projects back
                // onto the pixel.
                RaySpace::World => {
                    let x = glam::DVec3::from(go) + 5.0 * glam::DVec3::from(gd);
                    let (u, v, z) = cam.project(x);
                    assert!(
                        (u - px[0]).abs() < 2e-3
                            && (v - px[1]).abs() < 2e-3
                            && (z - 5.0).abs() < 1e-4,
                        "camera {c} pixel {p}: projects to ({u}, {v}, {z})"
                    );
                }
                // NDC origins sit on the near plane, z = -1.
                RaySpace::Ndc { .. } => {
                    assert!((go[2] + 1.0).abs() < 1e-5, "NDC origin z {}", go[2])
                }
            }
        }
    }
    assert!(gen
        .generate(
            &mut e.ctx.recorder("x").unwrap(),
            cb.binding(),
            nc,
            pb.binding(),
            ob.binding(),
            db.binding(),
            1,
            RaySpace::Ndc { near: 0.0 }
        )
        .is_err());
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn ray_losses_match_reference() {
    use extranerf_nerf::reference::ray_loss;
    use extranerf_nerf::render::loss::{LossConfig, RayLoss, RgbLoss, Targets};
    let e = engine();
    let kernel = RayLoss::new(&e.ctx).unwrap();
    let mut rng = Rng::new(51);
    let n = 1001;
    let rendered: Vec<[f32; 4]> = (0..n)
        .map(|_| {
            [
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
            ]
        })
        .collect();
    let depth: Vec<f32> = (0..n).map(|_| rng.uniform(1.0, 10.0)).collect();
    // All-black and all-white targets included; signed colour weights: 1, partial, L1
    // (negative) and none.
    let target: Vec<[f32; 4]> = (0..n)
        .map(|i| {
            let w = match i % 4 {
                0 => 1.0,
                1 => rng.uniform(0.0, 2.0),
                2 => -rng.uniform(0.0, 2.0),
                _ => 0.0,
            };
            match i % 10 {
                0 => [0.0, 0.0, 0.0, w],
                1 => [1.0, 1.0, 1.0, w],
                _ => [
                    rng.uniform(0.0, 1.0),
                    rng.uniform(0.0, 1.0),
                    rng.uniform(0.0, 1.0),
                    w,
                ],
            }
        })
        .collect();
    let tdepth: Vec<[f32; 2]> = (0..n)
        .map(|i| {
            [
                rng.uniform(1.0, 10.0),
                if i % 3 == 0 {
                    rng.uniform(0.1, 1.0)
                } else {
                    0.0
                },
            ]
        })
        .collect();
    let flat4 = |v: &[[f32; 4]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    let rb = Buffer::from_slice(&e.ctx, "rendered", &flat4(&rendered)).unwrap();
    let db = Buffer::from_slice(&e.ctx, "depth", &depth).unwrap();
    let tb = Buffer::from_slice(&e.ctx, "target", &flat4(&target)).unwrap();
    let tdb = Buffer::from_slice(
        &e.ctx,
        "target depth",
        &tdepth.iter().flatten().copied().collect::<Vec<f32>>(),
    )
    .unwrap();
    let loss = Buffer::<f32>::new(&e.ctx, "loss", n).unwrap();
    let g = Buffer::<f32>::new(&e.ctx, "d_rgba", 4 * n).unwrap();
    let gd = Buffer::<f32>::new(&e.ctx, "d_depth", n).unwrap();
    // The L1 core (smooth L1 of the negative weights): off, and with cores that the random
    // errors (up to 1) fall both inside and outside of.
    for (rgb, l1_core) in [
        (RgbLoss::L2, 0.0),
        (RgbLoss::Huber(0.05), 0.0),
        (RgbLoss::L2, 0.1),
        (RgbLoss::Huber(0.05), 0.3),
    ] {
        let cfg = LossConfig {
            rgb,
            depth_lambda: 0.1,
            l1_core,
        };
        let mut rec = e.ctx.recorder("loss").unwrap();
        let t = Targets {
            rgb: tb.binding(),
            depth: tdb.binding(),
        };
        kernel
            .record(
                &mut rec,
                &cfg,
                rb.binding(),
                db.binding(),
                &t,
                loss.binding(),
                g.binding(),
                gd.binding(),
                n as u64,
            )
            .unwrap();
        e.ctx.run(rec).unwrap();
        let (l, gg, ggd) = (loss.read().unwrap(), g.read().unwrap(), gd.read().unwrap());
        for i in 0..n {
            let (wl, wg, wgd) = ray_loss(rendered[i], depth[i], target[i], tdepth[i], &cfg);
            let inv = 1.0 / n as f64;
            // f32 arithmetic on values of order 1 (depth errors up to 9): 1e-6 relative.
            assert!(
                (l[i] as f64 - wl * inv).abs() <= 1e-6 * (1.0 + wl) * inv,
                "{rgb:?} core {l1_core} ray {i} loss"
            );
            for c in 0..3 {
                assert!(
                    (gg[4 * i + c] as f64 - wg[c] * inv).abs() <= 1e-6 * inv,
                    "{rgb:?} core {l1_core} ray {i} dL/drgb {c}"
                );
            }
            assert!(
                (ggd[i] as f64 - wgd * inv).abs() <= 1e-6 * (1.0 + wgd.abs()) * inv,
                "{rgb:?} ray {i} dL/ddepth"
            );
        }
    }
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn occupancy_grid_matches_reference() {
    use extranerf_nerf::reference::{occ_cell, occ_cell_point};
    use extranerf_nerf::render::occupancy::{Occupancy, OccupancyConfig};
    let e = engine();
    let cfg = OccupancyConfig {
        res: 16,
        cascades: 3,
        decay: 0.9,
        threshold: 0.5,
    };
    let occ = Occupancy::new(&e.ctx, cfg).unwrap();
    let cells = cfg.cells() as usize;
    let mut rng = Rng::new(71);
    let mut grid = vec![0f32; cells];
    // Three updates over windows that wrap around the end of the grid.
    for (step, (first, count)) in [(0usize, cells), (cells - 1000, 5000), (7, 3000)]
        .into_iter()
        .enumerate()
    {
        let pos = Buffer::<f32>::new(&e.ctx, "positions", 3 * count).unwrap();
        let dens: Vec<f32> = (0..count)
            .map(|i| match i % 50 {
                0 => f32::NAN,
                1 => -3.0,
                2 => f32::INFINITY,
                _ => rng.uniform(0.0, 2.0).powi(3),
            })
            .collect();
        let db = Buffer::from_slice(&e.ctx, "densities", &dens).unwrap();
        let mut rec = e.ctx.recorder("occupancy").unwrap();
        occ.record_sample(
            &mut rec,
            pos.binding(),
            first as u64,
            count as u64,
            step as u32,
        )
        .unwrap();
        occ.record_update(&mut rec, db.binding(), first as u64, count as u64)
            .unwrap();
        occ.record_bits(&mut rec, &e.prims).unwrap();
        e.ctx.run(rec).unwrap();
        let p = pos.read().unwrap();
        for k in 0..count {
            let cell = ((first + k) % cells) as u32;
            let want = occ_cell_point(cell, step as u32, cfg.res, cfg.cascades);
            let got = [p[3 * k], p[3 * k + 1], p[3 * k + 2]];
            for d in 0..3 {
                assert!(
                    (got[d] - want[d]).abs() <= 1e-6 * (1.0 + want[d].abs()),
                    "sample {k} of cell {cell}: {got:?} vs {want:?}"
                );
            }
            // Each sample lies in its own cell, except in the inner part of a coarse cascade,
            // which the finer cascade covers (queries never reach those cells).
            let (back, edge) = occ_cell(got, cfg.res, cfg.cascades);
            let cascade = cell / cfg.res.pow(3);
            let inner = cascade > 0 && got.iter().all(|v| v.abs() <= 2f32.powi(cascade as i32 - 1));
            assert!(
                edge || inner || back == Some(cell),
                "sample of cell {cell} maps to {back:?}"
            );
            let d = dens[k];
            let d = if d.is_nan() || d < 0.0 {
                0.0
            } else {
                d.min(3.0e38)
            };
            grid[cell as usize] = (grid[cell as usize] * cfg.decay).max(d);
        }
        let got = occ.grid().read().unwrap();
        assert!(got == grid, "grid differs after update {step}");
    }
    let mean = grid.iter().map(|&v| v as f64).sum::<f64>() / cells as f64;
    let thresh = (cfg.threshold as f64).min(mean);
    let bits = occ.bits().read().unwrap();
    for (i, &g) in grid.iter().enumerate() {
        if ((g as f64) - thresh).abs() < 1e-3 * thresh {
            continue; // the f32 mean may fall either side
        }
        assert_eq!(
            (bits[i / 32] >> (i % 32)) & 1 == 1,
            g as f64 > thresh,
            "cell {i}: density {g}, threshold {thresh}"
        );
    }
    // Queries: random points in and beyond the cascades, NaN, the origin.
    let mut q: Vec<[f32; 3]> = vec![
        [0.0; 3],
        [f32::NAN, 0.0, 0.0],
        [5.0, 0.0, 0.0],
        [4.0, -4.0, 4.0],
        [1.0, 1.0, 1.0],
        [2.0, 0.0, -1.0],
    ];
    for _ in 0..3000 {
        q.push([
            rng.uniform(-4.5, 4.5),
            rng.uniform(-4.5, 4.5),
            rng.uniform(-4.5, 4.5),
        ]);
    }
    let qb = Buffer::from_slice(
        &e.ctx,
        "query",
        &q.iter().flatten().copied().collect::<Vec<f32>>(),
    )
    .unwrap();
    let ob = Buffer::<u32>::new(&e.ctx, "occupied", q.len()).unwrap();
    let mut rec = e.ctx.recorder("query").unwrap();
    occ.record_query(&mut rec, qb.binding(), ob.binding(), q.len() as u64)
        .unwrap();
    e.ctx.run(rec).unwrap();
    let got = ob.read().unwrap();
    for (i, p) in q.iter().enumerate() {
        let (cell, edge) = occ_cell(*p, cfg.res, cfg.cascades);
        if edge {
            continue;
        }
        let want = cell.map_or(0, |c| (bits[c as usize / 32] >> (c % 32)) & 1);
        assert_eq!(got[i], want, "query {p:?} (cell {cell:?})");
    }
    assert_no_validation_messages(&e.ctx);
}

/// Rays (origins, directions, near/far) on the device and room for `per_ray` samples each:
/// the sampler tests' operands.
struct SampleBuffers {
    o: Buffer<f32>,
    d: Buffer<f32>,
    nf: Buffer<f32>,
    pos: Buffer<f32>,
    tdt: Buffer<f32>,
    sds: Buffer<f32>,
    rays: Buffer<u32>,
}

impl SampleBuffers {
    fn new(
        ctx: &extranerf_gpu::Context,
        o: &[[f32; 4]],
        d: &[[f32; 4]],
        nf: &[[f32; 2]],
        per_ray: u32,
    ) -> SampleBuffers {
        let n = o.len();
        let total = n * per_ray as usize;
        SampleBuffers {
            o: Buffer::from_slice(ctx, "o", o.as_flattened()).unwrap(),
            d: Buffer::from_slice(ctx, "d", d.as_flattened()).unwrap(),
            nf: Buffer::from_slice(ctx, "near_far", nf.as_flattened()).unwrap(),
            pos: Buffer::new(ctx, "positions", 3 * total).unwrap(),
            tdt: Buffer::new(ctx, "t_dt", 2 * total).unwrap(),
            sds: Buffer::new(ctx, "s_ds", 2 * total).unwrap(),
            rays: Buffer::new(ctx, "rays", 2 * n).unwrap(),
        }
    }

    fn outputs(&self) -> extranerf_nerf::render::sample::SampleOutputs<'_> {
        extranerf_nerf::render::sample::SampleOutputs {
            positions: self.pos.binding(),
            t_dt: self.tdt.binding(),
            s_ds: self.sds.binding(),
            rays: self.rays.binding(),
        }
    }
}

#[test]
fn stratified_samples_match_reference() {
    use extranerf_nerf::reference::stratified;
    use extranerf_nerf::render::sample::{Sampler, Spacing};
    let e = engine();
    let sampler = Sampler::new(&e.ctx).unwrap();
    let mut rng = Rng::new(81);
    let (n, k) = (300usize, 37u32);
    let o: Vec<[f32; 4]> = (0..n)
        .map(|_| {
            [
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                0.0,
            ]
        })
        .collect();
    // Axis-parallel directions included.
    let d: Vec<[f32; 4]> = (0..n)
        .map(|i| {
            if i % 7 == 0 {
                [0.0, 0.0, -1.0, 1.0]
            } else {
                [rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), -1.0, 0.0]
            }
        })
        .collect();
    let nf: Vec<[f32; 2]> = (0..n)
        .map(|_| {
            let a = rng.uniform(0.01, 2.0);
            [a, a * rng.uniform(1.5, 1000.0)]
        })
        .collect();
    let b = SampleBuffers::new(&e.ctx, &o, &d, &nf, k);
    // A training batch's target colours: every third ray a virtual view's (negative weight,
    // centred samples even when the others are jittered), some weighted 0 (jittered).
    let virt = |ray: usize| ray.is_multiple_of(3);
    let targets: Vec<f32> = (0..n)
        .flat_map(|ray| {
            let w = if virt(ray) {
                -0.7
            } else if ray % 3 == 1 {
                0.0
            } else {
                1.0
            };
            [0.5, 0.5, 0.5, w]
        })
        .collect();
    let tb = Buffer::from_slice(&e.ctx, "targets", &targets).unwrap();
    for (spacing, seed, with_targets) in [
        (Spacing::Linear, None, false),
        (Spacing::Linear, Some(5u32), false),
        (Spacing::Disparity, Some(9u32), false),
        (Spacing::Disparity, Some(9u32), true),
        (Spacing::Linear, None, true),
    ] {
        let out = b.outputs();
        let mut rec = e.ctx.recorder("sample").unwrap();
        sampler
            .record(
                &mut rec,
                b.o.binding(),
                b.d.binding(),
                b.nf.binding(),
                &out,
                n as u64,
                k,
                spacing,
                seed,
                with_targets.then(|| tb.binding()),
                None,
            )
            .unwrap();
        e.ctx.run(rec).unwrap();
        let (p, t, s, r) = (
            b.pos.read().unwrap(),
            b.tdt.read().unwrap(),
            b.sds.read().unwrap(),
            b.rays.read().unwrap(),
        );
        for ray in 0..n {
            assert_eq!((r[2 * ray], r[2 * ray + 1]), (ray as u32 * k, k));
            let want = stratified(
                ray as u32,
                nf[ray][0],
                nf[ray][1],
                k,
                spacing == Spacing::Disparity,
                if with_targets && virt(ray) {
                    None
                } else {
                    seed
                },
            );
            let mut sum_dt = 0.0;
            for (i, w) in want.iter().enumerate() {
                let idx = ray * k as usize + i;
                let got = [
                    t[2 * idx] as f64,
                    t[2 * idx + 1] as f64,
                    s[2 * idx] as f64,
                    s[2 * idx + 1] as f64,
                ];
                for c in 0..4 {
                    assert!(
                        (got[c] - w[c]).abs() <= 2e-5 * w[c].abs().max(1e-3),
                        "{spacing:?} ray {ray} sample {i} field {c}: {} vs {}",
                        got[c],
                        w[c]
                    );
                }
                assert!(
                    got[0] >= nf[ray][0] as f64 * (1.0 - 1e-6)
                        && got[0] <= nf[ray][1] as f64 * (1.0 + 1e-6)
                );
                for c in 0..3 {
                    let want_p = o[ray][c] as f64 + got[0] * d[ray][c] as f64;
                    assert!(
                        (p[3 * idx + c] as f64 - want_p).abs() <= 1e-5 * (1.0 + want_p.abs()),
                        "position"
                    );
                }
                sum_dt += got[1];
            }
            let span = (nf[ray][1] - nf[ray][0]) as f64;
            assert!(
                (sum_dt - span).abs() <= 1e-4 * span,
                "intervals cover near..far: {sum_dt} vs {span}"
            );
        }
    }
    assert_no_validation_messages(&e.ctx);
}

/// Occupancy-aware sampling against the f64 reference: random, empty and full grids, linear
/// and disparity spacing, with and without jitter. Rays whose probe centres sit within rounding
/// of a cell face are skipped (f32 and f64 may put them in different cells). A ray whose probes
/// are all occupied, or none (points outside the grid count as occupied), gets the plain
/// stratified samples.
#[test]
fn occupied_samples_match_reference() {
    use extranerf_nerf::field::encodings::{Contraction, SceneBox};
    use extranerf_nerf::reference::{occ_cell, stratified, stratified_occupied};
    use extranerf_nerf::render::occupancy::{Occupancy, OccupancyConfig};
    use extranerf_nerf::render::sample::{Sampler, SkipEmpty, Spacing};
    let e = engine();
    let sampler = Sampler::new(&e.ctx).unwrap();
    let cfg = OccupancyConfig {
        res: 8,
        cascades: 1,
        ..OccupancyConfig::default()
    };
    let occ = Occupancy::new(&e.ctx, cfg).unwrap();
    let mut rng = Rng::new(83);
    let (n, k, m) = (400usize, 19u32, 64u32);
    // Rays through the grid's cube (|u| <= 1), some parallel to an axis, some leaving it.
    let o: Vec<[f32; 4]> = (0..n)
        .map(|_| [rng.uniform(-0.9, 0.9), rng.uniform(-0.9, 0.9), 0.9, 0.0])
        .collect();
    let d: Vec<[f32; 4]> = (0..n)
        .map(|i| {
            if i % 5 == 0 {
                [0.0, 0.0, -1.0, 0.0]
            } else {
                [rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), -1.0, 0.0]
            }
        })
        .collect();
    let nf: Vec<[f32; 2]> = (0..n)
        .map(|_| {
            let a = rng.uniform(0.05, 0.3);
            [a, a + rng.uniform(0.5, 2.0)]
        })
        .collect();
    let b = SampleBuffers::new(&e.ctx, &o, &d, &nf, k);
    let words = (cfg.cells() as usize).div_ceil(32);
    let random: Vec<u32> = (0..words).map(|_| rng.next_u32()).collect();
    let (mut checked, mut plain_rays) = (0, 0);
    for (grid, bits) in [
        ("random", random),
        ("empty", vec![0u32; words]),
        ("full", vec![u32::MAX; words]),
    ] {
        occ.bits().write(&bits).unwrap();
        for (spacing, seed) in [
            (Spacing::Linear, None),
            (Spacing::Linear, Some(5u32)),
            (Spacing::Disparity, Some(9u32)),
        ] {
            let disparity = spacing == Spacing::Disparity;
            let out = b.outputs();
            let skip = SkipEmpty {
                grid: &occ,
                scene: SceneBox {
                    center: [0.0; 3],
                    radius: 1.0,
                    contraction: Contraction::None,
                },
                probes: m,
            };
            let mut rec = e.ctx.recorder("sample occupied").unwrap();
            sampler
                .record(
                    &mut rec,
                    b.o.binding(),
                    b.d.binding(),
                    b.nf.binding(),
                    &out,
                    n as u64,
                    k,
                    spacing,
                    seed,
                    None,
                    Some(&skip),
                )
                .unwrap();
            e.ctx.run(rec).unwrap();
            let (t, s) = (b.tdt.read().unwrap(), b.sds.read().unwrap());
            'rays: for ray in 0..n {
                let (near, far) = (nf[ray][0], nf[ray][1]);
                let mut occupied = Vec::new();
                for j in 0..m {
                    let sj = (j as f64 + 0.5) / m as f64;
                    let tj = if disparity {
                        1.0 / ((1.0 - sj) / near as f64 + sj / far as f64)
                    } else {
                        near as f64 + sj * (far - near) as f64
                    };
                    let u = [0, 1, 2].map(|c| (o[ray][c] as f64 + tj * d[ray][c] as f64) as f32);
                    let (cell, edge) = occ_cell(u, cfg.res, cfg.cascades);
                    if edge {
                        continue 'rays;
                    }
                    occupied
                        .push(cell.is_none_or(|c| (bits[c as usize / 32] >> (c % 32)) & 1 == 1));
                }
                let want =
                    stratified_occupied(ray as u32, near, far, k, disparity, seed, &occupied);
                if occupied.iter().all(|&b| b == occupied[0]) {
                    // No occupied interval, or all: the plain strata.
                    plain_rays += 1;
                    let plain = stratified(ray as u32, near, far, k, disparity, seed);
                    for (a, b) in want.iter().zip(&plain) {
                        for c in 0..4 {
                            assert!(
                                (a[c] - b[c]).abs() <= 1e-9 * b[c].abs().max(1.0),
                                "{grid} ray {ray} field {c}: {} vs plain {}",
                                a[c],
                                b[c]
                            );
                        }
                    }
                }
                let mut sum_ds = 0.0;
                for (i, w) in want.iter().enumerate() {
                    let idx = ray * k as usize + i;
                    let got = [t[2 * idx], t[2 * idx + 1], s[2 * idx], s[2 * idx + 1]];
                    for c in 0..4 {
                        // dt sums differences of f32 distances: add a few ulps of t.
                        let slack = if c == 1 { 2e-6 * w[0].abs() } else { 0.0 };
                        assert!(
                            (got[c] as f64 - w[c]).abs() <= 2e-5 * w[c].abs().max(1e-2) + slack,
                            "{grid} {spacing:?} ray {ray} sample {i} field {c}: {} vs {}",
                            got[c],
                            w[c]
                        );
                    }
                    sum_ds += got[3] as f64;
                }
                // The strata tile the occupied part of s.
                let frac = occupied.iter().filter(|&&b| b).count().max(1) as f64 / m as f64;
                let frac = if occupied.iter().any(|&b| b) {
                    frac
                } else {
                    1.0
                };
                assert!(
                    (sum_ds - frac).abs() <= 1e-4,
                    "{grid} ray {ray}: {sum_ds} vs {frac}"
                );
                checked += 1;
            }
        }
    }
    assert!(checked > 3000, "only {checked} rays clear of cell faces");
    assert!(
        plain_rays > 300 && plain_rays < checked - 300,
        "{plain_rays} of {checked} rays were all or nothing"
    );
    // Probe counts outside 1..=256 are refused.
    let out = b.outputs();
    let bad = SkipEmpty {
        grid: &occ,
        scene: SceneBox {
            center: [0.0; 3],
            radius: 1.0,
            contraction: Contraction::None,
        },
        probes: 257,
    };
    let mut rec = e.ctx.recorder("bad probes").unwrap();
    let err = sampler
        .record(
            &mut rec,
            b.o.binding(),
            b.d.binding(),
            b.nf.binding(),
            &out,
            n as u64,
            k,
            Spacing::Linear,
            None,
            None,
            Some(&bad),
        )
        .unwrap_err();
    assert!(matches!(err, GpuError::Usage(_)), "{err}");
    drop(rec);
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn activations_match_reference_at_the_extremes() {
    use extranerf_nerf::field::activation::{Activation, Activations, Column};
    use extranerf_nerf::reference::activation;
    let e = engine();
    let act = Activations::new(&e.ctx).unwrap();
    let mut rng = Rng::new(91);
    let n = 2000usize;
    // Values in column 1 of a stride-3 layout; extremes first.
    let extremes = [
        0.0f32,
        15.0,
        15.5,
        80.0,
        1e30,
        -1e30,
        -100.0,
        88.0,
        -88.0,
        f32::MAX,
        -f32::MAX,
    ];
    let mut x = vec![7.0f32; 3 * n];
    for i in 0..n {
        x[3 * i + 1] = extremes
            .get(i)
            .copied()
            .unwrap_or_else(|| rng.uniform(-20.0, 20.0));
    }
    let dy: Vec<f32> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let xb = Buffer::from_slice(&e.ctx, "x", &x).unwrap();
    let dyb = Buffer::from_slice(&e.ctx, "dy", &dy).unwrap();
    let col = Column {
        stride: 3,
        offset: 1,
    };
    for kind in [Activation::TruncExp, Activation::Sigmoid] {
        let y = Buffer::<f32>::new(&e.ctx, "y", n).unwrap();
        let dx = Buffer::from_slice(
            &e.ctx,
            "dx",
            &vec![f32::from_bits(extranerf_tests::POISON); 3 * n],
        )
        .unwrap();
        let mut rec = e.ctx.recorder("act").unwrap();
        act.forward(&mut rec, kind, xb.binding(), col, y.binding(), n as u64)
            .unwrap();
        act.backward(
            &mut rec,
            kind,
            xb.binding(),
            col,
            dyb.binding(),
            dx.binding(),
            n as u64,
        )
        .unwrap();
        e.ctx.run(rec).unwrap();
        let (y, dx) = (y.read().unwrap(), dx.read().unwrap());
        for i in 0..n {
            let (wy, wd) = activation(kind, x[3 * i + 1]);
            assert!(
                y[i].is_finite() && (y[i] as f64 - wy).abs() <= 2e-6 * wy.abs().max(1e-30),
                "{kind:?} x={} y {} vs {wy}",
                x[3 * i + 1],
                y[i]
            );
            let g = dx[3 * i + 1] as f64;
            assert!(
                g.is_finite()
                    && (g - dy[i] as f64 * wd).abs() <= 4e-6 * (dy[i] as f64 * wd).abs().max(1e-30),
                "{kind:?} x={} dx {g} vs {}",
                x[3 * i + 1],
                dy[i] as f64 * wd
            );
            assert_eq!(
                dx[3 * i].to_bits(),
                extranerf_tests::POISON,
                "other columns untouched"
            );
        }
    }
    assert_no_validation_messages(&e.ctx);
}

/// Runs depth completion on the device; returns the completed map.
fn complete_on_device(
    w: usize,
    h: usize,
    depth: &[f32],
    known: &[u32],
    guide: &[[f32; 4]],
    sigma: f32,
    iterations: u32,
) -> Vec<f32> {
    use extranerf_nerf::depth_completion::DepthCompletion;
    let e = engine();
    let dc = DepthCompletion::new(&e.ctx).unwrap();
    let d = Buffer::from_slice(&e.ctx, "depth", depth).unwrap();
    let s = Buffer::<f32>::new(&e.ctx, "scratch", w * h).unwrap();
    let k = Buffer::from_slice(&e.ctx, "known", known).unwrap();
    let g = Buffer::from_slice(&e.ctx, "guide", guide).unwrap();
    let mut rec = e.ctx.recorder("depth completion").unwrap();
    dc.record(
        &mut rec,
        w as u32,
        h as u32,
        d.binding(),
        s.binding(),
        k.binding(),
        g.binding(),
        sigma,
        iterations,
    )
    .unwrap();
    e.ctx.run(rec).unwrap();
    d.read().unwrap()
}

/// Depth completion against the f64 reference on random maps, masks and colours (odd and even
/// iteration counts), and the extremes (nothing known, everything known, huge colour
/// differences, no edges).
#[test]
fn depth_completion_matches_reference() {
    use extranerf_nerf::reference::depth_complete;
    let mut rng = Rng::new(77);
    let (w, h) = (37, 23);
    let n = w * h;
    let depth: Vec<f32> = (0..n).map(|_| rng.uniform(0.5, 10.0)).collect();
    let known: Vec<u32> = (0..n)
        .map(|_| u32::from(rng.uniform(0.0, 1.0) < 0.3))
        .collect();
    let guide: Vec<[f32; 4]> = (0..n)
        .map(|_| {
            [
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
                0.0,
            ]
        })
        .collect();
    for (sigma, iters) in [(0.3f32, 7u32), (0.3, 8), (f32::INFINITY, 15), (1e-3, 5)] {
        let got = complete_on_device(w, h, &depth, &known, &guide, sigma, iters);
        let want = depth_complete(w, h, &depth, &known, &guide, sigma, iters);
        for i in 0..n {
            assert!(
                (got[i] as f64 - want[i]).abs() <= 1e-5 * want[i].abs().max(1.0),
                "sigma {sigma} iterations {iters} pixel {i}: {} vs {}",
                got[i],
                want[i]
            );
            if known[i] != 0 {
                assert_eq!(got[i], depth[i]);
            }
        }
    }
    // Nothing known: values only average (finite, within the initial range); all known:
    // unchanged.
    let none = complete_on_device(w, h, &depth, &vec![0; n], &guide, 0.3, 9);
    assert!(none
        .iter()
        .all(|v| v.is_finite() && (0.5..=10.0).contains(v)));
    let all = complete_on_device(w, h, &depth, &vec![1; n], &guide, 0.3, 9);
    assert_eq!(all, depth);
    assert_no_validation_messages(&engine().ctx);
}

/// With uniform colours the fill reproduces a plane in a hole enclosed by known pixels; a
/// colour edge through the hole keeps two planes' depths apart.
#[test]
fn depth_completion_reproduces_a_plane_and_respects_colour_edges() {
    let (w, h) = (40, 30);
    let n = w * h;
    let plane = |x: usize, y: usize| 2.0 + 0.05 * x as f32 - 0.03 * y as f32;
    let in_hole = |x: usize, y: usize| (12..28).contains(&x) && (8..22).contains(&y);
    let mut depth = vec![0f32; n];
    let mut known = vec![0u32; n];
    for y in 0..h {
        for x in 0..w {
            if !in_hole(x, y) {
                depth[y * w + x] = plane(x, y);
                known[y * w + x] = 1;
            }
        }
    }
    let flat = vec![[0.5f32, 0.5, 0.5, 0.0]; n];
    let got = complete_on_device(w, h, &depth, &known, &flat, 0.1, 3000);
    for y in 0..h {
        for x in 0..w {
            let e = (got[y * w + x] - plane(x, y)).abs();
            assert!(
                e < 1e-3,
                "pixel ({x}, {y}): {} vs plane {}",
                got[y * w + x],
                plane(x, y)
            );
        }
    }
    // Two colour regions split at x = 20: the left known at depth 1, the right at depth 5.
    let guide: Vec<[f32; 4]> = (0..n)
        .map(|i| {
            if i % w < 20 {
                [1.0, 0.0, 0.0, 0.0]
            } else {
                [0.0, 0.0, 1.0, 0.0]
            }
        })
        .collect();
    let two: Vec<f32> = (0..n).map(|i| if i % w < 20 { 1.0 } else { 5.0 }).collect();
    let edged = complete_on_device(w, h, &two, &known, &guide, 0.1, 3000);
    let blurred = complete_on_device(w, h, &two, &known, &flat, 0.1, 3000);
    let (l, r) = (15 * w + 19, 15 * w + 20);
    assert!(
        (edged[l] - 1.0).abs() < 1e-2 && (edged[r] - 5.0).abs() < 1e-2,
        "{} {}",
        edged[l],
        edged[r]
    );
    // Without the edge, depth mixes across the boundary.
    assert!(
        blurred[l] > 2.0 && blurred[r] < 4.0,
        "{} {}",
        blurred[l],
        blurred[r]
    );
    assert_no_validation_messages(&engine().ctx);
}

/// Bad sizes and scales are clear errors.
#[test]
fn depth_completion_refuses_bad_input() {
    use extranerf_nerf::depth_completion::DepthCompletion;
    let e = engine();
    let dc = DepthCompletion::new(&e.ctx).unwrap();
    let b = Buffer::<f32>::new(&e.ctx, "small", 4).unwrap();
    let k = Buffer::<u32>::new(&e.ctx, "known", 4).unwrap();
    let g = Buffer::<[f32; 4]>::new(&e.ctx, "guide", 4).unwrap();
    let mut rec = e.ctx.recorder("bad completion").unwrap();
    for (w, h, sigma) in [(0, 4, 1.0), (4, 4, 1.0), (2, 2, 0.0), (2, 2, f32::NAN)] {
        let r = dc.record(
            &mut rec,
            w,
            h,
            b.binding(),
            b.binding(),
            k.binding(),
            g.binding(),
            sigma,
            3,
        );
        assert!(r.is_err(), "{w}x{h} sigma {sigma}");
    }
    drop(rec);
    assert_no_validation_messages(&e.ctx);
}
