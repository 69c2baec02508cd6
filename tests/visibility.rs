//! Multi-view transmittance visibility against the f64 reference of the same definition, on
//! analytic scenes with a known answer (a sphere in front of a plane, a wall with a hole) and
//! on a random NDC field; the properties the definition implies (a training camera's own
//! footprint, points behind every camera, a single camera, rank 1 against rank 2); the relative
//! measure on surfaces rendered as semi-transparent shells; the accuracy cuts; and the extremes
//! (opaque and empty fields, axis-parallel rays).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use glam::{DMat4, DVec3};

use extranerf_nerf::data::Camera;
use extranerf_nerf::model::{init_params, ModelConfig, ParamLayout};
use extranerf_nerf::reference::{
    field_forward, sample_t, transmittance_volume, visibility_pixel, visibility_pixel_given,
    visibility_pixel_volume, VisibilitySetup,
};
use extranerf_nerf::render::visibility::{
    mask_all_but, AnalyticField, Density, Shape, TransmittanceVolume, Visibility, VisibilityConfig,
    VisibilityMap, VisibilityMeasure,
};
use extranerf_nerf::renderer::Nerf;
use extranerf_prims::reference::Rng;
use extranerf_tests::{assert_no_validation_messages, engine};

/// A camera at `eye` turned by `yaw` about y (0: looking along -z), `w` x `h` pixels.
fn camera(eye: [f64; 3], yaw: f64, w: u32, h: u32, f: f64) -> Camera {
    Camera {
        c2w: DMat4::from_translation(DVec3::from(eye)) * DMat4::from_rotation_y(yaw),
        width: w,
        height: h,
        fx: f,
        fy: f,
        cx: w as f64 / 2.0,
        cy: h as f64 / 2.0,
        bounds: None,
        image: "none.png".into(),
    }
}

/// Training rig: cameras on the x axis at z = 0 looking along -z.
fn rig(xs: &[f64]) -> Vec<Camera> {
    xs.iter()
        .map(|&x| camera([x, 0.0, 0.0], 0.0, 16, 12, 12.0))
        .collect()
}

fn cfg(samples: u32, vis_samples: u32, rank: u32) -> VisibilityConfig {
    VisibilityConfig {
        samples,
        vis_samples,
        rank,
        ..VisibilityConfig::default()
    }
}

/// A sphere in front of a thick plane (world space).
fn sphere_before_plane() -> Vec<Shape> {
    vec![
        Shape::Sphere {
            centre: [0.0, 0.0, -2.0],
            radius: 0.5,
            sigma: 40.0,
            soft: 0.02,
        },
        Shape::Box {
            min: [-6.0, -6.0, -4.6],
            max: [6.0, 6.0, -4.0],
            sigma: 20.0,
            soft: 0.02,
        },
    ]
}

/// A wall at z = -2 with a square hole |x|, |y| < 0.4, and a back plane.
fn wall_with_hole() -> Vec<Shape> {
    let wall = |min: [f32; 3], max: [f32; 3]| Shape::Box {
        min,
        max,
        sigma: 40.0,
        soft: 0.02,
    };
    vec![
        wall([-6.0, -6.0, -2.3], [-0.4, 6.0, -2.0]),
        wall([0.4, -6.0, -2.3], [6.0, 6.0, -2.0]),
        wall([-0.4, -6.0, -2.3], [0.4, -0.4, -2.0]),
        wall([-0.4, 0.4, -2.3], [0.4, 6.0, -2.0]),
        Shape::Box {
            min: [-8.0, -8.0, -5.2],
            max: [8.0, 8.0, -4.4],
            sigma: 20.0,
            soft: 0.02,
        },
    ]
}

const NEAR: f32 = 0.5;
const FAR: f32 = 7.0;

fn analytic(shapes: &[Shape]) -> AnalyticField {
    AnalyticField::new(&engine().ctx, shapes, false, NEAR, FAR).unwrap()
}

fn vis_map(
    density: &Density<'_>,
    cam: &Camera,
    train: &[Camera],
    mask: u32,
    c: &VisibilityConfig,
) -> VisibilityMap {
    let v = Visibility::new(&engine().ctx).unwrap();
    v.map(&engine().ctx, density, cam, train, mask, c, None, 37)
        .unwrap()
}

