//! GPU primitives on the engine's device, recorded into a [`Recorder`] so later stages can chain
//! them on the device without host round trips: fill, SAXPY (vec4), reduce-sum, exclusive
//! prefix sum over arbitrary lengths, stream compaction, key/value radix sort and f32 atomic
//! scatter-add with subgroup pre-reduction. Scratch memory lives in plans sized once for a
//! maximum length. [`micro`] holds the microbenchmarks of the fused training step's
//! operations (`bench kernels --only micro`). [`reference`](mod@reference) holds the
//! plain-Rust definitions the tests compare against.
#![forbid(unsafe_code)]

pub mod micro;
pub mod reference;

use extranerf_gpu::kernels::prims as k;
use extranerf_gpu::{Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};

/// Elements per scan / sort tile (256 threads x 4).
pub const TILE: u64 = 1024;
/// f32/u32 elements each thread of fill and saxpy handles (16 vec4s).
const ELEMS_PER_THREAD: u64 = 64;
/// Most workgroups the first reduce pass uses.
pub const REDUCE_GROUPS: u64 = 1024;

/// How [`Prims::scatter_add`] issues its atomics.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScatterMode {
    /// One f32 atomicAdd per element.
    Direct = 0,
    /// Lanes of a subgroup that share an index sum first; one atomic per distinct index.
    SubgroupPreReduce = 1,
}

/// The primitive kernels, built once per context.
#[derive(Debug)]
pub struct Prims {
    ctx: Context,
    fill: Kernel,
    iota: Kernel,
    saxpy: Kernel,
    gemm: Kernel,
    reduce: Kernel,
    scan_tiles: Kernel,
    add_offsets: Kernel,
    compact: Kernel,
    histogram: Kernel,
    scatter: Kernel,
    scatter_add: Kernel,
}

fn usage(msg: String) -> GpuError {
    GpuError::Usage(msg)
}

/// Scratch for [`Prims::reduce_sum`].
#[derive(Debug)]
pub struct ReducePlan {
    partial: Buffer<f32>,
}

impl ReducePlan {
    /// Scratch for any length.
    pub fn new(ctx: &Context) -> Result<ReducePlan> {
        Ok(ReducePlan {
            partial: Buffer::new(ctx, "reduce partial sums", REDUCE_GROUPS as usize)?,
        })
    }
}

/// Scratch for exclusive scans of up to `max_n` elements.
#[derive(Debug)]
pub struct ScanPlan {
    max_n: u64,
    /// sums[l]: tile totals of level l (ceil(n_l / TILE) elements).
    sums: Vec<Buffer<u32>>,
    /// outs[l - 1]: exclusive scan of sums[l - 1], i.e. the tile offsets of level l - 1.
    outs: Vec<Buffer<u32>>,
    total: Buffer<u32>,
}

/// Sizes of the scan levels for `n`: [n, ceil(n/T), ...] down to the level whose tile count is 1.
fn scan_levels(n: u64) -> Vec<u64> {
    let mut levels = vec![n];
    let mut m = n;
    while m > TILE {
        m = m.div_ceil(TILE);
        levels.push(m);
    }
    levels
}

impl ScanPlan {
    /// Scratch for scans of up to `max_n` u32 elements.
    pub fn new(ctx: &Context, max_n: u64) -> Result<ScanPlan> {
        let levels = scan_levels(max_n.max(1));
        let mut sums = Vec::new();
        let mut outs = Vec::new();
        for (l, &n) in levels.iter().enumerate() {
            sums.push(Buffer::new(
                ctx,
                &format!("scan tile sums L{l}"),
                n.div_ceil(TILE) as usize,
            )?);
            if l > 0 {
                outs.push(Buffer::new(
                    ctx,
                    &format!("scan tile offsets L{}", l - 1),
                    n as usize,
                )?);
            }
        }
        Ok(ScanPlan {
            max_n,
            sums,
            outs,
            total: Buffer::new(ctx, "scan total", 1)?,
        })
    }

    /// One element: the sum of the last scan's (binarized) input.
    pub fn total(&self) -> &Buffer<u32> {
        &self.total
    }
}

/// Scratch for compaction of up to `max_n` elements.
#[derive(Debug)]
pub struct CompactPlan {
    scan: ScanPlan,
    offsets: Buffer<u32>,
}

impl CompactPlan {
    /// Scratch for compaction of up to `max_n` elements.
    pub fn new(ctx: &Context, max_n: u64) -> Result<CompactPlan> {
        Ok(CompactPlan {
            scan: ScanPlan::new(ctx, max_n)?,
            offsets: Buffer::new(ctx, "compact offsets", max_n.max(1) as usize)?,
        })
    }

