//! The proposal sampler's kernels (`render/proposal.wgsl`) against the f64 reference: the
//! resampling on hand-made weight histograms (a single spike, two spikes, uniform, all zero)
//! and random ones, with shared uniform and per-ray source edges, jittered and not; the
//! interlevel loss and its gradient, checked by central differences through the proposal's
//! densities (the kernel's dL/dw fed to composite_bwd).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_gpu::Buffer;
use extranerf_nerf::reference::{bin_samples, interlevel, proposal_resample, ray_weights};
use extranerf_nerf::render::composite::{
    pcg_hash, rand01, Background, Compositor, RayGrads, Samples,
};
use extranerf_nerf::render::proposal::{
    MainBins, Proposal, RaySet, SourceBins, HISTOGRAM_PAD, RESAMPLE_SALT,
};
use extranerf_nerf::render::sample::{SampleOutputs, Spacing};
use extranerf_prims::reference::Rng;
use extranerf_tests::{assert_no_validation_messages, engine};

/// Source bins per ray, and main samples per ray.
const NP: usize = 24;
const K: usize = 10;

/// One ray's source bins: edges in s, and per bin a density and (t, dt).
struct Ray {
    edges: Vec<f32>,
    sigma: Vec<f32>,
    nf: [f32; 2],
}

impl Ray {
    /// The bins' (t, dt): t at the bin's middle, dt its length in t (linear spacing).
    fn t_dt(&self) -> Vec<[f32; 2]> {
        let t = |s: f32| self.nf[0] + s * (self.nf[1] - self.nf[0]);
        self.edges
            .windows(2)
            .map(|e| [t(0.5 * (e[0] + e[1])), t(e[1]) - t(e[0])])
            .collect()
    }

    fn weights(&self) -> Vec<f64> {
        let dt: Vec<f32> = self.t_dt().iter().map(|v| v[1]).collect();
        ray_weights(&self.sigma, &dt).0
    }
}

fn uniform_edges() -> Vec<f32> {
    (0..=NP).map(|i| i as f32 / NP as f32).collect()
}

/// Hand-made histograms first (a single spike, two spikes, uniform, all zero, an opaque first
/// bin), then random ones; `shared` gives every ray the uniform edges, else the random rays
/// get random sorted edges from 0 to 1 (some bins of zero width).
fn rays(rng: &mut Rng, n: usize, shared: bool) -> Vec<Ray> {
    let mut out = vec![];
    for case in 0..n {
        let a = rng.uniform(0.0, 0.5);
        let nf = [a, a + rng.uniform(0.2, 3.0)];
        // The hand-made cases by optical depth per bin (uniform bins of dt = span / NP).
        let dt = (nf[1] - nf[0]) / NP as f32;
        let mut sigma = vec![0f32; NP];
        match case {
            0 => sigma[7] = 20.0 / dt,
            1 => {
                sigma[3] = std::f32::consts::LN_2 / dt;
                sigma[17] = 20.0 / dt;
            }
            2 => sigma.fill(0.02 / dt),
            3 => {}
            4 => sigma[0] = 1e8,
            _ => {
                for s in &mut sigma {
                    *s = if rng.uniform(0.0, 1.0) < 0.3 {
                        0.0
                    } else {
                        rng.uniform(0.0, 1.0).powi(3) * 50.0
                    };
                }
            }
        }
        let edges = if shared || case < 5 {
            uniform_edges()
        } else {
            let mut e: Vec<f32> = (0..NP - 1).map(|_| rng.uniform(0.0, 1.0)).collect();
            if case % 4 == 0 {
                e[3] = e[4];
            }
            e.push(0.0);
            e.push(1.0);
            e.sort_by(f32::total_cmp);
            e
        };
        out.push(Ray { edges, sigma, nf });
    }
    out
}

/// The source bins of the test rays: NP bins per ray, the edges shared or one set per ray.
fn source_bins<'a>(
    edges: &'a Buffer<f32>,
    sigma: &'a Buffer<f32>,
    t_dt: &'a Buffer<f32>,
    shared: bool,
) -> SourceBins<'a> {
    SourceBins {
        edges: edges.binding(),
        stride: if shared { 0 } else { NP as u32 + 1 },
        sigma: sigma.binding(),
        t_dt: t_dt.binding(),
        count: NP as u32,
    }
}

/// The jitter of main edge j of ray r, as the kernel draws it.
fn jitter(seed: u32, r: u32, j: u32) -> f64 {
    rand01(pcg_hash(seed ^ RESAMPLE_SALT ^ pcg_hash(r)).wrapping_add(j)) as f64
}

struct Resampled {
    edges: Vec<f32>,
    t_dt: Vec<f32>,
    s_ds: Vec<f32>,
    pos: Vec<f32>,
    spans: Vec<u32>,
}

