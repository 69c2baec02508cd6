//! Plane-sweep multi-view stereo on the device (`kernels/wgsl/depth/mvs.wgsl`): a dense depth
//! prior for the input views without SPARF. Per reference view, a sweep over fronto-parallel
//! planes scores windows by NCC against the other views (winner-take-all in registers, parabola
//! refinement, a confidence per pixel); a multi-view consistency pass then keeps the depths
//! that other views' depth maps agree with.

use extranerf_gpu::kernels::depth::mvs as k;
use extranerf_gpu::{count_u32, Buffer, Context, GpuError, Kernel, Result};

use crate::data::Camera;
use crate::render::rays::{gpu_camera, GpuCamera};

/// Largest window radius.
pub const MAX_RADIUS: u32 = 3;
/// Most views one sweep can use (a 32-bit mask selects them).
pub const MAX_VIEWS: usize = 32;

/// Plane-sweep settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MvsConfig {
    /// Depth planes, uniform in inverse depth from `near` to `far`.
    pub planes: u32,
    /// Nearest plane (depth along the reference camera's viewing axis).
    pub near: f32,
    /// Farthest plane.
    pub far: f32,
    /// Window radius: (2 radius + 1)^2 pixels (at most 3).
    pub radius: u32,
    /// Sources averaged per plane: the lowest costs count (robust to occlusion; at most 8).
    pub best_k: u32,
    /// Sources whose depth must agree for a pixel to be kept.
    pub min_agree: u32,
    /// Agreement: reprojection error in pixels.
    pub px_tol: f32,
    /// Agreement: relative depth difference.
    pub rel_tol: f32,
}

impl MvsConfig {
    /// Defaults for a scene whose depths lie in [near, far].
    pub fn new(near: f32, far: f32) -> MvsConfig {
        MvsConfig {
            planes: 64,
            near,
            far,
            radius: 2,
            best_k: 2,
            min_agree: 1,
            px_tol: 1.0,
            rel_tol: 0.01,
        }
    }

    fn validate(&self, views: usize) -> Result<()> {
        let bad = |m: String| Err(GpuError::Usage(format!("multi-view stereo: {m}")));
        if self.planes < 2 {
            return bad(format!("{} planes; use at least 2", self.planes));
        }
        if !(self.near > 0.0 && self.far > self.near && self.far.is_finite()) {
            return bad(format!(
                "depth range {} to {}: need 0 < near < far < infinity",
                self.near, self.far
            ));
        }
        if self.radius > MAX_RADIUS {
            return bad(format!("window radius {} above {MAX_RADIUS}", self.radius));
        }
        if !(1..=8).contains(&self.best_k) {
            return bad(format!("best_k {} outside 1..=8", self.best_k));
        }
        if !(self.px_tol >= 0.0 && self.rel_tol >= 0.0) {
            return bad("negative agreement tolerances".into());
        }
        if !(2..=MAX_VIEWS).contains(&views) {
            return bad(format!("{views} views; use 2 to {MAX_VIEWS}"));
        }
        Ok(())
    }
}

/// One view's result.
#[derive(Clone, Debug, PartialEq)]
pub struct MvsDepth {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Winner-take-all depth before the consistency check (0: no match).
    pub raw_depth: Vec<f32>,
    /// Its confidence (the winning NCC clamped to [0, 1]).
    pub raw_confidence: Vec<f32>,
    /// Depth kept by the consistency check (0: none).
    pub depth: Vec<f32>,
    /// Confidence of `depth` in [0, 1] (the winning NCC; 0 where no depth).
    pub confidence: Vec<f32>,
}

impl MvsDepth {
    /// Fraction of pixels with a kept depth.
    pub fn coverage(&self) -> f64 {
        self.depth.iter().filter(|&&d| d > 0.0).count() as f64 / self.depth.len().max(1) as f64
    }
}

/// The kernels.
#[derive(Debug)]
pub struct Mvs {
    sweep: Kernel,
    consistency: Kernel,
}

impl Mvs {
    /// Builds the kernels.
    pub fn new(ctx: &Context) -> Result<Mvs> {
        Ok(Mvs {
            sweep: Kernel::new(ctx, &k::mvs_sweep::DESC)?,
            consistency: Kernel::new(ctx, &k::mvs_consistency::DESC)?,
        })
    }