fn setup(ndc: bool, near: f32, far: f32, c: &VisibilityConfig, mask: u32) -> VisibilitySetup {
    VisibilitySetup {
        ndc,
        near: near as f64,
        far: far as f64,
        samples: c.samples,
        vis_samples: c.vis_samples,
        rank: c.rank,
        mask,
        measure: c.measure,
    }
}

/// Every pixel within `tol` of the reference (visibility, opacity, depth); returns the
/// reference's (visibility, opacity) per pixel.
fn check(
    got: &VisibilityMap,
    density: &dyn Fn([f64; 3]) -> f64,
    cam: &Camera,
    train: &[Camera],
    s: &VisibilitySetup,
    tol: f64,
) -> Vec<[f64; 2]> {
    let mut out = Vec::new();
    for px in 0..cam.width * cam.height {
        let want = visibility_pixel(density, cam, px, train, s);
        let i = px as usize;
        let g = [got.visibility[i], got.opacity[i], got.depth[i]];
        for c in 0..3 {
            let scale = if c == 2 { 1.0 + want[2].abs() } else { 1.0 };
            assert!(
                (g[c] as f64 - want[c]).abs() <= tol * scale,
                "pixel {px} ({}, {}) quantity {c}: kernel {} vs reference {} (all: {g:?} vs {want:?})",
                px % cam.width,
                px / cam.width,
                g[c],
                want[c]
            );
        }
        assert!(got.evals[i].is_finite() && got.evals[i] >= 0.0);
        out.push([want[0], want[1]]);
    }
    out
}

/// Sorted samples `(t, dt)` per pixel that are not strata: `k` bins between random edges in
/// the sampling parameter s (disparity for world space), each sample at its bin's midpoint in
/// s, as the proposal sampler places them.
fn random_samples(rng: &mut Rng, pixels: u32, s: &VisibilitySetup) -> Vec<[f32; 2]> {
    let (k, t_of) = (s.samples, |u| sample_t(s, u));
    let mut out = Vec::new();
    for _ in 0..pixels {
        // Gaps from 0.2 to 1.8 times the even spacing: dense and sparse stretches.
        let gaps: Vec<f64> = (0..k).map(|_| rng.uniform(0.2, 1.8) as f64).collect();
        let sum: f64 = gaps.iter().sum();
        let mut e = 0.0;
        for g in gaps {
            let e1 = (e + g / sum).min(1.0);
            out.push([t_of(0.5 * (e + e1)) as f32, (t_of(e1) - t_of(e)) as f32]);
            e = e1;
        }
    }
    out
}