/// Runs `resample` on the rays (source edges shared when `shared`), origins and directions
/// made up per ray; a ray with a negative target weight (every third with targets) keeps
/// unjittered edges.
fn run_resample(
    rays: &[Ray],
    shared: bool,
    seed: Option<u32>,
    targets: bool,
) -> (Resampled, Vec<[f32; 4]>, Vec<[f32; 4]>) {
    let e = engine();
    let prop = Proposal::new(&e.ctx).unwrap();
    let n = rays.len();
    let src_edges: Vec<f32> = if shared {
        uniform_edges()
    } else {
        rays.iter().flat_map(|r| r.edges.clone()).collect()
    };
    let sigma: Vec<f32> = rays.iter().flat_map(|r| r.sigma.clone()).collect();
    let t_dt: Vec<f32> = rays.iter().flat_map(|r| r.t_dt()).flatten().collect();
    let o: Vec<[f32; 4]> = (0..n).map(|i| [0.1 * i as f32, -0.3, 0.2, 0.0]).collect();
    let d: Vec<[f32; 4]> = (0..n).map(|i| [0.01 * i as f32, 0.5, -1.0, 0.0]).collect();
    let nf: Vec<f32> = rays.iter().flat_map(|r| r.nf).collect();
    let tgt: Vec<f32> = (0..n)
        .flat_map(|i| [0.5, 0.5, 0.5, if i % 3 == 0 { -1.0 } else { 1.0 }])
        .collect();
    let buf = |name: &str, v: &[f32]| Buffer::from_slice(&e.ctx, name, v).unwrap();
    let (be, bs, bt) = (
        buf("src_edges", &src_edges),
        buf("src_sigma", &sigma),
        buf("src_t_dt", &t_dt),
    );
    let (bo, bd, bnf, btg) = (
        buf("o", o.as_flattened()),
        buf("d", d.as_flattened()),
        buf("nf", &nf),
        buf("targets", &tgt),
    );
    // Poisoned outputs, one element longer than needed: the kernel must write exactly them.
    let poison = |name: &str, len: usize| buf(name, &vec![f32::NAN; len + 1]);
    let edges = poison("edges", n * (K + 1));
    let (pos, tdt, sds) = (
        poison("positions", 3 * n * K),
        poison("t_dt", 2 * n * K),
        poison("s_ds", 2 * n * K),
    );
    let spans = Buffer::<u32>::from_slice(&e.ctx, "spans", &vec![u32::MAX; 2 * n]).unwrap();
    let src = source_bins(&be, &bs, &bt, shared);
    let set = RaySet {
        origins: bo.binding(),
        directions: bd.binding(),
        near_far: bnf.binding(),
        targets: targets.then(|| btg.binding()),
        n_rays: n as u32,
    };
    let out = SampleOutputs {
        positions: pos.binding(),
        t_dt: tdt.binding(),
        s_ds: sds.binding(),
        rays: spans.binding(),
    };
    let mut rec = e.ctx.recorder("resample").unwrap();
    prop.resample(
        &mut rec,
        &src,
        &set,
        edges.binding(),
        &out,
        K as u32,
        HISTOGRAM_PAD,
        Spacing::Linear,
        seed,
    )
    .unwrap();
    e.ctx.run(rec).unwrap();
    assert_no_validation_messages(&e.ctx);
    (
        Resampled {
            edges: edges.read().unwrap(),
            t_dt: tdt.read().unwrap(),
            s_ds: sds.read().unwrap(),
            pos: pos.read().unwrap(),
            spans: spans.read().unwrap(),
        },
        o,
        d,
    )
}

#[test]
fn resample_matches_reference_on_hand_made_histograms() {
    let mut rng = Rng::new(53);
    for (shared, seed, targets) in [
        (true, None, false),
        (true, Some(11u32), false),
        (false, Some(12u32), true),
        (false, None, true),
    ] {
        let rays = rays(&mut rng, 40, shared);
        let (got, o, d) = run_resample(&rays, shared, seed, targets);
        let n = rays.len();
        assert!(got.edges[n * (K + 1)].is_nan(), "wrote past the edges");
        assert!(got.t_dt[2 * n * K].is_nan(), "wrote past t_dt");
        for (r, ray) in rays.iter().enumerate() {
            let jittered = seed.filter(|_| !(targets && r % 3 == 0));
            let jit: Option<Vec<f64>> =
                jittered.map(|s| (0..=K as u32).map(|j| jitter(s, r as u32, j)).collect());
            let src: Vec<f64> = ray.edges.iter().map(|&v| v as f64).collect();
            let want = proposal_resample(
                &src,
                &ray.weights(),
                HISTOGRAM_PAD as f64,
                K,
                jit.as_deref(),
            );
            let e = &got.edges[r * (K + 1)..(r + 1) * (K + 1)];
            for (j, (&g, &w)) in e.iter().zip(&want).enumerate() {
                assert!(
                    (g as f64 - w).abs() <= 2e-5,
                    "ray {r} ({shared}, {seed:?}) edge {j}: {g} vs {w}"
                );
            }
            assert!(e.windows(2).all(|p| p[0] <= p[1]), "ray {r}: edges sorted");
            assert!(e[0] >= 0.0 && e[K] <= 1.0);
            if jittered.is_none() {
                assert!(e[0] == 0.0 && (e[K] - 1.0).abs() <= 2e-5, "ray {r}: 0 to 1");
            }
            // The hand-made cases, by what their histograms mean.
            let in_bin = |b: usize| {
                let (lo, hi) = (b as f32 / NP as f32, (b + 1) as f32 / NP as f32);
                e.windows(2)
                    .filter(|p| 0.5 * (p[0] + p[1]) >= lo && 0.5 * (p[0] + p[1]) < hi)
                    .count()
            };
            match r {
                // Weight 1 in bin 7 against 0.24 of padding: about 0.8 of the samples.
                0 => assert!(in_bin(7) >= 7, "spike: {e:?}"),
                // Weights 1/2 and 1/2: about 0.4 of the samples each.
                1 => assert!(in_bin(3) >= 3 && in_bin(17) >= 3, "two spikes: {e:?}"),
                // Uniform weights: samples spread over the ray, none in most bins.
                2 => assert!((0..NP).all(|b| in_bin(b) <= 1), "uniform: {e:?}"),
                3 if jittered.is_none() => {
                    for (j, &v) in e.iter().enumerate() {
                        assert!(
                            (v - j as f32 / K as f32).abs() <= 1e-5,
                            "all zero: uniform edges, {e:?}"
                        );
                    }
                }
                4 => assert!(in_bin(0) >= 7, "opaque first bin: {e:?}"),
                _ => {}
            }
            // The samples from the kernel's own edges.
            let e64: Vec<f64> = e.iter().map(|&v| v as f64).collect();
            let samples = bin_samples(&e64, ray.nf[0], ray.nf[1], false);
            assert_eq!(
                (got.spans[2 * r], got.spans[2 * r + 1]),
                ((r * K) as u32, K as u32)
            );
            for (j, w) in samples.iter().enumerate() {
                let i = r * K + j;
                let g = [
                    got.t_dt[2 * i] as f64,
                    got.t_dt[2 * i + 1] as f64,
                    got.s_ds[2 * i] as f64,
                    got.s_ds[2 * i + 1] as f64,
                ];
                for c in 0..4 {
                    assert!(
                        (g[c] - w[c]).abs() <= 1e-5 * (1.0 + w[c].abs()),
                        "ray {r} sample {j} field {c}: {} vs {}",
                        g[c],
                        w[c]
                    );
                }
                for c in 0..3 {
                    let p = o[r][c] as f64 + g[0] * d[r][c] as f64;
                    assert!((got.pos[3 * i + c] as f64 - p).abs() <= 1e-5 * (1.0 + p.abs()));
                }
            }
        }
    }
}

