//! The fused march kernel against the f64 reference and the standalone chain (NDC and world
//! space with contraction), its accuracy cuts, the fused occupancy update against the reference,
//! renders that skip empty cells, and the extremes.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message
#![allow(clippy::needless_range_loop)] // pixels and channels index parallel arrays

use glam::{DMat4, DVec3};

use extranerf_nerf::data::Camera;
use extranerf_nerf::model::{init_params, ModelConfig, ParamLayout};
use extranerf_nerf::reference::{field_forward, march_pixel, occ_cell, occ_cell_point};
use extranerf_nerf::render::march::MarchCuts;
use extranerf_nerf::render::occupancy::OccupancyConfig;
use extranerf_nerf::renderer::{March, Nerf};
use extranerf_prims::reference::Rng;
use extranerf_tests::{assert_no_validation_messages, engine};

const BACKGROUND: [f32; 3] = [0.2, 0.5, 0.9];

/// A small model in `space` ("ndc" or "world" with L2 contraction).
fn model(space: &str) -> ModelConfig {
    let base = ModelConfig {
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
        ..ModelConfig::default()
    };
    if space == "ndc" {
        return base;
    }
    ModelConfig {
        space: extranerf_nerf::model::Space::World,
        near: 0.5,
        far: 30.0,
        center: [0.1, -0.2, 0.0],
        radius: 1.5,
        contraction: extranerf_nerf::field::encodings::Contraction::L2,
        ..base
    }
}

/// Random parameters with a table large enough to matter and a density bias `bias`.
fn params(cfg: &ModelConfig, seed: u64, bias: f32) -> Vec<f32> {
    let mut rng = Rng::new(seed);
    let mut p = init_params(cfg, seed);
    let lay = ParamLayout::new(cfg);
    for v in &mut p[lay.table.0..lay.table.0 + lay.table.1] {
        *v = rng.uniform(-2.0, 2.0);
    }
    let d = cfg.density_mlp();
    let last = d.layers() - 1;
    let b0 = lay.density.0 + d.offset(last) + (d.dims[last] * d.dims[last + 1]) as usize;
    p[b0] = bias;
    p
}

/// A 12x9 camera at `eye` looking along -z, turned a little about y and x.
fn camera(eye: [f64; 3]) -> Camera {
    let rot = DMat4::from_rotation_y(0.15) * DMat4::from_rotation_x(-0.1);
    Camera {
        c2w: DMat4::from_translation(DVec3::from(eye)) * rot,
        width: 12,
        height: 9,
        fx: 10.0,
        fy: 10.0,
        cx: 6.0,
        cy: 4.5,
        bounds: None,
        image: "none.png".into(),
    }
}

struct Image {
    rgb: Vec<f32>,
    depth: Vec<f32>,
    opacity: Vec<f32>,
}

fn render(nerf: &Nerf, cam: &Camera, samples: u32, march: March) -> Image {
    let (rgb, depth, opacity) = nerf
        .render_with(&engine().ctx, cam, 50, samples, march)
        .unwrap();
    Image {
        rgb,
        depth,
        opacity,
    }
}

/// Largest differences (colour and opacity, depth) between two renders.
fn max_diff(a: &Image, b: &Image) -> (f32, f32) {
    let d = |x: &[f32], y: &[f32]| {
        x.iter()
            .zip(y)
            .map(|(p, q)| (p - q).abs())
            .fold(0f32, f32::max)
    };
    (
        d(&a.rgb, &b.rgb).max(d(&a.opacity, &b.opacity)),
        d(&a.depth, &b.depth),
    )
}

/// Tolerance of the f32 fused march against the f64 reference (colour, opacity, and depth
/// relative to 1 + |depth|).
const F32_TOL: f64 = 2e-4;

