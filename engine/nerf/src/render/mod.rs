//! Rendering on the device: ray generation, stratified sampling, compositing, the photometric,
//! depth and distortion losses, the occupancy grid, and the fused march that samples, queries
//! the field and composites in one kernel (built on the same WGSL functions), and the fused
//! training step that adds the losses and the backward pass to it.

pub mod composite;
pub mod loss;
pub mod march;
pub mod occupancy;
pub mod proposal;
pub mod rays;
pub mod sample;
pub mod train_step;
pub mod visibility;

use bytemuck::Pod;
use extranerf_gpu::kernels::KernelDesc;
use extranerf_gpu::{Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};

use crate::field::mlp::MlpPath;
use crate::model::Field;

/// A fused kernel's cooperative-matrix twin (`common/coop_fused.wgsl`: the fused step's or the
/// march's) and the f16 copy of both MLPs' weights it multiplies with.
#[derive(Debug)]
pub(crate) struct FusedCoop {
    kernel: Kernel,
    to_f16: Kernel,
    /// Both MLPs' weights in f16 (density, then colour), per layer `[outputs][inputs]` padded
    /// to the tile.
    w16: Buffer<u16>,
    tile: u32,
}

impl FusedCoop {
    /// The kernel and its weight conversion for `field`'s MLPs with `tile` x `tile` tiles, from
    /// the 8x8 file's (`descs8`) or the 16x16 file's (`descs16`) `[kernel, conversion]`.
    pub(crate) fn new(
        ctx: &Context,
        field: &Field,
        tile: u32,
        descs8: [&'static KernelDesc; 2],
        descs16: [&'static KernelDesc; 2],
    ) -> Result<FusedCoop> {
        let descs = match tile {
            8 => descs8,
            16 => descs16,
            _ => {
                return Err(GpuError::Usage(format!(
                    "cooperative-matrix tiles of {tile}: the fused kernels exist for 8 and 16"
                )))
            }
        };
        let halves = Self::halves(field, tile);
        Ok(FusedCoop {
            kernel: Kernel::new(ctx, descs[0])?,
            to_f16: Kernel::new(ctx, descs[1])?,
            w16: Buffer::new(ctx, "fused f16 MLP weights", halves.next_multiple_of(2))?,
            tile,
        })
    }

    fn halves(field: &Field, tile: u32) -> usize {
        let cfg = field.config();
        cfg.density_mlp().coop_halves(tile) + cfg.color_mlp().coop_halves(tile)
    }

    /// The MLP path of a fused kernel that has this cooperative-matrix twin, or none.
    pub(crate) fn path(coop: Option<&FusedCoop>) -> MlpPath {
        match coop {
            Some(c) => MlpPath::Coop { tile: c.tile },
            None => MlpPath::Scalar,
        }
    }

    /// Records the f16 copy of `field`'s MLPs from the uniform block `mlp`, then the kernel
    /// over `threads` with its scalar twin's bindings `scalar` (then `w16`) and parameters.
    /// `shapes` are the density and colour MLPs' shape buffers.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub(crate) fn record<'a, P: Pod, const N: usize, const M: usize>(
        &'a self,
        rec: &mut Recorder<'a>,
        field: &Field,
        shapes: [Binding<'a>; 2],
        mlp: Binding<'a>,
        scalar: [Binding<'a>; N],
        params: &P,
        threads: u64,
    ) -> Result<()> {
        let halves = Self::halves(field, self.tile);
        if halves > self.w16.len() {
            return Err(GpuError::Usage(format!(
                "the cooperative-matrix kernels were set up for smaller MLPs ({} f16 weights, these need {halves})",
                self.w16.len()
            )));
        }
        // The conversion's bindings in order (both tile files alike; tested below).
        let to_f16 = [shapes[0], shapes[1], mlp, self.w16.binding()];
        rec.dispatch(&self.to_f16, to_f16, params, self.w16.len() as u64)?;
        let all: [Binding; M] = with_w16(scalar, self.w16.binding());
        rec.dispatch(&self.kernel, all, params, threads)
    }
}

/// The bindings of a fused cooperative-matrix kernel: its scalar twin's, in the same order,
/// then `w16` (binding 21, after every scalar one).
fn with_w16<'a, const N: usize, const M: usize>(
    scalar: [Binding<'a>; N],
    w16: Binding<'a>,
) -> [Binding<'a>; M] {
    const { assert!(M == N + 1) };
    let mut all = [w16; M];
    all[..N].copy_from_slice(&scalar);
    all
}

#[cfg(test)]
mod tests {
    use extranerf_gpu::kernels::render::{
        march, march_coop16, march_coop8, train_step, train_step_coop16, train_step_coop8,
    };
    use extranerf_gpu::kernels::KernelDesc;

    fn names(d: &KernelDesc) -> Vec<(u32, &str)> {
        d.bindings.iter().map(|b| (b.binding, b.name)).collect()
    }

    /// [`super::FusedCoop::record`]'s binding order: each fused cooperative-matrix kernel binds
    /// its scalar twin's bindings (but their given samples), then `w16`; its weight conversion the two MLP shapes, the
    /// uniform block and `w16_out`, in both tile files.
    #[test]
    fn coop_kernels_extend_their_scalar_twins() {
        for (scalar, coop, weights) in [
            (
                &train_step::train_step::DESC,
                [
                    &train_step_coop8::train_step_coop::DESC,
                    &train_step_coop16::train_step_coop::DESC,
                ],
                [
                    &train_step_coop8::step_weights_f16::DESC,
                    &train_step_coop16::step_weights_f16::DESC,
                ],
            ),
            (
                &march::march_render::DESC,
                [
                    &march_coop8::march_render_coop::DESC,
                    &march_coop16::march_render_coop::DESC,
                ],
                [
                    &march_coop8::march_weights_f16::DESC,
                    &march_coop16::march_weights_f16::DESC,
                ],
            ),
        ] {
            // The scalar fused step's and march's given samples (bindings 23 to 25, 14) are
            // their own.
            let mut want: Vec<_> = names(scalar)
                .into_iter()
                .filter(|b| b.0 < 21 && b.1 != "given_t_dt")
                .collect();
            want.push((21, "w16"));
            for c in coop {
                assert_eq!(names(c), want, "{}", c.name);
            }
            for w in weights {
                let got: Vec<&str> = names(w).into_iter().map(|(_, n)| n).collect();
                assert_eq!(
                    got,
                    ["density_shape", "color_shape", "mlp", "w16_out"],
                    "{}",
                    w.name
                );
            }
        }
    }
}