/// The interlevel loss and dL/dw against the reference, on rays resampled from their own
/// proposal histograms, on main bins equal to the source bins (edges on edges), and on main
/// bins of zero width; then dL/dsigma of the proposal's densities (the kernel's dL/dw through
/// composite_bwd) against central differences of the f64 loss.
#[test]
fn interlevel_matches_reference_and_its_gradient() {
    let e = engine();
    let prop = Proposal::new(&e.ctx).unwrap();
    let comp = Compositor::new(&e.ctx).unwrap();
    let mut rng = Rng::new(54);
    let lambda = 0.7f32;
    for shared in [true, false] {
        let rays = rays(&mut rng, 36, shared);
        let n = rays.len();
        // Main bins: resampled (jittered) for most rays; the source edges themselves (K of
        // them, every other) for ray 5; zero-width bins for ray 6.
        let (res, _, _) = run_resample(&rays, shared, Some(3), false);
        let mut main_edges = res.edges.clone();
        for j in 0..=K {
            main_edges[5 * (K + 1) + j] = rays[5].edges[(2 * j).min(NP)];
            let v = res.edges[6 * (K + 1) + j].max(0.25);
            main_edges[6 * (K + 1) + j] = if j < 4 { 0.25 } else { v };
        }
        let main_sigma: Vec<f32> = (0..n * K)
            .map(|i| {
                if i % 5 == 0 {
                    0.0
                } else {
                    rng.uniform(0.0, 40.0)
                }
            })
            .collect();
        let main_t_dt: Vec<f32> = (0..n)
            .flat_map(|r| {
                let e64: Vec<f64> = main_edges[r * (K + 1)..(r + 1) * (K + 1)]
                    .iter()
                    .map(|&v| v as f64)
                    .collect();
                bin_samples(&e64, rays[r].nf[0], rays[r].nf[1], false)
                    .into_iter()
                    .flat_map(|s| [s[0] as f32, s[1] as f32])
                    .collect::<Vec<_>>()
            })
            .collect();
        let src_edges: Vec<f32> = if shared {
            uniform_edges()
        } else {
            rays.iter().flat_map(|r| r.edges.clone()).collect()
        };
        let src_sigma: Vec<f32> = rays.iter().flat_map(|r| r.sigma.clone()).collect();
        let src_t_dt: Vec<f32> = rays.iter().flat_map(|r| r.t_dt()).flatten().collect();
        let buf = |name: &str, v: &[f32]| Buffer::from_slice(&e.ctx, name, v).unwrap();
        let (be, bs, bt) = (
            buf("src_edges", &src_edges),
            buf("src_sigma", &src_sigma),
            buf("src_t_dt", &src_t_dt),
        );
        let (me, ms, mt) = (
            buf("main_edges", &main_edges),
            buf("main_sigma", &main_sigma),
            buf("main_t_dt", &main_t_dt),
        );
        let loss = buf("loss", &vec![f32::NAN; n + 1]);
        let d_w = buf("d_weight", &vec![f32::NAN; n * NP + 1]);
        let src = source_bins(&be, &bs, &bt, shared);
        let main = MainBins {
            edges: me.binding(),
            sigma: ms.binding(),
            t_dt: mt.binding(),
            count: K as u32,
        };
        // dL/dsigma of the source samples: composite_bwd with only d_weight.
        let spans: Vec<u32> = (0..n).flat_map(|r| [(r * NP) as u32, NP as u32]).collect();
        let bspans = Buffer::<u32>::from_slice(&e.ctx, "spans", &spans).unwrap();
        let zeros = buf("zeros", &vec![0.0; 4 * n * NP]);
        let d_sigma = buf("d_sigma", &vec![f32::NAN; n * NP]);
        let d_rgb = buf("d_rgb", &vec![0.0; 4 * n * NP]);
        let mut rec = e.ctx.recorder("interlevel").unwrap();
        prop.interlevel(
            &mut rec,
            &src,
            &main,
            n as u32,
            lambda,
            loss.binding(),
            d_w.binding(),
        )
        .unwrap();
        let samples = Samples {
            rays: bspans.binding(),
            sigma: bs.binding(),
            rgb: zeros.binding(),
            t_dt: bt.binding(),
            n_rays: n as u64,
            n_samples: (n * NP) as u64,
        };
        let grads = RayGrads {
            d_rgba: zeros.binding(),
            d_depth: zeros.binding(),
            d_weight: d_w.binding(),
            grad_scaling: false,
        };
        comp.backward(
            &mut rec,
            &samples,
            Background::Fixed([0.0; 3]),
            &grads,
            d_sigma.binding(),
            d_rgb.binding(),
        )
        .unwrap();
        e.ctx.run(rec).unwrap();
        assert_no_validation_messages(&e.ctx);
        let (got_loss, got_dw, got_ds) = (
            loss.read().unwrap(),
            d_w.read().unwrap(),
            d_sigma.read().unwrap(),
        );
        assert!(
            got_loss[n].is_nan() && got_dw[n * NP].is_nan(),
            "wrote past the ends"
        );
        let mut hit = 0;
        for (r, ray) in rays.iter().enumerate() {
            let src64: Vec<f64> = ray.edges.iter().map(|&v| v as f64).collect();
            let me64: Vec<f64> = main_edges[r * (K + 1)..(r + 1) * (K + 1)]
                .iter()
                .map(|&v| v as f64)
                .collect();
            let dt: Vec<f32> = (0..K).map(|j| main_t_dt[2 * (r * K + j) + 1]).collect();
            let (w, _) = ray_weights(&main_sigma[r * K..(r + 1) * K], &dt);
            let f = |sigma: &[f32]| {
                let dt: Vec<f32> = ray.t_dt().iter().map(|v| v[1]).collect();
                interlevel(&src64, &ray_weights(sigma, &dt).0, &me64, &w, 1e-7)
            };
            let (want_l, want_g) = f(&ray.sigma);
            let want_l = lambda as f64 * want_l;
            assert!(
                (got_loss[r] as f64 - want_l).abs() <= 1e-4 * want_l.abs() + 1e-6,
                "ray {r} ({shared}): loss {} vs {want_l}",
                got_loss[r]
            );
            for (i, g) in want_g.iter().enumerate() {
                let want = lambda as f64 * g;
                let got = got_dw[r * NP + i] as f64;
                assert!(
                    (got - want).abs() <= 1e-4 * want.abs() + 1e-4,
                    "ray {r} ({shared}): dL/dw {i} {got} vs {want}"
                );
            }
            hit += usize::from(want_l > 1e-4);
            // Central differences through the densities, where the loss is smooth (a
            // densities' step large enough for f32 rounding, small against the kinks).
            for i in 0..NP {
                let s0 = ray.sigma[i];
                if !(0.05..1e4).contains(&s0) {
                    continue;
                }
                let h = 1e-3 * s0;
                let mut sp = ray.sigma.clone();
                sp[i] = s0 + h;
                let mut sm = ray.sigma.clone();
                sm[i] = s0 - h;
                let fd = lambda as f64 * (f(&sp).0 - f(&sm).0) / (2.0 * h as f64);
                let got = got_ds[r * NP + i] as f64;
                assert!(
                    (got - fd).abs() <= 2e-2 * fd.abs() + 1e-3,
                    "ray {r} ({shared}): dL/dsigma {i} {got} vs central difference {fd}"
                );
            }
        }
        assert!(
            hit >= n / 4,
            "too few rays with a loss to test ({hit} of {n})"
        );
    }
}