fn check_against_reference(
    cfg: &ModelConfig,
    p: &[f32],
    cam: &Camera,
    samples: u32,
    got: &Image,
    occupied: &dyn Fn([f32; 3]) -> bool,
    tol: f64,
) -> f64 {
    let mut worst = 0f64;
    let mut lit = 0;
    for px in 0..cam.width * cam.height {
        let want = march_pixel(cfg, p, cam, px, samples, BACKGROUND, occupied);
        let i = px as usize;
        for c in 0..3 {
            let g = got.rgb[3 * i + c] as f64;
            worst = worst.max((g - want[c]).abs());
            assert!(
                (g - want[c]).abs() < tol,
                "pixel {px} channel {c}: fused {g} vs reference {}",
                want[c]
            );
        }
        let o = (got.opacity[i] as f64 - want[3]).abs();
        worst = worst.max(o);
        assert!(
            o < tol,
            "opacity {px}: fused {} vs reference {}",
            got.opacity[i],
            want[3]
        );
        let d = (got.depth[i] as f64 - want[4]).abs() / (1.0 + want[4].abs());
        worst = worst.max(d);
        assert!(
            d < tol,
            "depth {px}: fused {} vs reference {}",
            got.depth[i],
            want[4]
        );
        lit += usize::from(want[3] > 0.05 && want[3] < 0.95);
    }
    // The field must be neither empty nor opaque everywhere, or the test shows little.
    assert!(
        lit > 10,
        "only {lit} partly transparent pixels; opacity {:?}",
        got.opacity
    );
    worst
}

#[test]
fn fused_march_matches_the_reference_and_the_standalone_chain() {
    let ctx = &engine().ctx;
    for (space, eye, bias, samples) in [
        ("ndc", [0.0, 0.0, 0.0], 0.0, 24),
        // 37: the last group of four samples in the march is partial.
        ("world", [0.3, 0.2, 3.0], -4.0, 37),
    ] {
        let cfg = model(space);
        let p = params(&cfg, 11, bias);
        let nerf = Nerf::new(ctx, cfg.clone(), &p, BACKGROUND).unwrap();
        let cam = camera(eye);
        let fused = render(&nerf, &cam, samples, March::Fused(MarchCuts::EXACT));
        check_against_reference(&cfg, &p, &cam, samples, &fused, &|_| true, F32_TOL);
        let chain = render(&nerf, &cam, samples, March::Standalone);
        let (c, d) = max_diff(&fused, &chain);
        assert!(
            c < 2e-5 && d < 2e-5,
            "{space}: fused and standalone differ by {c} (colour) and {d} (depth)"
        );
    }
    assert_no_validation_messages(ctx);
}

/// Tolerance of the fused march with cooperative-matrix MLPs (f16 activations and weights, f32
/// accumulation and biases) against the f64 reference and the f32 march, as F32_TOL.
const COOP_TOL: f64 = 2e-3;

