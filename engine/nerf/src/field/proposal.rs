//! The proposal field of the proposal sampler ([`crate::model::Sampler::Proposal`]): a small
//! density-only field, contraction -> its own hash grid -> a one-layer MLP -> trunc-exp, with
//! its parameters in the flat buffer after the main field's. Training evaluates it at
//! `samples` strata per ray, resamples the main field's samples from its weights
//! ([`crate::render::proposal::Proposal::resample`]) and trains it through the interlevel
//! loss alone (its gradient does not reach the main field).

use extranerf_gpu::{Binding, Buffer, Context, Recorder, Result};

use crate::field::activation::{Activation, Activations, Column};
use crate::field::encodings::{Encodings, SceneBox};
use crate::field::hash_grid::HashGrid;
use crate::field::mlp::{Mlp, MlpPath};
use crate::model::{mark, ModelConfig, Profiler, ProposalConfig};
use crate::render::proposal::SourceBins;
use crate::render::sample::SampleOutputs;

/// The density column of the MLP's one output.
const DENSITY: Column = Column {
    stride: 1,
    offset: 0,
};

/// The proposal field's kernels for one configuration.
#[derive(Debug)]
pub struct ProposalField {
    config: ProposalConfig,
    scene: SceneBox,
    grid: HashGrid,
    mlp: Mlp,
    enc: Encodings,
    act: Activations,
}

/// What a [`ProposalWork`] is for: which of its buffers are sized (the others hold one
/// element that no kernel binds).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ProposalUse {
    /// Rendering through the standalone chain: the proposal field forward and the resampling
    /// into the chain's samples.
    Render,
    /// Rendering through the fused march: also the main samples the march takes.
    March,
    /// Training with the standalone chain: also the backward pass (the main samples are the
    /// chain's workspace's).
    Standalone,
    /// Training with the fused step: also the main samples the step takes.
    Fused,
}

/// Per-sample buffers of the proposal field for batches of `rays` rays of `samples` strata:
/// its samples (as the stratified sampler writes them), the field's intermediates and, for
/// training, the gradient scratch of its backward pass.
#[derive(Debug)]
pub struct ProposalWork {
    /// Rays per batch.
    pub rays: u32,
    /// Proposal samples per ray.
    pub samples: u32,
    pub(crate) positions: Buffer<f32>,
    pub(crate) t_dt: Buffer<[f32; 2]>,
    pub(crate) s_ds: Buffer<[f32; 2]>,
    pub(crate) spans: Buffer<[u32; 2]>,
    contracted: Buffer<f32>,
    encoded: Buffer<f32>,
    dens: Buffer<f32>,
    pub(crate) sigma: Buffer<f32>,
    /// The strata's edges in s, `i / samples`, shared by every ray.
    pub(crate) uniform_edges: Buffer<f32>,
    /// The main samples' edges, `main_samples + 1` per ray.
    pub(crate) main_edges: Buffer<f32>,
    /// The main samples when the fused step or march takes them ([`ProposalUse::Fused`],
    /// [`ProposalUse::March`]; the standalone chain's are its workspace's): positions (unread by the
    /// step), `(t, dt)`, `(s, ds)`, spans, and the densities the step writes.
    pub(crate) main_positions: Buffer<f32>,
    pub(crate) main_t_dt: Buffer<[f32; 2]>,
    pub(crate) main_s_ds: Buffer<[f32; 2]>,
    pub(crate) main_spans: Buffer<[u32; 2]>,
    pub(crate) main_sigma: Buffer<f32>,
    /// Interlevel loss per ray, and its gradient per proposal sample's weight.
    pub(crate) loss: Buffer<f32>,
    pub(crate) d_weight: Buffer<f32>,
    pub(crate) d_sigma: Buffer<f32>,
    /// Zeros: the proposal samples' colours and the per-ray colour and depth gradients of
    /// its compositing backward (only d_weight drives it).
    pub(crate) zero_rgb: Buffer<[f32; 4]>,
    pub(crate) d_rgb: Buffer<[f32; 4]>,
    d_dens: Buffer<f32>,
    d_encoded: Buffer<f32>,
    saved: Buffer<f32>,
}