    /// One element: how many elements the last compaction kept.
    pub fn count(&self) -> &Buffer<u32> {
        self.scan.total()
    }
}

/// Scratch for key/value sorts of up to `max_n` elements.
#[derive(Debug)]
pub struct SortPlan {
    max_n: u64,
    keys: Buffer<u32>,
    vals: Buffer<u32>,
    hist: Buffer<u32>,
    offsets: Buffer<u32>,
    scan: ScanPlan,
}

impl SortPlan {
    /// Scratch for sorts of up to `max_n` elements.
    pub fn new(ctx: &Context, max_n: u64) -> Result<SortPlan> {
        let n = max_n.max(1);
        let hist_len = 16 * n.div_ceil(TILE);
        Ok(SortPlan {
            max_n,
            keys: Buffer::new(ctx, "sort keys ping-pong", n as usize)?,
            vals: Buffer::new(ctx, "sort values ping-pong", n as usize)?,
            hist: Buffer::new(ctx, "sort digit histogram", hist_len as usize)?,
            offsets: Buffer::new(ctx, "sort digit offsets", hist_len as usize)?,
            scan: ScanPlan::new(ctx, hist_len)?,
        })
    }
}

fn n32(n: u64, what: &str) -> Result<u32> {
    extranerf_gpu::count_u32(n, what)
}

impl Prims {
    /// Builds every primitive kernel on `ctx`.
    pub fn new(ctx: &Context) -> Result<Prims> {
        Ok(Prims {
            ctx: ctx.clone(),
            fill: Kernel::new(ctx, &k::fill::fill::DESC)?,
            iota: Kernel::new(ctx, &k::iota::iota::DESC)?,
            saxpy: Kernel::new(ctx, &k::saxpy::saxpy::DESC)?,
            gemm: Kernel::new(ctx, &k::gemm::gemm::DESC)?,
            reduce: Kernel::new(ctx, &k::reduce::reduce_sum::DESC)?,
            scan_tiles: Kernel::new(ctx, &k::scan::scan_tiles::DESC)?,
            add_offsets: Kernel::new(ctx, &k::scan::add_offsets::DESC)?,
            compact: Kernel::new(ctx, &k::compact::compact::DESC)?,
            histogram: Kernel::new(ctx, &k::radix_sort::histogram::DESC)?,
            scatter: Kernel::new(ctx, &k::radix_sort::scatter::DESC)?,
            scatter_add: Kernel::new(ctx, &k::scatter_add::scatter_add::DESC)?,
        })
    }

    /// The context the kernels belong to.
    pub fn context(&self) -> &Context {
        &self.ctx
    }