/// The fused march with both MLPs through cooperative matrices against the f64 reference and
/// the scalar march: NDC and world space (24 and 37 samples; the colour MLP's 24 inputs are a
/// partial 16-wide tile), exact and with the cuts (each within its bound of the exact render),
/// and skipping the cells of an occupancy grid as the scalar march does. Skips (saying so)
/// where the device offers no usable cooperative matrix, unless `EXTRANERF_REQUIRE_COOP` is set.
#[test]
fn coop_march_matches_the_reference_and_the_scalar_march() {
    use extranerf_nerf::field::mlp::{MlpMode, MlpPath};
    let e = engine();
    let ctx = &e.ctx;
    let Some(tile) = extranerf_tests::coop_tile_or_skip(ctx) else {
        return;
    };
    for (space, eye, bias, samples) in [
        ("ndc", [0.0, 0.0, 0.0], 0.0, 24),
        ("world", [0.3, 0.2, 3.0], -4.0, 37),
    ] {
        let cfg = model(space);
        let p = params(&cfg, 11, bias);
        let mut nerf = Nerf::new(ctx, cfg.clone(), &p, BACKGROUND).unwrap();
        let cam = camera(eye);
        let scalar = render(&nerf, &cam, samples, March::Fused(MarchCuts::EXACT));
        assert_eq!(
            nerf.set_mlp(ctx, MlpMode::Coop).unwrap(),
            MlpPath::Coop { tile }
        );
        assert_eq!(nerf.march_mlp_path(), MlpPath::Coop { tile });
        let coop = render(&nerf, &cam, samples, March::Fused(MarchCuts::EXACT));
        let worst = check_against_reference(&cfg, &p, &cam, samples, &coop, &|_| true, COOP_TOL);
        let (c, d) = max_diff(&coop, &scalar);
        // Depth within COOP_TOL of 1 + the largest depth.
        let depth_tol = COOP_TOL * (1.0 + scalar.depth.iter().fold(0f32, |m, v| m.max(*v)) as f64);
        eprintln!("{space}: coop march vs reference {worst:.1e}, vs scalar march {c:.1e} (colour) {d:.1e} (depth)");
        assert!((c as f64) < COOP_TOL && (d as f64) < depth_tol);
        for cuts in [
            MarchCuts::FAST,
            MarchCuts {
                min_weight: 1e-2,
                min_transmittance: 0.05,
            },
        ] {
            let cut = render(&nerf, &cam, samples, March::Fused(cuts));
            let bound =
                samples as f64 * cuts.min_weight as f64 + cuts.min_transmittance as f64 + COOP_TOL;
            let (c, _) = max_diff(&scalar, &cut);
            assert!(
                (c as f64) <= bound,
                "{space} {cuts:?}: error {c} above {bound}"
            );
        }
        if space == "world" {
            // The same grid for both paths (the occupancy update stays scalar).
            let occ = OccupancyConfig {
                res: 8,
                cascades: 3,
                decay: 0.95,
                threshold: 0.5,
            };
            nerf.build_occupancy(ctx, &e.prims, Some(occ), 2).unwrap();
            let coop_skip = render(&nerf, &cam, samples, March::Fused(MarchCuts::EXACT));
            nerf.set_mlp(ctx, MlpMode::Scalar).unwrap();
            assert_eq!(nerf.march_mlp_path(), MlpPath::Scalar);
            let scalar_skip = render(&nerf, &cam, samples, March::Fused(MarchCuts::EXACT));
            let (c, d) = max_diff(&coop_skip, &scalar_skip);
            let (moved, _) = max_diff(&scalar_skip, &scalar);
            eprintln!("world with a grid: coop vs scalar {c:.1e} (colour) {d:.1e} (depth); skipping moved {moved:.1e}");
            assert!(
                moved > 1e-3,
                "skipping changed nothing: the case shows nothing"
            );
            assert!((c as f64) < COOP_TOL && (d as f64) < depth_tol);
        }
    }
    assert_no_validation_messages(ctx);
}

#[test]
fn march_cuts_stay_within_their_bounds() {
    let ctx = &engine().ctx;
    let cfg = model("ndc");
    let samples = 32;
    for bias in [0.0, 3.0, 6.0] {
        let p = params(&cfg, 5, bias);
        let nerf = Nerf::new(ctx, cfg.clone(), &p, BACKGROUND).unwrap();
        let cam = camera([0.0; 3]);
        let exact = render(&nerf, &cam, samples, March::Fused(MarchCuts::EXACT));
        for cuts in [
            MarchCuts::FAST,
            MarchCuts {
                min_weight: 1e-2,
                min_transmittance: 0.0,
            },
            MarchCuts {
                min_weight: 0.0,
                min_transmittance: 0.05,
            },
        ] {
            let cut = render(&nerf, &cam, samples, March::Fused(cuts));
            let bound = samples as f32 * cuts.min_weight + cuts.min_transmittance + 1e-5;
            let (c, _) = max_diff(&exact, &cut);
            assert!(c <= bound, "{cuts:?} bias {bias}: error {c} above {bound}");
        }
    }
    let bad = Nerf::new(ctx, cfg.clone(), &params(&cfg, 5, 0.0), BACKGROUND).unwrap();
    let err = bad
        .render_with(
            ctx,
            &camera([0.0; 3]),
            64,
            8,
            March::Fused(MarchCuts {
                min_weight: f32::NAN,
                min_transmittance: 0.0,
            }),
        )
        .unwrap_err()
        .to_string();
    assert!(err.contains("cuts"), "{err}");
    assert_no_validation_messages(ctx);
}