    /// Depth for every view against all the others. `cams` and `grey` (one luminance image per
    /// view) must share one size. The sweeps run first, one submission per view; then every
    /// consistency pass in one submission.
    pub fn run(
        &self,
        ctx: &Context,
        cams: &[Camera],
        grey: &[Vec<f32>],
        cfg: &MvsConfig,
    ) -> Result<Vec<MvsDepth>> {
        cfg.validate(cams.len())?;
        if grey.len() != cams.len() {
            return Err(GpuError::Usage(format!(
                "multi-view stereo: {} cameras but {} images",
                cams.len(),
                grey.len()
            )));
        }
        let (w, h) = (cams[0].width, cams[0].height);
        let n = w as u64 * h as u64;
        for (i, (c, g)) in cams.iter().zip(grey).enumerate() {
            if c.width != w || c.height != h || g.len() as u64 != n {
                return Err(GpuError::Usage(format!(
                    "multi-view stereo: view {i} is {}x{} with {} pixels; every view must be {w}x{h}",
                    c.width,
                    c.height,
                    g.len()
                )));
            }
        }
        let views = cams.len();
        count_u32(n * views as u64, "multi-view stereo pixels")?;
        let gpu: Vec<GpuCamera> = cams.iter().map(gpu_camera).collect();
        let cam_buf = Buffer::from_slice(ctx, "mvs cameras", &gpu)?;
        let all: Vec<f32> = grey.iter().flatten().copied().collect();
        let grey_buf = Buffer::from_slice(ctx, "mvs grey images", &all)?;
        let depths = Buffer::<f32>::new(ctx, "mvs depths", n as usize * views)?;
        let confs = Buffer::<f32>::new(ctx, "mvs confidences", n as usize * views)?;
        let out_d = Buffer::<f32>::new(ctx, "mvs kept depths", n as usize * views)?;
        let out_c = Buffer::<f32>::new(ctx, "mvs kept confidences", n as usize * views)?;
        let mask = if views >= 32 {
            u32::MAX
        } else {
            (1u32 << views) - 1
        };
        let params = |r: usize| k::Params {
            n: n as u32,
            width: w,
            height: h,
            ref_view: r as u32,
            src_mask: mask,
            n_views: views as u32,
            planes: cfg.planes,
            radius: cfg.radius,
            near: cfg.near,
            far: cfg.far,
            best_k: cfg.best_k,
            min_agree: cfg.min_agree,
            px_tol: cfg.px_tol,
            rel_tol: cfg.rel_tol,
            _pad0: 0,
            _pad1: 0,
        };
        // One view per submission: a sweep takes seconds on a CPU device.
        for r in 0..views {
            let mut rec = ctx.recorder("mvs sweep")?;
            let b = k::mvs_sweep::Bindings {
                cams: cam_buf.binding(),
                grey: grey_buf.binding(),
                depths: depths.binding(),
                confs: confs.binding(),
            };
            rec.dispatch(&self.sweep, b.into_array(), &params(r), n)?;
            ctx.run(rec)?;
        }
        let mut rec = ctx.recorder("mvs consistency")?;
        for r in 0..views {
            let b = k::mvs_consistency::Bindings {
                cams: cam_buf.binding(),
                depths: depths.binding(),
                confs: confs.binding(),
                out_depth: out_d.binding(),
                out_conf: out_c.binding(),
            };
            rec.dispatch(&self.consistency, b.into_array(), &params(r), n)?;
        }
        ctx.run(rec)?;
        let (raw, raw_conf) = (depths.read()?, confs.read()?);
        let (kept, conf) = (out_d.read()?, out_c.read()?);
        let n = n as usize;
        Ok((0..views)
            .map(|r| MvsDepth {
                width: w,
                height: h,
                raw_depth: raw[r * n..(r + 1) * n].to_vec(),
                raw_confidence: raw_conf[r * n..(r + 1) * n].to_vec(),
                depth: kept[r * n..(r + 1) * n].to_vec(),
                confidence: conf[r * n..(r + 1) * n].to_vec(),
            })
            .collect())
    }
}
