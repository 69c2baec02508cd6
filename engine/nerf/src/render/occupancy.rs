//! Multi-cascade occupancy grid (Instant-NGP): an EMA of density per cell, thresholded into a
//! bitfield the march uses to skip empty space. Updates run on the device in windows of cells
//! so the trainer can refresh it every few steps without host round trips.

use extranerf_gpu::kernels::render::occupancy as k;
use extranerf_gpu::{count_u32, Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};
use extranerf_prims::{Prims, ReducePlan};

/// Grid settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OccupancyConfig {
    /// Cells per axis per cascade.
    pub res: u32,
    /// Cascades: cascade c covers |u|_inf <= 2^c of the scene-normalised position.
    pub cascades: u32,
    /// EMA decay per update (Instant-NGP: 0.95).
    pub decay: f32,
    /// Density threshold (Instant-NGP: 0.01), lowered to the mean density when that is lower.
    pub threshold: f32,
}

impl Default for OccupancyConfig {
    fn default() -> Self {
        OccupancyConfig {
            res: 128,
            cascades: 1,
            decay: 0.95,
            threshold: 0.01,
        }
    }
}

impl OccupancyConfig {
    /// Cells in all cascades.
    pub fn cells(&self) -> u64 {
        (self.res as u64).pow(3) * self.cascades as u64
    }
}

/// The grid, its bitfield and kernels.
#[derive(Debug)]
pub struct Occupancy {
    cfg: OccupancyConfig,
    grid: Buffer<f32>,
    bits: Buffer<u32>,
    sum: Buffer<f32>,
    plan: ReducePlan,
    sample: Kernel,
    update: Kernel,
    make_bits: Kernel,
    query: Kernel,
}

impl Occupancy {
    /// A grid of zero density with every cell marked occupied (so the first march samples
    /// everywhere until updates arrive).
    pub fn new(ctx: &Context, cfg: OccupancyConfig) -> Result<Occupancy> {
        if !(1..=512).contains(&cfg.res)
            || !(1..=8).contains(&cfg.cascades)
            || !(0.0..1.0).contains(&cfg.decay)
            || cfg.threshold.is_nan()
            || cfg.threshold < 0.0
            || cfg.cells() > u32::MAX as u64
        {
            return Err(GpuError::Usage(format!("occupancy grid {cfg:?}: resolution 1-512, 1-8 cascades, decay in [0, 1), threshold >= 0")));
        }
        let n = cfg.cells() as usize;
        Ok(Occupancy {
            cfg,
            grid: Buffer::from_slice(ctx, "occupancy density", &vec![0f32; n])?,
            bits: Buffer::from_slice(ctx, "occupancy bits", &vec![u32::MAX; n.div_ceil(32)])?,
            sum: Buffer::new(ctx, "occupancy density sum", 1)?,
            plan: ReducePlan::new(ctx)?,
            sample: Kernel::new(ctx, &k::occ_sample::DESC)?,
            update: Kernel::new(ctx, &k::occ_update::DESC)?,
            make_bits: Kernel::new(ctx, &k::occ_bits::DESC)?,
            query: Kernel::new(ctx, &k::occ_query::DESC)?,
        })
    }

    /// Settings.
    pub fn config(&self) -> &OccupancyConfig {
        &self.cfg
    }

    /// The per-cell density EMA.
    pub fn grid(&self) -> &Buffer<f32> {
        &self.grid
    }

    /// One bit per cell.
    pub fn bits(&self) -> &Buffer<u32> {
        &self.bits
    }

    fn window(&self, count: u64) -> Result<()> {
        if count > self.cfg.cells() {
            return Err(GpuError::Usage(format!(
                "a window of {count} cells exceeds the grid's {}",
                self.cfg.cells()
            )));
        }
        Ok(())
    }

    fn params(&self, first: u64, count: u64, seed: u32) -> Result<k::Params> {
        let count = count_u32(count, "occupancy cells")?;
        Ok(k::Params {
            res: self.cfg.res,
            cascades: self.cfg.cascades,
            first: (first % self.cfg.cells()) as u32,
            count,
            seed,
            decay: self.cfg.decay,
            threshold: self.cfg.threshold,
            _pad: 0,
        })
    }

    /// Records one jittered scene-normalised position per cell of the window
    /// `[first, first + count)` (wrapping) into `positions[count, 3]`.
    pub fn record_sample<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        positions: Binding<'a>,
        first: u64,
        count: u64,
        seed: u32,
    ) -> Result<()> {
        positions.check_fits(3 * count, 4, "occupancy sample positions")?;
        self.window(count)?;
        let b = k::occ_sample::Bindings { positions };
        rec.dispatch(
            &self.sample,
            b.into_array(),
            &self.params(first, count, seed)?,
            count,
        )
    }

    /// Records the EMA update of the window from `density[count]` (evaluated at the sampled
    /// positions); NaN or negative densities count as 0.
    pub fn record_update<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        density: Binding<'a>,
        first: u64,
        count: u64,
    ) -> Result<()> {
        density.check_fits(count, 4, "occupancy densities")?;
        self.window(count)?;
        let b = k::occ_update::Bindings {
            density,
            grid: self.grid.binding(),
        };
        rec.dispatch(
            &self.update,
            b.into_array(),
            &self.params(first, count, 0)?,
            count,
        )
    }

    /// Records the bitfield from the grid: occupied = density > min(threshold, mean density).
    pub fn record_bits<'a>(&'a self, rec: &mut Recorder<'a>, prims: &'a Prims) -> Result<()> {
        let n = self.cfg.cells();
        prims.reduce_sum(rec, &self.plan, self.grid.binding(), n, self.sum.binding())?;
        let b = k::occ_bits::Bindings {
            grid: self.grid.binding(),
            bits: self.bits.binding(),
            grid_sum: self.sum.binding(),
        };
        rec.dispatch(
            &self.make_bits,
            b.into_array(),
            &self.params(0, 0, 0)?,
            n.div_ceil(32),
        )
    }

    /// Records `occupied[n]` = 1 where the scene-normalised point `points[n, 3]` lies in an
    /// occupied cell (0 outside the grid or for NaN).
    pub fn record_query<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        points: Binding<'a>,
        occupied: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        points.check_fits(3 * n, 4, "query points")?;
        occupied.check_fits(n, 4, "occupancy results")?;
        let b = k::occ_query::Bindings {
            bits: self.bits.binding(),
            query: points,
            occupied,
        };
        rec.dispatch(&self.query, b.into_array(), &self.params(0, n, 0)?, n)
    }
}
