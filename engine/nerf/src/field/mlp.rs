//! Tiny fully connected networks (hidden width <= 64, ReLU, linear output) on the device:
//! forward, backward to the inputs, and weight gradients. The fused march kernels share the
//! WGSL layout (`common/mlp.wgsl`).

use extranerf_gpu::kernels::field::mlp as k;
use extranerf_gpu::kernels::field::mlp_coop16 as kc16;
use extranerf_gpu::kernels::field::mlp_coop8 as kc8;
use extranerf_gpu::kernels::field::mlp_f16 as k16;
use extranerf_gpu::{count_u32, Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};
use serde::{Deserialize, Serialize};

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

/// Fewest points per chunk of the weight-gradient pass (`common/mlp_wgrad.wgsl`): every chunk
/// adds each gradient once with an f32 atomic, so a chunk's FMAs should outweigh them.
pub const WGRAD_CHUNK: u32 = 4096;

/// Most chunks of the weight-gradient pass: past it the chunks grow instead.
pub const WGRAD_MAX_CHUNKS: u32 = 64;

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

    /// Elements of the f16 copy of the weights that the cooperative-matrix kernels multiply
    /// with (`common/coop_tiles.wgsl`): per layer `[outputs][inputs]`, both rounded up to
    /// `tile`.
    pub fn coop_halves(&self, tile: u32) -> usize {
        self.dims
            .windows(2)
            .map(|w| (w[0].next_multiple_of(tile) * w[1].next_multiple_of(tile)) as usize)
            .sum()
    }

    /// Floats per point the backward pass saves: per layer its input and the gradient of its
    /// pre-activation, each padded to a multiple of 4 floats (read as vec4s).
    pub fn saved_stride(&self) -> usize {
        self.dims
            .windows(2)
            .map(|w| (w[0].next_multiple_of(4) + w[1].next_multiple_of(4)) as usize)
            .sum()
    }

    /// Tiles of the weight-gradient pass per chunk of points (`common/mlp_wgrad.wgsl`): per
    /// layer, its outputs in blocks of 16 rows times its inputs in blocks of 16 columns.
    fn wgrad_tiles(&self) -> u64 {
        self.dims
            .windows(2)
            .map(|w| (w[1].div_ceil(16) * w[0].div_ceil(16)) as u64)
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

/// How the MLPs' matrix products run, as the command line (`--mlp`) and configs name it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum MlpMode {
    /// Cooperative matrices where a GPU offers a usable shape and the model keeps f32
    /// records; the scalar kernels otherwise, and on CPU devices (lavapipe emulates the tiles:
    /// its cooperative-matrix step and march measured slower than the scalar ones,
    /// `results/mlp_coop_lavapipe/`).
    #[default]
    Auto,
    /// Cooperative matrices (`VK_KHR_cooperative_matrix`, f16 inputs, f32 accumulation); an
    /// error where the device or the model cannot use them.
    Coop,
    /// Per-thread f32 arithmetic.
    Scalar,
}

impl MlpMode {
    /// The name in configs and reports.
    pub fn name(self) -> &'static str {
        match self {
            MlpMode::Auto => "auto",
            MlpMode::Coop => "coop",
            MlpMode::Scalar => "scalar",
        }
    }

    /// The path this mode takes on `ctx`'s device for MLPs whose backward record is f16
    /// (`f16_record`) or f32. `Coop` where it cannot run is an error naming the reason.
    pub fn resolve(self, ctx: &Context, f16_record: bool) -> Result<MlpPath> {
        let info = ctx.info();
        let tile = info.coop_tile();
        match (self, tile) {
            (MlpMode::Scalar, _) => Ok(MlpPath::Scalar),
            (MlpMode::Auto, Some(tile)) if !f16_record && !info.is_cpu() => {
                Ok(MlpPath::Coop { tile })
            }
            (MlpMode::Auto, _) => Ok(MlpPath::Scalar),
            (MlpMode::Coop, Some(_)) if f16_record => Err(GpuError::Usage(
                "--mlp coop reads the MLPs' f32 backward records; precision f16 keeps f16 ones (use --precision f32 or --mlp scalar)".into(),
            )),
            (MlpMode::Coop, Some(tile)) => Ok(MlpPath::Coop { tile }),
            (MlpMode::Coop, None) => {
                let offered = if info.coop_matrix.is_empty() {
                    "it does not offer VK_KHR_cooperative_matrix".to_string()
                } else {
                    let shapes: Vec<String> =
                        info.coop_matrix.iter().map(|s| s.to_string()).collect();
                    format!("it offers only {}", shapes.join(", "))
                };
                Err(GpuError::MissingFeature {
                    device: info.name.clone(),
                    what: format!(
                        "cooperative matrices with 8x8x8 or 16x16x16 f16*f16+f32 subgroup tiles ({offered})"
                    ),
                    needed_by: "--mlp coop (use --mlp scalar or auto)".into(),
                })
            }
        }
    }
}

