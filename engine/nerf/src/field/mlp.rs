//! Tiny fully connected networks (hidden width <= 64, ReLU, linear output) on the device:
//! forward, backward to the inputs, and weight gradients. The fused march kernels share the
//! WGSL layout (`common/mlp.wgsl`).

use extranerf_gpu::kernels::field::mlp as k;
use extranerf_gpu::kernels::field::mlp_f16 as k16;
use extranerf_gpu::{count_u32, Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};

/// The identity table that the push constants of every kernel evaluating MLPs from the uniform
/// weight block carry as `lut` (`mlp_uni` in `kernels/wgsl/common/mlp_block.wgsl`: weight
/// offsets rebuilt from it count as uniform across lanes on lavapipe, so their loads run once
/// per SIMD group instead of once per lane).
pub const UNIFORM_LUT: [u32; 4] = [0, 1, 2, 3];

pub use k::MlpShape;

/// Layer widths: `[inputs, hidden..., outputs]`, 1 to 4 layers, every width 1..=64.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MlpConfig {
    /// Widths.
    pub dims: Vec<u32>,
}

/// Point groups per weight block in the weight-gradient pass (at least the subgroup size, so
/// the lanes of a subgroup share a block and sum before their atomics).
pub const WGRAD_GROUPS: u32 = 16;

/// Floats of the uniform weight block (64 KiB, the smallest `maxUniformBufferRange` Vulkan
/// allows); see `common/mlp_block.wgsl`.
pub const BLOCK_FLOATS: usize = 16384;

impl MlpConfig {
    /// Checks the limits of the kernels.
    pub fn validate(&self) -> Result<()> {
        if !(2..=5).contains(&self.dims.len()) || self.dims.iter().any(|&d| d == 0 || d > 64) {
            return Err(GpuError::Usage(format!(
                "MLP widths {:?}: give 2 to 5 widths, each 1 to 64",
                self.dims
            )));
        }
        Ok(())
    }

    /// Number of layers.
    pub fn layers(&self) -> usize {
        self.dims.len() - 1
    }

    /// Float offset of layer `l`'s weights (its bias follows them).
    pub fn offset(&self, l: usize) -> usize {
        (0..l)
            .map(|k| (self.dims[k] as usize + 1) * self.dims[k + 1] as usize)
            .sum()
    }

    /// True when every layer's input width and weight offset are multiples of 4, so the
    /// weights can be read as vec4 rows from a uniform block (`common/mlp_block.wgsl`).
    pub fn vec4_rows(&self) -> bool {
        (0..self.layers())
            .all(|l| self.dims[l].is_multiple_of(4) && self.offset(l).is_multiple_of(4))
    }

    /// Weights and biases of all layers.
    pub fn param_count(&self) -> usize {
        self.offset(self.layers())
    }

    /// Floats per point the backward pass saves: per layer its input and the gradient of its
    /// pre-activation, each padded to a multiple of 4 floats (read as vec4s).
    pub fn saved_stride(&self) -> usize {
        self.dims
            .windows(2)
            .map(|w| (w[0].next_multiple_of(4) + w[1].next_multiple_of(4)) as usize)
            .sum()
    }

    /// Weight blocks of the f16 record's weight-gradient pass: per layer 4-row blocks times
    /// (4-column blocks + one bias column).
    fn wgrad_blocks(&self) -> u64 {
        self.dims
            .windows(2)
            .map(|w| (w[1].div_ceil(4) * (w[0].div_ceil(4) + 1)) as u64)
            .sum()
    }

    /// Weight blocks of the f32 record's weight-gradient pass: per layer 4-row blocks times
    /// (16-column blocks + one bias column).
    fn wgrad_blocks_wide(&self) -> u64 {
        self.dims
            .windows(2)
            .map(|w| (w[1].div_ceil(4) * (w[0].next_multiple_of(4).div_ceil(16) + 1)) as u64)
            .sum()
    }

    fn shape(&self) -> MlpShape {
        let d = |i: usize| self.dims.get(i).copied().unwrap_or(0);
        MlpShape {
            dims: [d(0), d(1), d(2), d(3)],
            dims_hi: [d(4), 0, 0, 0],
            layers: self.layers() as u32,
            params: self.param_count() as u32,
            _pad0: 0,
            _pad1: 0,
        }
    }
}

/// The MLP kernels for one configuration.
#[derive(Debug)]
pub struct Mlp {
    config: MlpConfig,
    shape: Buffer<MlpShape>,
    fwd: Kernel,
    bwd: Kernel,
    wgrad: Kernel,
    /// Point groups per weight block of the weight-gradient pass.
    groups: u32,
    /// The uniform-block kernels and their weight block, when the shape suits them.
    block: Option<Block>,
    /// The backward kernels with an f16 record, when enabled ([`Mlp::with_f16`]).
    f16: Option<F16>,
}

