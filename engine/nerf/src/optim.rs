//! Adam over the flat parameter buffer, as one kernel, with the Instant-NGP / ExtraNeRF
//! learning-rate schedule (1e-2 decaying exponentially to 3e-4 over 5000 steps by default).

use extranerf_gpu::kernels::optim::adam as k;
use extranerf_gpu::kernels::optim::adam_sparse as ks;
use extranerf_gpu::{count_u32, Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};

/// Adam hyperparameters and the learning-rate schedule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamConfig {
    /// Learning rate at step 1.
    pub lr_start: f32,
    /// Learning rate at `decay_steps` and after.
    pub lr_end: f32,
    /// Steps of the exponential decay.
    pub decay_steps: u32,
    /// First-moment decay.
    pub beta1: f32,
    /// Second-moment decay.
    pub beta2: f32,
    /// Denominator epsilon.
    pub eps: f32,
    /// L2 weight decay added to the gradient.
    pub weight_decay: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        AdamConfig {
            lr_start: 1e-2,
            lr_end: 3e-4,
            decay_steps: 5000,
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-15,
            weight_decay: 0.0,
        }
    }
}

impl AdamConfig {
    /// Learning rate of step `step` (1-based): log-linear from `lr_start` to `lr_end`.
    pub fn lr_at(&self, step: u32) -> f32 {
        let f = if self.decay_steps <= 1 {
            1.0
        } else {
            ((step.max(1) - 1) as f64 / (self.decay_steps - 1) as f64).min(1.0)
        };
        ((self.lr_start as f64).ln() * (1.0 - f) + (self.lr_end as f64).ln() * f).exp() as f32
    }

    fn validate(&self) -> Result<()> {
        let ok = self.lr_start > 0.0
            && self.lr_end > 0.0
            && (0.0..1.0).contains(&self.beta1)
            && (0.0..1.0).contains(&self.beta2)
            && self.eps > 0.0
            && self.weight_decay >= 0.0
            && [self.lr_start, self.lr_end, self.eps, self.weight_decay]
                .iter()
                .all(|v| v.is_finite());
        if ok {
            Ok(())
        } else {
            Err(GpuError::Usage(format!("Adam: invalid settings {self:?} (learning rates and eps > 0, betas in [0, 1), weight decay >= 0)")))
        }
    }
}

/// Hash decay folded into the Adam update: for the `floats` parameters from `start` (a hash
/// table), the gradient of `lambda * sum_l mean(V_l^2)`, i.e. `2 lambda V / (size_l F)`, is
/// added. `block` is the table's level block (`HashGrid::level_block`) with `levels` levels.
#[derive(Clone, Copy, Debug)]
pub struct TableDecay<'a> {
    /// Per level (first float relative to the table, size * features, 0, 0).
    pub block: Binding<'a>,
    /// Levels in `block`.
    pub levels: u32,
    /// First table float in the parameter buffer.
    pub start: u64,
    /// Table floats.
    pub floats: u64,
    /// Decay weight.
    pub lambda: f32,
}

/// The part of the parameters that [`Adam::record_step_sparse`] updates sparsely: a hash table
/// at float 0 of `floats` floats (within one storage binding), with its touched mask (a bit per
/// vec4, [`touched_words`] words, set by the step's backward pass), and the first float of
/// the densely updated rest (the MLPs).
#[derive(Clone, Copy, Debug)]
pub struct SparseTable<'a> {
    pub floats: u64,
    pub touched: Binding<'a>,
    pub rest: u64,
}

/// Words of the touched mask of a table of `floats` floats (a bit per vec4).
pub fn touched_words(floats: u64) -> u64 {
    floats.div_ceil(128)
}

/// Which parameters Adam updates each step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum AdamMode {
    /// Every parameter, every step.
    #[default]
    Dense,
    /// The hash table's entries that the step's batch reached (tiny-cuda-nn's rule: an entry
    /// without a gradient keeps its parameter and moments), the MLPs densely.
    Sparse,
}

/// Adam state (first and second moments) for `n` parameters.
#[derive(Debug)]
pub struct Adam {
    config: AdamConfig,
    kernel: Kernel,
    sparse: Kernel,
    m: Buffer<f32>,
    v: Buffer<f32>,
    n: u64,
    /// Bound as the decay block when there is no hash decay (never read then).
    no_block: Buffer<[u32; 4]>,
    /// Floats per dispatch (a multiple of 64): buffers larger than one storage binding are
    /// updated range by range.
    chunk: u64,
}

