//! `extranerf bench kernels`: primitive microbenchmarks on GPU timestamps.

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use extranerf_gpu::{Buffer, Context, GpuTimer, Recorder};
use extranerf_nerf::field::hash_grid::{HashGrid, HashGridConfig};
use extranerf_nerf::field::mlp::{Mlp, MlpConfig, MlpPath};
use extranerf_nerf::optim::{Adam, AdamConfig};
use extranerf_prims::micro::{Micro, MicroOp, DENSE_GROUP, DENSE_WIDTH};
use extranerf_prims::reference::Rng;
use extranerf_prims::{CompactPlan, Prims, ReducePlan, ScanPlan, ScatterMode, SortPlan};

/// Options of `extranerf bench kernels`.
#[derive(clap::Args, Debug)]
pub struct KernelsArgs {
    /// Problem sizes in 32-bit elements, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [1u64 << 16, 1 << 20, 1 << 24])]
    sizes: Vec<u64>,
    /// Timed repetitions per kernel and size; the median is reported (after one warm-up run).
    #[arg(long, default_value_t = 7)]
    repeats: u32,
    /// Only kernels whose name contains one of these words (comma-separated), e.g. `sort,scan`.
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
    /// Also write every measurement as JSON to FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Lanes (threads) of each microbenchmark (`micro`: the fused training step's operations
    /// one by one); the default is the fused step's 256 rays of issue 61's configuration.
    #[arg(long, default_value_t = 256, value_name = "N")]
    micro_lanes: u32,
    /// Operations per lane of each memory microbenchmark (32x as many FMAs, and one 64-wide
    /// dense layer per 256).
    #[arg(long, default_value_t = 4096, value_name = "N")]
    micro_ops: u32,
}

/// One measured kernel at one size.
#[derive(Debug, serde::Serialize)]
struct Row {
    kernel: String,
    elements: u64,
    /// Bytes the traffic model counts for one run (minimal reads + writes).
    bytes: u64,
    median_ms: f64,
    min_ms: f64,
    gb_per_s: f64,
    elements_per_s: f64,
    /// vkCmdCopyBuffer bandwidth (read + write) at the same size, same run.
    copy_gb_per_s: f64,
    /// gb_per_s / copy_gb_per_s.
    ratio_to_copy: f64,
}

pub fn write_json(path: &Path, value: &serde_json::Value) -> anyhow::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    // Atomically, so an interrupted run leaves no half file.
    extranerf_gpu::files::write_atomic(
        path,
        (serde_json::to_string_pretty(value)? + "\n").as_bytes(),
    )
    .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// One microbenchmark (`micro`): the cost of one operation of the fused training step.
#[derive(Debug, serde::Serialize)]
struct MicroRow {
    op: String,
    unit: &'static str,
    lanes: u32,
    ops_per_lane: u64,
    median_ms: f64,
    min_ms: f64,
    /// GPU time over every lane's operations (the throughput cost of one).
    ns_per_op: f64,
    /// GPU time over one lane's operations (what a lane waits per operation).
    ns_per_lane_op: f64,
    /// ns_per_op less the same kernel's random indexing alone (`random index` row), for the
    /// reads and atomics.
    net_ns_per_op: Option<f64>,
}