/// The backward pass with the saved record in f16 (`field/mlp_f16.wgsl`).
#[derive(Debug)]
struct F16 {
    bwd: Kernel,
    wgrad: Kernel,
}

#[derive(Debug)]
struct Block {
    fwd: Kernel,
    bwd: Kernel,
    weights: Buffer<f32>,
}

impl Block {
    /// Records the copy of `weights` into the uniform block; returns the block's binding.
    fn load<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        weights: Binding<'a>,
        config: &MlpConfig,
    ) -> Result<Binding<'a>> {
        let block = self.weights.binding();
        rec.copy(weights, 0, block, 0, config.param_count() as u64 * 4)?;
        Ok(block)
    }
}

impl Mlp {
    /// Builds the kernels.
    pub fn new(ctx: &Context, config: MlpConfig) -> Result<Mlp> {
        Self::build(ctx, config, true)
    }

    /// The storage-buffer kernels only, even where the uniform-block ones apply: the
    /// reference path for benchmarks and tests.
    pub fn with_storage_kernels(ctx: &Context, config: MlpConfig) -> Result<Mlp> {
        Self::build(ctx, config, false)
    }

    fn build(ctx: &Context, config: MlpConfig, allow_block: bool) -> Result<Mlp> {
        config.validate()?;
        let block = if allow_block && config.vec4_rows() && config.param_count() <= BLOCK_FLOATS {
            Some(Block {
                fwd: Kernel::new(ctx, &k::mlp_fwd_block::DESC)?,
                bwd: Kernel::new(ctx, &k::mlp_bwd_data_block::DESC)?,
                weights: Buffer::new(ctx, "mlp weight block", BLOCK_FLOATS)?,
            })
        } else {
            None
        };
        Ok(Mlp {
            block,
            f16: None,
            groups: WGRAD_GROUPS.max(ctx.info().subgroup_size),
            shape: Buffer::from_slice(ctx, "mlp shape", &[config.shape()])?,
            config,
            fwd: Kernel::new(ctx, &k::mlp_fwd::DESC)?,
            bwd: Kernel::new(ctx, &k::mlp_bwd_data::DESC)?,
            wgrad: Kernel::new(ctx, &k::mlp_wgrad::DESC)?,
        })
    }

    /// Stores the backward pass's saved record (every layer's input and pre-activation
    /// gradient) in f16 with a power-of-two scale per point and segment, half the bytes of the
    /// f32 record; arithmetic and the forward pass stay f32. Needs the uniform-block shape
    /// ([`Mlp::uses_block`]); the values are packed into words, so any device runs it.
    pub fn with_f16(mut self, ctx: &Context) -> Result<Mlp> {
        if self.block.is_none() {
            return Err(GpuError::Usage(format!(
                "the f16 MLP record needs widths and offsets in multiples of 4 and at most {BLOCK_FLOATS} parameters; {:?} has {}",
                self.config.dims,
                self.config.param_count()
            )));
        }
        self.f16 = Some(F16 {
            bwd: Kernel::new(ctx, &k16::mlp_bwd_data_f16::DESC)?,
            wgrad: Kernel::new(ctx, &k16::mlp_wgrad_f16::DESC)?,
        });
        Ok(self)
    }

    /// True when the backward pass keeps its record in f16.
    pub fn is_f16(&self) -> bool {
        self.f16.is_some()
    }

    /// 32-bit words per point of the backward pass's `saved` scratch: the f32 record
    /// ([`MlpConfig::saved_stride`]), or the f16 one (half of it plus a 4-word header).
    pub fn saved_words(&self) -> usize {
        let f = self.config.saved_stride();
        if self.f16.is_some() {
            f / 2 + 4
        } else {
            f
        }
    }

    /// The shape record on the device (common/mlp.wgsl's `MlpShape`).
    pub fn shape(&self) -> &Buffer<MlpShape> {
        &self.shape
    }

    /// True when the uniform-block kernels run this MLP (see `common/mlp_block.wgsl`).
    pub fn uses_block(&self) -> bool {
        self.block.is_some()
    }