/// The visibility kernel at given samples (not strata), on the analytic scenes in world space
/// and on a sphere in NDC, against the f64 reference at the same samples; the strata given as
/// samples give the strata's map.
#[test]
fn given_samples_match_the_reference() {
    use extranerf_gpu::Buffer;
    use extranerf_nerf::render::rays::gpu_camera;
    let ctx = &engine().ctx;
    let v = Visibility::new(ctx).unwrap();
    let mut rng = Rng::new(41);
    let ndc_sphere = vec![Shape::Sphere {
        centre: [0.05, 0.0, 0.3],
        radius: 0.35,
        sigma: 30.0,
        soft: 0.05,
    }];
    for (name, shapes, ndc, near, far, eye, yaw) in [
        (
            "sphere before plane",
            sphere_before_plane(),
            false,
            NEAR,
            FAR,
            [1.6, 0.1, 0.4],
            0.35,
        ),
        (
            "wall with hole",
            wall_with_hole(),
            false,
            NEAR,
            FAR,
            [1.2, -0.1, 0.3],
            0.3,
        ),
        (
            "NDC sphere",
            ndc_sphere,
            true,
            0.0,
            1.0,
            [0.3, 0.05, 0.0],
            0.1,
        ),
    ] {
        let field = AnalyticField::new(ctx, &shapes, ndc, near, far).unwrap();
        let train = rig(&[-0.6, 0.0, 0.6]);
        let cam = camera(eye, yaw, 16, 12, 11.0);
        let n = cam.width * cam.height;
        let c = cfg(40, 48, 2);
        let mask = mask_all_but(train.len(), None);
        let s = setup(ndc, near, far, &c, mask);
        let given = random_samples(&mut rng, n, &s);
        let run = |given: &[[f32; 2]]| -> Result<Vec<[f32; 4]>, extranerf_gpu::GpuError> {
            let cams = Buffer::from_slice(ctx, "camera", &[gpu_camera(&cam)]).unwrap();
            let train_gpu: Vec<_> = train.iter().map(gpu_camera).collect();
            let train_buf = Buffer::from_slice(ctx, "training cameras", &train_gpu).unwrap();
            let px: Vec<[u32; 2]> = (0..n).map(|p| [0, p]).collect();
            let pixels = Buffer::from_slice(ctx, "pixels", &px).unwrap();
            let t_dt = Buffer::from_slice(ctx, "given samples", given).unwrap();
            let out = Buffer::<[f32; 4]>::new(ctx, "visibility", n as usize).unwrap();
            let mut rec = ctx.recorder("visibility at given samples")?;
            v.record(
                &mut rec,
                &Density::Analytic(&field),
                cams.binding(),
                1,
                pixels.binding(),
                n as u64,
                train_buf.binding(),
                train.len() as u32,
                mask,
                &c,
                None,
                Some(t_dt.binding()),
                out.binding(),
            )?;
            ctx.run(rec)?;
            out.read()
        };
        let got = run(&given).unwrap();
        let (mut seen, mut hidden) = (0, 0);
        for px in 0..n {
            let g: Vec<[f64; 2]> = given
                [(px * c.samples) as usize..((px + 1) * c.samples) as usize]
                .iter()
                .map(|v| [v[0] as f64, v[1] as f64])
                .collect();
            let want =
                visibility_pixel_given(&|x| field.density(x), &cam, px, &train, &s, Some(&g));
            let k = got[px as usize];
            for q in 0..3 {
                let scale = if q == 2 { 1.0 + want[2].abs() } else { 1.0 };
                assert!(
                    (k[q] as f64 - want[q]).abs() <= 2e-3 * scale,
                    "{name} pixel {px} quantity {q}: kernel {:?} vs reference {want:?}",
                    k
                );
            }
            seen += usize::from(want[1] > 0.9 && want[0] > 0.8);
            hidden += usize::from(want[1] > 0.9 && want[0] < 0.2);
        }
        assert!(
            seen > 5 && (ndc || hidden > 5),
            "{name}: {seen} visible, {hidden} hidden opaque pixels"
        );
        // The strata, given: the kernel's own strata's map (to f32 rounding of t and dt, which
        // the kernel computes in f32 and the given ones come from f64).
        let k = c.samples as f64;
        let t_of = |u| sample_t(&s, u);
        let strata: Vec<[f32; 2]> = (0..n * c.samples)
            .map(|i| {
                let j = (i % c.samples) as f64;
                let (s0, s1) = (j / k, (j + 1.0) / k);
                [t_of(0.5 * (s0 + s1)) as f32, (t_of(s1) - t_of(s0)) as f32]
            })
            .collect();
        let own = v
            .map(
                ctx,
                &Density::Analytic(&field),
                &cam,
                &train,
                mask,
                &c,
                None,
                64,
            )
            .unwrap();
        for (px, k) in run(&strata).unwrap().iter().enumerate() {
            let o = [own.visibility[px], own.opacity[px], own.depth[px]];
            for q in 0..3 {
                assert!(
                    (k[q] - o[q]).abs() <= 5e-3 * (1.0 + o[q].abs()),
                    "{name} pixel {px}: strata given {k:?}, the kernel's strata {o:?}"
                );
            }
        }
        // Fewer given samples than the pixels need are refused.
        let err = run(&given[..given.len() / 2]).unwrap_err().to_string();
        assert!(err.contains("given samples"), "{err}");
    }
    assert_no_validation_messages(ctx);
}

#[test]
fn analytic_scenes_match_the_reference() {
    let ctx = &engine().ctx;
    let train = rig(&[-0.6, 0.0, 0.6]);
    for (name, shapes, eye, yaw) in [
        (
            "sphere before plane",
            sphere_before_plane(),
            [1.6, 0.1, 0.4],
            0.35,
        ),
        ("wall with hole", wall_with_hole(), [1.2, -0.1, 0.3], 0.3),
    ] {
        let field = analytic(&shapes);
        let cam = camera(eye, yaw, 16, 12, 11.0);
        for (rank, measure) in [1, 2, 3].into_iter().flat_map(|r| {
            [
                (r, VisibilityMeasure::Relative),
                (r, VisibilityMeasure::Absolute),
            ]
        }) {
            let c = VisibilityConfig {
                measure,
                ..cfg(64, 48, rank)
            };
            let mask = mask_all_but(train.len(), None);
            let got = vis_map(&Density::Analytic(&field), &cam, &train, mask, &c);
            let want = check(
                &got,
                &|x| field.density(x),
                &cam,
                &train,
                &setup(false, NEAR, FAR, &c, mask),
                2e-3,
            );
            // The scene must show both: surfaces the rig saw and surfaces it did not.
            let seen = want.iter().filter(|w| w[1] > 0.9 && w[0] > 0.8).count();
            let hidden = want.iter().filter(|w| w[1] > 0.9 && w[0] < 0.2).count();
            assert!(
                seen > 5 && (rank == 1 || hidden > 5),
                "{name} rank {rank} {measure:?}: {seen} visible and {hidden} hidden opaque pixels"
            );
        }
    }
    assert_no_validation_messages(ctx);
}