/// The median of `v` (not empty; the mean of the middle two for an even count).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Records `repeats` timed runs of `op` (each after an untimed `pre`) plus one warm-up, and
/// returns the per-run GPU milliseconds.
fn measure<'a>(
    ctx: &Context,
    timer: &'a GpuTimer,
    repeats: u32,
    mut pre: impl FnMut(&mut Recorder<'a>) -> extranerf_gpu::Result<()>,
    mut op: impl FnMut(&mut Recorder<'a>) -> extranerf_gpu::Result<()>,
) -> anyhow::Result<Vec<f64>> {
    let mut rec = ctx.recorder("bench")?;
    rec.reset_timer(timer)?;
    pre(&mut rec)?;
    op(&mut rec)?;
    for r in 0..repeats {
        pre(&mut rec)?;
        rec.barrier();
        rec.timestamp(timer, 2 * r)?;
        op(&mut rec)?;
        rec.timestamp(timer, 2 * r + 1)?;
    }
    ctx.run(rec)?;
    let t = timer.read_ns(2 * repeats)?;
    Ok((0..repeats as usize)
        .map(|r| (t[2 * r + 1] - t[2 * r]) * 1e-6)
        .collect())
}

/// `mlp.backward` on `[weights, inputs, d_outputs, d_inputs, saved, d_weights]`.
fn mlp_backward<'a>(
    r: &mut Recorder<'a>,
    mlp: &'a Mlp,
    b: [&'a Buffer<f32>; 6],
    n: u64,
) -> extranerf_gpu::Result<()> {
    let [w, x, dy, dx, saved, dw] = b.map(|b| b.binding());
    mlp.backward(r, w, x, dy, dx, saved, dw, n)
}

fn none(_: &mut Recorder<'_>) -> extranerf_gpu::Result<()> {
    Ok(())
}

struct Bench<'c> {
    ctx: &'c Context,
    prims: Prims,
    repeats: u32,
    only: Vec<String>,
    rows: Vec<Row>,
    micro: Vec<MicroRow>,
    notes: Vec<String>,
}