impl ProposalWork {
    /// Buffers for `field` with batches of `rays` rays and `main_samples` main samples each,
    /// for `purpose`.
    pub fn new(
        ctx: &Context,
        field: &ProposalField,
        rays: u32,
        main_samples: u32,
        purpose: ProposalUse,
    ) -> Result<ProposalWork> {
        let kp = field.config.samples;
        let r = rays as usize;
        let n = r * kp as usize;
        extranerf_gpu::count_u32(n as u64, "proposal samples per batch")?;
        extranerf_gpu::count_u32(r as u64 * main_samples as u64, "main samples per batch")?;
        let enc = (field.config.levels * field.config.features) as usize;
        let edges: Vec<f32> = (0..=kp).map(|i| i as f32 / kp as f32).collect();
        let (grads, fused) = match purpose {
            ProposalUse::Render => (false, false),
            ProposalUse::March => (false, true),
            ProposalUse::Standalone => (true, false),
            ProposalUse::Fused => (true, true),
        };
        let main = if fused { r * main_samples as usize } else { 1 };
        let g = |len: usize| if grads { len } else { 1 };
        Ok(ProposalWork {
            rays,
            samples: kp,
            positions: Buffer::new(ctx, "proposal positions", 3 * n)?,
            t_dt: Buffer::new(ctx, "proposal t_dt", n)?,
            s_ds: Buffer::new(ctx, "proposal s_ds", n)?,
            spans: Buffer::new(ctx, "proposal spans", r)?,
            contracted: Buffer::new(ctx, "proposal contracted", 3 * n)?,
            encoded: Buffer::new(ctx, "proposal encoding", enc * n)?,
            dens: Buffer::new(ctx, "proposal MLP output", n)?,
            sigma: Buffer::new(ctx, "proposal density", n)?,
            uniform_edges: Buffer::from_slice(ctx, "proposal strata edges", &edges)?,
            main_edges: Buffer::new(ctx, "main sample edges", r * (main_samples as usize + 1))?,
            main_positions: Buffer::new(ctx, "main sample positions", 3 * main)?,
            main_t_dt: Buffer::new(ctx, "main sample t_dt", main)?,
            main_s_ds: Buffer::new(ctx, "main sample s_ds", main)?,
            main_spans: Buffer::new(ctx, "main sample spans", if fused { r } else { 1 })?,
            main_sigma: Buffer::new(ctx, "main sample densities", main)?,
            loss: Buffer::new(ctx, "interlevel loss", g(r))?,
            d_weight: Buffer::new(ctx, "interlevel dL/dw", g(n))?,
            d_sigma: Buffer::new(ctx, "proposal dL/dsigma", g(n))?,
            zero_rgb: Buffer::from_slice(ctx, "proposal zero colours", &vec![[0f32; 4]; g(n)])?,
            d_rgb: Buffer::new(ctx, "proposal dL/drgb", g(n))?,
            d_dens: Buffer::new(ctx, "proposal dL/d MLP output", g(n))?,
            d_encoded: Buffer::new(ctx, "proposal dL/d encoding", g(enc * n))?,
            saved: Buffer::new(ctx, "proposal MLP record", g(field.mlp.saved_words() * n))?,
        })
    }

    /// The proposal strata, as the stratified sampler writes them.
    pub(crate) fn strata_outputs(&self) -> SampleOutputs<'_> {
        SampleOutputs {
            positions: self.positions.binding(),
            t_dt: self.t_dt.binding(),
            s_ds: self.s_ds.binding(),
            rays: self.spans.binding(),
        }
    }

    /// The main samples the fused step takes, as the resampling writes them.
    pub(crate) fn main_outputs(&self) -> SampleOutputs<'_> {
        SampleOutputs {
            positions: self.main_positions.binding(),
            t_dt: self.main_t_dt.binding(),
            s_ds: self.main_s_ds.binding(),
            rays: self.main_spans.binding(),
        }
    }

    /// The proposal strata as the resampling's and the interlevel loss's source bins (uniform
    /// edges in s, shared by every ray).
    pub(crate) fn source_bins(&self) -> SourceBins<'_> {
        SourceBins {
            edges: self.uniform_edges.binding(),
            stride: 0,
            sigma: self.sigma.binding(),
            t_dt: self.t_dt.binding(),
            count: self.samples,
        }
    }

    /// Proposal samples of `n_rays` rays.
    fn points(&self, n_rays: u64) -> u64 {
        n_rays * self.samples as u64
    }
}