#[test]
fn a_training_camera_sees_its_footprint_only_where_a_second_camera_did() {
    let ctx = &engine().ctx;
    let field = analytic(&sphere_before_plane());
    let train = rig(&[0.0, 1.2]);
    let own = train[0].clone();
    let c2 = cfg(64, 48, 2);
    let c1 = cfg(64, 48, 1);
    let d = Density::Analytic(&field);
    let both = vis_map(&d, &own, &train, 0b11, &c2);
    let itself = vis_map(&d, &own, &train, 0b01, &c1);
    let other = vis_map(&d, &own, &train, 0b10, &c1);
    check(
        &both,
        &|x| field.density(x),
        &own,
        &train,
        &setup(false, NEAR, FAR, &c2, 0b11),
        2e-3,
    );
    let n = both.visibility.len();
    let (mut hidden, mut seen) = (0, 0);
    for i in 0..n {
        let o = both.opacity[i];
        // A camera sees its own footprint.
        assert!(
            (itself.visibility[i] - o).abs() < 0.05,
            "pixel {i}: self-visibility {} vs opacity {o}",
            itself.visibility[i]
        );
        // With rank 2 the pixel is visible exactly where the second camera saw it.
        assert!(
            (both.visibility[i] - other.visibility[i]).abs() < 0.05,
            "pixel {i}: two-camera visibility {} vs second camera alone {}",
            both.visibility[i],
            other.visibility[i]
        );
        hidden += usize::from(o > 0.9 && other.visibility[i] < 0.1);
        seen += usize::from(o > 0.9 && other.visibility[i] > 0.8);
    }
    assert!(
        hidden > 3 && seen > 3,
        "{hidden} hidden and {seen} seen pixels"
    );
    assert_no_validation_messages(ctx);
}

#[test]
fn points_behind_every_camera_and_a_single_camera_give_zero() {
    let ctx = &engine().ctx;
    // A plane behind the rig (z > 0) seen by a camera turned around.
    let field = analytic(&[Shape::Box {
        min: [-9.0, -9.0, 3.0],
        max: [9.0, 9.0, 3.5],
        sigma: 30.0,
        soft: 0.0,
    }]);
    let train = rig(&[-0.5, 0.5]);
    let back = camera([0.0, 0.0, 0.5], std::f64::consts::PI, 16, 12, 12.0);
    let d = Density::Analytic(&field);
    let m = vis_map(&d, &back, &train, 0b11, &cfg(48, 32, 1));
    assert!(m.mean_opacity() > 0.9, "opacity {}", m.mean_opacity());
    assert!(m.visibility.iter().all(|&v| v == 0.0), "{:?}", m.visibility);
    assert!(m.evals.iter().all(|&e| e == 0.0), "no segment is marched");

    // One training camera: the second largest transmittance is 0 everywhere.
    let field = analytic(&sphere_before_plane());
    let d = Density::Analytic(&field);
    let cam = camera([0.3, 0.0, 0.2], 0.1, 16, 12, 12.0);
    let one = rig(&[0.0]);
    let r2 = vis_map(&d, &cam, &one, 1, &cfg(48, 32, 2));
    assert!(r2.visibility.iter().all(|&v| v == 0.0));
    let r1 = vis_map(&d, &cam, &one, 1, &cfg(48, 32, 1));
    assert!(r1.mean() > 0.3, "rank 1 mean visibility {}", r1.mean());
    // Masked-out cameras count as absent.
    let train = rig(&[0.0, 0.4]);
    let masked = vis_map(&d, &cam, &train, 0b01, &cfg(48, 32, 2));
    assert!(masked.visibility.iter().all(|&v| v == 0.0));
    assert_no_validation_messages(ctx);
}

