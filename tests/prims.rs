//! Every primitive against its plain-Rust reference on random inputs, outputs poisoned first:
//! sizes 0, 1, not a multiple of the workgroup, and above 65535 workgroups where a single
//! binding can hold that many (see each test).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_gpu::Buffer;
use extranerf_prims::reference::{self as r, Rng};
use extranerf_prims::{CompactPlan, ReducePlan, ScanPlan, ScatterMode, SortPlan};
use extranerf_tests::{assert_no_validation_messages, engine, POISON};

/// Extra elements past `n` in every output buffer, checked to stay poisoned.
const GUARD: usize = 37;

fn poisoned(name: &str, n: usize) -> Buffer<u32> {
    let e = engine();
    Buffer::from_slice(&e.ctx, name, &vec![POISON; n + GUARD]).expect("poisoned buffer")
}

#[test]
fn fill_all_sizes() {
    let e = engine();
    // 4096 words per workgroup (64 threads x 16 vec4s): 65536 workgroups would need 1 GiB, past
    // the 128 MiB binding limit; iota and scatter-add cross 65535 workgroups instead.
    for n in [0usize, 1, 3, 4, 255, 4096, 4096 * 3 + 7, (1 << 24) + 13] {
        let buf = poisoned("fill out", n);
        let mut rec = e.ctx.recorder("fill").unwrap();
        e.prims
            .fill(&mut rec, buf.binding(), n as u64, 0x1234_5678)
            .unwrap();
        e.ctx.run(rec).unwrap();
        let got = buf.read().unwrap();
        let mut want = vec![POISON; n + GUARD];
        r::fill(&mut want, n, 0x1234_5678);
        assert!(
            got == want,
            "fill n={n}: first mismatch at {:?}",
            got.iter().zip(&want).position(|(a, b)| a != b)
        );
    }
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn iota_crosses_65535_workgroups() {
    let e = engine();
    // 64 threads per workgroup, one element each: 64 * 65536 + 9 elements need 65537
    // workgroups, which the recorder folds into a 2-D grid.
    for (n, start) in [
        (0usize, 0u32),
        (1, 5),
        (63, 0),
        (65, 7),
        (64 * 65536 + 9, u32::MAX - 100),
    ] {
        let buf = poisoned("iota out", n);
        let mut rec = e.ctx.recorder("iota").unwrap();
        e.prims
            .iota(&mut rec, buf.binding(), n as u64, start)
            .unwrap();
        e.ctx.run(rec).unwrap();
        let got = buf.read().unwrap();
        assert!(got[..n] == r::iota(n, start)[..], "iota n={n}");
        assert!(
            got[n..].iter().all(|&v| v == POISON),
            "iota n={n} wrote past n"
        );
    }
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn saxpy_matches_f64_reference() {
    let e = engine();
    let mut rng = Rng::new(1);
    // 4096 elements per workgroup: see fill_all_sizes for why none crosses 65535 workgroups.
    for n in [0usize, 1, 5, 1000, 4096 * 5 + 3, (1 << 24) + 6] {
        let a = rng.uniform(-3.0, 3.0);
        let x: Vec<f32> = (0..n).map(|_| rng.uniform(-10.0, 10.0)).collect();
        let mut y: Vec<f32> = (0..n).map(|_| rng.uniform(-10.0, 10.0)).collect();
        let want = r::saxpy(a, &x, &y);
        y.extend(std::iter::repeat_n(f32::from_bits(POISON), GUARD));
        let xb = Buffer::from_slice(&e.ctx, "x", &x).unwrap();
        let yb = Buffer::from_slice(&e.ctx, "y", &y).unwrap();
        let mut rec = e.ctx.recorder("saxpy").unwrap();
        e.prims
            .saxpy(&mut rec, a, xb.binding(), yb.binding(), n as u64)
            .unwrap();
        e.ctx.run(rec).unwrap();
        let got = yb.read().unwrap();
        for i in 0..n {
            // Fused: one rounding of the result; unfused: one more of a*x. Stated tolerance:
            // eps * (|a x| + |y|).
            let tol = f32::EPSILON as f64 * ((a as f64 * x[i] as f64).abs() + (y[i] as f64).abs())
                + f32::MIN_POSITIVE as f64;
            assert!(
                (got[i] as f64 - want[i]).abs() <= tol,
                "saxpy n={n} i={i}: {} vs {}",
                got[i],
                want[i]
            );
        }
        assert!(
            got[n..].iter().all(|v| v.to_bits() == POISON),
            "saxpy n={n} wrote past n"
        );
    }
    assert_no_validation_messages(&e.ctx);
}

/// The tiled matrix product against an f64 reference (several shapes, more than one K slice
/// and tile row or column), outputs poisoned first; bad shapes are errors.
#[test]
fn gemm_matches_f64_reference() {
    let e = engine();
    let mut rng = Rng::new(9);
    for (m, n, k) in [(32u32, 32u32, 16u32), (64, 96, 48), (96, 32, 80)] {
        let a: Vec<f32> = (0..m * k).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let b: Vec<f32> = (0..k * n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let ab = Buffer::from_slice(&e.ctx, "a", &a).unwrap();
        let bb = Buffer::from_slice(&e.ctx, "b", &b).unwrap();
        let mut c = vec![f32::from_bits(POISON); (m * n) as usize];
        c.extend(std::iter::repeat_n(f32::from_bits(POISON), GUARD));
        let cb = Buffer::from_slice(&e.ctx, "c", &c).unwrap();
        let mut rec = e.ctx.recorder("gemm").unwrap();
        e.prims
            .gemm(&mut rec, ab.binding(), bb.binding(), cb.binding(), m, n, k)
            .unwrap();
        e.ctx.run(rec).unwrap();
        let got = cb.read().unwrap();
        for i in 0..m as usize {
            for j in 0..n as usize {
                let (mut want, mut mag) = (0f64, 0f64);
                for q in 0..k as usize {
                    let p = a[i * k as usize + q] as f64 * b[q * n as usize + j] as f64;
                    want += p;
                    mag += p.abs();
                }
                let g = got[i * n as usize + j] as f64;
                assert!(
                    (g - want).abs() <= 4.0 * f32::EPSILON as f64 * mag + 1e-30,
                    "gemm {m}x{n}x{k} at ({i}, {j}): {g} vs {want}"
                );
            }
        }
        assert!(got[(m * n) as usize..]
            .iter()
            .all(|v| v.to_bits() == POISON));
    }
    let x = Buffer::<f32>::new(&e.ctx, "x", 4096).unwrap();
    let mut rec = e.ctx.recorder("gemm bad").unwrap();
    for (m, n, k) in [(30u32, 32u32, 16u32), (32, 32, 8), (0, 32, 16)] {
        let err = e
            .prims
            .gemm(&mut rec, x.binding(), x.binding(), x.binding(), m, n, k)
            .unwrap_err();
        assert!(err.to_string().contains("multiples"), "{err}");
    }
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn reduce_sum_within_tolerance_of_f64() {
    let e = engine();
    let plan = ReducePlan::new(&e.ctx).unwrap();
    let out = poisoned("sum", 1);
    let mut rng = Rng::new(2);
    for n in [0usize, 1, 3, 5, 1000, 1 << 20, (1 << 24) + 5] {
        let x: Vec<f32> = (0..n).map(|_| rng.uniform(-1.0, 2.0)).collect();
        let (exact, mag) = r::sum(&x);
        let xb = Buffer::from_slice(&e.ctx, "x", &x).unwrap();
        let mut rec = e.ctx.recorder("reduce").unwrap();
        e.prims
            .reduce_sum(&mut rec, &plan, xb.binding(), n as u64, out.binding())
            .unwrap();
        e.ctx.run(rec).unwrap();
        let got = f32::from_bits(out.read_range(0, 1).unwrap()[0]) as f64;
        // Stated tolerance: 64 eps times the sum of magnitudes (each thread adds at most 16
        // vec4s sequentially, then a tree of depth <= 21).
        let tol = 64.0 * f32::EPSILON as f64 * mag;
        assert!(
            (got - exact).abs() <= tol,
            "sum n={n}: {got} vs {exact} (tol {tol})"
        );
    }
    assert_no_validation_messages(&e.ctx);
}

fn check_scan(n: usize, x: &[u32], binarize: bool, plan: &ScanPlan) {
    let e = engine();
    let xb = Buffer::from_slice(&e.ctx, "scan in", x).unwrap();
    let out = poisoned("scan out", n);
    let mut rec = e.ctx.recorder("scan").unwrap();
    e.prims
        .exclusive_scan(
            &mut rec,
            plan,
            xb.binding(),
            out.binding(),
            n as u64,
            binarize,
        )
        .unwrap();
    e.ctx.run(rec).unwrap();
    let got = out.read().unwrap();
    let (want, total) = r::exclusive_scan(x, binarize);
    assert!(
        got[..n] == want[..],
        "scan n={n} binarize={binarize}: first mismatch at {:?}",
        got.iter().zip(&want).position(|(a, b)| a != b)
    );
    assert!(
        got[n..].iter().all(|&v| v == POISON),
        "scan n={n} wrote past n"
    );
    assert_eq!(plan.total().read().unwrap()[0], total, "scan total n={n}");
}

#[test]
fn exclusive_scan_all_lengths() {
    let e = engine();
    let max = 3 * 1024 * 1024 + 5;
    let plan = ScanPlan::new(&e.ctx, max as u64).unwrap();
    let mut rng = Rng::new(3);
    // 0, 1, around the tile size, several levels (3 levels above 1024^2).
    for n in [
        0usize,
        1,
        2,
        7,
        1023,
        1024,
        1025,
        3 * 4097,
        (1 << 20) + 77,
        max,
    ] {
        let small: Vec<u32> = (0..n).map(|_| rng.below(16)).collect();
        check_scan(n, &small, false, &plan);
        let wide: Vec<u32> = (0..n).map(|_| rng.next_u32()).collect();
        check_scan(n, &wide, n % 2 == 0, &plan);
    }
    let too_big = Buffer::<u32>::new(&e.ctx, "too big", max + 1).unwrap();
    let mut rec = e.ctx.recorder("scan").unwrap();
    let err = e
        .prims
        .exclusive_scan(
            &mut rec,
            &plan,
            too_big.binding(),
            too_big.binding(),
            max as u64 + 1,
            false,
        )
        .unwrap_err();
    assert!(err.to_string().contains("plan"), "{err}");
    drop(rec);
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn compaction_values_and_indices() {
    let e = engine();
    // 1024 elements per workgroup in every kernel involved (the binding limit keeps it below
    // 65536 workgroups, see fill_all_sizes).
    let max = (1 << 24) + 5;
    let plan = CompactPlan::new(&e.ctx, max as u64).unwrap();
    let mut rng = Rng::new(4);
    for (n, density) in [
        (0usize, 2),
        (1, 2),
        (1000, 2),
        (1000, 0),
        (1000, 4),
        ((1 << 20) + 3, 3),
        (max, 2),
    ] {
        // density 0: no flag; 4: every flag set; else about 1/density unset. Flags up to 3.
        let flags: Vec<u32> = (0..n)
            .map(|_| match density {
                0 => 0,
                4 => 1 + rng.below(3),
                d => u32::from(rng.below(d) != 0) * (1 + rng.below(3)),
            })
            .collect();
        let values: Vec<u32> = (0..n).map(|_| rng.next_u32()).collect();
        let fb = Buffer::from_slice(&e.ctx, "flags", &flags).unwrap();
        let vb = Buffer::from_slice(&e.ctx, "values", &values).unwrap();
        for with_values in [true, false] {
            let out = poisoned("compacted", n);
            let mut rec = e.ctx.recorder("compact").unwrap();
            e.prims
                .compact(
                    &mut rec,
                    &plan,
                    fb.binding(),
                    with_values.then(|| vb.binding()),
                    out.binding(),
                    n as u64,
                )
                .unwrap();
            e.ctx.run(rec).unwrap();
            let want = r::compact(&flags, with_values.then_some(&values[..]));
            let count = plan.count().read().unwrap()[0] as usize;
            assert_eq!(count, want.len(), "compact n={n} count");
            let got = out.read().unwrap();
            assert!(
                got[..count] == want[..],
                "compact n={n} values={with_values}"
            );
            assert!(
                got[count..].iter().all(|&v| v == POISON),
                "compact n={n} wrote past count"
            );
        }
    }
    assert_no_validation_messages(&e.ctx);
}

fn check_sort(keys: &[u32], bits: u32, plan: &SortPlan, what: &str) {
    let e = engine();
    let n = keys.len();
    let vals: Vec<u32> = (0..n as u32).collect();
    let mut kpad = keys.to_vec();
    kpad.extend(std::iter::repeat_n(POISON, GUARD));
    let mut vpad = vals.clone();
    vpad.extend(std::iter::repeat_n(POISON, GUARD));
    let kb = Buffer::from_slice(&e.ctx, "keys", &kpad).unwrap();
    let vb = Buffer::from_slice(&e.ctx, "values", &vpad).unwrap();
    let mut rec = e.ctx.recorder("sort").unwrap();
    e.prims
        .radix_sort(&mut rec, plan, kb.binding(), vb.binding(), n as u64, bits)
        .unwrap();
    e.ctx.run(rec).unwrap();
    let (wk, wv) = r::radix_sort(keys, &vals, bits);
    let (gk, gv) = (kb.read().unwrap(), vb.read().unwrap());
    assert!(
        gk[..n] == wk[..],
        "sort {what} n={n}: keys differ at {:?}",
        gk.iter().zip(&wk).position(|(a, b)| a != b)
    );
    // Values are the original positions: equal values mean the sort was stable.
    assert!(
        gv[..n] == wv[..],
        "sort {what} n={n}: not stable / values differ at {:?}",
        gv.iter().zip(&wv).position(|(a, b)| a != b)
    );
    assert!(
        gk[n..].iter().chain(&gv[n..]).all(|&v| v == POISON),
        "sort {what} n={n} wrote past n"
    );
}

#[test]
fn radix_sort_keys_values_stable() {
    let e = engine();
    let max = (1 << 20) + 7;
    let plan = SortPlan::new(&e.ctx, max as u64).unwrap();
    let mut rng = Rng::new(5);
    for n in [0usize, 1, 2, 1000, 1024, 1025, 100_000, max] {
        let keys: Vec<u32> = (0..n).map(|_| rng.next_u32()).collect();
        check_sort(&keys, 32, &plan, "random 32-bit");
        let dup: Vec<u32> = (0..n).map(|_| rng.below(16) * 0x1111_1111).collect();
        check_sort(&dup, 32, &plan, "16 distinct keys (duplicates)");
    }
    check_sort(&vec![0xABCD_0123; 5000], 32, &plan, "all keys equal");
    check_sort(
        &vec![u32::MAX; 3000],
        32,
        &plan,
        "all keys 0xffffffff (the padding value)",
    );
    // 12 bits = 3 passes: the odd pass count ends in the scratch buffers and is copied back.
    let k12: Vec<u32> = (0..70_000).map(|_| rng.below(4096)).collect();
    check_sort(&k12, 12, &plan, "12-bit keys");
    assert_no_validation_messages(&e.ctx);
}

fn check_scatter(
    acc0: &[f32],
    acc_len: usize,
    idx: &[u32],
    vals: &[f32],
    mode: ScatterMode,
    what: &str,
) {
    let e = engine();
    let n = idx.len();
    let ab = Buffer::from_slice(&e.ctx, "acc", acc0).unwrap();
    let ib = Buffer::from_slice(&e.ctx, "indices", idx).unwrap();
    let vb = Buffer::from_slice(&e.ctx, "values", vals).unwrap();
    let mut rec = e.ctx.recorder("scatter-add").unwrap();
    e.prims
        .scatter_add(
            &mut rec,
            ib.binding(),
            vb.binding(),
            ab.binding(),
            n as u64,
            acc_len as u64,
            mode,
        )
        .unwrap();
    e.ctx.run(rec).unwrap();
    let got = ab.read().unwrap();
    let (want, mag) = r::scatter_add(&acc0[..acc_len], idx, vals);
    let mut terms = vec![0f64; acc_len];
    for &i in idx {
        if (i as usize) < acc_len {
            terms[i as usize] += 1.0;
        }
    }
    for i in 0..acc_len {
        // Stated tolerance: rounding of m atomic f32 additions behaves like a random walk:
        // 4 sqrt(m) eps times the sum of magnitudes, plus one ulp of the result.
        let tol = 4.0 * (terms[i] + 1.0).sqrt() * f32::EPSILON as f64 * mag[i]
            + f32::EPSILON as f64 * want[i].abs();
        assert!(
            (got[i] as f64 - want[i]).abs() <= tol,
            "scatter-add {what} {mode:?} n={n} target {i}: {} vs {} (tol {tol})",
            got[i],
            want[i]
        );
    }
    assert!(
        got[acc_len..]
            .iter()
            .zip(&acc0[acc_len..])
            .all(|(a, b)| a.to_bits() == b.to_bits()),
        "scatter-add {what} wrote past acc_len"
    );
}

#[test]
fn scatter_add_contention_patterns() {
    let e = engine();
    let mut rng = Rng::new(6);
    for mode in [ScatterMode::Direct, ScatterMode::SubgroupPreReduce] {
        // 64 threads per workgroup: 64 * 65536 + 3 elements need 65537 workgroups.
        for n in [0usize, 1, 1000, 64 * 65536 + 3] {
            let vals: Vec<f32> = (0..n).map(|_| rng.uniform(0.0, 1.0)).collect();
            // Worst contention: every element hits index 7.
            let acc0: Vec<f32> = (0..16 + GUARD).map(|_| rng.uniform(-1.0, 1.0)).collect();
            check_scatter(&acc0, 16, &vec![7; n], &vals, mode, "all indices equal");
            // No contention: a permutation.
            let mut perm: Vec<u32> = (0..n as u32).collect();
            for i in (1..n).rev() {
                perm.swap(i, rng.below(i as u32 + 1) as usize);
            }
            let acc0: Vec<f32> = (0..n + GUARD).map(|_| rng.uniform(-1.0, 1.0)).collect();
            check_scatter(&acc0, n, &perm, &vals, mode, "all indices distinct");
            // Mixed, with out-of-range indices that must be skipped.
            let idx: Vec<u32> = (0..n).map(|_| rng.below(1100)).collect();
            let acc0: Vec<f32> = (0..1000 + GUARD).map(|_| rng.uniform(-1.0, 1.0)).collect();
            check_scatter(&acc0, 1000, &idx, &vals, mode, "random with out-of-range");
        }
    }
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn chained_primitives_without_host_round_trips() {
    // fill -> saxpy -> reduce in one submission: the recorder's automatic barriers order them.
    let e = engine();
    let n = 100_003usize;
    let x = Buffer::<f32>::new(&e.ctx, "x", n).unwrap();
    let y = Buffer::<f32>::new(&e.ctx, "y", n).unwrap();
    let out = Buffer::<f32>::new(&e.ctx, "sum", 1).unwrap();
    let plan = ReducePlan::new(&e.ctx).unwrap();
    let mut rec = e.ctx.recorder("chain").unwrap();
    e.prims
        .fill(&mut rec, x.binding(), n as u64, 2.0f32.to_bits())
        .unwrap();
    e.prims
        .fill(&mut rec, y.binding(), n as u64, 0.5f32.to_bits())
        .unwrap();
    e.prims
        .saxpy(&mut rec, 3.0, x.binding(), y.binding(), n as u64)
        .unwrap();
    e.prims
        .reduce_sum(&mut rec, &plan, y.binding(), n as u64, out.binding())
        .unwrap();
    assert!(
        rec.barriers >= 2,
        "expected hazard barriers, got {}",
        rec.barriers
    );
    e.ctx.run(rec).unwrap();
    let got = out.read().unwrap()[0] as f64;
    let want = 6.5 * n as f64;
    assert!(
        (got - want).abs() <= 64.0 * f32::EPSILON as f64 * want,
        "{got} vs {want}"
    );
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn back_to_back_submissions_see_each_others_writes() {
    // Three submissions without a host wait in between; each reads what the previous wrote.
    let e = engine();
    let n = 50_001u64;
    let x = Buffer::<f32>::new(&e.ctx, "x", n as usize).unwrap();
    let y = Buffer::<f32>::new(&e.ctx, "y", n as usize).unwrap();
    let mut rec = e.ctx.recorder("first").unwrap();
    e.prims
        .fill(&mut rec, x.binding(), n, 1.5f32.to_bits())
        .unwrap();
    e.prims
        .fill(&mut rec, y.binding(), n, 0.25f32.to_bits())
        .unwrap();
    e.ctx.submit(rec).unwrap();
    let mut rec = e.ctx.recorder("second").unwrap();
    e.prims
        .saxpy(&mut rec, 2.0, x.binding(), y.binding(), n)
        .unwrap();
    e.ctx.submit(rec).unwrap();
    let mut rec = e.ctx.recorder("third").unwrap();
    e.prims
        .saxpy(&mut rec, -1.0, x.binding(), y.binding(), n)
        .unwrap();
    let last = e.ctx.submit(rec).unwrap();
    e.ctx.wait(last).unwrap();
    assert!(
        y.read().unwrap().iter().all(|&v| v == 1.75),
        "2 * 1.5 + 0.25 - 1.5"
    );
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn micro_benchmarks_match_their_reference() {
    use extranerf_prims::micro::{Micro, MicroOp, DENSE_GROUP, DENSE_WIDTH};
    let e = engine();
    // Two workgroups and a part (the third one's lanes past 150 return at once).
    let (lanes, ops) = (150u32, 600u32);
    let mut rng = Rng::new(61);
    let w = DENSE_WIDTH as usize;
    let weights: Vec<f32> = (0..w * (w + 1)).map(|_| rng.uniform(-0.1, 0.1)).collect();
    let inputs: Vec<f32> = (0..lanes as usize * DENSE_GROUP as usize * w)
        .map(|_| rng.uniform(-1.0, 1.0))
        .collect();
    let micro = Micro::new(&e.ctx, lanes, &weights, &inputs).unwrap();
    for op in MicroOp::all() {
        let mut rec = e.ctx.recorder("micro").unwrap();
        micro.record_setup(&mut rec, op).unwrap();
        micro.record(&mut rec, op, ops).unwrap();
        e.ctx.run(rec).unwrap();
        if let MicroOp::Atomic { .. } | MicroOp::AtomicPrefetched | MicroOp::AtomicU32 = op {
            let got = micro.read_atomics().unwrap();
            let want = r::micro_atomic_counts(op, lanes, ops);
            let total: u64 = want.values().map(|&c| c as u64).sum();
            assert_eq!(total, lanes as u64 * op.kernel_ops(ops) as u64);
            for (e, &g) in got.iter().enumerate() {
                let c = want.get(&(e as u32)).copied().unwrap_or(0);
                let g = if op == MicroOp::AtomicU32 {
                    g.to_bits() as f32
                } else {
                    g
                };
                assert!(g == c as f32, "{}: entry {e} is {g}, want {c}", op.name());
            }
            continue;
        }
        let got = micro.read_out().unwrap();
        let want: Vec<f64> = (0..lanes)
            .map(|l| r::micro_lane(op, l, ops, &weights, &inputs))
            .collect();
        let scale = want.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        // Exact for the memory kernels (small integers); f32 rounding for the arithmetic.
        let tol = match op {
            MicroOp::Fma | MicroOp::Dense1 | MicroOp::Dense4 | MicroOp::Dense4Back => 1e-4 * scale,
            _ => 0.0,
        };
        for (l, (g, w)) in got.iter().zip(&want).enumerate() {
            assert!(
                g.is_finite() && (*g as f64 - w).abs() <= tol,
                "{}: lane {l} wrote {g}, want {w} (tolerance {tol:e})",
                op.name()
            );
        }
    }
    assert_no_validation_messages(&e.ctx);
}