impl Adam {
    /// Sets the steps of the learning-rate decay (a time budget re-fitting its steps as it
    /// runs); the moments are kept.
    pub fn set_decay_steps(&mut self, steps: u32) -> Result<()> {
        if steps == 0 {
            return Err(GpuError::Usage(
                "the learning-rate decay needs a positive number of steps".into(),
            ));
        }
        self.config.decay_steps = steps;
        Ok(())
    }

    /// Zeroed moments for `n` parameters.
    pub fn new(ctx: &Context, n: u64, config: AdamConfig) -> Result<Adam> {
        config.validate()?;
        let zeros = vec![0f32; n as usize];
        Ok(Adam {
            config,
            kernel: Kernel::new(ctx, &k::adam::DESC)?,
            sparse: Kernel::new(ctx, &ks::adam_sparse::DESC)?,
            m: Buffer::from_slice(ctx, "adam first moment", &zeros)?,
            v: Buffer::from_slice(ctx, "adam second moment", &zeros)?,
            n,
            no_block: Buffer::from_slice(ctx, "adam no decay block", &[[0u32; 4]; 65])?,
            chunk: (ctx.info().max_storage_buffer_range / 4 / 64 * 64).max(64),
        })
    }

    /// Updates at most `floats` parameters per dispatch (rounded down to a multiple of 64, at
    /// least 64; the tests use it to run the ranged path on small buffers).
    pub fn with_chunk(mut self, floats: u64) -> Adam {
        self.chunk = self.chunk.min(floats / 64 * 64).max(64);
        self
    }

    /// The settings.
    pub fn config(&self) -> &AdamConfig {
        &self.config
    }

    /// The first and second moments (for checkpoints).
    pub fn moments(&self) -> Result<(Vec<f32>, Vec<f32>)> {
        Ok((self.m.read()?, self.v.read()?))
    }

    /// Restores moments saved by [`Adam::moments`].
    pub fn load_moments(&self, m: &[f32], v: &[f32]) -> Result<()> {
        if m.len() as u64 != self.n || v.len() as u64 != self.n {
            return Err(GpuError::Usage(format!(
                "Adam moments of {} and {} values for {} parameters",
                m.len(),
                v.len(),
                self.n
            )));
        }
        self.m.write(m)?;
        self.v.write(v)
    }