/// The sphere and back plane of [`sphere_before_plane`] as shells: opaque in sum but spread
/// over several samples in depth, as an under-fitted field renders surfaces.
fn shells() -> Vec<Shape> {
    vec![
        Shape::Sphere {
            centre: [0.0, 0.0, -2.0],
            radius: 0.6,
            sigma: 5.0,
            soft: 0.4,
        },
        Shape::Box {
            min: [-6.0, -6.0, -6.5],
            max: [6.0, 6.0, -4.0],
            sigma: 2.5,
            soft: 0.4,
        },
    ]
}

#[test]
fn the_relative_measure_sees_shells_where_the_cameras_did() {
    let ctx = &engine().ctx;
    let train = rig(&[-0.6, 0.0, 0.6]);
    let sharp = analytic(&sphere_before_plane());
    let shell = analytic(&shells());
    let rel = cfg(192, 48, 2);
    let abs = VisibilityConfig {
        measure: VisibilityMeasure::Absolute,
        ..rel
    };
    let cam = camera([1.6, 0.1, 0.4], 0.35, 16, 12, 11.0);
    let mask = 0b111;
    // (seen share, opacity) per pixel, checked against the reference.
    let shares = |field: &AnalyticField, c: &VisibilityConfig| {
        let m = vis_map(&Density::Analytic(field), &cam, &train, mask, c);
        check(
            &m,
            &|x| field.density(x),
            &cam,
            &train,
            &setup(false, NEAR, FAR, c, mask),
            2e-3,
        );
        m.visibility
            .iter()
            .zip(&m.opacity)
            .map(|(v, o)| ((v / o.max(1e-6)) as f64, *o as f64))
            .collect::<Vec<_>>()
    };
    let (sharp_abs, sharp_rel) = (shares(&sharp, &abs), shares(&sharp, &rel));
    let (shell_abs, shell_rel) = (shares(&shell, &abs), shares(&shell, &rel));
    // Mean seen share over the opaque pixels the sharp scene says were seen (or hidden).
    let mean = |r: &[(f64, f64)], seen: bool| {
        let v: Vec<f64> = r
            .iter()
            .zip(&sharp_abs)
            .filter(|(x, s)| x.1 > 0.9 && s.1 > 0.9 && (s.0 > 0.5) == seen)
            .map(|(x, _)| x.0)
            .collect();
        (v.iter().sum::<f64>() / v.len().max(1) as f64, v.len())
    };
    for (name, r) in [
        ("sharp absolute", &sharp_abs),
        ("sharp relative", &sharp_rel),
        ("shells absolute", &shell_abs),
        ("shells relative", &shell_rel),
    ] {
        eprintln!(
            "{name}: seen {:?}, hidden {:?}",
            mean(r, true),
            mean(r, false)
        );
    }
    let (seen, n_seen) = mean(&sharp_abs, true);
    let (hidden, n_hidden) = mean(&sharp_abs, false);
    assert!(n_seen > 20 && n_hidden > 5 && seen > 0.9 && hidden < 0.1);
    // On sharp surfaces the measures agree.
    assert!((mean(&sharp_rel, true).0 - seen).abs() < 0.05);
    assert!((mean(&sharp_rel, false).0 - hidden).abs() < 0.05);
    // On shells the absolute measure loses much of what was seen; the relative one keeps it,
    // and what the sphere hid stays hidden.
    // (Seen through the shells at an angle, the cameras' paths through them are longer than
    // the pixel's, so the relative share stays below 1.)
    assert!(
        mean(&shell_abs, true).0 < 0.65,
        "{:?}",
        mean(&shell_abs, true)
    );
    assert!(
        mean(&shell_rel, true).0 > 0.8,
        "{:?}",
        mean(&shell_rel, true)
    );
    assert!(
        mean(&shell_rel, false).0 < 0.2,
        "{:?}",
        mean(&shell_rel, false)
    );
    assert_no_validation_messages(ctx);
}