    /// Records only the weight-gradient pass over `n` points whose f32 records (every layer's
    /// input and pre-activation gradient, [`MlpConfig::saved_stride`] floats per point) another
    /// kernel wrote into `saved`, such as the fused training step: adds the parameter gradient
    /// to `d_weights`.
    pub fn weight_gradient<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        saved: Binding<'a>,
        d_weights: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        let c = &self.config;
        if self.f16.is_some() {
            return Err(GpuError::Usage(
                "the weight-gradient pass over external records reads the f32 record; this MLP keeps an f16 one".into(),
            ));
        }
        d_weights.check_fits(c.param_count() as u64, 4, "MLP weight gradients")?;
        saved.check_fits(n * c.saved_stride() as u64, 4, "MLP records")?;
        let mut p = self.params(n)?;
        p.saved_stride = c.saved_stride() as u32;
        let b = k::mlp_wgrad::Bindings {
            shape_buf: self.shape.binding(),
            d_weights,
            saved4: saved,
        };
        rec.dispatch(
            &self.wgrad,
            b.into_array(),
            &p,
            c.wgrad_blocks_wide() * self.groups as u64,
        )
    }

    /// The configuration.
    pub fn config(&self) -> &MlpConfig {
        &self.config
    }

    fn params(&self, n: u64) -> Result<k::Params> {
        let n32 = count_u32(n, "MLP points")?;
        Ok(k::Params {
            n: n32,
            chunk: n32.div_ceil(self.groups).max(1),
            // In units of 4 f16 values for the f16 record (its words / 2).
            saved_stride: if self.f16.is_some() {
                self.saved_words() as u32 / 2
            } else {
                self.saved_words() as u32
            },
            groups: self.groups,
            lut: UNIFORM_LUT,
        })
    }

    /// Records `outputs[n, out] = mlp(inputs[n, in])`.
    pub fn forward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        weights: Binding<'a>,
        inputs: Binding<'a>,
        outputs: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        let c = &self.config;
        weights.check_fits(c.param_count() as u64, 4, "MLP weights")?;
        inputs.check_fits(n * c.dims[0] as u64, 4, "MLP inputs")?;
        outputs.check_fits(n * c.dims[c.layers()] as u64, 4, "MLP outputs")?;
        if let Some(block) = &self.block {
            let block_weights = block.load(rec, weights, c)?;
            let b = k::mlp_fwd_block::Bindings {
                shape_buf: self.shape.binding(),
                inputs,
                outputs,
                mlp: block_weights,
            };
            return rec.dispatch(&block.fwd, b.into_array(), &self.params(n)?, n);
        }
        let b = k::mlp_fwd::Bindings {
            shape_buf: self.shape.binding(),
            weights,
            inputs,
            outputs,
        };
        rec.dispatch(&self.fwd, b.into_array(), &self.params(n)?, n)
    }

    /// Records the backward pass for `d_outputs[n, out]`: writes `d_inputs[n, in]` and adds
    /// the parameter gradient to `d_weights` (zero it first for a fresh gradient). `saved`
    /// holds `n * saved_words()` words of scratch.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand of the backward pass
    pub fn backward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        weights: Binding<'a>,
        inputs: Binding<'a>,
        d_outputs: Binding<'a>,
        d_inputs: Binding<'a>,
        saved: Binding<'a>,
        d_weights: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        let c = &self.config;
        weights.check_fits(c.param_count() as u64, 4, "MLP weights")?;
        d_weights.check_fits(c.param_count() as u64, 4, "MLP weight gradients")?;
        inputs.check_fits(n * c.dims[0] as u64, 4, "MLP inputs")?;
        d_inputs.check_fits(n * c.dims[0] as u64, 4, "MLP input gradients")?;
        d_outputs.check_fits(n * c.dims[c.layers()] as u64, 4, "MLP output gradients")?;
        saved.check_fits(
            n * self.saved_words() as u64,
            4,
            "MLP saved activations (process fewer points per call)",
        )?;
        let p = self.params(n)?;
        let shape_buf = self.shape.binding();
        if let (Some(f16), Some(block)) = (&self.f16, &self.block) {
            let b = k16::mlp_bwd_data_f16::Bindings {
                shape_buf,
                inputs,
                d_outputs,
                d_inputs,
                saved,
                mlp: block.load(rec, weights, c)?,
            };
            rec.dispatch(&f16.bwd, b.into_array(), &p, n)?;
            let b = k16::mlp_wgrad_f16::Bindings {
                shape_buf,
                saved,
                d_weights,
            };
            let threads = c.wgrad_blocks() * self.groups as u64;
            return rec.dispatch(&f16.wgrad, b.into_array(), &p, threads);
        }
        if let Some(block) = &self.block {
            let block_weights = block.load(rec, weights, c)?;
            let b = k::mlp_bwd_data_block::Bindings {
                shape_buf,
                inputs,
                d_outputs,
                d_inputs,
                saved,
                mlp: block_weights,
            };
            rec.dispatch(&block.bwd, b.into_array(), &p, n)?;
        } else {
            let b = k::mlp_bwd_data::Bindings {
                shape_buf,
                weights,
                inputs,
                d_outputs,
                d_inputs,
                saved,
            };
            rec.dispatch(&self.bwd, b.into_array(), &p, n)?;
        }
        let b = k::mlp_wgrad::Bindings {
            shape_buf,
            d_weights,
            saved4: saved,
        };
        rec.dispatch(
            &self.wgrad,
            b.into_array(),
            &p,
            c.wgrad_blocks_wide() * self.groups as u64,
        )
    }
}