/// Training with the proposal sampler on the demo scene (48x36): the loss falls as with the
/// uniform strata, the proposal's parameters move, and the trained proposal bounds the main
/// field's weights far better than the untrained one on the same batch (the interlevel loss
/// with the proposal's parameters put back to their initial values); the main samples of a
/// step lie sorted within the sampling range; rendered with the proposal's samples the field
/// is nearer the training views than with as few uniform strata; a checkpoint keeps the
/// sampler and every parameter. Precision f16 and the cooperative-matrix MLPs (where the device has them) train
/// with it too; an occupancy grid is refused.
#[test]
fn proposal_sampler_trains_on_the_demo_scene() {
    use extranerf_nerf::field::mlp::MlpMode;
    use extranerf_nerf::metrics::psnr;
    use extranerf_nerf::model::{init_params, ModelConfig, Precision, ProposalConfig, Sampler};
    use extranerf_nerf::render::march::MarchCuts;
    use extranerf_nerf::renderer::{March, Nerf};
    use extranerf_nerf::run::{
        load_checkpoint, save_checkpoint, training_views, Checkpoint, RunConfig,
    };
    use extranerf_nerf::trainer::{TrainConfig, Trainer};
    use extranerf_nerf::views::TrainData;
    let e = engine();
    let ctx = &e.ctx;
    let dir = extranerf_tests::scratch_dir("proposal-train");
    extranerf_nerf::demo::write_demo_scene(&dir, 48, 36).unwrap();
    let spec = extranerf_tests::demo_scene_spec(dir.clone());
    let loaded = spec.load().unwrap();
    let base = ModelConfig {
        levels: 8,
        log2_table: 14,
        max_res: 256,
        ..extranerf_nerf::autoconfig::model_for_scene(&loaded.scene)
    };
    let proposal = Sampler::Proposal(ProposalConfig {
        samples: 48,
        levels: 4,
        log2_table: 12,
        min_res: 8,
        max_res: 64,
        ..ProposalConfig::default()
    });
    let views = training_views(&spec, &loaded, &base).unwrap();
    let data = TrainData::new(ctx, &views).unwrap();
    let cfg = TrainConfig {
        steps: 300,
        decay_steps: 300,
        rays: 256,
        samples: 16,
        seed: 7,
        ..TrainConfig::default()
    };
    // The first and last window's loss, and the trainer.
    let train = |sampler: &Sampler, precision: Precision, mlp: MlpMode| {
        let model = ModelConfig {
            sampler: sampler.clone(),
            precision,
            ..base.clone()
        };
        let p0 = init_params(&model, 7);
        let nerf = Nerf::new(ctx, model, &p0, cfg.background).unwrap();
        let mut t = Trainer::new(ctx, nerf, TrainConfig { mlp, ..cfg.clone() }, 0, None).unwrap();
        let first = t.run_steps(ctx, &e.prims, &data, 50).unwrap().loss;
        let mut last = first;
        for _ in 1..6 {
            last = t.run_steps(ctx, &e.prims, &data, 50).unwrap().loss;
        }
        (first, last, p0, t)
    };
    let (u_first, u_last, _, u) = train(&Sampler::Uniform, Precision::F32, MlpMode::Scalar);
    let (p_first, p_last, p0, mut t) = train(&proposal, Precision::F32, MlpMode::Scalar);
    assert_eq!(u.interlevel_loss().unwrap(), None);
    assert!(t.is_fused(), "{:?}", t.standalone_reason());
    assert!(
        p_last < 0.5 * p_first,
        "the loss falls: {p_first} -> {p_last}"
    );
    assert!(
        p_last < 1.5 * u_last,
        "as with the uniform strata: {p_last} vs {u_last} (from {u_first})"
    );
    let params = t.nerf().params().read().unwrap();
    let lay = *t.nerf().field().layout();
    let [pt, pm] = lay.proposal.unwrap();
    for (name, (start, len)) in [("table", pt), ("MLP", pm)] {
        let moved = (start..start + len).filter(|&i| params[i] != p0[i]).count();
        assert!(moved > len / 10, "proposal {name}: {moved} of {len} moved");
    }
    // The same batch with the trained proposal, then with the untrained one.
    t.gradient(ctx, &e.prims, &data).unwrap();
    let trained = t.interlevel_loss().unwrap().unwrap();
    let (t_dt, _) = t.last_batch_samples().unwrap();
    let model = t.nerf().field().config().clone();
    for ray in t_dt.chunks(cfg.samples as usize) {
        assert!(
            ray.windows(2).all(|p| p[0][0] <= p[1][0]),
            "sorted: {ray:?}"
        );
        assert!(ray
            .iter()
            .all(|v| v[0] >= model.near && v[0] <= model.far && v[1] >= 0.0));
    }
    let mut reset = params.clone();
    for (start, len) in [pt, pm] {
        reset[start..start + len].copy_from_slice(&p0[start..start + len]);
    }
    t.nerf().params().write(&reset).unwrap();
    t.gradient(ctx, &e.prims, &data).unwrap();
    let untrained = t.interlevel_loss().unwrap().unwrap();
    t.nerf().params().write(&params).unwrap();
    eprintln!(
        "loss: uniform {u_first:.5} -> {u_last:.5}, proposal {p_first:.5} -> {p_last:.5}; interlevel loss on one batch: trained proposal {trained:.5}, untrained {untrained:.5}"
    );
    assert!(
        trained < 0.5 * untrained,
        "the trained proposal bounds the weights: {trained} vs untrained {untrained}"
    );
    // Rendered as `render` renders it (the fused march at the proposal sampler's samples,
    // centred), two training views are nearer their true colours than the same field's
    // uniform strata make them at 8 samples per ray (about 0.5 dB here), and no
    // farther at the 16 it trained with; the render does not depend on the chunk (the last
    // chunk here is partial).
    let nerf = t.nerf();
    assert!(nerf.has_proposal());
    assert_eq!(nerf.default_march(), March::default());
    // The same field without its proposal: uniform strata (its parameters are a prefix).
    let uniform_model = ModelConfig {
        sampler: Sampler::Uniform,
        ..nerf.field().config().clone()
    };
    let total = extranerf_nerf::model::ParamLayout::new(&uniform_model).total;
    let all = nerf.params().read().unwrap();
    let uniform = Nerf::new(ctx, uniform_model, &all[..total], cfg.background).unwrap();
    let mut db = [[0.0; 2]; 2];
    for &i in loaded.split.train.iter().take(2) {
        let cam = &loaded.scene.cameras[i];
        let truth = extranerf_nerf::data::load_image_over(&cam.image, cfg.background)
            .unwrap()
            .rgb;
        for (k, samples) in [8u32, 16].into_iter().enumerate() {
            let image = nerf.render(ctx, cam, 1000, samples).unwrap();
            assert_eq!(
                image,
                nerf.render(ctx, cam, 4096, samples).unwrap(),
                "chunks"
            );
            assert!(image.0.iter().chain(&image.1).all(|v| v.is_finite()));
            let strata = uniform
                .render_with(ctx, cam, 4096, samples, March::Fused(MarchCuts::EXACT))
                .unwrap()
                .0;
            db[k][0] += psnr(&image.0, &truth).unwrap() / 2.0;
            db[k][1] += psnr(&strata, &truth).unwrap() / 2.0;
        }
    }
    eprintln!("training views, [proposal, uniform strata] dB at 8 and 16 samples: {db:?}");
    assert!(db[0][0] > db[0][1] + 0.2, "8 samples: {:?}", db[0]);
    assert!(db[1][0] > db[1][1] - 0.1, "16 samples: {:?}", db[1]);
    visibility_at_the_proposal_samples(ctx, nerf, &uniform, &loaded);
    // A checkpoint keeps the sampler and every parameter.
    let run = extranerf_tests::scratch_dir("proposal-checkpoint");
    let config = RunConfig {
        scene: spec.clone(),
        model: model.clone(),
        train: cfg.clone(),
    };
    save_checkpoint(
        &run,
        &Checkpoint {
            config,
            step: 300,
            params: params.clone(),
            moments: None,
        },
    )
    .unwrap();
    let ck = load_checkpoint(&run).unwrap();
    assert_eq!(ck.config.model.sampler, proposal);
    assert_eq!(ck.params, params);
    // Precision f16 (the f16 table copy and MLP records of the main field) and, where the
    // device has them, cooperative-matrix MLPs.
    let (f_first, f_last, ..) = train(&proposal, Precision::F16, MlpMode::Scalar);
    assert!(f_last < 0.5 * f_first, "f16: the loss falls");
    if extranerf_tests::coop_tile_or_skip(ctx).is_some() {
        let (c_first, c_last, ..) = train(&proposal, Precision::F32, MlpMode::Coop);
        assert!(c_last < 0.5 * c_first, "coop: the loss falls");
    }
    // An occupancy grid is refused, saying why.
    let nerf = Nerf::new(ctx, model.clone(), &p0, cfg.background).unwrap();
    let occ = TrainConfig {
        occupancy_res: 32,
        ..cfg.clone()
    };
    let err = Trainer::new(ctx, nerf, occ, 0, None)
        .unwrap_err()
        .to_string();
    assert!(err.contains("occupancy"), "{err}");
    assert_no_validation_messages(ctx);
}