impl Bench<'_> {
    fn wanted(&self, name: &str) -> bool {
        self.only.is_empty() || self.only.iter().any(|w| name.contains(w.as_str()))
    }

    fn push(&mut self, kernel: &str, n: u64, bytes: u64, times: Vec<f64>, copy_gbps: f64) {
        let min_ms = times.iter().copied().fold(f64::INFINITY, f64::min);
        let median_ms = median(times);
        let gbps = bytes as f64 / (median_ms * 1e-3) / 1e9;
        let row = Row {
            kernel: kernel.into(),
            elements: n,
            bytes,
            median_ms,
            min_ms,
            gb_per_s: gbps,
            elements_per_s: n as f64 / (median_ms * 1e-3),
            copy_gb_per_s: copy_gbps,
            ratio_to_copy: if copy_gbps > 0.0 {
                gbps / copy_gbps
            } else {
                0.0
            },
        };
        println!(
            "{:<34} {:>10} {:>11.4} {:>9.2} {:>10.1} {:>8.2}",
            row.kernel,
            row.elements,
            row.median_ms,
            row.gb_per_s,
            row.elements_per_s / 1e6,
            row.ratio_to_copy
        );
        self.rows.push(row);
    }

    /// The microbenchmarks of the fused training step's operations, `ops` per lane.
    fn micro(&mut self, lanes: u32, ops: u32, rng: &mut Rng) -> anyhow::Result<()> {
        let ctx = self.ctx;
        let reps = self.repeats;
        let timer = GpuTimer::new(ctx, "micro timer", 2 * reps)?;
        let w = DENSE_WIDTH as usize;
        // Weights small enough that 16 layers neither blow up nor vanish.
        let weights: Vec<f32> = (0..w * (w + 1)).map(|_| rng.uniform(-0.1, 0.1)).collect();
        let inputs: Vec<f32> = (0..lanes as usize * DENSE_GROUP as usize * w)
            .map(|_| rng.uniform(-1.0, 1.0))
            .collect();
        let micro = Micro::new(ctx, lanes, &weights, &inputs)?;
        println!(
            "\nmicrobenchmarks: the fused training step's operations, {lanes} lanes (workgroups of 64); ns/op = GPU time over all lanes' operations, per lane = over one lane's; net = less the random index's own cost"
        );
        println!(
            "{:<56} {:>8} {:>10} {:>10} {:>9} {:>10} {:>9}",
            "operation", "unit", "ops/lane", "median ms", "ns/op", "per lane", "net ns/op"
        );
        let mut index_ns = None;
        for op in MicroOp::all() {
            let t = measure(
                ctx,
                &timer,
                reps,
                |r| micro.record_setup(r, op),
                |r| micro.record(r, op, ops),
            )?;
            let min_ms = t.iter().copied().fold(f64::INFINITY, f64::min);
            let median_ms = median(t);
            let per_lane = op.ops_per_lane(ops);
            let ns = median_ms * 1e6 / (per_lane as f64 * lanes as f64);
            if op == MicroOp::Index {
                index_ns = Some(ns);
            }
            let row = MicroRow {
                op: op.name(),
                unit: op.unit(),
                lanes,
                ops_per_lane: per_lane,
                median_ms,
                min_ms,
                ns_per_op: ns,
                ns_per_lane_op: median_ms * 1e6 / per_lane as f64,
                net_ns_per_op: op.baseline().and(index_ns).map(|b| ns - b),
            };
            println!(
                "{:<56} {:>8} {:>10} {:>10.4} {:>9.4} {:>10.3} {:>9}",
                row.op,
                row.unit,
                row.ops_per_lane,
                row.median_ms,
                row.ns_per_op,
                row.ns_per_lane_op,
                row.net_ns_per_op
                    .map_or("-".to_string(), |n| format!("{n:.4}"))
            );
            self.micro.push(row);
        }
        Ok(())
    }

    fn size(&mut self, n: u64, rng: &mut Rng) -> anyhow::Result<()> {
        let ctx = self.ctx;
        let reps = self.repeats;
        let timer = GpuTimer::new(ctx, "bench timer", 2 * reps)?;
        let nu = n as usize;
        let bytes = 4 * n;
        let a = Buffer::<u32>::from_slice(
            ctx,
            "bench a",
            &(0..nu).map(|_| rng.next_u32()).collect::<Vec<_>>(),
        )?;
        let b = Buffer::<u32>::new(ctx, "bench b", nu)?;
        let xf = Buffer::<f32>::from_slice(
            ctx,
            "bench x",
            &(0..nu).map(|_| rng.uniform(-1.0, 1.0)).collect::<Vec<_>>(),
        )?;
        let yf = Buffer::<f32>::from_slice(
            ctx,
            "bench y",
            &(0..nu).map(|_| rng.uniform(-1.0, 1.0)).collect::<Vec<_>>(),
        )?;

        // The reference: a plain buffer copy, counted as read + write.
        let t = measure(ctx, &timer, reps, none, |r| {
            r.copy(a.binding(), 0, b.binding(), 0, bytes)
        })?;
        let copy_gbps = 2.0 * bytes as f64 / (median(t.clone()) * 1e-3) / 1e9;
        self.push(
            "copy (vkCmdCopyBuffer, reference)",
            n,
            2 * bytes,
            t,
            copy_gbps,
        );

        if self.wanted("fill") {
            let t = measure(ctx, &timer, reps, none, |r| r.fill_words(b.binding(), n, 7))?;
            self.push("fill (vkCmdFillBuffer)", n, bytes, t, copy_gbps);
            let t = measure(ctx, &timer, reps, none, |r| {
                self.prims.fill(r, b.binding(), n, 7)
            })?;
            self.push("fill (kernel, vec4)", n, bytes, t, copy_gbps);
        }
        if self.wanted("saxpy") {
            let t = measure(ctx, &timer, reps, none, |r| {
                self.prims.saxpy(r, 0.5, xf.binding(), yf.binding(), n)
            })?;
            self.push("saxpy (vec4)", n, 3 * bytes, t, copy_gbps);
        }
        if self.wanted("reduce") {
            let plan = ReducePlan::new(ctx)?;
            let out = Buffer::<f32>::new(ctx, "bench sum", 1)?;
            let t = measure(ctx, &timer, reps, none, |r| {
                self.prims
                    .reduce_sum(r, &plan, xf.binding(), n, out.binding())
            })?;
            self.push("reduce-sum f32", n, bytes, t, copy_gbps);
        }
        if self.wanted("scan") {
            let plan = ScanPlan::new(ctx, n)?;
            let t = measure(ctx, &timer, reps, none, |r| {
                self.prims
                    .exclusive_scan(r, &plan, a.binding(), b.binding(), n, false)
            })?;
            self.push("exclusive scan u32", n, 2 * bytes, t, copy_gbps);
        }
        if self.wanted("compact") {
            let plan = CompactPlan::new(ctx, n)?;
            let flags = Buffer::<u32>::from_slice(
                ctx,
                "bench flags",
                &(0..nu).map(|_| rng.below(2)).collect::<Vec<_>>(),
            )?;
            let t = measure(ctx, &timer, reps, none, |r| {
                self.prims
                    .compact(r, &plan, flags.binding(), Some(a.binding()), b.binding(), n)
            })?;
            // flags + values read, about half written.
            self.push("compact (50% kept)", n, 2 * bytes + bytes / 2, t, copy_gbps);
        }
        if self.wanted("sort") {
            let plan = SortPlan::new(ctx, n)?;
            let keys = Buffer::<u32>::new(ctx, "bench keys", nu)?;
            let vals = Buffer::<u32>::new(ctx, "bench vals", nu)?;
            let t = measure(
                ctx,
                &timer,
                reps,
                |r| r.copy(a.binding(), 0, keys.binding(), 0, bytes),
                |r| {
                    self.prims
                        .radix_sort(r, &plan, keys.binding(), vals.binding(), n, 32)
                },
            )?;
            // 8 passes, each reading and writing keys and values.
            self.push(
                "radix sort k/v 32-bit (8 passes)",
                n,
                8 * 4 * bytes,
                t,
                copy_gbps,
            );
        }
        if self.wanted("adam") {
            let adam = Adam::new(ctx, n, AdamConfig::default())?;
            let t = measure(ctx, &timer, reps, none, |r| {
                adam.record_step(r, yf.binding(), xf.binding(), 1, 1.0, None)
            })?;
            // Reads parameter, gradient and both moments; writes parameter and moments.
            self.push("adam (flat buffer), parameters", n, 7 * bytes, t, copy_gbps);
        }
        if self.wanted("hash") {
            // The paper's grid (16 levels x 2 features x 2^19 entries, N 16..2048) on n / 16
            // points (at 2^24 the features fill one 128 MiB binding).
            let cfg = HashGridConfig::default();
            let grid = HashGrid::new(ctx, cfg)?;
            let pts = n / 16;
            let table = Buffer::<f32>::from_slice(
                ctx,
                "bench table",
                &(0..cfg.param_count())
                    .map(|_| rng.uniform(-1e-4, 1e-4))
                    .collect::<Vec<_>>(),
            )?;
            let pos = Buffer::<f32>::from_slice(
                ctx,
                "bench positions",
                &(0..3 * pts)
                    .map(|_| rng.uniform(0.0, 1.0))
                    .collect::<Vec<_>>(),
            )?;
            let width = cfg.output_dim() as u64;
            let enc = Buffer::<f32>::new(ctx, "bench encoded", (pts * width) as usize)?;
            let grad = Buffer::<f32>::new(ctx, "bench d_table", cfg.param_count() as usize)?;
            // Per point and level: 8 corners x F floats read, F written, plus the position.
            let f = cfg.features as u64;
            let bytes = pts * (12 + cfg.levels as u64 * (8 * f * 4 + f * 4));
            let t = measure(ctx, &timer, reps, none, |r| {
                grid.forward(r, pos.binding(), table.binding(), enc.binding(), pts)
            })?;
            let fwd_ms = median(t.clone());
            self.push(
                "hash grid fwd (L16 F2 T2^19), points",
                pts,
                bytes,
                t,
                copy_gbps,
            );
            let t = measure(ctx, &timer, reps, none, |r| {
                grid.backward(r, pos.binding(), enc.binding(), grad.binding(), pts)
            })?;
            let bwd_ms = median(t.clone());
            self.push("hash grid bwd (atomics), points", pts, bytes, t, copy_gbps);
            // Ray-coherent points, as a march produces them: 256 samples 1/512 apart along each
            // random ray (random points above are the cache-hostile worst case).
            let mut coherent = Vec::with_capacity(3 * pts as usize);
            while coherent.len() < 3 * pts as usize {
                let o = [
                    rng.uniform(0.2, 0.8),
                    rng.uniform(0.2, 0.8),
                    rng.uniform(0.2, 0.8),
                ];
                let d = [
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-1.0, 1.0),
                ];
                let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
                for s in 0..256 {
                    let t = (s as f32 - 128.0) / 512.0 / len;
                    coherent.extend([o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]);
                }
            }
            coherent.truncate(3 * pts as usize);
            let pos_c = Buffer::<f32>::from_slice(ctx, "bench ray points", &coherent)?;
            let t = measure(ctx, &timer, reps, none, |r| {
                grid.forward(r, pos_c.binding(), table.binding(), enc.binding(), pts)
            })?;
            let fwd_c = median(t.clone());
            self.push(
                "hash grid fwd, ray-coherent points",
                pts,
                bytes,
                t,
                copy_gbps,
            );
            let t = measure(ctx, &timer, reps, none, |r| {
                grid.backward(r, pos_c.binding(), enc.binding(), grad.binding(), pts)
            })?;
            let bwd_c = median(t.clone());
            self.push(
                "hash grid bwd, ray-coherent points",
                pts,
                bytes,
                t,
                copy_gbps,
            );
            if ctx.info().shader_float16 && ctx.info().storage_buffer_16bit {
                // The f16 path: the same points through an f16 copy of the table (the copy is
                // part of every forward and of the timing), and its difference from f32.
                let half = HashGrid::new(ctx, cfg)?.with_f16(ctx)?;
                let enc16 = Buffer::<f32>::new(ctx, "bench encoded f16", (pts * width) as usize)?;
                for (label, p, f32_ms) in
                    [("random", &pos, fwd_ms), ("ray-coherent", &pos_c, fwd_c)]
                {
                    let t = measure(ctx, &timer, reps, none, |r| {
                        half.forward(r, p.binding(), table.binding(), enc16.binding(), pts)
                    })?;
                    let ms = median(t.clone());
                    // Table copy: 4 B read + 2 B written per entry; corners: 2 B per feature.
                    let bytes16 = cfg.param_count() * 6
                        + pts * (12 + cfg.levels as u64 * (8 * f * 2 + f * 4));
                    self.push(
                        &format!("hash grid fwd f16 (with table copy), {label} points"),
                        pts,
                        bytes16,
                        t,
                        copy_gbps,
                    );
                    let mut rec = ctx.recorder("f16 check")?;
                    grid.forward(&mut rec, p.binding(), table.binding(), enc.binding(), pts)?;
                    half.forward(&mut rec, p.binding(), table.binding(), enc16.binding(), pts)?;
                    ctx.run(rec)?;
                    let (a, b) = (enc.read()?, enc16.read()?);
                    let worst = a
                        .iter()
                        .zip(&b)
                        .map(|(x, y)| (x - y).abs())
                        .fold(0f32, f32::max);
                    let scale = a.iter().map(|x| x.abs()).fold(0f32, f32::max);
                    self.notes.push(format!(
                        "hash grid fwd f16 on {label} points: {:.2}x the f32 time; max |f16 - f32| {worst:.2e} for features up to {scale:.2e} (table entries in [-1e-4, 1e-4])",
                        ms / f32_ms
                    ));
                }
            }
            self.notes.push(format!(
                "hash grid fwd+bwd at {pts} ray-coherent points: {:.3} us/point",
                (fwd_c + bwd_c) * 1e3 / pts as f64
            ));
            self.notes.push(format!(
                "hash grid fwd+bwd at {pts} random points: {:.3} us/point (the guide's pure-PyTorch hash grid: 8.2 us/point on this machine class, not measured in this run)",
                (fwd_ms + bwd_ms) * 1e3 / pts as f64
            ));
        }
        if self.wanted("mlp") {
            // Instant-NGP's colour MLP (32 -> 64 -> 64 -> 3) on n / 16 points (at most 65536,
            // the saved activations of the backward pass must fit one binding).
            let cfg = MlpConfig {
                dims: vec![32, 64, 64, 3],
            };
            let pts = (n / 16).min(65536);
            let w = Buffer::<f32>::from_slice(
                ctx,
                "bench mlp w",
                &(0..cfg.param_count())
                    .map(|_| rng.uniform(-0.2, 0.2))
                    .collect::<Vec<_>>(),
            )?;
            let x = Buffer::<f32>::from_slice(
                ctx,
                "bench mlp x",
                &(0..32 * pts)
                    .map(|_| rng.uniform(-1.0, 1.0))
                    .collect::<Vec<_>>(),
            )?;
            let y = Buffer::<f32>::new(ctx, "bench mlp y", 3 * pts as usize)?;
            let dx = Buffer::<f32>::new(ctx, "bench mlp dx", 32 * pts as usize)?;
            let saved =
                Buffer::<f32>::new(ctx, "bench mlp saved", pts as usize * cfg.saved_stride())?;
            let dw = Buffer::<f32>::new(ctx, "bench mlp dw", cfg.param_count())?;
            let flops = 2 * pts * (32 * 64 + 64 * 64 + 64 * 3);
            // The uniform-block kernels (what training uses), the same with the backward record
            // in f16 (precision f16) where the device has it, and the storage-buffer kernels as
            // the same-run reference (the weight-gradient pass is shared).
            let mut variants = vec![("uniform block", Mlp::new(ctx, cfg.clone())?)];
            match Mlp::new(ctx, cfg.clone())?.with_f16(ctx) {
                Ok(m) => variants.push(("uniform block, f16 record", m)),
                Err(e) => self
                    .notes
                    .push(format!("mlp: no f16 record on this device: {e}")),
            }
            match ctx.info().coop_tile() {
                Some(tile) => {
                    let mut m = Mlp::new(ctx, cfg.clone())?;
                    m.set_path(ctx, MlpPath::Coop { tile })?;
                    variants.push(("cooperative matrix", m));
                }
                None => self.notes.push(
                    "mlp: no cooperative-matrix path on this device (VK_KHR_cooperative_matrix with 8x8x8 or 16x16x16 f16*f16+f32 subgroup tiles)".into(),
                ),
            }
            variants.push((
                "storage buffer",
                Mlp::with_storage_kernels(ctx, cfg.clone())?,
            ));
            let mut times = Vec::new();
            let mut grads = Vec::new();
            for (label, mlp) in &variants {
                let t = measure(ctx, &timer, reps, none, |r| {
                    mlp.forward(r, w.binding(), x.binding(), y.binding(), pts)
                })?;
                let fwd_ms = median(t.clone());
                self.push(
                    &format!("mlp fwd 32-64-64-3 ({label}), points"),
                    pts,
                    4 * pts * 35,
                    t,
                    copy_gbps,
                );
                // The output doubles as the output gradient.
                let bufs = [&w, &x, &y, &dx, &saved, &dw];
                let t = measure(ctx, &timer, reps, none, |r| mlp_backward(r, mlp, bufs, pts))?;
                let bwd_ms = median(t.clone());
                self.push(
                    &format!("mlp bwd, data + weights ({label}), points"),
                    pts,
                    4 * pts * (35 + 2 * mlp.saved_words() as u64),
                    t,
                    copy_gbps,
                );
                self.notes.push(format!(
                    "mlp 32-64-64-3 ({label}) at {pts} points: fwd {:.2} GFLOP/s, fwd+bwd {:.3} us/point",
                    flops as f64 / (fwd_ms * 1e-3) / 1e9,
                    (fwd_ms + bwd_ms) * 1e3 / pts as f64
                ));
                times.push((*label, fwd_ms, bwd_ms));
                // One fresh weight gradient per variant, for the f16 error below.
                let mut rec = ctx.recorder("bench mlp gradient")?;
                rec.fill_words(dw.binding(), cfg.param_count() as u64, 0)?;
                mlp_backward(&mut rec, mlp, bufs, pts)?;
                ctx.run(rec)?;
                grads.push(dw.read()?);
            }
            let (_, f, b) = times[0];
            for &(label, fwd_ms, bwd_ms) in &times[1..] {
                self.notes.push(format!(
                    "mlp: uniform block vs {label} in this run: fwd {:.2}x, bwd {:.2}x faster",
                    fwd_ms / f,
                    bwd_ms / b
                ));
            }
            // A variant's weight gradient against the f32 one: (max, mean) |difference| over
            // the largest f32 gradient, and that gradient.
            let differs = |i: usize| {
                let (g32, g) = (&grads[0], &grads[i]);
                let scale = g32.iter().fold(0f32, |m, v| m.max(v.abs()));
                let d = g32.iter().zip(g).map(|(a, b)| (a - b).abs());
                let worst = d.clone().fold(0f32, f32::max);
                let mean = d.sum::<f32>() / g32.len() as f32;
                (worst / scale, mean / scale, scale)
            };
            if let Some(i) = variants
                .iter()
                .position(|(_, m)| m.path() != MlpPath::Scalar)
            {
                let (worst, _, scale) = differs(i);
                self.notes.push(format!(
                    "mlp {} weight gradient at {pts} points: vs f32 max |d| {worst:.2e} of the largest gradient ({scale:.3e})",
                    variants[i].1.path(),
                ));
            }
            if let Some(i) = variants.iter().position(|(_, m)| m.is_f16()) {
                let (worst, mean, scale) = differs(i);
                self.notes.push(format!(
                    "mlp f16 record at {pts} points: weight gradient vs f32 max |d| {worst:.2e}, mean |d| {mean:.2e} of the largest gradient ({scale:.3e}); record {} vs {} bytes per point",
                    4 * variants[i].1.saved_words(),
                    4 * cfg.saved_stride()
                ));
            }
        }
        if self.wanted("gemm wgrad") {
            // An MLP layer as one matrix product: W[64, 64] times activations[64, points], the
            // points n / 64 rounded down to a multiple of 32 (at least 32). The same run times
            // the MLP weight gradient (a reduction over the points) against it.
            let pts = ((n / 64) / 32 * 32).max(32) as u32;
            let (m, k) = (64u32, 64u32);
            let wa = Buffer::<f32>::from_slice(
                ctx,
                "bench gemm w",
                &(0..m * k)
                    .map(|_| rng.uniform(-1.0, 1.0))
                    .collect::<Vec<_>>(),
            )?;
            let xb = Buffer::<f32>::from_slice(
                ctx,
                "bench gemm x",
                &(0..k * pts)
                    .map(|_| rng.uniform(-1.0, 1.0))
                    .collect::<Vec<_>>(),
            )?;
            let yb = Buffer::<f32>::new(ctx, "bench gemm y", (m * pts) as usize)?;
            let t = measure(ctx, &timer, reps, none, |r| {
                self.prims
                    .gemm(r, wa.binding(), xb.binding(), yb.binding(), m, pts, k)
            })?;
            let ms = median(t.clone());
            let bytes = 4 * (m as u64 * k as u64 + (k as u64 + m as u64) * pts as u64);
            self.push(
                "gemm 64x64 by 64xN (tiled), columns",
                pts as u64,
                bytes,
                t,
                copy_gbps,
            );
            let gemm_rate = 2.0 * m as f64 * k as f64 * pts as f64 / (ms * 1e-3) / 1e9;
            self.notes.push(format!(
                "gemm 64x64 x 64x{pts}: {gemm_rate:.2} GFLOP/s (an MLP layer over {pts} points; compare the mlp rows' GFLOP/s)"
            ));
            // The weight gradient of the field's two MLPs (the training step's `MLP weight
            // gradients` stage) over the same points, from records of random values.
            let mut flops = 0u64;
            let mut wgrad_ms = 0.0;
            for dims in [vec![32, 64, 16], vec![32, 64, 64, 3]] {
                let cfg = MlpConfig { dims };
                let mlp = Mlp::new(ctx, cfg.clone())?;
                let saved = Buffer::<f32>::from_slice(
                    ctx,
                    "bench wgrad records",
                    &(0..pts as usize * cfg.saved_stride())
                        .map(|_| rng.uniform(-1.0, 1.0))
                        .collect::<Vec<_>>(),
                )?;
                let dw = Buffer::<f32>::new(ctx, "bench wgrad dw", cfg.param_count())?;
                let t = measure(ctx, &timer, reps, none, |r| {
                    mlp.weight_gradient(r, saved.binding(), dw.binding(), pts as u64)
                })?;
                wgrad_ms += median(t.clone());
                flops += 2 * pts as u64 * cfg.param_count() as u64;
                self.push(
                    &format!("mlp weight gradient {:?} (tiled), points", cfg.dims),
                    pts as u64,
                    4 * pts as u64 * cfg.saved_stride() as u64,
                    t,
                    copy_gbps,
                );
            }
            let wgrad_rate = flops as f64 / (wgrad_ms * 1e-3) / 1e9;
            self.notes.push(format!(
                "mlp weight gradient [32, 64, 16] + [32, 64, 64, 3] at {pts} points: {wgrad_ms:.3} ms, {wgrad_rate:.2} GFLOP/s = {:.2}x the gemm's rate in this run",
                wgrad_rate / gemm_rate
            ));
        }
        if self.wanted("scatter") {
            let distinct = Buffer::<u32>::from_slice(
                ctx,
                "bench distinct idx",
                &(0..n as u32).collect::<Vec<_>>(),
            )?;
            let same = Buffer::<u32>::from_slice(ctx, "bench same idx", &vec![3u32; nu])?;
            let acc = Buffer::<f32>::new(ctx, "bench acc", nu)?;
            for (label, idx) in [("distinct", &distinct), ("all equal", &same)] {
                for (mname, mode) in [
                    ("direct", ScatterMode::Direct),
                    ("subgroup", ScatterMode::SubgroupPreReduce),
                ] {
                    let t = measure(ctx, &timer, reps, none, |r| {
                        self.prims.scatter_add(
                            r,
                            idx.binding(),
                            xf.binding(),
                            acc.binding(),
                            n,
                            n,
                            mode,
                        )
                    })?;
                    self.push(
                        &format!("scatter-add {mname}, {label}"),
                        n,
                        3 * bytes,
                        t,
                        copy_gbps,
                    );
                }
            }
        }
        Ok(())
    }
}

