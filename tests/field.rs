//! The hash-grid encoding kernels against the f64 reference: forward values and table
//! gradients on random points, dense and hashed levels, every feature width, and the extremes
//! (points on the boundary, far outside, NaN).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_gpu::{Buffer, GpuError};
use extranerf_nerf::field::hash_grid::{HashGrid, HashGridConfig};
use extranerf_nerf::reference::{hash_grid_backward, hash_grid_forward, round_f16};
use extranerf_prims::reference::Rng;
use extranerf_tests::{assert_no_validation_messages, engine, POISON};

fn points(rng: &mut Rng, n: usize) -> Vec<f32> {
    let mut p: Vec<f32> = (0..3 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
    // Extremes: corners and faces of the unit cube, outside points (clamped), far points, axis
    // lines, and NaN (no features, no gradient).
    let special = [
        [0.0, 0.0, 0.0],
        [1.0, 1.0, 1.0],
        [1.0, 0.5, 0.0],
        [0.5, 0.5, 0.5],
        [-0.25, 0.3, 1.5],
        [1e6, -1e6, 0.5],
        [f32::MAX, f32::MIN_POSITIVE, -f32::MAX],
        [0.125, 0.125, 0.9999999],
        [f32::NAN, 0.5, 0.5],
        [0.5, f32::INFINITY, 0.5],
    ];
    for (i, s) in special.iter().enumerate() {
        p[3 * i..3 * i + 3].copy_from_slice(s);
    }
    p
}

fn check(cfg: HashGridConfig, n: usize, seed: u64) {
    check_grid(cfg, n, seed, None);
}

/// The encoding against the f64 reference; with `limit`, as if one binding held at most that
/// many bytes (so the table is split in two ranges).
fn check_grid(cfg: HashGridConfig, n: usize, seed: u64, limit: Option<u64>) {
    let e = engine();
    let mut rng = Rng::new(seed);
    let grid = match limit {
        None => HashGrid::new(&e.ctx, cfg).unwrap(),
        Some(l) => HashGrid::with_binding_limit(&e.ctx, cfg, l).unwrap(),
    };
    assert_eq!(grid.split().is_some(), limit.is_some(), "{cfg:?} {limit:?}");
    let count = cfg.param_count() as usize;
    let table: Vec<f32> = (0..count).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let pos = points(&mut rng, n);
    let out_len = n * cfg.output_dim() as usize;
    let d: Vec<f32> = (0..out_len).map(|_| rng.uniform(-1.0, 1.0)).collect();

    let tb = Buffer::from_slice(&e.ctx, "table", &table).unwrap();
    let pb = Buffer::from_slice(&e.ctx, "positions", &pos).unwrap();
    let enc =
        Buffer::from_slice(&e.ctx, "encoded", &vec![f32::from_bits(POISON); out_len]).unwrap();
    let db = Buffer::from_slice(&e.ctx, "d_encoded", &d).unwrap();
    let grad = Buffer::<f32>::new(&e.ctx, "d_table", count).unwrap();
    let mut rec = e.ctx.recorder("hash grid").unwrap();
    grid.forward(
        &mut rec,
        pb.binding(),
        tb.binding(),
        enc.binding(),
        n as u64,
    )
    .unwrap();
    e.prims
        .fill(&mut rec, grad.binding(), count as u64, 0)
        .unwrap();
    grid.backward(
        &mut rec,
        pb.binding(),
        db.binding(),
        grad.binding(),
        n as u64,
    )
    .unwrap();
    e.ctx.run(rec).unwrap();

    let got = enc.read().unwrap();
    let want = hash_grid_forward(&cfg, &table, &pos);
    for (i, (&g, &w)) in got.iter().zip(&want).enumerate() {
        // 8 products of |w| <= 1 weights and |t| <= 1 entries summed in f32.
        assert!(
            g.is_finite() && (g as f64 - w).abs() <= 1e-5,
            "{cfg:?} output {i} (point {}): {g} vs {w}",
            i / cfg.output_dim() as usize
        );
    }
    let got = grad.read().unwrap();
    let want = hash_grid_backward(&cfg, &pos, &d);
    let d_abs: Vec<f32> = d.iter().map(|v| v.abs()).collect();
    let mag = hash_grid_backward(&cfg, &pos, &d_abs);
    for (i, ((&g, &w), &m)) in got.iter().zip(&want).zip(&mag).enumerate() {
        // Atomic accumulation in any order: 1e-5 of the summed magnitudes.
        assert!(
            g.is_finite() && (g as f64 - w).abs() <= 1e-5 * m + 1e-7,
            "{cfg:?} table entry {i}: {g} vs {w} (magnitude {m})"
        );
    }
}

/// The f16 forward path: exact against the f64 reference on the table rounded to f16, within
/// the rounding error of the f32 path, and finite for table entries beyond the f16 range,
/// subnormal or NaN. Prints the per-kernel error against f32.
#[test]
fn hash_grid_f16_forward_matches_the_reference_on_the_rounded_table() {
    let e = engine();
    let info = e.ctx.info();
    assert!(
        info.shader_float16 && info.storage_buffer_16bit,
        "this device has no f16 path; lavapipe has one"
    );
    let cfg = HashGridConfig {
        levels: 6,
        features: 2,
        log2_table: 12,
        min_res: 4,
        max_res: 128,
    };
    let n = 4000;
    let mut rng = Rng::new(7);
    let count = cfg.param_count() as usize;
    let mut table: Vec<f32> = (0..count).map(|_| rng.uniform(-2.0, 2.0)).collect();
    let pos = points(&mut rng, n);
    let run = |table: &[f32]| {
        let grid = HashGrid::new(&e.ctx, cfg)
            .unwrap()
            .with_f16(&e.ctx)
            .unwrap();
        assert!(grid.is_f16());
        let tb = Buffer::from_slice(&e.ctx, "table", table).unwrap();
        let pb = Buffer::from_slice(&e.ctx, "positions", &pos).unwrap();
        let out_len = n * cfg.output_dim() as usize;
        let enc =
            Buffer::from_slice(&e.ctx, "encoded", &vec![f32::from_bits(POISON); out_len]).unwrap();
        let mut rec = e.ctx.recorder("hash grid f16").unwrap();
        grid.forward(
            &mut rec,
            pb.binding(),
            tb.binding(),
            enc.binding(),
            n as u64,
        )
        .unwrap();
        e.ctx.run(rec).unwrap();
        enc.read().unwrap()
    };
    let got = run(&table);
    let rounded: Vec<f32> = table.iter().map(|&v| round_f16(v)).collect();
    let want = hash_grid_forward(&cfg, &rounded, &pos);
    let exact = hash_grid_forward(&cfg, &table, &pos);
    let (mut worst, mut sum) = (0f64, 0f64);
    for (i, ((&g, &w), &x)) in got.iter().zip(&want).zip(&exact).enumerate() {
        assert!(
            g.is_finite() && (g as f64 - w).abs() <= 1e-5,
            "output {i}: {g} vs {w} from the rounded table"
        );
        let d = (g as f64 - x).abs();
        // Each entry rounds by at most 2^-11 of |t| <= 2; the weights sum to 1.
        assert!(
            d <= 2.0 * 2f64.powi(-11) + 1e-6,
            "output {i}: {g} vs f32 {x}"
        );
        worst = worst.max(d);
        sum += d;
    }
    eprintln!(
        "f16 hash grid forward vs f32: max |d| {worst:.3e}, mean |d| {:.3e} (table in [-2, 2])",
        sum / got.len() as f64
    );
    // The extremes of the table: beyond the f16 range, subnormal, underflow, NaN.
    for (i, v) in [1e6f32, -1e6, 3e-6, 1e-9, f32::NAN, 65519.0, -0.0]
        .iter()
        .enumerate()
    {
        for k in 0..count / 7 {
            table[k * 7 + i % 7] = *v;
        }
    }
    let got = run(&table);
    let rounded: Vec<f32> = table.iter().map(|&v| round_f16(v)).collect();
    let want = hash_grid_forward(&cfg, &rounded, &pos);
    let abs: Vec<f32> = rounded.iter().map(|v| v.abs()).collect();
    let mag = hash_grid_forward(&cfg, &abs, &pos);
    for (i, ((&g, &w), &m)) in got.iter().zip(&want).zip(&mag).enumerate() {
        // Entries up to 65504 cancel: f32 rounding of the summed magnitudes.
        assert!(
            g.is_finite() && (g as f64 - w).abs() <= 2e-6 * m + 1e-5,
            "extreme table, output {i}: {g} vs {w} (magnitude {m})"
        );
    }
    // F = 4 has no f16 path: a clear error.
    let e4 = HashGrid::new(&e.ctx, HashGridConfig { features: 4, ..cfg })
        .unwrap()
        .with_f16(&e.ctx)
        .unwrap_err();
    assert!(matches!(e4, GpuError::Usage(_)) && e4.to_string().contains("f16"));
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn hash_grid_matches_reference_dense_and_hashed() {
    // Levels 4, 8, 16, 32: the first two dense, the rest hashed into 2^10 entries.
    check(
        HashGridConfig {
            levels: 4,
            features: 2,
            log2_table: 10,
            min_res: 4,
            max_res: 32,
        },
        3000,
        1,
    );
    assert_no_validation_messages(&engine().ctx);
}

/// Tables larger than one binding are split in two at a level boundary: forward and backward
/// match the reference for every feature width and for the f16 path, and a table that two
/// bindings cannot hold is a clear error.
#[test]
fn hash_grid_split_tables_match_reference() {
    use extranerf_nerf::field::hash_grid::split_table;
    let cfg = HashGridConfig {
        levels: 6,
        features: 2,
        log2_table: 10,
        min_res: 4,
        max_res: 64,
    };
    let total = cfg.param_count() * 4;
    for features in [1, 2, 4, 8] {
        let c = HashGridConfig { features, ..cfg };
        // Three quarters of the table per binding: levels are cut whole, so the first range
        // takes what fits and the second (from an offset rounded down to 128 floats) the rest.
        let limit = c.param_count() * 4 * 3 / 4;
        check_grid(c, 700, 31 + features as u64, Some(limit));
    }
    let sp = split_table(&cfg.level_layout(), 2, total * 3 / 4)
        .unwrap()
        .unwrap();
    assert!(sp.level > 0 && sp.hi_base.is_multiple_of(128) && sp.hi_base <= sp.lo_floats);
    assert!(split_table(&cfg.level_layout(), 2, total)
        .unwrap()
        .is_none());
    // Two ranges of a third of the table cannot hold it.
    let e = split_table(&cfg.level_layout(), 2, total / 3).unwrap_err();
    assert!(matches!(e, GpuError::BufferTooLarge { .. }), "{e}");
    // The f16 path on a split table: the two ranges convert into one f16 copy.
    let e = engine();
    if e.ctx.info().shader_float16 && e.ctx.info().storage_buffer_16bit {
        let mut rng = Rng::new(41);
        let n = 500;
        let grid = HashGrid::with_binding_limit(&e.ctx, cfg, total * 3 / 4)
            .unwrap()
            .with_f16(&e.ctx)
            .unwrap();
        assert!(grid.split().is_some());
        let table: Vec<f32> = (0..cfg.param_count())
            .map(|_| rng.uniform(-2.0, 2.0))
            .collect();
        let pos = points(&mut rng, n);
        let out_len = n * cfg.output_dim() as usize;
        let tb = Buffer::from_slice(&e.ctx, "table", &table).unwrap();
        let pb = Buffer::from_slice(&e.ctx, "positions", &pos).unwrap();
        let enc = Buffer::<f32>::new(&e.ctx, "encoded", out_len).unwrap();
        let mut rec = e.ctx.recorder("split f16").unwrap();
        grid.forward(
            &mut rec,
            pb.binding(),
            tb.binding(),
            enc.binding(),
            n as u64,
        )
        .unwrap();
        e.ctx.run(rec).unwrap();
        let rounded: Vec<f32> = table.iter().map(|&v| round_f16(v)).collect();
        let want = hash_grid_forward(&cfg, &rounded, &pos);
        for (i, (&g, &w)) in enc.read().unwrap().iter().zip(&want).enumerate() {
            assert!(
                g.is_finite() && (g as f64 - w).abs() <= 2e-5,
                "split f16 output {i}: {g} vs {w}"
            );
        }
    }
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn hash_grid_every_feature_width() {
    for (f, seed) in [(1, 2), (4, 3), (8, 4)] {
        check(
            HashGridConfig {
                levels: 5,
                features: f,
                log2_table: 12,
                min_res: 3,
                max_res: 200,
            },
            1500,
            seed,
        );
    }
    assert_no_validation_messages(&engine().ctx);
}

#[test]
fn hash_grid_sixteen_levels_heavy_collisions() {
    // 16 levels up to 2048 into 2^14 entries: most levels hashed, many points per entry.
    check(
        HashGridConfig {
            levels: 16,
            features: 2,
            log2_table: 14,
            min_res: 16,
            max_res: 2048,
        },
        20_000,
        5,
    );
    assert_no_validation_messages(&engine().ctx);
}

#[test]
fn hash_grid_sizes_and_errors() {
    let e = engine();
    let paper = HashGridConfig::default();
    assert_eq!(paper.level_layout().len(), 16);
    assert!(paper.param_count() <= 16 * 2 * (1 << 19));
    HashGrid::new(&e.ctx, paper).unwrap();
    let huge = HashGridConfig {
        levels: 16,
        features: 8,
        log2_table: 24,
        min_res: 16,
        max_res: 1 << 16,
    };
    assert!(matches!(
        HashGrid::new(&e.ctx, huge),
        Err(GpuError::BufferTooLarge { .. })
    ));
    for bad in [
        HashGridConfig {
            features: 3,
            ..paper
        },
        HashGridConfig { levels: 0, ..paper },
        HashGridConfig {
            min_res: 64,
            max_res: 32,
            ..paper
        },
        HashGridConfig {
            log2_table: 40,
            ..paper
        },
    ] {
        assert!(
            matches!(HashGrid::new(&e.ctx, bad), Err(GpuError::Usage(_))),
            "{bad:?}"
        );
    }
    assert_no_validation_messages(&e.ctx);
}

/// Bound of the cooperative-matrix MLP's error relative to the largest value of its f64
/// definition (`reference::mlp_coop_reference`; forward, input gradient and weight gradient,
/// measured at most 5.7e-4 on lavapipe; see `check_mlp`).
const COOP_TOL: f64 = 2e-3;

/// Which MLP kernels `check_mlp` runs.
#[derive(Clone, Copy, PartialEq)]
enum MlpPath {
    Storage,
    Block,
    /// The uniform-block kernels with the backward record in f16.
    F16,
    /// The uniform-block kernels with the cooperative-matrix weight gradient of this tile.
    Coop(u32),
}

/// The MLP kernels against the f64 reference on random inputs; returns the largest weight
/// gradient error relative to the largest gradient, against the exact (unrounded) reference.
/// `dy_scale` multiplies the output gradients.
fn check_mlp(dims: Vec<u32>, n: usize, seed: u64, path: MlpPath, dy_scale: f32) -> f64 {
    use extranerf_nerf::field::mlp::{Mlp, MlpConfig};
    use extranerf_nerf::reference::{mlp_backward, mlp_forward, mlp_weight_grad_f16};
    let e = engine();
    let cfg = MlpConfig { dims };
    let mlp = match path {
        MlpPath::Storage => Mlp::with_storage_kernels(&e.ctx, cfg.clone()).unwrap(),
        MlpPath::Block => Mlp::new(&e.ctx, cfg.clone()).unwrap(),
        MlpPath::F16 => Mlp::new(&e.ctx, cfg.clone())
            .unwrap()
            .with_f16(&e.ctx)
            .unwrap(),
        MlpPath::Coop(tile) => {
            let mut m = Mlp::new(&e.ctx, cfg.clone()).unwrap();
            let path = extranerf_nerf::field::mlp::MlpPath::Coop { tile };
            m.set_path(&e.ctx, path).unwrap();
            assert_eq!(m.path(), path);
            m
        }
    };
    assert_eq!(mlp.is_f16(), path == MlpPath::F16);
    let mut rng = Rng::new(seed);
    let (n_in, n_out) = (cfg.dims[0] as usize, *cfg.dims.last().unwrap() as usize);
    let w: Vec<f32> = (0..cfg.param_count())
        .map(|_| rng.uniform(-0.4, 0.4))
        .collect();
    let x: Vec<f32> = (0..n * n_in).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let dy: Vec<f32> = (0..n * n_out)
        .map(|_| rng.uniform(-1.0, 1.0) * dy_scale)
        .collect();
    let wb = Buffer::from_slice(&e.ctx, "w", &w).unwrap();
    let xb = Buffer::from_slice(&e.ctx, "x", &x).unwrap();
    let dyb = Buffer::from_slice(&e.ctx, "dy", &dy).unwrap();
    let yb = Buffer::from_slice(&e.ctx, "y", &vec![f32::from_bits(POISON); n * n_out]).unwrap();
    let dxb = Buffer::from_slice(&e.ctx, "dx", &vec![f32::from_bits(POISON); n * n_in]).unwrap();
    // Poisoned, so that a kernel reading the records' unwritten padding shows.
    let saved = Buffer::from_slice(
        &e.ctx,
        "saved",
        &vec![f32::from_bits(POISON); n * mlp.saved_words()],
    )
    .unwrap();
    let dwb = Buffer::<f32>::new(&e.ctx, "dw", cfg.param_count()).unwrap();
    // A fresh weight gradient from `m`'s backward pass (its records into `saved`).
    fn backward<'a>(
        rec: &mut extranerf_gpu::Recorder<'a>,
        m: &'a Mlp,
        [w, x, dy, dx, saved, dw]: [&'a Buffer<f32>; 6],
        n: usize,
    ) {
        engine()
            .prims
            .fill(rec, dw.binding(), m.config().param_count() as u64, 0)
            .unwrap();
        m.backward(
            rec,
            w.binding(),
            x.binding(),
            dy.binding(),
            dx.binding(),
            saved.binding(),
            dw.binding(),
            n as u64,
        )
        .unwrap();
    }
    let bufs = [&wb, &xb, &dyb, &dxb, &saved, &dwb];
    let mut rec = e.ctx.recorder("mlp").unwrap();
    mlp.forward(&mut rec, wb.binding(), xb.binding(), yb.binding(), n as u64)
        .unwrap();
    backward(&mut rec, &mlp, bufs, n);
    e.ctx.run(rec).unwrap();
    // f32 dot products of at most 64 terms (and sums over n points for the weights): 1e-5 of
    // the largest magnitude. The cooperative-matrix path rounds the scaled pre-activation
    // gradients to f16 (11-bit mantissas) on top of its reference's roundings: COOP_TOL.
    let tol = match path {
        MlpPath::Coop(_) => COOP_TOL,
        _ => 1e-5,
    };
    let close = |got: &[f32], want: &[f64], what: &str| {
        let scale = want.iter().fold(f64::MIN_POSITIVE, |m, v| m.max(v.abs()));
        let mut worst = 0.0f64;
        for (i, (&g, &r)) in got.iter().zip(want).enumerate() {
            assert!(
                g.is_finite() && (g as f64 - r).abs() <= tol * scale,
                "MLP {:?} {what} {i}: {g} vs {r}",
                cfg.dims
            );
            worst = worst.max((g as f64 - r).abs() / scale);
        }
        if let MlpPath::Coop(_) = path {
            eprintln!("  coop {what}: max |coop - exact| / max |exact| = {worst:.2e}");
        }
    };
    let (d_in, d_w) = mlp_backward(&cfg, &w, &x, &dy);
    if let MlpPath::Coop(_) = path {
        // Against the f64 definition of the cooperative-matrix MLP (f16 weights and layer
        // inputs, their ReLU gates): an exact f32 reference can gate a hidden unit whose
        // pre-activation lies within f16 rounding of 0 the other way, which changes that
        // point's input gradient by the unit's whole contribution.
        let (want_y, want_dx, want_dw) =
            extranerf_nerf::reference::mlp_coop_reference(&cfg, &w, &x, &dy);
        close(&yb.read().unwrap(), &want_y, "output");
        close(&dxb.read().unwrap(), &want_dx, "input gradient");
        close(
            &dwb.read().unwrap(),
            &want_dw,
            "weight gradient (coop reference)",
        );
    } else {
        close(&yb.read().unwrap(), &mlp_forward(&cfg, &w, &x), "output");
        close(&dxb.read().unwrap(), &d_in, "input gradient");
    }
    let got = dwb.read().unwrap();
    if path == MlpPath::F16 {
        // Against the reference on the same f16 record (exact up to f32 sums and the odd f16
        // tie rounded the other way from an f32 rather than f64 value).
        let want = mlp_weight_grad_f16(&cfg, &w, &x, &dy);
        let scale = want.iter().fold(f64::MIN_POSITIVE, |m, v| m.max(v.abs()));
        for (i, (&g, &r)) in got.iter().zip(&want).enumerate() {
            assert!(
                g.is_finite() && (g as f64 - r).abs() <= 1e-4 * scale,
                "MLP {:?} f16 weight gradient {i}: {g} vs {r}",
                cfg.dims
            );
        }
    } else if let MlpPath::Coop(tile) = path {
        // The weight gradient alone on the scalar kernels' f32 records (what the fused step
        // hands it): two f16 roundings per product, averaging down over the sum, 1e-3.
        let scalar = Mlp::new(&e.ctx, cfg.clone()).unwrap();
        let dwc = Buffer::<f32>::new(&e.ctx, "dw coop", cfg.param_count()).unwrap();
        let mut rec = e.ctx.recorder("mlp records").unwrap();
        backward(&mut rec, &scalar, bufs, n);
        e.prims
            .fill(&mut rec, dwc.binding(), cfg.param_count() as u64, 0)
            .unwrap();
        mlp.weight_gradient(&mut rec, saved.binding(), dwc.binding(), n as u64)
            .unwrap();
        e.ctx.run(rec).unwrap();
        let only = dwc.read().unwrap();
        let scale = d_w.iter().fold(f64::MIN_POSITIVE, |m, v| m.max(v.abs()));
        let err = only
            .iter()
            .zip(&d_w)
            .fold(0.0f64, |m, (&g, &r)| m.max((g as f64 - r).abs()))
            / scale;
        eprintln!("  coop {tile}x{tile} weight gradient on f32 records: {err:.2e}");
        assert!(
            only.iter().all(|g| g.is_finite()) && err < 1e-3,
            "MLP {:?} coop weight gradient on f32 records: {err}",
            cfg.dims
        );
    } else {
        close(&got, &d_w, "weight gradient");
    }
    let scale = d_w.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    got.iter()
        .zip(&d_w)
        .fold(0.0f64, |m, (&g, &r)| m.max((g as f64 - r).abs()))
        / scale
}

#[test]
fn mlp_forward_and_gradients_match_reference() {
    // Instant-NGP's density MLP (32 -> 64 -> 16) and colour MLP (32 -> 64 -> 64 -> 3), an odd
    // shape, a single linear layer, and the widest 4-layer net; n not a multiple of the chunk.
    // The first two and [4, 1] run the uniform-block kernels; the odd shape (widths not
    // multiples of 4) and the widest net (16,640 weights > 16,384) the storage-buffer ones.
    for (dims, n, seed, block) in [
        (vec![32, 64, 16], 1000, 11, true),
        (vec![32, 64, 64, 3], 777, 12, true),
        (vec![5, 7, 6, 3], 300, 13, false),
        (vec![4, 1], 257, 14, true),
        (vec![64, 64, 64, 64, 64], 130, 15, false),
    ] {
        let cfg = extranerf_nerf::field::mlp::MlpConfig { dims: dims.clone() };
        let mlp = extranerf_nerf::field::mlp::Mlp::new(&engine().ctx, cfg).unwrap();
        assert_eq!(mlp.uses_block(), block, "{dims:?}");
        if block {
            check_mlp(dims.clone(), n, seed, MlpPath::Block, 1.0);
            // The storage-buffer kernels on the same shape (the benchmark's reference path).
            check_mlp(dims, n, seed, MlpPath::Storage, 1.0);
        } else {
            check_mlp(dims, n, seed, MlpPath::Storage, 1.0);
        }
    }
    let bad = extranerf_nerf::field::mlp::MlpConfig {
        dims: vec![3, 65, 1],
    };
    assert!(matches!(
        extranerf_nerf::field::mlp::Mlp::new(&engine().ctx, bad),
        Err(GpuError::Usage(_))
    ));
    assert_no_validation_messages(&engine().ctx);
}

/// The tiled weight gradient (common/mlp_wgrad.wgsl) against the f64 reference where its
/// tiles and chunks are partial: point counts of one, fewer than an unrolled iteration, one
/// past a chunk, and several chunks with a partial last one (WGRAD_CHUNK points each); widths
/// not multiples of 4, 8 or 16 (partial row and column tiles, the padding of the records
/// poisoned); and the f16 record over several chunks.
#[test]
fn mlp_weight_gradient_tiles_and_chunks_match_reference() {
    use extranerf_nerf::field::mlp::WGRAD_CHUNK;
    let chunk = WGRAD_CHUNK as usize;
    for (dims, n, seed, path) in [
        (vec![32, 64, 16], 2 * chunk + 37, 61, MlpPath::Block),
        (vec![32, 64, 64, 3], chunk + 1, 62, MlpPath::Block),
        (vec![32, 64, 64, 3], 3, 63, MlpPath::Block),
        (vec![37, 50, 19, 2], 1, 64, MlpPath::Storage),
        (vec![37, 50, 19, 2], chunk + 3, 65, MlpPath::Storage),
        (vec![5, 7, 6, 3], 2 * chunk + 2, 66, MlpPath::Storage),
        (vec![64, 64, 64, 64, 64], 5, 67, MlpPath::Storage),
        (vec![32, 64, 16], 2 * chunk + 37, 68, MlpPath::F16),
        (vec![20, 36, 4], chunk + 3, 69, MlpPath::F16),
    ] {
        let err = check_mlp(dims.clone(), n, seed, path, 1.0);
        // The f16 record rounds its values to 11 bits; f32 sums otherwise.
        let tol = if path == MlpPath::F16 { 2e-3 } else { 1e-5 };
        assert!(err < tol, "{dims:?}, {n} points: {err}");
    }
    assert_no_validation_messages(&engine().ctx);
}

/// The f16 backward record: the weight gradients match the reference on the same rounded
/// record, stay within f16 rounding of the exact ones, and the block scaling keeps gradients
/// far below f16's range (1e-9) and above it (1e6) alive and finite. Prints the error.
#[test]
fn mlp_f16_record_matches_the_reference() {
    use extranerf_nerf::field::mlp::{Mlp, MlpConfig};
    for (dims, n, seed) in [
        (vec![32, 64, 16], 1000, 21),
        (vec![32, 64, 64, 3], 777, 22),
        (vec![4, 1], 257, 23),
    ] {
        for dy_scale in [1.0, 1e-9, 1e6] {
            let err = check_mlp(dims.clone(), n, seed, MlpPath::F16, dy_scale);
            eprintln!(
                "f16 MLP record {dims:?}, output gradients x {dy_scale:e}: weight gradient max |f16 - exact| / max |grad| = {err:.2e}"
            );
            // f16 keeps 11 bits: about 5e-4 per product at worst, averaging down over the sum.
            assert!(err < 2e-3, "{dims:?} x {dy_scale:e}: {err}");
        }
    }
    // Widths that are not multiples of 4 have no f16 record: a clear error.
    let odd = Mlp::new(
        &engine().ctx,
        MlpConfig {
            dims: vec![5, 7, 3],
        },
    )
    .unwrap();
    let e = odd.with_f16(&engine().ctx).unwrap_err();
    assert!(
        matches!(e, GpuError::Usage(_)) && e.to_string().contains("f16"),
        "{e}"
    );
    assert_no_validation_messages(&engine().ctx);
}

/// The MLP through cooperative matrices (f16 tiles, f32 accumulation) against the f64
/// reference: forward, input gradient and weight gradient (within COOP_TOL of the largest
/// value), and the weight gradient alone on f32 records (1e-3); widths 16, 32 and 64, odd
/// widths, point counts that leave partial tiles and partial blocks (1, 7, 63, 65, ...), more
/// points than one workgroup's chunk, and output gradients far below f16's range (1e-9) and
/// above it (1e6). Prints the errors. Where the device offers no usable shape the test says it
/// skipped, unless `EXTRANERF_REQUIRE_COOP` is set (CI sets it), when it fails.
#[test]
fn mlp_coop_matches_the_reference() {
    let Some(tile) = extranerf_tests::coop_tile_or_skip(&engine().ctx) else {
        return;
    };
    for (dims, n, seed) in [
        // Outputs not a multiple of 4: the records' unwritten padding must not set the scale.
        (vec![64, 3], 777, 40),
        (vec![64, 8], 33, 49),
        (vec![32, 64, 16], 1000, 41),
        (vec![32, 64, 64, 3], 777, 42),
        (vec![16, 16, 16], 65, 43),
        (vec![16, 32, 1], 7, 44),
        (vec![5, 7, 6, 3], 63, 45),
        (vec![4, 1], 1, 46),
        (vec![64, 64, 64, 64, 64], 130, 47),
        (vec![32, 64, 16], 64 * 64 * 3 + 5, 48),
    ] {
        for dy_scale in [1.0, 1e-9, 1e6] {
            let err = check_mlp(dims.clone(), n, seed, MlpPath::Coop(tile), dy_scale);
            eprintln!(
                "coop {tile}x{tile} MLP {dims:?}, {n} points, output gradients x {dy_scale:e}: weight gradient max |coop - exact| / max |grad| = {err:.2e}"
            );
        }
    }
    assert_no_validation_messages(&engine().ctx);
}

/// `--mlp coop` where the device has no cooperative matrices (a context created with them left
/// off, as on the stock lavapipe) is a clear error naming the device and the fallback; `auto`
/// and `scalar` take the scalar path there, and `auto` takes the cooperative one where a GPU
/// offers it (on a CPU device the scalar one).
#[test]
fn mlp_modes_resolve_by_device() {
    use extranerf_gpu::Context;
    use extranerf_nerf::field::mlp::{MlpMode, MlpPath as Path};
    let plain = Context::new(&extranerf_gpu::ContextDesc {
        no_coop_matrix: true,
        ..extranerf_tests::desc()
    })
    .unwrap();
    assert!(plain.info().coop_matrix.is_empty());
    let e = MlpMode::Coop.resolve(&plain, false).unwrap_err();
    let msg = e.to_string();
    assert!(
        matches!(e, GpuError::MissingFeature { .. })
            && msg.contains(&plain.info().name)
            && msg.contains("VK_KHR_cooperative_matrix")
            && msg.contains("--mlp scalar"),
        "{msg}"
    );
    assert_eq!(MlpMode::Auto.resolve(&plain, false).unwrap(), Path::Scalar);
    assert_eq!(
        MlpMode::Scalar.resolve(&plain, false).unwrap(),
        Path::Scalar
    );
    // The kernel itself refuses to build there.
    let mut m = extranerf_nerf::field::mlp::Mlp::new(
        &plain,
        extranerf_nerf::field::mlp::MlpConfig {
            dims: vec![32, 64, 16],
        },
    )
    .unwrap();
    let e = m.set_path(&plain, Path::Coop { tile: 8 }).unwrap_err();
    assert!(matches!(e, GpuError::MissingFeature { .. }), "{e}");
    assert_no_validation_messages(&plain);

    let ctx = &engine().ctx;
    match ctx.info().coop_tile() {
        Some(tile) => {
            // auto takes the tiles on GPUs; on a CPU device (lavapipe) the scalar kernel.
            let auto = if ctx.info().is_cpu() {
                Path::Scalar
            } else {
                Path::Coop { tile }
            };
            assert_eq!(MlpMode::Auto.resolve(ctx, false).unwrap(), auto);
            assert_eq!(
                MlpMode::Coop.resolve(ctx, false).unwrap(),
                Path::Coop { tile }
            );
            // The f16 record has no cooperative path: auto falls back, coop refuses.
            assert_eq!(MlpMode::Auto.resolve(ctx, true).unwrap(), Path::Scalar);
            let e = MlpMode::Coop.resolve(ctx, true).unwrap_err().to_string();
            assert!(e.contains("f16") && e.contains("--mlp scalar"), "{e}");
        }
        None => {
            let _ = extranerf_tests::coop_tile_or_skip(ctx);
        }
    }
    assert_no_validation_messages(ctx);
}

#[test]
fn contraction_and_sh_match_reference_at_the_extremes() {
    use extranerf_nerf::field::encodings::{Contraction, Encodings, SceneBox};
    use extranerf_nerf::reference::{contract, sh4};
    let e = engine();
    let enc = Encodings::new(&e.ctx).unwrap();
    let mut rng = Rng::new(31);
    let mut pts: Vec<[f32; 3]> = vec![
        [0.0, 0.0, 0.0],
        [1e6, 0.0, 0.0],
        [0.0, -1e6, 0.0],
        [1e30, 1e30, -1e30],
        [3e38, -3e38, 1.0],
        [f32::INFINITY, 0.0, 0.0],
        [1e-30, 1e-30, 0.0],
        [0.5, 0.5, 0.5],
    ];
    for _ in 0..2000 {
        let scale = 10f32.powf(rng.uniform(-3.0, 6.0));
        pts.push([
            rng.uniform(-1.0, 1.0) * scale,
            rng.uniform(-1.0, 1.0) * scale,
            rng.uniform(-1.0, 1.0) * scale,
        ]);
    }
    let n = pts.len();
    let flat: Vec<f32> = pts.iter().flatten().copied().collect();
    let pb = Buffer::from_slice(&e.ctx, "points", &flat).unwrap();
    let out = Buffer::<f32>::new(&e.ctx, "contracted", 3 * n).unwrap();
    let sh = Buffer::<f32>::new(&e.ctx, "sh", 16 * n).unwrap();
    for contraction in [Contraction::None, Contraction::L2, Contraction::LInf] {
        let scene = SceneBox {
            center: [0.25, -0.5, 1.0],
            radius: 1.5,
            contraction,
        };
        let mut rec = e.ctx.recorder("contract").unwrap();
        enc.contract(&mut rec, pb.binding(), out.binding(), n as u64, &scene)
            .unwrap();
        e.ctx.run(rec).unwrap();
        let got = out.read().unwrap();
        for (i, p) in pts.iter().enumerate() {
            let want = contract(*p, &scene);
            for d in 0..3 {
                let g = got[3 * i + d];
                // Inside [0, 1] by construction; 2e-6 absolute (f32 of values <= 1).
                assert!(
                    (0.0..=1.0).contains(&g) && (g as f64 - want[d]).abs() <= 2e-6,
                    "{contraction:?} point {p:?} axis {d}: {g} vs {}",
                    want[d]
                );
            }
        }
    }
    let mut rec = e.ctx.recorder("sh").unwrap();
    enc.sh(&mut rec, pb.binding(), sh.binding(), n as u64)
        .unwrap();
    e.ctx.run(rec).unwrap();
    let got = sh.read().unwrap();
    for (i, p) in pts.iter().enumerate() {
        let (m, ok) = (
            p.iter().fold(0f64, |m, v| m.max(v.abs() as f64)),
            p.iter().all(|v| v.is_finite()),
        );
        let d = if ok && m > 0.0 {
            let u = p.map(|v| v as f64 / m);
            let l = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
            u.map(|v| v / l)
        } else {
            [0.0, 0.0, 1.0]
        };
        let want = sh4(d);
        for k in 0..16 {
            assert!(
                (got[16 * i + k] as f64 - want[k]).abs() <= 2e-6,
                "direction {p:?} coefficient {k}: {} vs {}",
                got[16 * i + k],
                want[k]
            );
        }
    }
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn hash_decay_matches_reference() {
    use extranerf_nerf::optim::{Adam, AdamConfig, TableDecay};
    use extranerf_nerf::reference::{adam_step_with, hash_decay};
    let e = engine();
    let cfg = HashGridConfig {
        levels: 8,
        features: 2,
        log2_table: 14,
        min_res: 8,
        max_res: 512,
    };
    let grid = HashGrid::new(&e.ctx, cfg).unwrap();
    let mut rng = Rng::new(61);
    let n = cfg.param_count() as usize;
    let table: Vec<f32> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let g0: Vec<f32> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let tb = Buffer::from_slice(&e.ctx, "table", &table).unwrap();
    let gb = Buffer::from_slice(&e.ctx, "grad", &g0).unwrap();
    let partial = Buffer::<f32>::new(&e.ctx, "partial", grid.decay_partials() as usize).unwrap();
    let total = Buffer::<f32>::new(&e.ctx, "total", 1).unwrap();
    let plan = extranerf_prims::ReducePlan::new(&e.ctx).unwrap();
    let mut rec = e.ctx.recorder("decay").unwrap();
    grid.decay(
        &mut rec,
        tb.binding(),
        gb.binding(),
        partial.binding(),
        0.25,
    )
    .unwrap();
    e.prims
        .reduce_sum(
            &mut rec,
            &plan,
            partial.binding(),
            grid.decay_partials(),
            total.binding(),
        )
        .unwrap();
    e.ctx.run(rec).unwrap();
    let (want_loss, want_grad) = hash_decay(&cfg, &table, 0.25);
    let got = total.read().unwrap()[0] as f64;
    assert!(
        (got - want_loss).abs() <= 1e-5 * want_loss,
        "loss {got} vs {want_loss}"
    );
    let grad = gb.read().unwrap();
    for i in 0..n {
        let want = g0[i] as f64 + want_grad[i];
        assert!(
            (grad[i] as f64 - want).abs() <= 1e-6,
            "entry {i}: {} vs {want}",
            grad[i]
        );
    }
    // The gradient training folds into Adam, with this grid's level block: one Adam step on
    // g0 plus decay equals the reference step on g0 plus the reference decay gradient. Level
    // offsets that are not multiples of 4 exercise the vec4s that straddle two levels.
    assert!(cfg.level_layout().iter().any(|l| l.offset % 4 != 0));
    let adam_cfg = AdamConfig::default();
    let adam = Adam::new(&e.ctx, n as u64, adam_cfg).unwrap();
    let params = Buffer::from_slice(&e.ctx, "params", &table).unwrap();
    let g0b = Buffer::from_slice(&e.ctx, "g0", &g0).unwrap();
    let mut rec = e.ctx.recorder("adam decay").unwrap();
    let decay = TableDecay {
        block: grid.level_block().binding(),
        levels: cfg.levels,
        start: 0,
        floats: n as u64,
        lambda: 0.25,
    };
    adam.record_step(
        &mut rec,
        params.binding(),
        g0b.binding(),
        1,
        1.0,
        Some(decay),
    )
    .unwrap();
    e.ctx.run(rec).unwrap();
    let got = params.read().unwrap();
    let mut p: Vec<f64> = table.iter().map(|&x| x as f64).collect();
    let (mut m, mut v) = (vec![0f64; n], vec![0f64; n]);
    let g_eff: Vec<f32> = (0..n)
        .map(|i| (g0[i] as f64 + want_grad[i]) as f32)
        .collect();
    adam_step_with(&mut p, &mut m, &mut v, &g_eff, &adam_cfg, 1, 1.0);
    for i in 0..n {
        let tol = 1e-5 * adam_cfg.lr_start as f64 + 2.0 * f32::EPSILON as f64 * p[i].abs();
        assert!(
            (got[i] as f64 - p[i]).abs() <= tol,
            "Adam with folded decay, entry {i}: {} vs {}",
            got[i],
            p[i]
        );
    }
    assert_no_validation_messages(&e.ctx);
}