/// Visibility of a view outside the training views from a proposal-trained field at its
/// proposal sampler's 16 samples per ray matches the uniform march of the same field at 128
/// strata: mean absolute difference at most 0.045 in visibility and opacity, every pixel within
/// 0.35 (measured 0.030 and 0.19 in visibility, 0.005 and 0.04 in opacity), and nearer it than
/// 16 uniform strata are (0.049 and 0.40); the chunking does not change it, and the proposal's
/// samples with another field's density are refused.
fn visibility_at_the_proposal_samples(
    ctx: &extranerf_gpu::Context,
    nerf: &extranerf_nerf::renderer::Nerf,
    uniform: &extranerf_nerf::renderer::Nerf,
    loaded: &extranerf_nerf::run::LoadedScene,
) {
    use extranerf_nerf::data::Camera;
    use extranerf_nerf::render::visibility::{
        mask_all_but, Density, RaySamples, Visibility, VisibilityConfig, VisibilityMap,
    };
    let vis = Visibility::new(ctx).unwrap();
    let train: Vec<Camera> = loaded
        .split
        .train
        .iter()
        .map(|&i| loaded.scene.cameras[i].clone())
        .collect();
    // A held-out view outside the rig (the demo's extrapolation split): parts of it no two
    // training views saw.
    let view = loaded.scene.cameras[loaded.split.test[0]].clone();
    let mask = mask_all_but(train.len(), None);
    fn density(n: &extranerf_nerf::renderer::Nerf) -> Density<'_> {
        Density::Field {
            field: n.field(),
            params: n.field().layout().sections(n.params()).unwrap(),
            occupancy: None,
        }
    }
    let cfg = |samples| VisibilityConfig {
        samples,
        vis_samples: 24,
        ..VisibilityConfig::default()
    };
    assert!(matches!(RaySamples::of(nerf), RaySamples::Proposal(_)));
    assert!(matches!(RaySamples::of(uniform), RaySamples::Strata));
    let proposal = |chunk| {
        vis.map_with(
            ctx,
            &density(nerf),
            RaySamples::of(nerf),
            &view,
            &train,
            mask,
            &cfg(16),
            None,
            chunk,
        )
        .unwrap()
    };
    let got = proposal(1000);
    assert_eq!(got, proposal(4096), "chunks");
    let strata = |samples| {
        vis.map(
            ctx,
            &density(uniform),
            &view,
            &train,
            mask,
            &cfg(samples),
            None,
            4096,
        )
        .unwrap()
    };
    let dense = strata(128);
    let few = strata(16);
    // (mean, largest) absolute difference of visibility and of opacity.
    let diff = |a: &VisibilityMap, b: &VisibilityMap| {
        let d = |x: &[f32], y: &[f32]| {
            let e: Vec<f64> = x.iter().zip(y).map(|(p, q)| (p - q).abs() as f64).collect();
            (
                e.iter().sum::<f64>() / e.len() as f64,
                e.iter().cloned().fold(0.0, f64::max),
            )
        };
        [d(&a.visibility, &b.visibility), d(&a.opacity, &b.opacity)]
    };
    let [(vm, vx), (om, ox)] = diff(&got, &dense);
    eprintln!(
        "visibility against 128 strata (mean, largest |difference|): proposal at 16 samples visibility ({vm:.4}, {vx:.4}), opacity ({om:.4}, {ox:.4}); 16 strata {:?}; mean visibility {:.3} of opacity {:.3}",
        diff(&few, &dense),
        dense.mean(),
        dense.mean_opacity()
    );
    assert!(
        vm <= 0.045 && om <= 0.045,
        "mean: visibility {vm}, opacity {om}"
    );
    assert!(
        vx <= 0.35 && ox <= 0.35,
        "largest: visibility {vx}, opacity {ox}"
    );
    let [(fm, _), _] = diff(&few, &dense);
    assert!(vm < fm, "16 strata are nearer: {fm} against {vm}");
    // The scene shows both what the training views saw and what they did not.
    assert!(dense.mean() > 0.2 && dense.mean() < dense.mean_opacity() - 0.02);
    let err = vis
        .map_with(
            ctx,
            &density(uniform),
            RaySamples::Proposal(nerf),
            &view,
            &train,
            mask,
            &cfg(16),
            None,
            64,
        )
        .unwrap_err()
        .to_string();
    assert!(err.contains("density"), "{err}");
}