pub fn kernels(ctx: &Context, args: &KernelsArgs) -> anyhow::Result<()> {
    if args.repeats == 0 {
        anyhow::bail!("--repeats must be at least 1");
    }
    if args.micro_lanes == 0 || args.micro_ops == 0 {
        anyhow::bail!("--micro-lanes and --micro-ops must be at least 1");
    }
    let info = ctx.info();
    let limit = info.max_storage_buffer_range / 4;
    for &n in &args.sizes {
        if n == 0 || n > limit {
            anyhow::bail!("--sizes: {n} elements is outside 1..={limit} (this device binds at most {} bytes per buffer)", info.max_storage_buffer_range);
        }
    }
    println!(
        "device: {} ({} {}), Vulkan {}",
        info.name, info.driver_name, info.driver_info, info.api_version
    );
    println!("median of {} runs after one warm-up; GB/s from each kernel's minimal traffic; ratio = GB/s over vkCmdCopyBuffer GB/s at the same size", args.repeats);
    println!(
        "{:<34} {:>10} {:>11} {:>9} {:>10} {:>8}",
        "kernel", "elements", "median ms", "GB/s", "Melem/s", "vs copy"
    );
    let mut bench = Bench {
        ctx,
        prims: Prims::new(ctx)?,
        repeats: args.repeats,
        only: args.only.clone(),
        rows: Vec::new(),
        micro: Vec::new(),
        notes: Vec::new(),
    };
    let mut rng = Rng::new(0x5eed);
    for &n in &args.sizes {
        bench.size(n, &mut rng)?;
    }
    if bench.wanted("micro") {
        bench.micro(args.micro_lanes, args.micro_ops, &mut rng)?;
    }
    for note in &bench.notes {
        println!("{note}");
    }
    if let Some(path) = &args.json {
        let value = serde_json::json!({
            "notes": bench.notes,
            "device": {"name": info.name, "driver": info.driver_name, "driver_info": info.driver_info, "api_version": info.api_version, "subgroup_size": info.subgroup_size},
            "repeats": args.repeats,
            "command": std::env::args().collect::<Vec<_>>().join(" "),
            "results": bench.rows,
            "micro": bench.micro,
        });
        write_json(path, &value)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}