impl ProposalField {
    /// The kernels for `model`'s proposal field, when it has one.
    pub fn new(ctx: &Context, model: &ModelConfig) -> Result<Option<ProposalField>> {
        let Some(config) = model.sampler.proposal() else {
            return Ok(None);
        };
        config.validate()?;
        Ok(Some(ProposalField {
            config: config.clone(),
            scene: model.scene_box(),
            grid: HashGrid::new(ctx, config.grid())?,
            mlp: Mlp::new(ctx, config.mlp())?,
            enc: Encodings::new(ctx)?,
            act: Activations::new(ctx)?,
        }))
    }

    /// The settings.
    pub fn config(&self) -> &ProposalConfig {
        &self.config
    }

    /// The MLP's path.
    pub fn path(&self) -> MlpPath {
        self.mlp.path()
    }

    /// Sets the MLP's path (as the main field's, [`crate::model::Field::set_mlp`]).
    pub fn set_path(&mut self, ctx: &Context, path: MlpPath) -> Result<()> {
        self.mlp.set_path(ctx, path)
    }

    /// Records the density at the proposal samples of `w`'s first `n_rays` rays (their
    /// positions) into `w.sigma`; `params`: the proposal's sections of the flat buffer (table,
    /// MLP).
    pub fn forward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        params: [Binding<'a>; 2],
        w: &'a ProposalWork,
        n_rays: u64,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        if n_rays > w.rays as u64 {
            return Err(extranerf_gpu::GpuError::Usage(format!(
                "{n_rays} rays for proposal buffers of {}",
                w.rays
            )));
        }
        let n = w.points(n_rays);
        let [table, mlp] = params;
        self.enc.contract(
            rec,
            w.positions.binding(),
            w.contracted.binding(),
            n,
            &self.scene,
        )?;
        self.grid
            .forward(rec, w.contracted.binding(), table, w.encoded.binding(), n)?;
        self.mlp
            .forward(rec, mlp, w.encoded.binding(), w.dens.binding(), n)?;
        self.act.forward(
            rec,
            Activation::TruncExp,
            w.dens.binding(),
            DENSITY,
            w.sigma.binding(),
            n,
        )?;
        mark(prof, rec, "proposal field fwd")
    }

    /// Records the backward pass from `w.d_sigma` after [`ProposalField::forward`] of all of
    /// `w`'s rays: adds the gradients to `d_params` (the same sections of the gradient buffer).
    /// `w` must be a training one ([`ProposalUse::Standalone`] or [`ProposalUse::Fused`]).
    pub fn backward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        params: [Binding<'a>; 2],
        d_params: [Binding<'a>; 2],
        w: &'a ProposalWork,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        if w.d_sigma.len() < w.points(w.rays as u64) as usize {
            return Err(extranerf_gpu::GpuError::Usage(
                "the proposal field's backward pass needs training buffers".into(),
            ));
        }
        let n = w.points(w.rays as u64);
        let [_, mlp] = params;
        let [d_table, d_mlp] = d_params;
        self.act.backward(
            rec,
            Activation::TruncExp,
            w.dens.binding(),
            DENSITY,
            w.d_sigma.binding(),
            w.d_dens.binding(),
            n,
        )?;
        self.mlp.backward(
            rec,
            mlp,
            w.encoded.binding(),
            w.d_dens.binding(),
            w.d_encoded.binding(),
            w.saved.binding(),
            d_mlp,
            n,
        )?;
        self.grid.backward(
            rec,
            w.contracted.binding(),
            w.d_encoded.binding(),
            d_table,
            n,
        )?;
        mark(prof, rec, "proposal field bwd")
    }
}
