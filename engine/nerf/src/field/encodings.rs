//! Position contraction and direction encoding on the device (standalone kernels; the fused
//! march shares `common/contract.wgsl` and `common/sh.wgsl`).

use extranerf_gpu::kernels::field::encodings as k;
use extranerf_gpu::{count_u32, Binding, Context, GpuError, Kernel, Recorder, Result};

/// How world positions are mapped into the hash grid's unit cube.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Contraction {
    /// Bounded scene: [-1, 1]^3 (after centring and scaling) maps to [0, 1]^3, outside clamps.
    None = 0,
    /// mip-NeRF 360: Euclidean norm, all of space into the ball of radius 2.
    L2 = 1,
    /// The same with the max norm: all of space into the cube [-2, 2]^3.
    #[cfg_attr(feature = "clap", value(name = "linf"))]
    LInf = 2,
}

impl Contraction {
    /// The name in configs and reports.
    pub fn name(self) -> &'static str {
        match self {
            Contraction::None => "none",
            Contraction::L2 => "l2",
            Contraction::LInf => "linf",
        }
    }
}

/// Where the scene is: world points are mapped as `(x - center) / radius` before contraction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneBox {
    /// Centre.
    pub center: [f32; 3],
    /// Radius of the region modelled at full resolution.
    pub radius: f32,
    /// Contraction of everything else.
    pub contraction: Contraction,
}

/// The encoding kernels.
#[derive(Debug)]
pub struct Encodings {
    contract: Kernel,
    sh: Kernel,
}

impl Encodings {
    /// Builds the kernels.
    pub fn new(ctx: &Context) -> Result<Encodings> {
        Ok(Encodings {
            contract: Kernel::new(ctx, &k::contract::DESC)?,
            sh: Kernel::new(ctx, &k::sh_encode::DESC)?,
        })
    }

    fn params(n: u64, scene: &SceneBox) -> Result<k::Params> {
        if !(scene.radius.is_finite() && scene.radius > 0.0)
            || scene.center.iter().any(|c| !c.is_finite())
        {
            return Err(GpuError::Usage(format!(
                "scene box {scene:?}: the radius must be positive and everything finite"
            )));
        }
        Ok(k::Params {
            n: count_u32(n, "points")?,
            mode: scene.contraction as u32,
            inv_radius: 1.0 / scene.radius,
            _pad: 0,
            center: [scene.center[0], scene.center[1], scene.center[2], 0.0],
        })
    }

    /// Records `contracted[n, 3]` in [0, 1]^3 from world `points[n, 3]`.
    pub fn contract<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        points: Binding<'a>,
        contracted: Binding<'a>,
        n: u64,
        scene: &SceneBox,
    ) -> Result<()> {
        points.check_fits(3 * n, 4, "points")?;
        contracted.check_fits(3 * n, 4, "contracted points")?;
        let b = k::contract::Bindings { points, contracted };
        rec.dispatch(&self.contract, b.into_array(), &Self::params(n, scene)?, n)
    }

    /// Records the 16 degree-4 spherical-harmonics coefficients of each direction
    /// (`dirs[n, 3]`, any length; zero or non-finite vectors count as +z) into `sh[n, 16]`.
    pub fn sh<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        dirs: Binding<'a>,
        sh: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        dirs.check_fits(3 * n, 4, "directions")?;
        sh.check_fits(16 * n, 4, "SH coefficients")?;
        let scene = SceneBox {
            center: [0.0; 3],
            radius: 1.0,
            contraction: Contraction::None,
        };
        let b = k::sh_encode::Bindings { points: dirs, sh };
        rec.dispatch(&self.sh, b.into_array(), &Self::params(n, &scene)?, n)
    }
}