/// The tiny test model with a small proposal field, in NDC and in contracted world space.
fn tiny_proposal_models() -> [extranerf_nerf::model::ModelConfig; 2] {
    use extranerf_nerf::model::{ModelConfig, ProposalConfig, Sampler};
    let ndc = ModelConfig {
        sampler: Sampler::Proposal(ProposalConfig {
            samples: 24,
            levels: 2,
            log2_table: 8,
            min_res: 4,
            max_res: 16,
            width: 8,
            ..ProposalConfig::default()
        }),
        ..extranerf_tests::tiny_model()
    };
    let world = extranerf_tests::in_world(ndc.clone());
    [ndc, world]
}

/// `model`'s initial parameters with both hash tables (the main field's and the proposal's)
/// drawn uniformly from [-1, 1] with `seed`: densities that vary along every ray.
fn random_tables(model: &extranerf_nerf::model::ModelConfig, seed: u64) -> Vec<f32> {
    let mut rng = Rng::new(seed);
    let mut params = extranerf_nerf::model::init_params(model, 5);
    let lay = extranerf_nerf::model::ParamLayout::new(model);
    let [pt, _] = lay.proposal.expect("a model with the proposal sampler");
    for (start, len) in [lay.table, pt] {
        for v in &mut params[start..start + len] {
            *v = rng.uniform(-1.0, 1.0);
        }
    }
    params
}