#[test]
fn fused_occupancy_matches_the_reference_and_renders_skip_only_empty_cells() {
    let e = engine();
    let ctx = &e.ctx;
    // World space, unit scene box at the origin so scene-normalised = field positions.
    let cfg = ModelConfig {
        center: [0.0; 3],
        radius: 1.0,
        ..model("world")
    };
    let p = params(&cfg, 21, -1.0);
    let mut nerf = Nerf::new(ctx, cfg.clone(), &p, BACKGROUND).unwrap();
    let occ = OccupancyConfig {
        res: 8,
        cascades: 3,
        decay: 0.95,
        threshold: 0.5,
    };
    let passes = 2;
    let stats = nerf
        .build_occupancy(ctx, &e.prims, Some(occ), passes)
        .unwrap()
        .unwrap();
    let cells = occ.cells() as usize;
    assert_eq!(stats.cells, cells as u64);
    // Reference: the largest density over the passes' jittered points, thresholded at
    // min(threshold, mean).
    let points: Vec<f32> = (0..passes)
        .flat_map(|s| {
            (0..cells).flat_map(move |c| occ_cell_point(c as u32, s, occ.res, occ.cascades))
        })
        .collect();
    let dens = field_forward(&cfg, &p, &points, &[[0.0, 0.0, 1.0]], points.len() / 3);
    let best: Vec<f64> = (0..cells)
        .map(|c| dens[c].0.max(dens[cells + c].0))
        .collect();
    let thresh = (occ.threshold as f64).min(best.iter().sum::<f64>() / cells as f64);
    let bits = nerf.occupancy().unwrap().bits().read().unwrap();
    let bit = |c: usize| (bits[c / 32] >> (c % 32)) & 1 == 1;
    let mut occupied = 0;
    for (c, &b) in best.iter().enumerate() {
        if (b - thresh).abs() > 1e-4 * (1.0 + thresh) {
            assert_eq!(
                bit(c),
                b > thresh,
                "cell {c}: density {b}, threshold {thresh}"
            );
        }
        occupied += usize::from(bit(c));
    }
    assert_eq!(stats.occupied, occupied as u64);
    assert!(
        occupied > cells / 10 && occupied < cells * 9 / 10,
        "{occupied} of {cells} cells occupied: the test needs a mix"
    );
    // A render that skips the empty cells equals the reference with the same cells skipped
    // (samples within 1e-4 cells of a face may land on either side in f32 and are avoided
    // by comparing only pixels whose samples are all clear of faces).
    let cam = camera([0.3, 0.2, 3.0]);
    let samples = 40;
    let got = render(&nerf, &cam, samples, March::Fused(MarchCuts::EXACT));
    let on_edge = std::cell::Cell::new(false);
    let occupied_ref = |u: [f32; 3]| {
        let (cell, edge) = occ_cell(u, occ.res, occ.cascades);
        on_edge.set(on_edge.get() | edge);
        cell.is_none_or(|c| bit(c as usize))
    };
    let mut compared = 0;
    let mut differs = 0;
    let all = render(&nerf, &cam, samples, March::Standalone);
    for px in 0..cam.width * cam.height {
        on_edge.set(false);
        let want = march_pixel(&cfg, &p, &cam, px, samples, BACKGROUND, &occupied_ref);
        if on_edge.get() {
            continue;
        }
        compared += 1;
        let i = px as usize;
        for c in 0..3 {
            let g = got.rgb[3 * i + c] as f64;
            assert!((g - want[c]).abs() < 2e-4, "pixel {px}: {g} vs {}", want[c]);
        }
        differs += usize::from((all.rgb[3 * i] - got.rgb[3 * i]).abs() > 1e-3);
    }
    assert!(compared > 80, "only {compared} pixels clear of cell faces");
    assert!(
        differs > 0,
        "skipping changed no pixel: the test shows nothing"
    );
    // Removing the grid restores the full march.
    nerf.build_occupancy(ctx, &e.prims, None, 1).unwrap();
    let full = render(&nerf, &cam, samples, March::Fused(MarchCuts::EXACT));
    let (c, _) = max_diff(&full, &all);
    assert!(c < 2e-5);
    assert_no_validation_messages(ctx);
}

