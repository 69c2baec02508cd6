//! Ray generation from the loaded cameras, in world space or NeRF's NDC.

use extranerf_gpu::kernels::render::rays as k;
use extranerf_gpu::{count_u32, Binding, Context, GpuError, Kernel, Recorder, Result};

pub use k::GpuCamera;

use crate::data::Camera;

/// The device form of a camera (f32 rows of camera-to-world, intrinsics, size).
pub fn gpu_camera(c: &Camera) -> GpuCamera {
    let m = c.c2w;
    let row = |r: usize| {
        [
            m.x_axis[r] as f32,
            m.y_axis[r] as f32,
            m.z_axis[r] as f32,
            m.w_axis[r] as f32,
        ]
    };
    GpuCamera {
        c2w0: row(0),
        c2w1: row(1),
        c2w2: row(2),
        intr: [c.fx as f32, c.fy as f32, c.cx as f32, c.cy as f32],
        size: [c.width, c.height, 0, 0],
    }
}

/// The ray-generation kernel.
#[derive(Debug)]
pub struct RayGen {
    kernel: Kernel,
}

/// Where rays live.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RaySpace {
    /// World space; t is depth along each camera's viewing axis.
    World,
    /// NeRF's NDC for forward-facing scenes with the given near plane (NeRF: 1).
    Ndc {
        /// Near plane distance.
        near: f32,
    },
}

impl RayGen {
    /// Builds the kernel.
    pub fn new(ctx: &Context) -> Result<RayGen> {
        Ok(RayGen {
            kernel: Kernel::new(ctx, &k::generate_rays::DESC)?,
        })
    }

    /// Records `n` rays for `pixels[n]` = (camera index, y * width + x): `origins[n]` (xyz, 0)
    /// and `directions[n]` (xyz, length). Out-of-range indices give zero rays.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn generate<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        cameras: Binding<'a>,
        n_cameras: u32,
        pixels: Binding<'a>,
        origins: Binding<'a>,
        directions: Binding<'a>,
        n: u64,
        space: RaySpace,
    ) -> Result<()> {
        cameras.check_fits(
            n_cameras as u64,
            std::mem::size_of::<GpuCamera>() as u64,
            "cameras",
        )?;
        pixels.check_fits(2 * n, 4, "ray pixels")?;
        origins.check_fits(4 * n, 4, "ray origins")?;
        directions.check_fits(4 * n, 4, "ray directions")?;
        let (ndc, near) = match space {
            RaySpace::World => (0, 0.0),
            RaySpace::Ndc { near } if near > 0.0 && near.is_finite() => (1, near),
            RaySpace::Ndc { near } => {
                return Err(GpuError::Usage(format!(
                    "NDC near plane {near} must be positive"
                )))
            }
        };
        let p = k::Params {
            n: count_u32(n, "rays")?,
            ndc,
            near,
            n_cameras,
        };
        let b = k::generate_rays::Bindings {
            cameras,
            pixels,
            origins,
            directions,
        };
        rec.dispatch(&self.kernel, b.into_array(), &p, n)
    }
}