/// The MLP path that runs, once [`MlpMode`] is resolved on a device.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MlpPath {
    /// Per-thread f32 arithmetic.
    Scalar,
    /// Cooperative matrices with `tile` x `tile` x `tile` f16 tiles and f32 accumulators.
    Coop {
        /// Tile edge: 8 (lavapipe) or 16 (NVIDIA).
        tile: u32,
    },
}

impl std::fmt::Display for MlpPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MlpPath::Scalar => write!(f, "scalar f32"),
            MlpPath::Coop { tile } => {
                write!(f, "cooperative matrix {tile}x{tile}x{tile} f16*f16+f32")
            }
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
    /// The uniform-block kernels and their weight block, when the shape suits them.
    block: Option<Block>,
    /// The backward kernels with an f16 record, when enabled ([`Mlp::with_f16`]).
    f16: Option<F16>,
    /// The cooperative-matrix weight gradient, when enabled ([`Mlp::set_path`]).
    coop: Option<Coop>,
}

/// The MLP through cooperative matrices (`common/mlp_coop.wgsl`): forward, backward to the
/// inputs, weight gradient, and the f16 copy of the weights they multiply with.
#[derive(Debug)]
struct Coop {
    wgrad: Kernel,
    fwd: Kernel,
    bwd: Kernel,
    to_f16: Kernel,
    /// The weights in f16, per layer `[outputs][inputs]` padded to the tile.
    w16: Buffer<u16>,
    /// Bound as the forward kernel's `saved`, which it never writes (its record flag is off).
    no_record: Buffer<f32>,
    tile: u32,
}

impl Coop {
    fn new(ctx: &Context, config: &MlpConfig, tile: u32) -> Result<Coop> {
        let descs = match tile {
            8 => [
                &kc8::mlp_wgrad_coop::DESC,
                &kc8::mlp_fwd_coop::DESC,
                &kc8::mlp_bwd_data_coop::DESC,
                &kc8::mlp_weights_to_f16::DESC,
            ],
            16 => [
                &kc16::mlp_wgrad_coop::DESC,
                &kc16::mlp_fwd_coop::DESC,
                &kc16::mlp_bwd_data_coop::DESC,
                &kc16::mlp_weights_to_f16::DESC,
            ],
            _ => {
                return Err(GpuError::Usage(format!(
                    "cooperative-matrix tiles of {tile}: the kernels exist for 8 and 16"
                )))
            }
        };
        let halves = config.coop_halves(tile);
        Ok(Coop {
            wgrad: Kernel::new(ctx, descs[0])?,
            fwd: Kernel::new(ctx, descs[1])?,
            bwd: Kernel::new(ctx, descs[2])?,
            to_f16: Kernel::new(ctx, descs[3])?,
            w16: Buffer::new(ctx, "mlp f16 weights", halves.next_multiple_of(2))?,
            no_record: Buffer::new(ctx, "mlp forward without records", 4)?,
            tile,
        })
    }

    fn params(&self, n: u64, chunk: u64, saved_stride: usize) -> Result<kc8::Params> {
        Ok(kc8::Params {
            n: count_u32(n, "MLP points")?,
            chunk: count_u32(chunk, "MLP points per workgroup")?,
            saved_stride: saved_stride as u32,
            _pad: 0,
        })
    }

    /// Records a kernel of the tile's file with the 8x8 file's parameters and binding order
    /// (both files are the same source, `common/mlp_coop.wgsl`).
    fn dispatch<'a, const N: usize>(
        &'a self,
        rec: &mut Recorder<'a>,
        kernel: &'a Kernel,
        bindings: [Binding<'a>; N],
        p: &kc8::Params,
        threads: u64,
    ) -> Result<()> {
        if self.tile == 8 {
            rec.dispatch(kernel, bindings, p, threads)
        } else {
            let p = kc16::Params {
                n: p.n,
                chunk: p.chunk,
                saved_stride: p.saved_stride,
                _pad: 0,
            };
            rec.dispatch(kernel, bindings, &p, threads)
        }
    }

    /// Records the f16 copy of `weights`.
    fn load_weights<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        shape: Binding<'a>,
        weights: Binding<'a>,
    ) -> Result<()> {
        let b = kc8::mlp_weights_to_f16::Bindings {
            shape_buf: shape,
            weights,
            w16_out: self.w16.binding(),
        };
        let p = self.params(0, 0, 0)?;
        self.dispatch(rec, &self.to_f16, b.into_array(), &p, self.w16.len() as u64)
    }
}

/// Workgroups of the cooperative-matrix weight gradient (each adds its sums with one atomic per
/// parameter): at most this many, each at least one block of points.
pub const COOP_WORKGROUPS: u64 = 64;

