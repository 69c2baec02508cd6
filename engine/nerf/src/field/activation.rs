//! Output activations of the field: truncated exponential (density) and sigmoid (colour).

use extranerf_gpu::kernels::field::activation as k;
use extranerf_gpu::{count_u32, Binding, Context, GpuError, Kernel, Recorder, Result};

/// Which activation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    /// exp(min(x, 15)), with the gradient truncated alike (Instant-NGP's density).
    TruncExp = 0,
    /// 1 / (1 + exp(-x)).
    Sigmoid = 1,
}

/// Where the inputs sit: element i is `x[i * stride + offset]` (a column of an MLP output).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Column {
    /// Floats between consecutive elements.
    pub stride: u32,
    /// Index of the first element.
    pub offset: u32,
}

/// The activation kernels.
#[derive(Debug)]
pub struct Activations {
    fwd: Kernel,
    bwd: Kernel,
}

fn params(n: u64, kind: Activation, col: Column) -> Result<k::Params> {
    if col.stride == 0 || col.offset >= col.stride {
        return Err(GpuError::Usage(format!(
            "activation column {col:?}: need offset < stride"
        )));
    }
    let n = count_u32(n, "activation elements")?;
    Ok(k::Params {
        n,
        kind: kind as u32,
        stride: col.stride,
        offset: col.offset,
    })
}

impl Activations {
    /// Builds the kernels.
    pub fn new(ctx: &Context) -> Result<Activations> {
        Ok(Activations {
            fwd: Kernel::new(ctx, &k::activation_fwd::DESC)?,
            bwd: Kernel::new(ctx, &k::activation_bwd::DESC)?,
        })
    }

    /// Records `y[i] = act(x[i * stride + offset])` for `i < n`.
    pub fn forward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        kind: Activation,
        x: Binding<'a>,
        col: Column,
        y: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        let p = params(n, kind, col)?;
        x.check_fits(
            n.saturating_sub(1) * col.stride as u64 + col.offset as u64 + u64::from(n > 0),
            4,
            "activation input",
        )?;
        y.check_fits(n, 4, "activation output")?;
        rec.dispatch(
            &self.fwd,
            k::activation_fwd::Bindings { x, y }.into_array(),
            &p,
            n,
        )
    }

    /// Records `dx[i * stride + offset] = dy[i] * act'(x[i * stride + offset])`.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn backward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        kind: Activation,
        x: Binding<'a>,
        col: Column,
        dy: Binding<'a>,
        dx: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        let p = params(n, kind, col)?;
        let span = n.saturating_sub(1) * col.stride as u64 + col.offset as u64 + u64::from(n > 0);
        x.check_fits(span, 4, "activation input")?;
        dx.check_fits(span, 4, "activation input gradient")?;
        dy.check_fits(n, 4, "activation output gradient")?;
        rec.dispatch(
            &self.bwd,
            k::activation_bwd::Bindings { x, dy, dx }.into_array(),
            &p,
            n,
        )
    }
}