#[test]
fn cuts_stay_within_their_bounds() {
    let ctx = &engine().ctx;
    let field = analytic(&wall_with_hole());
    let d = Density::Analytic(&field);
    let train = rig(&[-0.6, -0.2, 0.2, 0.6]);
    let cam = camera([1.0, 0.0, 0.3], 0.25, 16, 12, 11.0);
    for (min_weight, min_transmittance, measure) in [
        (1e-3, 0.0, VisibilityMeasure::Relative),
        (0.0, 1e-2, VisibilityMeasure::Relative),
        (1e-2, 1e-2, VisibilityMeasure::Relative),
        (0.0, 1e-2, VisibilityMeasure::Absolute),
        (1e-2, 1e-2, VisibilityMeasure::Absolute),
    ] {
        let exact = vis_map(
            &d,
            &cam,
            &train,
            0b1111,
            &VisibilityConfig {
                measure,
                ..cfg(64, 48, 2)
            },
        );
        let c = VisibilityConfig {
            min_weight,
            min_transmittance,
            measure,
            ..cfg(64, 48, 2)
        };
        let cut = vis_map(&d, &cam, &train, 0b1111, &c);
        let bound = 64.0 * min_weight + min_transmittance + 1e-5;
        let mut saved = 0.0;
        for i in 0..exact.visibility.len() {
            let e = (exact.visibility[i] - cut.visibility[i]).abs();
            assert!(e <= bound, "{c:?} pixel {i}: error {e} above {bound}");
            assert_eq!(exact.opacity[i], cut.opacity[i]);
            saved += (exact.evals[i] - cut.evals[i]) as f64;
        }
        assert!(saved > 0.0, "{c:?} saved no evaluations");
    }
    assert_no_validation_messages(ctx);
}

#[test]
fn extremes_give_finite_bounded_maps() {
    let ctx = &engine().ctx;
    let train = rig(&[-0.3, 0.3]);
    // cx on a pixel centre: the middle pixel's ray is parallel to the z axis.
    let mut cam = camera([0.0, 0.0, 0.0], 0.0, 15, 11, 12.0);
    cam.cx = 7.5;
    cam.cy = 5.5;
    for (name, sigma) in [("empty", 0.0f32), ("opaque", 1e8), ("thin", 1e-6)] {
        for ndc in [false, true] {
            // A slab filling the view: world z in [-6, -1], or NDC z' in [0, 0.9].
            let (z0, z1, near, far) = if ndc {
                (0.0, 0.9, 0.0, 1.0)
            } else {
                (-6.0, -1.0, NEAR, FAR)
            };
            let slab = [Shape::Box {
                min: [-50.0, -50.0, z0],
                max: [50.0, 50.0, z1],
                sigma,
                soft: 0.0,
            }];
            let field = AnalyticField::new(ctx, &slab, ndc, near, far).unwrap();
            let m = vis_map(
                &Density::Analytic(&field),
                &cam,
                &train,
                0b11,
                &cfg(32, 24, 2),
            );
            for i in 0..m.visibility.len() {
                let (v, o) = (m.visibility[i], m.opacity[i]);
                assert!(
                    v.is_finite() && o.is_finite() && m.depth[i].is_finite(),
                    "{name} ndc {ndc}: pixel {i} gives {v}, {o}, {}",
                    m.depth[i]
                );
                assert!(
                    (0.0..=o + 1e-5).contains(&v) && o <= 1.0 + 1e-5,
                    "{name} ndc {ndc}: pixel {i}: visibility {v}, opacity {o}"
                );
            }
            if sigma == 0.0 {
                assert!(m.opacity.iter().all(|&o| o == 0.0));
            }
            if sigma == 1e8 {
                assert!(m.mean_opacity() > 0.99, "{name}: {}", m.mean_opacity());
                // The near face is seen by both cameras wherever both frustums hold it.
                assert!(m.mean() > 0.3, "{name} ndc {ndc}: {}", m.mean());
            }
        }
    }
    assert_no_validation_messages(ctx);
}

