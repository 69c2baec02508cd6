//! Multi-resolution hash encoding (Instant-NGP) on the engine's device: level layout, and the
//! standalone forward / backward kernels. The fused march kernels share the WGSL functions.

use extranerf_gpu::kernels::field::hash_decay as kdecay;
use extranerf_gpu::kernels::field::hash_grid as k;
use extranerf_gpu::kernels::field::hash_grid_f16 as k16;
use extranerf_gpu::kernels::field::hash_grid_f2 as k2;
use extranerf_gpu::{Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};

pub use k::HashLevel;

/// Hash-grid hyperparameters (Instant-NGP's L, F, log2 T, N_min, N_max).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HashGridConfig {
    /// Number of levels L.
    pub levels: u32,
    /// Features per level F (1, 2, 4 or 8).
    pub features: u32,
    /// log2 of the table size T per level.
    pub log2_table: u32,
    /// Coarsest resolution N_min.
    pub min_res: u32,
    /// Finest resolution N_max.
    pub max_res: u32,
}

impl Default for HashGridConfig {
    /// The paper's NeRF setting: 16 levels x 2 features x 2^19 entries, N_min 16, N_max 2048.
    fn default() -> Self {
        HashGridConfig {
            levels: 16,
            features: 2,
            log2_table: 19,
            min_res: 16,
            max_res: 2048,
        }
    }
}

impl HashGridConfig {
    /// Checks the ranges the kernels support.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(GpuError::Usage(format!("hash grid: {m}")));
        if !matches!(self.features, 1 | 2 | 4 | 8) {
            return bad(format!(
                "features per level must be 1, 2, 4 or 8, not {}",
                self.features
            ));
        }
        if self.levels == 0 || self.levels > 64 {
            return bad(format!("levels must be 1 to 64, not {}", self.levels));
        }
        if !(4..=26).contains(&self.log2_table) {
            return bad(format!(
                "log2 table size must be 4 to 26, not {}",
                self.log2_table
            ));
        }
        if self.min_res < 1 || self.max_res < self.min_res || self.max_res > 1 << 20 {
            return bad(format!(
                "resolutions must satisfy 1 <= N_min ({}) <= N_max ({}) <= 2^20",
                self.min_res, self.max_res
            ));
        }
        Ok(())
    }

    /// ln of the per-level growth factor b = exp((ln N_max - ln N_min) / (L - 1)).
    pub fn ln_growth(&self) -> f64 {
        if self.levels <= 1 {
            return 0.0;
        }
        ((self.max_res as f64).ln() - (self.min_res as f64).ln()) / (self.levels - 1) as f64
    }

    /// The levels: resolution floor(N_min b^l), dense when (N_l + 1)^3 <= T, offsets in floats.
    pub fn level_layout(&self) -> Vec<HashLevel> {
        let t = 1u64 << self.log2_table;
        let ln_b = self.ln_growth();
        let mut offset = 0u64;
        (0..self.levels)
            .map(|l| {
                let res = ((self.min_res as f64) * (ln_b * l as f64).exp() + 1e-9)
                    .floor()
                    .max(1.0) as u64;
                let dense_size = (res + 1).pow(3);
                let (size, dense) = if dense_size <= t {
                    (dense_size, 1)
                } else {
                    (t, 0)
                };
                let lv = HashLevel {
                    offset: offset as u32,
                    res: res as u32,
                    size: size as u32,
                    dense,
                };
                offset += size * self.features as u64;
                lv
            })
            .collect()
    }

    /// Floats in the flat table (all levels).
    pub fn param_count(&self) -> u64 {
        self.level_layout()
            .iter()
            .map(|l| l.size as u64 * self.features as u64)
            .sum()
    }

    /// Output width L * F.
    pub fn output_dim(&self) -> u32 {
        self.levels * self.features
    }
}

/// The encoding kernels and the level table of one configuration.
#[derive(Debug)]
pub struct HashGrid {
    config: HashGridConfig,
    levels: Buffer<HashLevel>,
    /// Per level (first float, size * features, 0, 0), then (floats, 1, 0, 0), padded to 65
    /// entries: the uniform block of the hash-decay gradient folded into Adam.
    level_block: Buffer<[u32; 4]>,
    /// Generic kernels (any F) or the F = 2 specialisation.
    kernels: Kernels,
    decay: Kernel,
    /// The f16 forward path, when enabled ([`HashGrid::with_f16`]).
    half: Option<Half>,
    /// Where a table larger than one storage binding is cut in two.
    split: Option<Split>,
}