/// Points per block of the cooperative-matrix weight gradient (its workgroup size).
const COOP_POINTS: u64 = 32;

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
            coop: None,
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

    /// Selects the path of the forward pass, the backward pass and the weight gradient (see
    /// [`MlpPath`]); the f16 record has only the scalar one.
    pub fn set_path(&mut self, ctx: &Context, path: MlpPath) -> Result<()> {
        self.coop = match path {
            MlpPath::Scalar => None,
            MlpPath::Coop { .. } if self.f16.is_some() => {
                return Err(GpuError::Usage(
                    "the cooperative-matrix weight gradient reads the f32 record; this MLP keeps an f16 one".into(),
                ))
            }
            MlpPath::Coop { tile } => Some(Coop::new(ctx, &self.config, tile)?),
        };
        Ok(())
    }

    /// The path the MLP takes.
    pub fn path(&self) -> MlpPath {
        match &self.coop {
            Some(c) => MlpPath::Coop { tile: c.tile },
            None => MlpPath::Scalar,
        }
    }

    /// Records the cooperative-matrix weight gradient over `n` f32 records in `saved`.
    fn coop_wgrad<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        coop: &'a Coop,
        saved: Binding<'a>,
        d_weights: Binding<'a>,
        n: u64,
    ) -> Result<()> {
        if n == 0 {
            return Ok(());
        }
        let chunk = n
            .div_ceil(COOP_WORKGROUPS)
            .next_multiple_of(COOP_POINTS)
            .max(COOP_POINTS);
        let p = coop.params(n, chunk, self.config.saved_stride())?;
        let threads = n.div_ceil(chunk) * COOP_POINTS;
        let b = kc8::mlp_wgrad_coop::Bindings {
            shape_buf: self.shape.binding(),
            saved4: saved,
            d_weights,
        };
        coop.dispatch(rec, &coop.wgrad, b.into_array(), &p, threads)
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
        if let Some(coop) = &self.coop {
            return self.coop_wgrad(rec, coop, saved, d_weights, n);
        }
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
            Self::wgrad_threads(&p, k::mlp_wgrad::WORKGROUP_SIZE),
        )
    }

    /// The configuration.
    pub fn config(&self) -> &MlpConfig {
        &self.config
    }

    /// Threads of the weight-gradient pass, whose workgroups hold `wg` threads: a workgroup
    /// per tile and chunk of points (one chunk for no points, which adds zeros).
    fn wgrad_threads(p: &k::Params, wg: [u32; 3]) -> u64 {
        let chunks = p.n.div_ceil(p.chunk).max(1) as u64;
        p.groups as u64 * chunks * wg[0] as u64
    }

    fn params(&self, n: u64) -> Result<k::Params> {
        let n32 = count_u32(n, "MLP points")?;
        // The weight-gradient pass's chunks: at least WGRAD_CHUNK points, at most
        // WGRAD_MAX_CHUNKS of them (the other kernels ignore chunk and groups).
        Ok(k::Params {
            n: n32,
            chunk: n32.div_ceil(WGRAD_MAX_CHUNKS).max(WGRAD_CHUNK),
            // In units of 4 f16 values for the f16 record (its words / 2).
            saved_stride: if self.f16.is_some() {
                self.saved_words() as u32 / 2
            } else {
                self.saved_words() as u32
            },
            groups: self.config.wgrad_tiles() as u32,
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
        if let Some(coop) = &self.coop {
            coop.load_weights(rec, self.shape.binding(), weights)?;
            let b = kc8::mlp_fwd_coop::Bindings {
                shape_buf: self.shape.binding(),
                w16: coop.w16.binding(),
                weights,
                inputs,
                outputs,
                saved: coop.no_record.binding(),
            };
            let p = coop.params(n, 0, c.saved_stride())?;
            let threads = n.next_multiple_of(COOP_POINTS);
            return coop.dispatch(rec, &coop.fwd, b.into_array(), &p, threads);
        }
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
        if let Some(coop) = &self.coop {
            coop.load_weights(rec, shape_buf, weights)?;
            let b = kc8::mlp_bwd_data_coop::Bindings {
                shape_buf,
                w16: coop.w16.binding(),
                weights,
                inputs,
                d_outputs,
                d_inputs,
                saved,
            };
            let pc = coop.params(n, 0, c.saved_stride())?;
            let threads = n.next_multiple_of(COOP_POINTS);
            coop.dispatch(rec, &coop.bwd, b.into_array(), &pc, threads)?;
            return self.coop_wgrad(rec, coop, saved, d_weights, n);
        }
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
            let threads = Self::wgrad_threads(&p, k16::mlp_wgrad_f16::WORKGROUP_SIZE);
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
            Self::wgrad_threads(&p, k::mlp_wgrad::WORKGROUP_SIZE),
        )
    }
}