#[test]
fn fused_march_extremes_stay_finite() {
    use extranerf_nerf::field::mlp::MlpMode;
    let e = engine();
    let ctx = &e.ctx;
    let coop = extranerf_tests::coop_tile_or_skip(ctx).is_some();
    for space in ["ndc", "world"] {
        let cfg = model(space);
        for (scale, bias) in [(1e3f32, 40.0), (0.0, -80.0), (1.0, 1e6)] {
            let mut p = params(&cfg, 3, bias);
            let lay = ParamLayout::new(&cfg);
            for v in &mut p[lay.table.0..lay.table.0 + lay.table.1] {
                *v *= scale;
            }
            let mut nerf = Nerf::new(ctx, cfg.clone(), &p, BACKGROUND).unwrap();
            nerf.build_occupancy(
                ctx,
                &e.prims,
                Some(OccupancyConfig {
                    res: 4,
                    cascades: 2,
                    ..Default::default()
                }),
                1,
            )
            .unwrap();
            // A camera far away along an axis (rays parallel to it at the centre pixel).
            let mut cam = camera([0.0, 0.0, 1e6]);
            cam.c2w = DMat4::from_translation(DVec3::new(0.0, 0.0, 1e6));
            cam.cx = 5.5;
            // Both MLP paths where the device offers cooperative matrices, whose f16
            // activations saturate rather than overflow: they render what the scalar path
            // renders (a density logit of 1e6 overflowed f16 and gave grey, not white).
            let mut modes = vec![MlpMode::Scalar];
            if coop {
                modes.push(MlpMode::Coop);
            }
            let mut scalar = Vec::new();
            for mode in modes {
                nerf.set_mlp(ctx, mode).unwrap();
                let mut k = 0;
                for c in [camera([0.0, 0.0, 0.5]), cam.clone()] {
                    for cuts in [MarchCuts::EXACT, MarchCuts::FAST] {
                        let img = render(&nerf, &c, 16, March::Fused(cuts));
                        for v in img.rgb.iter().chain(&img.opacity).chain(&img.depth) {
                            assert!(
                                v.is_finite(),
                                "{space} scale {scale} bias {bias} {mode:?}: {v}"
                            );
                        }
                        assert!(img.opacity.iter().all(|&o| (0.0..=1.0 + 1e-5).contains(&o)));
                        if mode == MlpMode::Scalar {
                            scalar.push(img);
                        } else {
                            let (c, _) = max_diff(&img, &scalar[k]);
                            assert!(
                                c < 0.05,
                                "{space} scale {scale} bias {bias}: coop differs by {c}"
                            );
                        }
                        k += 1;
                    }
                }
            }
        }
    }
    assert_no_validation_messages(ctx);
}

/// `Nerf::render` takes the fused march (no cuts) where the field allows it, and the
/// standalone chain where it does not (a colour MLP width that is not a multiple of 4).
#[test]
fn render_defaults_to_the_fused_march_and_falls_back() {
    use extranerf_nerf::render::march::{MarchCuts, Marcher};
    let e = engine();
    let cam = camera([0.0, 0.0, 0.0]);
    let cfg = model("ndc");
    let nerf = Nerf::new(&e.ctx, cfg.clone(), &params(&cfg, 5, 1.0), BACKGROUND).unwrap();
    assert!(Marcher::supports(nerf.field()).is_ok());
    let (rgb, depth, opacity) = nerf.render(&e.ctx, &cam, 50, 24).unwrap();
    let fused = render(&nerf, &cam, 24, March::Fused(MarchCuts::EXACT));
    assert_eq!(
        (rgb, depth, opacity),
        (fused.rgb, fused.depth, fused.opacity)
    );
    let odd = ModelConfig {
        color_width: 18,
        ..cfg
    };
    let nerf = Nerf::new(&e.ctx, odd.clone(), &params(&odd, 5, 1.0), BACKGROUND).unwrap();
    let why = Marcher::supports(nerf.field()).unwrap_err().to_string();
    assert!(why.contains("multiples of 4"), "{why}");
    let (rgb, depth, opacity) = nerf.render(&e.ctx, &cam, 50, 24).unwrap();
    let chain = render(&nerf, &cam, 24, March::Standalone);
    assert_eq!(
        (rgb, depth, opacity),
        (chain.rgb, chain.depth, chain.opacity)
    );
    assert_no_validation_messages(&e.ctx);
}