/// A table bound as two ranges (common/hash_grid.wgsl): levels `level..` live in the second,
/// which starts at float `hi_base` (a multiple of 128, so both ranges start 256-byte aligned and
/// the f16 copy's second range does too); the first range covers floats `..lo_floats`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Split {
    /// First level of the second range.
    pub level: u32,
    /// Floats of the first range.
    pub lo_floats: u64,
    /// Float offset of the second range.
    pub hi_base: u64,
}

/// Where to cut a table of levels `layout` (floats per level `features`) so that each range
/// fits `limit` bytes: `Ok(None)` when the whole table fits, an error when two ranges do not.
pub fn split_table(layout: &[HashLevel], features: u32, limit: u64) -> Result<Option<Split>> {
    let end = |l: &HashLevel| l.offset as u64 + l.size as u64 * features as u64;
    let total = layout.last().map_or(0, end);
    if total * 4 <= limit {
        return Ok(None);
    }
    // The first level whose end does not fit the first range starts the second.
    let level = layout
        .iter()
        .position(|l| end(l) * 4 > limit)
        .unwrap_or(layout.len());
    let too_large = || GpuError::BufferTooLarge {
        name: "hash grid table (split in two ranges)".into(),
        bytes: total * 4,
        limit: 2 * limit,
    };
    if level == 0 {
        return Err(too_large());
    }
    let lo_floats = layout[level].offset as u64;
    let hi_base = lo_floats / 128 * 128;
    if (total - hi_base) * 4 > limit {
        return Err(too_large());
    }
    Ok(Some(Split {
        level: level as u32,
        lo_floats,
        hi_base,
    }))
}

/// The f16 forward path: the kernels and the f16 copy of the table.
#[derive(Debug)]
struct Half {
    convert: Kernel,
    fwd: Kernel,
    table: Buffer<u16>,
}

#[derive(Debug)]
enum Kernels {
    Generic { fwd: Kernel, bwd: Kernel },
    F2 { fwd: Kernel, bwd: Kernel },
}

impl HashGrid {
    /// Builds the kernels and uploads the level layout. A table larger than one storage
    /// binding (`maxStorageBufferRange`) is bound as two ranges; larger than two, it is an
    /// error.
    pub fn new(ctx: &Context, config: HashGridConfig) -> Result<HashGrid> {
        Self::with_binding_limit(ctx, config, ctx.info().max_storage_buffer_range)
    }

    /// [`HashGrid::new`] as if one binding held at most `limit` bytes (the tests split small
    /// tables with it).
    pub fn with_binding_limit(
        ctx: &Context,
        config: HashGridConfig,
        limit: u64,
    ) -> Result<HashGrid> {
        config.validate()?;
        let count = config.param_count();
        let layout = config.level_layout();
        let split = split_table(
            &layout,
            config.features,
            limit.min(ctx.info().max_storage_buffer_range),
        )?;
        // The device's layout: second-range levels count from hi_base and carry flag bit 1.
        let device_layout: Vec<HashLevel> = layout
            .iter()
            .enumerate()
            .map(|(l, lv)| match split {
                Some(sp) if l as u32 >= sp.level => HashLevel {
                    offset: lv.offset - sp.hi_base as u32,
                    dense: lv.dense | 2,
                    ..*lv
                },
                _ => *lv,
            })
            .collect();
        let mut block: Vec<[u32; 4]> = layout
            .iter()
            .map(|l| [l.offset, l.size * config.features, 0, 0])
            .collect();
        block.push([count as u32, 1, 0, 0]);
        block.resize(65, [count as u32, 1, 0, 0]);
        Ok(HashGrid {
            config,
            levels: Buffer::from_slice(ctx, "hash grid levels", &device_layout)?,
            level_block: Buffer::from_slice(ctx, "hash grid level block", &block)?,
            kernels: if config.features == 2 {
                Kernels::F2 {
                    fwd: Kernel::new(ctx, &k2::encode_fwd_f2::DESC)?,
                    bwd: Kernel::new(ctx, &k2::encode_bwd_f2::DESC)?,
                }
            } else {
                Kernels::Generic {
                    fwd: Kernel::new(ctx, &k::encode_fwd::DESC)?,
                    bwd: Kernel::new(ctx, &k::encode_bwd::DESC)?,
                }
            },
            decay: Kernel::new(ctx, &kdecay::hash_decay::DESC)?,
            half: None,
            split,
        })
    }

    /// Where the table is cut into two bindings (`None`: one binding).
    pub fn split(&self) -> Option<Split> {
        self.split
    }