/// The fused step with the proposal sampler's samples gives the standalone chain's losses and
/// gradient, the proposal field's included (both draw the same samples: the proposal field and
/// the resampling run as the same kernels before either), in NDC with L2 and in contracted
/// world space with Huber, both with the distortion loss (over bins of unequal width) and
/// random parameters. With cooperative-matrix MLPs the step is the standalone chain's, saying
/// why.
#[test]
fn fused_step_with_the_proposal_sampler_matches_the_standalone_chain() {
    use extranerf_nerf::field::mlp::MlpMode;
    use extranerf_nerf::renderer::Nerf;
    use extranerf_nerf::trainer::{RgbLossKind, TrainConfig, Trainer};
    use extranerf_nerf::views::TrainData;
    let e = engine();
    let ctx = &e.ctx;
    let [ndc, world] = tiny_proposal_models();
    for (ci, (model, rgb_loss)) in [(ndc, RgbLossKind::L2), (world, RgbLossKind::Huber)]
        .into_iter()
        .enumerate()
    {
        let views = extranerf_tests::demo_training_views("proposal-fused", &model);
        let data = TrainData::new(ctx, &views).unwrap();
        let params = random_tables(&model, 60 + ci as u64);
        let lay = extranerf_nerf::model::ParamLayout::new(&model);
        let [pt, pm] = lay.proposal.unwrap();
        let run = |fused: bool, mlp: MlpMode| {
            let cfg = TrainConfig {
                mlp,
                rays: 100,
                samples: 10,
                rgb_loss,
                huber_delta: 0.05,
                distortion_lambda: 5e-2,
                seed: 9,
                background: [0.2, 0.5, 0.9],
                random_background: ci == 1,
                fused_step: fused,
                ..TrainConfig::default()
            };
            let nerf = Nerf::new(ctx, model.clone(), &params, cfg.background).unwrap();
            let mut t = Trainer::new(ctx, nerf, cfg, 3, None).unwrap();
            let g = t.gradient(ctx, &e.prims, &data).unwrap();
            let il = t.interlevel_loss().unwrap().unwrap();
            (g, il, t)
        };
        let ((g_fused, s_fused), il_fused, t_fused) = run(true, MlpMode::Scalar);
        let ((g_std, s_std), il_std, _) = run(false, MlpMode::Scalar);
        assert!(t_fused.is_fused(), "{:?}", t_fused.standalone_reason());
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-5 * (1.0 + b.abs());
        assert!(
            close(s_fused.loss, s_std.loss) && close(s_fused.mse, s_std.mse),
            "case {ci}: fused {s_fused:?} vs standalone {s_std:?}"
        );
        assert!(
            (il_fused - il_std).abs() <= 1e-4 * il_std.abs() + 1e-7 && il_std > 0.0,
            "case {ci}: interlevel loss fused {il_fused} vs standalone {il_std}"
        );
        let sections = [lay.table, lay.density, lay.color, pt, pm];
        for (si, &(start, len)) in sections.iter().enumerate() {
            let want = &g_std[start..start + len];
            let got = &g_fused[start..start + len];
            let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
            assert!(scale > 0.0, "case {ci} section {si}: no gradient");
            for (j, (&g, &w)) in got.iter().zip(want).enumerate() {
                assert!(
                    g.is_finite() && (g - w).abs() <= 2e-5 * scale + 1e-3 * w.abs(),
                    "case {ci} section {si} param {j}: fused {g} vs standalone {w} (largest {scale})"
                );
            }
        }
        if extranerf_tests::coop_tile_or_skip(ctx).is_some() {
            let (_, _, t) = run(true, MlpMode::Coop);
            assert!(!t.is_fused());
            assert!(t.standalone_reason().unwrap().contains("proposal"));
        }
    }
    assert_no_validation_messages(ctx);
}