    /// The kernel parameters of update number `step` and the decay block to bind.
    fn step_params<'a>(
        &'a self,
        step: u32,
        grad_scale: f32,
        decay: Option<TableDecay<'a>>,
    ) -> Result<(k::Params, Binding<'a>)> {
        if step == 0 {
            return Err(GpuError::Usage("Adam steps count from 1".into()));
        }
        let c = &self.config;
        let mut p = k::Params {
            n: count_u32(self.n, "Adam parameters")?,
            lr: c.lr_at(step),
            beta1: c.beta1,
            beta2: c.beta2,
            eps: c.eps,
            bias1: (1.0 - (c.beta1 as f64).powi(step as i32)) as f32,
            bias2: (1.0 - (c.beta2 as f64).powi(step as i32)) as f32,
            grad_scale,
            weight_decay: c.weight_decay,
            decay_lambda: 0.0,
            decay_start: 0,
            decay_floats: 0,
            decay_levels: 0,
            offset: 0,
            _pad1: 0,
            _pad2: 0,
        };
        let mut block = self.no_block.binding();
        if let Some(d) = decay {
            if !(d.lambda >= 0.0 && d.lambda.is_finite() && (1..=64).contains(&d.levels)) {
                return Err(GpuError::Usage(format!(
                    "hash decay weight {} must be >= 0, over 1 to 64 levels ({} given)",
                    d.lambda, d.levels
                )));
            }
            if d.start + d.floats > self.n {
                return Err(GpuError::Usage(format!(
                    "hash decay over floats {}..{} of {} parameters",
                    d.start,
                    d.start + d.floats,
                    self.n
                )));
            }
            p.decay_lambda = d.lambda;
            p.decay_start = d.start as u32;
            p.decay_floats = d.floats as u32;
            p.decay_levels = d.levels;
            block = d.block;
        }
        Ok((p, block))
    }

    /// Floats `first..first + len` of a buffer of the `n` parameters (the whole binding when
    /// that is all of it).
    fn range<'a>(&self, b: Binding<'a>, first: u64, len: u64) -> Result<Binding<'a>> {
        if first == 0 && len == self.n {
            Ok(b)
        } else {
            b.sub(first * 4, len * 4)
        }
    }

    /// Records the dense update of floats `from..to` of `params`, range by range.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    fn record_dense<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        params: Binding<'a>,
        grads: Binding<'a>,
        p: &k::Params,
        block: Binding<'a>,
        from: u64,
        to: u64,
    ) -> Result<()> {
        let mut first = from;
        while first < to {
            let len = self.chunk.min(to - first);
            let range = |b: Binding<'a>| self.range(b, first, len);
            let b = k::adam::Bindings {
                param: range(params)?,
                grad: range(grads)?,
                m1: range(self.m.binding())?,
                m2: range(self.v.binding())?,
                decay_block: block,
            };
            let p = k::Params {
                n: len as u32,
                offset: first as u32,
                ..*p
            };
            // 4 vec4s (16 parameters) per thread.
            rec.dispatch(&self.kernel, b.into_array(), &p, len.div_ceil(16))?;
            first += len;
        }
        Ok(())
    }

    /// Records update number `step` (1-based) of `params` with `grads * grad_scale`, plus the
    /// hash decay gradient when `decay` is given.
    pub fn record_step<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        params: Binding<'a>,
        grads: Binding<'a>,
        step: u32,
        grad_scale: f32,
        decay: Option<TableDecay<'a>>,
    ) -> Result<()> {
        params.check_fits(self.n, 4, "Adam parameters")?;
        grads.check_fits(self.n, 4, "Adam gradients")?;
        let (p, block) = self.step_params(step, grad_scale, decay)?;
        self.record_dense(rec, params, grads, &p, block, 0, self.n)
    }

    /// Records update number `step` with the table's floats `0..sparse.floats` updated sparsely
    /// (only the vec4s marked in `sparse.touched`, whose gradients are then zeroed and marks
    /// cleared: `optim/adam_sparse.wgsl`) and floats `sparse.rest..` densely. Floats between
    /// the two (a section's alignment gap) are not updated.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn record_step_sparse<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        params: Binding<'a>,
        grads: Binding<'a>,
        step: u32,
        grad_scale: f32,
        decay: Option<TableDecay<'a>>,
        sparse: SparseTable<'a>,
    ) -> Result<()> {
        params.check_fits(self.n, 4, "Adam parameters")?;
        grads.check_fits(self.n, 4, "Adam gradients")?;
        let t = sparse.floats;
        if t > self.n || sparse.rest < t || sparse.rest > self.n {
            return Err(GpuError::Usage(format!(
                "sparse Adam over floats 0..{t} and dense from {} of {} parameters",
                sparse.rest, self.n
            )));
        }
        if t > self.chunk {
            return Err(GpuError::Usage(format!(
                "sparse Adam: a table of {t} floats is larger than one storage binding ({} floats)",
                self.chunk
            )));
        }
        sparse
            .touched
            .check_fits(touched_words(t), 4, "Adam touched mask")?;
        let (p, block) = self.step_params(step, grad_scale, decay)?;
        if t > 0 {
            let whole = |b: Binding<'a>| self.range(b, 0, t);
            let b = ks::adam_sparse::Bindings {
                param: whole(params)?,
                grad: whole(grads)?,
                m1: whole(self.m.binding())?,
                m2: whole(self.v.binding())?,
                decay_block: block,
                touched: sparse.touched,
            };
            let ps = k::Params {
                n: t as u32,
                offset: 0,
                ..p
            };
            // 4 vec4s per thread, as the dense kernel; then the mask is emptied (the update
            // reads each word from 32 threads, so none of them may clear it).
            rec.dispatch(&self.sparse, b.into_array(), &ps, t.div_ceil(16))?;
            rec.fill_words(sparse.touched, touched_words(t), 0)?;
        }
        self.record_dense(rec, params, grads, &p, block, sparse.rest, self.n)
    }
}