    /// The two table bindings the kernels take (`table`, `table_hi`): the ranges of a split
    /// table, or the whole table twice.
    pub fn parts<'a>(&self, table: Binding<'a>) -> Result<(Binding<'a>, Binding<'a>)> {
        match self.split {
            None => Ok((table, table)),
            Some(sp) => {
                let total = self.config.param_count();
                Ok((
                    table.sub(0, sp.lo_floats * 4)?,
                    table.sub(sp.hi_base * 4, (total - sp.hi_base) * 4)?,
                ))
            }
        }
    }

    /// Switches the forward pass to f16 table reads (`field/hash_grid_f16.wgsl`): each
    /// forward copies the f32 table (the master weights) to f16 first, then interpolates the
    /// f16 entries in f32. Needs F = 2 and a device with shaderFloat16 and 16-bit storage.
    pub fn with_f16(mut self, ctx: &Context) -> Result<HashGrid> {
        if self.config.features != 2 {
            return Err(GpuError::Usage(format!(
                "the f16 hash grid supports 2 features per level, not {}",
                self.config.features
            )));
        }
        let n = self.config.param_count() as usize;
        if n as u64 * 2 > ctx.info().max_storage_buffer_range {
            return Err(GpuError::BufferTooLarge {
                name: "hash grid f16 table".into(),
                bytes: n as u64 * 2,
                limit: ctx.info().max_storage_buffer_range,
            });
        }
        self.half = Some(Half {
            convert: Kernel::new(ctx, &k16::table_to_f16::DESC)?,
            fwd: Kernel::new(ctx, &k16::encode_fwd_f16::DESC)?,
            table: Buffer::new(ctx, "hash grid f16 table", n)?,
        });
        Ok(self)
    }

    /// True when the forward pass reads an f16 copy of the table.
    pub fn is_f16(&self) -> bool {
        self.half.is_some()
    }

    /// Partial sums the hash-decay pass writes (sum them, e.g. with `Prims::reduce_sum`).
    pub fn decay_partials(&self) -> u64 {
        self.config.param_count().div_ceil(256)
    }

    /// The checks and parameters both decay kernels share: (table floats, Params).
    fn decay_params(
        &self,
        table: &Binding<'_>,
        d_table: &Binding<'_>,
        lambda: f32,
    ) -> Result<(u64, kdecay::Params)> {
        let n = self.config.param_count();
        table.check_fits(n, 4, "hash grid table")?;
        d_table.check_fits(n, 4, "hash grid gradient")?;
        if self.split.is_some() {
            return Err(GpuError::Usage(
                "the standalone hash-decay kernel needs the table in one binding; training folds hash decay into Adam, which handles split tables".into(),
            ));
        }
        if !(lambda >= 0.0 && lambda.is_finite()) {
            return Err(GpuError::Usage(format!(
                "hash decay weight {lambda} must be >= 0"
            )));
        }
        let p = kdecay::Params {
            n: n as u32,
            levels: self.config.levels,
            features: self.config.features,
            lambda,
        };
        Ok((n, p))
    }

    /// Records hash decay (Zip-NeRF): adds the gradient of `lambda * sum_l mean(V_l^2)` to
    /// `d_table` and writes [`HashGrid::decay_partials`] partial losses into `partial`.
    pub fn decay<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        table: Binding<'a>,
        d_table: Binding<'a>,
        partial: Binding<'a>,
        lambda: f32,
    ) -> Result<()> {
        let (n, p) = self.decay_params(&table, &d_table, lambda)?;
        partial.check_fits(self.decay_partials(), 4, "hash decay partial losses")?;
        let b = kdecay::hash_decay::Bindings {
            level_info: self.levels.binding(),
            table,
            d_table,
            partial,
        };
        rec.dispatch(&self.decay, b.into_array(), &p, n)
    }

    /// Per level (first float, size * features, 0, 0), then (floats, 1, 0, 0), padded to 65
    /// entries: the level block of the hash-decay gradient Adam folds in
    /// (`optim::TableDecay`).
    pub fn level_block(&self) -> &Buffer<[u32; 4]> {
        &self.level_block
    }

    /// The level layout on the device (common/hash_grid.wgsl's `HashLevel` per level).
    pub fn levels(&self) -> &Buffer<HashLevel> {
        &self.levels
    }

    /// The configuration.
    pub fn config(&self) -> &HashGridConfig {
        &self.config
    }

    fn check(
        &self,
        positions: &Binding<'_>,
        table: &Binding<'_>,
        enc: &Binding<'_>,
        n: u64,
    ) -> Result<()> {
        positions.check_fits(3 * n, 4, "hash grid positions")?;
        table.check_fits(self.config.param_count(), 4, "hash grid table")?;
        enc.check_fits(n * self.config.output_dim() as u64, 4, "hash grid features")
    }

    /// The kernel for this configuration and its thread count: the F = 2 kernels run one
    /// thread per point, the generic ones one per (point, level). Both entry points of a pair
    /// declare the same bindings and `Params` (checked by the test below).
    fn pick(&self, n: u64, forward: bool) -> Result<(&Kernel, u64, k::Params)> {
        let levels = self.config.levels as u64;
        if n * levels > u32::MAX as u64 {
            return Err(GpuError::Usage(format!(
                "hash grid: {n} points x {levels} levels exceed 2^32 threads"
            )));
        }
        let p = k::Params {
            n: n as u32,
            levels: self.config.levels,
            features: self.config.features,
            _pad: 0,
        };
        Ok(match (&self.kernels, forward) {
            (Kernels::F2 { fwd, .. }, true) => (fwd, n, p),
            (Kernels::F2 { bwd, .. }, false) => (bwd, n, p),
            (Kernels::Generic { fwd, .. }, true) => (fwd, n * levels, p),
            (Kernels::Generic { bwd, .. }, false) => (bwd, n * levels, p),
        })
    }

    /// Records `encoded[n, L*F]` = the encoding of `positions[n, 3]` (in [0, 1]^3, clamped;
    /// NaN gives zeros) from `table` (through its f16 copy when [`HashGrid::with_f16`]).
    pub fn forward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        positions: Binding<'a>,
        table: Binding<'a>,
        encoded: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        self.check(&positions, &table, &encoded, n)?;
        let (kernel, threads, p) = self.pick(n, true)?;
        let (lo, hi) = self.parts(table)?;
        if let Some(h) = &self.half {
            let total = self.config.param_count();
            let hi_base = self.split.map_or(0, |sp| sp.hi_base);
            let half = h.table.binding();
            // The f32 ranges convert one at a time into the one f16 copy.
            // (f32 range, f16 range, feature pairs).
            let ranges = match self.split {
                None => vec![(table, half, total / 2)],
                Some(sp) => vec![
                    (lo, half.sub(0, sp.lo_floats * 2)?, sp.lo_floats / 2),
                    (
                        hi,
                        half.sub(hi_base * 2, (total - hi_base) * 2)?,
                        (total - hi_base) / 2,
                    ),
                ],
            };
            let pc = k16::Params {
                n: 0,
                levels: p.levels,
                features: p.features,
                hi_base: hi_base as u32,
            };
            for (part, out, pairs) in ranges {
                let b = k16::table_to_f16::Bindings {
                    table: part,
                    half_out: out,
                };
                let pc = k16::Params {
                    n: pairs as u32,
                    ..pc
                };
                rec.dispatch(&h.convert, b.into_array(), &pc, pairs)?;
            }
            let pf = k16::Params { n: p.n, ..pc };
            let b = k16::encode_fwd_f16::Bindings {
                positions,
                level_info: self.levels.binding(),
                table_half: h.table.binding(),
                encoded,
            };
            return rec.dispatch(&h.fwd, b.into_array(), &pf, threads);
        }
        let b = k::encode_fwd::Bindings {
            positions,
            level_info: self.levels.binding(),
            table: lo,
            table_hi: hi,
            encoded,
        };
        rec.dispatch(kernel, b.into_array(), &p, threads)
    }

    /// Records `d_table += dL/dtable` given `d_encoded[n, L*F]` (f32 atomics; zero `d_table`
    /// first for a fresh gradient).
    pub fn backward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        positions: Binding<'a>,
        d_encoded: Binding<'a>,
        d_table: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        self.check(&positions, &d_table, &d_encoded, n)?;
        let (kernel, threads, p) = self.pick(n, false)?;
        let (lo, hi) = self.parts(d_table)?;
        let b = k::encode_bwd::Bindings {
            positions,
            level_info: self.levels.binding(),
            d_encoded,
            d_table: lo,
            d_table_hi: hi,
        };
        rec.dispatch(kernel, b.into_array(), &p, threads)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The F = 2 kernels are driven with the generic kernels' Bindings and Params.
    #[test]
    fn f2_kernels_share_the_generic_interface() {
        assert_eq!(
            k::encode_fwd::DESC.bindings,
            k2::encode_fwd_f2::DESC.bindings
        );
        assert_eq!(
            k::encode_bwd::DESC.bindings,
            k2::encode_bwd_f2::DESC.bindings
        );
        let names =
            |l: &[(&str, u32, usize)]| l.iter().map(|m| (m.0.to_string(), m.1)).collect::<Vec<_>>();
        assert_eq!(names(k::PARAMS_LAYOUT), names(k2::PARAMS_LAYOUT));
    }
}