/// A random NDC field (the fused march's test model) against the reference: over NDC's unit
/// cube sampled from t 0 to 1, and as auto-config fits a scene, a shifted box of half side 1.3
/// sampled from t 0.15 to 0.85 (the segments toward the cameras then end where t = 0.15).
#[test]
fn trained_field_path_matches_the_reference_in_ndc() {
    let ctx = &engine().ctx;
    for (near, far, center, radius) in [
        (0.0f32, 1.0f32, [0.0f32; 3], 1.0f32),
        (0.15, 0.85, [0.05, -0.02, -0.06], 1.3),
    ] {
        let cfg_m = ModelConfig {
            levels: 4,
            features: 2,
            log2_table: 9,
            min_res: 4,
            max_res: 48,
            density_width: 16,
            density_layers: 1,
            geo_dims: 8,
            color_width: 16,
            color_layers: 2,
            near,
            far,
            center,
            radius,
            ..ModelConfig::default()
        };
        let mut rng = Rng::new(3);
        let mut p = init_params(&cfg_m, 3);
        let lay = ParamLayout::new(&cfg_m);
        for v in &mut p[lay.table.0..lay.table.0 + lay.table.1] {
            *v = rng.uniform(-2.0, 2.0);
        }
        let nerf = Nerf::new(ctx, cfg_m.clone(), &p, [0.0; 3]).unwrap();
        let train: Vec<Camera> = [-0.2, 0.0, 0.25]
            .iter()
            .map(|&x| camera([x, 0.05, 0.0], 0.0, 12, 9, 10.0))
            .collect();
        let cam = camera([0.35, -0.05, 0.1], 0.12, 12, 9, 10.0);
        let c = cfg(24, 16, 2);
        let d = Density::Field {
            field: nerf.field(),
            params: nerf.field().layout().sections(nerf.params()).unwrap(),
            occupancy: None,
        };
        let got = vis_map(&d, &cam, &train, 0b111, &c);
        let density = |x: [f64; 3]| {
            let pos = [x[0] as f32, x[1] as f32, x[2] as f32];
            field_forward(&cfg_m, &p, &pos, &[[0.0, 0.0, -1.0]], 1)[0].0
        };
        let want = check(
            &got,
            &density,
            &cam,
            &train,
            &setup(true, near, far, &c, 0b111),
            2e-3,
        );
        let partial = want.iter().filter(|w| w[0] > 0.05 && w[0] < w[1] - 0.05);
        assert!(
            partial.count() > 5,
            "near {near}: the field should be partly visible: {want:?}"
        );
        // The same through transmittance volumes (each camera's own NDC rays).
        check_volume(
            &d,
            &density,
            &cam,
            &train,
            &setup(true, near, far, &c, 0b111),
            &c,
            12,
            24,
        );
    }
    assert_no_validation_messages(ctx);
}

#[test]
fn bad_settings_are_errors() {
    let ctx = &engine().ctx;
    let field = analytic(&sphere_before_plane());
    let d = Density::Analytic(&field);
    let cam = camera([0.0; 3], 0.0, 4, 4, 4.0);
    let v = Visibility::new(ctx).unwrap();
    let train = rig(&[0.0, 0.5]);
    for (c, what) in [
        (cfg(32, 32, 0), "rank"),
        (cfg(32, 32, 9), "rank"),
        (cfg(0, 32, 2), "sample"),
        (cfg(32, 0, 2), "sample"),
        (
            VisibilityConfig {
                min_weight: 1.5,
                ..cfg(32, 32, 2)
            },
            "cuts",
        ),
    ] {
        let e = v.map(ctx, &d, &cam, &train, 3, &c, None, 16).unwrap_err();
        assert!(e.to_string().contains(what), "{c:?}: {e}");
    }
    let e = v
        .map(ctx, &d, &cam, &[], 0, &cfg(32, 32, 2), None, 16)
        .unwrap_err();
    assert!(e.to_string().contains("training cameras"), "{e}");
    assert_eq!(mask_all_but(3, Some(1)), 0b101);
    assert_eq!(mask_all_but(40, None), u32::MAX);
}

/// Checks a built volume against the reference, then a visibility map that looks it up against
/// the reference lookup (given the kernel's volume); returns the map.
#[allow(clippy::too_many_arguments)] // each is a distinct operand
fn check_volume(
    density: &Density<'_>,
    density_ref: &dyn Fn([f64; 3]) -> f64,
    cam: &Camera,
    train: &[Camera],
    s: &VisibilitySetup,
    c: &VisibilityConfig,
    w: u32,
    d: u32,
) -> (VisibilityMap, TransmittanceVolume) {
    let ctx = &engine().ctx;
    let v = Visibility::new(ctx).unwrap();
    let vol = v.build_volume(ctx, density, train, w, d).unwrap();
    let size = vol.size();
    let got = vol.buffer().read().unwrap();
    let want = transmittance_volume(density_ref, train, size, s);
    assert_eq!(got.len(), want.len());
    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
        assert!(
            (*g as f64 - w).abs() < 1e-3,
            "volume entry {i}: kernel {g} vs reference {w}"
        );
    }
    // Some rays must lose most of their transmittance, or the volume shows little.
    assert!(want.iter().any(|&t| t < 0.5));
    let m = v
        .map(ctx, density, cam, train, s.mask, c, Some(&vol), 29)
        .unwrap();
    let vol64: Vec<f64> = got.iter().map(|&x| x as f64).collect();
    for px in 0..cam.width * cam.height {
        let want = visibility_pixel_volume(density_ref, cam, px, train, s, &vol64, size);
        let i = px as usize;
        let g = [m.visibility[i], m.opacity[i], m.depth[i]];
        for q in 0..3 {
            let scale = if q == 2 { 1.0 + want[2].abs() } else { 1.0 };
            assert!(
                (g[q] as f64 - want[q]).abs() <= 2e-3 * scale,
                "pixel {px} quantity {q}: kernel {g:?} vs reference {want:?}"
            );
        }
    }
    (m, vol)
}