    /// Records `data[0..n] = value` for 32-bit words (pass f32 as its bits).
    pub fn fill<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        data: Binding<'a>,
        n: u64,
        value: u32,
    ) -> Result<()> {
        data.check_fits(n, 4, "fill")?;
        let params = k::fill::Params {
            n: n32(n, "fill")?,
            value,
        };
        rec.dispatch(
            &self.fill,
            k::fill::fill::Bindings { data }.into_array(),
            &params,
            n.div_ceil(ELEMS_PER_THREAD),
        )
    }

    /// Records `data[i] = start + i` for `i < n` (one element per thread, so large `n` crosses
    /// 65535 workgroups and exercises the 2-D folding).
    pub fn iota<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        data: Binding<'a>,
        n: u64,
        start: u32,
    ) -> Result<()> {
        data.check_fits(n, 4, "iota")?;
        let params = k::iota::Params {
            n: n32(n, "iota")?,
            start,
        };
        rec.dispatch(
            &self.iota,
            k::iota::iota::Bindings { data }.into_array(),
            &params,
            n,
        )
    }

    /// Records `y[0..n] = a * x[0..n] + y[0..n]` (f32, fused multiply-add).
    pub fn saxpy<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        a: f32,
        x: Binding<'a>,
        y: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        x.check_fits(n, 4, "saxpy x")?;
        y.check_fits(n, 4, "saxpy y")?;
        let params = k::saxpy::Params {
            n: n32(n, "saxpy")?,
            a,
        };
        rec.dispatch(
            &self.saxpy,
            k::saxpy::saxpy::Bindings { x, y }.into_array(),
            &params,
            n.div_ceil(ELEMS_PER_THREAD),
        )
    }

    /// Records `c[m, n] = a[m, k] * b[k, n]` (row-major f32, tiled through workgroup memory:
    /// 32 x 32 tiles of C, 4 x 4 per thread). `m` and `n` must be multiples of 32 and `k` of 16.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn gemm<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        a: Binding<'a>,
        b: Binding<'a>,
        c: Binding<'a>,
        m: u32,
        n: u32,
        k: u32,
    ) -> Result<()> {
        if m == 0
            || n == 0
            || k == 0
            || !m.is_multiple_of(32)
            || !n.is_multiple_of(32)
            || !k.is_multiple_of(16)
        {
            return Err(usage(format!(
                "gemm {m}x{k} by {k}x{n}: m and n must be positive multiples of 32, k of 16"
            )));
        }
        let (m64, n64, k64) = (m as u64, n as u64, k as u64);
        a.check_fits(m64 * k64, 4, "gemm a")?;
        b.check_fits(k64 * n64, 4, "gemm b")?;
        c.check_fits(m64 * n64, 4, "gemm c")?;
        let tiles = (m64 / 32) * (n64 / 32);
        let params = k::gemm::Params { m, n, k, _pad: 0 };
        rec.dispatch(
            &self.gemm,
            k::gemm::gemm::Bindings { a, b, c }.into_array(),
            &params,
            tiles * 64,
        )
    }

    /// Records `out[0] = sum(input[0..n])` in two passes (f32 accumulation, tree order).
    pub fn reduce_sum<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        plan: &'a ReducePlan,
        input: Binding<'a>,
        n: u64,
        out: Binding<'a>,
    ) -> Result<()> {
        input.check_fits(n, 4, "reduce input")?;
        out.check_fits(1, 4, "reduce output")?;
        // About 16 vec4s per thread before the tree: lavapipe pays per invocation.
        // At least 16 workgroups when there is work for them, so small inputs still spread.
        let groups = n
            .div_ceil(4 * 256 * 16)
            .max(n.div_ceil(1024).min(16))
            .clamp(1, REDUCE_GROUPS);
        let params = k::reduce::Params {
            n: n32(n, "reduce")?,
        };
        let partial = plan.partial.binding();
        rec.dispatch(
            &self.reduce,
            k::reduce::reduce_sum::Bindings { input, partial }.into_array(),
            &params,
            groups * 256,
        )?;
        let params = k::reduce::Params { n: groups as u32 };
        rec.dispatch(
            &self.reduce,
            k::reduce::reduce_sum::Bindings {
                input: partial,
                partial: out,
            }
            .into_array(),
            &params,
            256,
        )
    }

    /// Records the exclusive prefix sum `output[i] = sum(input[0..i])` (wrapping u32) for any
    /// `n <= plan`'s maximum; `plan.total()` receives the sum of all `n`. With `binarize`,
    /// every element counts as `min(x, 1)`.
    pub fn exclusive_scan<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        plan: &'a ScanPlan,
        input: Binding<'a>,
        output: Binding<'a>,
        n: u64,
        binarize: bool,
    ) -> Result<()> {
        if n > plan.max_n {
            return Err(usage(format!(
                "scan of {n} elements with a plan for {}",
                plan.max_n
            )));
        }
        input.check_fits(n, 4, "scan input")?;
        output.check_fits(n, 4, "scan output")?;
        if n == 0 {
            return rec.fill_words(plan.total.binding(), 1, 0);
        }
        let levels = scan_levels(n);
        for (l, &m) in levels.iter().enumerate() {
            let params = k::scan::Params {
                n: n32(m, "scan")?,
                binarize: u32::from(binarize && l == 0),
            };
            let (inp, out) = if l == 0 {
                (input, output)
            } else {
                (plan.sums[l - 1].binding(), plan.outs[l - 1].binding())
            };
            let b = k::scan::scan_tiles::Bindings {
                input: inp,
                output: out,
                tile_sums: plan.sums[l].binding(),
            };
            rec.dispatch(
                &self.scan_tiles,
                b.into_array(),
                &params,
                m.div_ceil(TILE) * 64,
            )?;
        }
        let last = levels.len() - 1;
        rec.copy(plan.sums[last].binding(), 0, plan.total.binding(), 0, 4)?;
        for l in (1..levels.len()).rev() {
            let m = levels[l - 1];
            let target = if l == 1 {
                output
            } else {
                plan.outs[l - 2].binding()
            };
            let params = k::scan::Params {
                n: m as u32,
                binarize: 0,
            };
            let b = k::scan::add_offsets::Bindings {
                output: target,
                tile_offsets: plan.outs[l - 1].binding(),
            };
            rec.dispatch(
                &self.add_offsets,
                b.into_array(),
                &params,
                m.div_ceil(TILE) * 64,
            )?;
        }
        Ok(())
    }

    /// Records stream compaction: `out[0..count]` = `values[i]` (or `i` when `values` is
    /// `None`) for every `i < n` with `flags[i] != 0`, in order; `plan.count()` gets `count`.
    pub fn compact<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        plan: &'a CompactPlan,
        flags: Binding<'a>,
        values: Option<Binding<'a>>,
        out: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        out.check_fits(n, 4, "compact output")?;
        let offsets = plan.offsets.binding();
        self.exclusive_scan(rec, &plan.scan, flags, offsets, n, true)?;
        if let Some(v) = &values {
            v.check_fits(n, 4, "compact values")?;
        }
        let params = k::compact::Params {
            n: n32(n, "compact")?,
            with_values: u32::from(values.is_some()),
        };
        // Without values the kernel writes indices and never reads `values`; bind the flags.
        let b = k::compact::compact::Bindings {
            flags,
            offsets,
            values: values.unwrap_or(flags),
            out,
        };
        rec.dispatch(&self.compact, b.into_array(), &params, n.div_ceil(16))
    }

    /// Records a stable sort of `keys[0..n]` with `values[0..n]` by the low `bits` bits of the
    /// keys (32 sorts by the whole key; keys must be below `2^bits`), 4 bits per pass.
    pub fn radix_sort<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        plan: &'a SortPlan,
        keys: Binding<'a>,
        values: Binding<'a>,
        n: u64,
        bits: u32,
    ) -> Result<()> {
        if n > plan.max_n {
            return Err(usage(format!(
                "sort of {n} elements with a plan for {}",
                plan.max_n
            )));
        }
        if bits == 0 || bits > 32 {
            return Err(usage(format!("sort by {bits} key bits; use 1 to 32")));
        }
        keys.check_fits(n, 4, "sort keys")?;
        values.check_fits(n, 4, "sort values")?;
        if n <= 1 {
            return Ok(());
        }
        let ntiles = n.div_ceil(TILE);
        let passes = bits.div_ceil(4);
        let (tk, tv) = (plan.keys.binding(), plan.vals.binding());
        for p in 0..passes {
            let (src_k, src_v, dst_k, dst_v) = if p % 2 == 0 {
                (keys, values, tk, tv)
            } else {
                (tk, tv, keys, values)
            };
            let params = k::radix_sort::Params {
                n: n32(n, "sort")?,
                shift: 4 * p,
                ntiles: ntiles as u32,
            };
            let b = k::radix_sort::histogram::Bindings {
                keys_in: src_k,
                hist: plan.hist.binding(),
            };
            rec.dispatch(&self.histogram, b.into_array(), &params, ntiles * 64)?;
            self.exclusive_scan(
                rec,
                &plan.scan,
                plan.hist.binding(),
                plan.offsets.binding(),
                16 * ntiles,
                false,
            )?;
            let b = k::radix_sort::scatter::Bindings {
                keys_in: src_k,
                vals_in: src_v,
                offsets: plan.offsets.binding(),
                keys_out: dst_k,
                vals_out: dst_v,
            };
            rec.dispatch(&self.scatter, b.into_array(), &params, ntiles * 64)?;
        }
        if passes % 2 == 1 {
            rec.copy(tk, 0, keys, 0, 4 * n)?;
            rec.copy(tv, 0, values, 0, 4 * n)?;
        }
        Ok(())
    }

    /// Records `acc[indices[i]] += values[i]` for `i < n` with f32 atomics; indices at or past
    /// `acc_len` are skipped.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand; a struct would only rename them
    pub fn scatter_add<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        indices: Binding<'a>,
        values: Binding<'a>,
        acc: Binding<'a>,
        n: u64,
        acc_len: u64,
        mode: ScatterMode,
    ) -> Result<()> {
        indices.check_fits(n, 4, "scatter-add indices")?;
        values.check_fits(n, 4, "scatter-add values")?;
        acc.check_fits(acc_len, 4, "scatter-add target")?;
        let params = k::scatter_add::Params {
            n: n32(n, "scatter-add")?,
            acc_len: n32(acc_len, "scatter-add target")?,
            mode: mode as u32,
        };
        rec.dispatch(
            &self.scatter_add,
            k::scatter_add::scatter_add::Bindings {
                indices,
                values,
                acc,
            }
            .into_array(),
            &params,
            n,
        )
    }
}