/// The fused march at the proposal sampler's samples renders what the standalone chain renders
/// at them (both draw them with the same kernels), in NDC and contracted world space, with the
/// last group of four samples partial and the last chunk partial; the render is what
/// `Nerf::render` takes, except with cooperative-matrix MLPs (the standalone chain then); an
/// occupancy grid is refused.
#[test]
fn fused_march_with_the_proposal_sampler_matches_the_standalone_chain() {
    use extranerf_nerf::field::mlp::MlpMode;
    use extranerf_nerf::model::{ModelConfig, Sampler};
    use extranerf_nerf::render::march::MarchCuts;
    use extranerf_nerf::render::occupancy::OccupancyConfig;
    use extranerf_nerf::renderer::{March, Nerf};
    let e = engine();
    let ctx = &e.ctx;
    let [ndc, world] = tiny_proposal_models();
    for (ci, (model, samples)) in [(ndc, 10u32), (world, 37)].into_iter().enumerate() {
        let views = extranerf_tests::demo_training_views("proposal-march", &model);
        let cam = &views[0].camera;
        let params = random_tables(&model, 80 + ci as u64);
        let mut nerf = Nerf::new(ctx, model.clone(), &params, [0.2, 0.5, 0.9]).unwrap();
        nerf.set_mlp(ctx, MlpMode::Scalar).unwrap();
        assert_eq!(nerf.default_march(), March::default());
        let chunk = (cam.width * cam.height).div_ceil(3) + 7;
        let fused = nerf
            .render_with(ctx, cam, chunk, samples, March::Fused(MarchCuts::EXACT))
            .unwrap();
        let chain = nerf
            .render_with(ctx, cam, chunk, samples, March::Standalone)
            .unwrap();
        let diff =
            |a: &[f32], b: &[f32]| a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
        let (c, d, o) = (
            diff(&fused.0, &chain.0),
            diff(&fused.1, &chain.1),
            diff(&fused.2, &chain.2),
        );
        let lit = fused.2.iter().filter(|&&v| v > 0.05 && v < 0.95).count();
        eprintln!("case {ci}: fused vs standalone colour {c:e} depth {d:e} opacity {o:e}; {lit} partly transparent pixels");
        // (The NDC case's random field is partly transparent; the world case's is opaque.)
        assert!(
            ci == 1 || lit > 10,
            "case {ci}: a scene with partly transparent pixels"
        );
        assert!(
            c < 2e-5 && d < 2e-5 && o < 2e-5,
            "case {ci}: fused and standalone differ by {c} (colour), {d} (depth), {o} (opacity)"
        );
        // The uniform strata give another picture: the march took the samples given.
        let uniform = ModelConfig {
            sampler: Sampler::Uniform,
            ..model.clone()
        };
        let total = extranerf_nerf::model::ParamLayout::new(&uniform).total;
        let strata = Nerf::new(ctx, uniform, &params[..total], [0.2, 0.5, 0.9])
            .unwrap()
            .render_with(ctx, cam, chunk, samples, March::Fused(MarchCuts::EXACT))
            .unwrap();
        assert!(
            diff(&strata.0, &fused.0) > 1e-3,
            "case {ci}: the proposal's samples change the render"
        );
        if ci == 0 {
            let occ = OccupancyConfig {
                res: 16,
                ..OccupancyConfig::default()
            };
            let err = nerf
                .build_occupancy(ctx, &e.prims, Some(occ), 1)
                .unwrap_err()
                .to_string();
            assert!(
                err.contains("proposal") && err.contains("occupancy"),
                "{err}"
            );
            assert!(nerf.occupancy().is_none());
            nerf.build_occupancy(ctx, &e.prims, None, 1).unwrap();
            if extranerf_tests::coop_tile_or_skip(ctx).is_some() {
                nerf.set_mlp(ctx, MlpMode::Coop).unwrap();
                assert_eq!(nerf.default_march(), March::Standalone);
            }
        }
    }
    assert_no_validation_messages(ctx);
}