#[test]
fn transmittance_volumes_match_the_reference_and_approximate_the_march() {
    let ctx = &engine().ctx;
    let train = rig(&[-0.6, 0.0, 0.6]);
    let field = analytic(&sphere_before_plane());
    let d = Density::Analytic(&field);
    let cam = camera([1.6, 0.1, 0.4], 0.35, 16, 12, 11.0);
    let absolute = VisibilityConfig {
        measure: VisibilityMeasure::Absolute,
        ..cfg(64, 48, 2)
    };
    let sa = setup(false, NEAR, FAR, &absolute, 0b111);
    check_volume(
        &d,
        &|x| field.density(x),
        &cam,
        &train,
        &sa,
        &absolute,
        24,
        96,
    );
    let c = cfg(64, 48, 2);
    let s = setup(false, NEAR, FAR, &c, 0b111);
    let (vm, vol) = check_volume(&d, &|x| field.density(x), &cam, &train, &s, &c, 24, 96);
    assert_eq!(vol.size(), [24, 18, 96]);
    assert_eq!(vol.bytes(), 3 * 24 * 18 * 97 * 4);
    // Against the exact march: the same picture up to the volume's resolution.
    let exact = vis_map(&d, &cam, &train, 0b111, &c);
    let n = exact.visibility.len() as f64;
    let mean_err = exact
        .visibility
        .iter()
        .zip(&vm.visibility)
        .map(|(a, b)| (a - b).abs() as f64)
        .sum::<f64>()
        / n;
    eprintln!("volume vs march: mean |diff| {mean_err}");
    assert!(mean_err < 0.06, "volume vs march: mean |diff| {mean_err}");
    assert_eq!(exact.opacity, vm.opacity);
    // At most one lookup per camera and weighted sample, no marching.
    assert!(vm.evals.iter().all(|&v| v <= 64.0 * 3.0));
    let total = |m: &VisibilityMap| m.evals.iter().map(|&e| e as f64).sum::<f64>();
    assert!(
        total(&vm) * 10.0 < total(&exact),
        "{} vs {}",
        total(&vm),
        total(&exact)
    );

    // Points behind every camera give 0; one camera with rank 2 gives 0.
    let back_field = analytic(&[Shape::Box {
        min: [-9.0, -9.0, 3.0],
        max: [9.0, 9.0, 3.5],
        sigma: 30.0,
        soft: 0.0,
    }]);
    let bd = Density::Analytic(&back_field);
    let back = camera([0.0, 0.0, 0.5], std::f64::consts::PI, 16, 12, 12.0);
    let v = Visibility::new(ctx).unwrap();
    let vol = v.build_volume(ctx, &bd, &train, 16, 32).unwrap();
    let m = v
        .map(
            ctx,
            &bd,
            &back,
            &train,
            0b111,
            &cfg(48, 32, 1),
            Some(&vol),
            64,
        )
        .unwrap();
    assert!(m.mean_opacity() > 0.9 && m.visibility.iter().all(|&x| x == 0.0));
    let one = rig(&[0.0]);
    let vol = v.build_volume(ctx, &d, &one, 16, 32).unwrap();
    let m = v
        .map(ctx, &d, &cam, &one, 1, &cfg(48, 32, 2), Some(&vol), 64)
        .unwrap();
    assert!(m.visibility.iter().all(|&x| x == 0.0));
    // A volume for other cameras is refused.
    let e = v
        .map(ctx, &d, &cam, &train, 0b111, &c, Some(&vol), 64)
        .unwrap_err();
    assert!(e.to_string().contains("volume"), "{e}");
    assert_no_validation_messages(ctx);
}
