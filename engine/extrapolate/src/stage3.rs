//! ExtraNeRF's stage 3: an enhancer trained on the scene's own corrupted renders sharpens the
//! renders of the virtual views, and the field is supervised by the result.
//!
//! - [`EnhancerDataStage`] (`RUN/stage3-data`): (corrupted render, mask, photo) triplets of
//!   the training views. A field whose supervision inside each training view's
//!   pseudo-disocclusion mask (the view against the other training cameras) comes from the
//!   stage-2 inpainter instead of the photo is optimised from the BaseNeRF, and the training
//!   views are rendered after each of its rounds; renders of an under-fitted field (a fresh
//!   field trained with the BaseNeRF's settings, at a few step counts) and of the BaseNeRF
//!   itself are added.
//! - [`EnhancerStage`] (`RUN/stage3-enhancer`): the enhancer trained on them
//!   ([`extranerf_diffusion::enhancer`]).
//! - [`EnhanceStage`] (`RUN/stage3-NAME`, one per stage-2 variant): rounds of rendering the
//!   virtual views, enhancing them from a moderate noise level in a few DDIM steps, and
//!   training on them (w(t)-weighted L1 of the colours, the depth loss on the rendered depth)
//!   mixed with the captured views.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context as _};
use extranerf_diffusion::device::Backend;
use extranerf_diffusion::enhancer::{self, EnhancerSpec};
use extranerf_diffusion::inpaint::SampleSettings;
use extranerf_diffusion::train::{Guide, TrainImage};
use extranerf_gpu::Context;
use extranerf_nerf::data::{Camera, Image};
use extranerf_nerf::metrics::psnr;
use extranerf_nerf::render::visibility::mask_all_but;
use extranerf_nerf::renderer::Nerf;
use extranerf_nerf::run::{load_checkpoint, training_views_in, write_png, RunConfig};
use extranerf_nerf::safetensors::{SafeTensors, Tensor};
use extranerf_nerf::trainer::Trainer;
use extranerf_nerf::views::{TrainData, View, ViewKind, ViewSampling};
use extranerf_prims::Prims;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::base::BaseField;
use crate::driver::{default_lpips_dir, lpips_alex, Progress, Reporter, Unit};
use crate::inpaint::{Fill, InpainterKind, Source, Target};
use crate::pipeline::{
    build_inpainter, load_map, load_round, make_virtual, render, train_round, train_steps,
    write_test_renders, DiffusionSpec, RoundSink, RunDir, Stage, Stage2Spec, VirtualSpec,
    MAPS_FILE,
};
use crate::visibility::{FieldVisibility, VisSettings};
use extranerf_nerf::image_ops::{detail_energy, downscale_image, resize_mask, unsharp};

/// Stage 3's settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Stage3Spec {
    /// Rounds of the inpainting-supervised field that makes training data (each: render the
    /// training views, inpaint their masks, train, render them again as triplets).
    pub data_rounds: u32,
    /// Training steps per data round.
    pub data_steps_per_round: u32,
    /// Step counts of a fresh field at which the training views are rendered as triplets
    /// (the blur of an under-fitted field); empty: none.
    pub base_checkpoints: Vec<u32>,
    /// The enhancer's training.
    pub enhancer: EnhancerSpec,
    /// Rounds over the virtual views (each: render, enhance, train).
    pub rounds: u32,
    /// Training steps per round (the paper: 500 iterations in all).
    pub steps_per_round: u32,
    /// Noise strength t the renders are enhanced from (a fraction of the schedule's timesteps,
    /// as stage 2's t); the loss weight is w(t) = sqrt(1 - t^2), as in stage 2.
    pub t: f32,
    /// DDIM steps per enhancement.
    pub ddim_steps: usize,
    /// Colour anchoring (0: off): the enhanced view keeps only its detail above a box blur of
    /// this radius (applied twice), on the render's own blur; see
    /// [`crate::inpaint::low_plus_detail`].
    pub anchor_radius: usize,
    /// Smoothing of the enhancement (0: off): the enhanced view keeps only its change to the
    /// render below a box blur of this radius (applied twice), on the render's own detail, i.e.
    /// `render + blur(enhanced - render)`; applied after the colour anchoring. An enhancer that
    /// adds pixel-level noise of its own (a different one in every view) gives the field targets
    /// that disagree between views, which it averages into blur.
    pub smooth_radius: usize,
    /// Weight of a virtual view's seen pixels relative to its not-visible ones (1: the whole
    /// enhanced view, as the paper; 0: only where no input camera saw).
    pub visible_weight: f32,
    /// Core of the virtual views' colour loss (0: the paper's plain L1; above 0: smooth L1,
    /// quadratic for per-channel errors below the core; see
    /// [`extranerf_nerf::trainer::TrainConfig::virtual_l1_core`]). Plain L1 pulls every seen
    /// pixel whose target is within noise of the render with a gradient as large as a real
    /// error's.
    pub l1_core: f32,
    /// Fraction of each batch's rays drawn from the virtual views.
    pub virtual_fraction: f32,
    /// Learning rate (constant) of the stage's steps.
    pub lr: f32,
    /// Seed of the enhancement noise.
    pub seed: u64,
    /// Where the enhancer runs.
    pub backend: Backend,
    /// What enhances the virtual views ([`Stage3Enhancer`]).
    #[serde(default)]
    pub enhance: Stage3Enhancer,
    /// [`Stage3Enhancer::Unsharp`]: how much of the render's detail above the blur is added.
    #[serde(default = "default_unsharp_amount")]
    pub unsharp_amount: f32,
    /// [`Stage3Enhancer::Unsharp`]: the box-blur radius (applied twice: a tent).
    #[serde(default = "default_unsharp_radius")]
    pub unsharp_radius: usize,
    /// Whether the enhancer is checked before stage 3 trusts it ([`Stage3Gate`]).
    #[serde(default)]
    pub gate: Stage3Gate,
    /// The folder of the LPIPS weights the gate scores with (None: [`default_lpips_dir`]);
    /// where none load, it scores with PSNR.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips: Option<PathBuf>,
}

fn default_unsharp_amount() -> f32 {
    0.5
}

fn default_unsharp_radius() -> usize {
    1
}

/// What stage 3 enhances the virtual views with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Stage3Enhancer {
    /// The diffusion enhancer trained on the scene's corrupted renders (the paper): stages
    /// `stage3-data` and `stage3-enhancer` make it.
    #[default]
    Diffusion,
    /// An unsharp mask of the render, `render + amount * (render - blur(render))` ([`unsharp`]):
    /// no model, no training data, no noise; it sharpens what is there and invents nothing.
    Unsharp,
}

/// Whether stage 3 first checks that its enhancer helps.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Stage3Gate {
    /// Enhance one corrupted render per training view (its triplets, the sources taken in
    /// turn) as stage 3 would, and run stage 3 only when that brings them closer to their
    /// photos (mean LPIPS lowered; PSNR raised where no LPIPS weights load). Otherwise the
    /// stage keeps the stage-2 field and says why: an enhancer that cannot improve renders of
    /// the views it was trained on would supervise the virtual views with its own errors.
    #[default]
    Check,
    /// Always run stage 3 (the paper's ablation, whatever the enhancer does).
    Off,
}

impl Default for Stage3Spec {
    fn default() -> Self {
        Stage3Spec {
            data_rounds: 3,
            data_steps_per_round: 100,
            base_checkpoints: vec![100, 400],
            enhancer: EnhancerSpec::default(),
            rounds: 2,
            steps_per_round: 250,
            t: 0.3,
            ddim_steps: 10,
            anchor_radius: 0,
            smooth_radius: 0,
            visible_weight: 1.0,
            l1_core: 0.0,
            virtual_fraction: 0.3,
            lr: 3e-3,
            seed: 0,
            backend: Backend::Auto,
            enhance: Stage3Enhancer::Diffusion,
            unsharp_amount: default_unsharp_amount(),
            unsharp_radius: default_unsharp_radius(),
            gate: Stage3Gate::Check,
            lpips: None,
        }
    }
}

impl Stage3Spec {
    /// Checks the settings.
    pub fn validate(&self) -> anyhow::Result<()> {
        if self.rounds == 0 || self.steps_per_round == 0 {
            bail!("stage 3 needs at least one round of at least one step");
        }
        if self.data_rounds == 0 || self.data_steps_per_round == 0 {
            bail!("stage 3's data collection needs at least one round of at least one step");
        }
        if !(self.t > 0.0 && self.t < 1.0) {
            bail!("--stage3-t {}: use a noise level in (0, 1)", self.t);
        }
        if self.ddim_steps == 0 {
            bail!("--stage3-ddim-steps must be at least 1");
        }
        if !(0.0..=1.0).contains(&self.virtual_fraction) {
            bail!(
                "--stage3-virtual-fraction {}: use a value in [0, 1]",
                self.virtual_fraction
            );
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            bail!("--stage3-lr {}: use a positive learning rate", self.lr);
        }
        for (flag, r) in [
            ("--stage3-anchor", self.anchor_radius),
            ("--stage3-smooth", self.smooth_radius),
        ] {
            if r > MAX_RADIUS {
                bail!("{flag} {r}: use a radius of at most {MAX_RADIUS} pixels (0: off)");
            }
        }
        if !(self.l1_core.is_finite() && (0.0..=1.0).contains(&self.l1_core)) {
            bail!(
                "--stage3-l1-core {}: use a colour error in [0, 1] (0: plain L1)",
                self.l1_core
            );
        }
        if !(0.0..=1.0).contains(&self.visible_weight) {
            bail!(
                "--stage3-visible-weight {}: use a value in [0, 1]",
                self.visible_weight
            );
        }
        if self.enhance == Stage3Enhancer::Unsharp
            && !(self.unsharp_amount.is_finite()
                && self.unsharp_amount > 0.0
                && self.unsharp_amount <= 4.0
                && (1..=MAX_RADIUS).contains(&self.unsharp_radius))
        {
            bail!(
                "--stage3-unsharp-amount {} and --stage3-unsharp-radius {}: use an amount in (0, 4] and a radius of 1 to {MAX_RADIUS} pixels",
                self.unsharp_amount,
                self.unsharp_radius
            );
        }
        let e = &self.enhancer;
        if e.steps == 0 || e.batch == 0 || e.crop == 0 || !(e.lr.is_finite() && e.lr > 0.0) {
            bail!(
                "the enhancer needs steps ({}), batch ({}) and crop ({}) of at least 1 and a positive learning rate ({})",
                e.steps,
                e.batch,
                e.crop,
                e.lr
            );
        }
        Ok(())
    }

    /// The loss weight w(t) = sqrt(1 - t^2).
    pub fn weight(&self) -> f32 {
        (1.0 - self.t * self.t).max(0.0).sqrt()
    }

    /// Stage 3's target for an `[h, w, 3]` render with its not-visible `mask`: the render
    /// enhanced (by the diffusion `model` from t in the DDIM steps, seeded with `seed`; None:
    /// the unsharp mask), then anchored and smoothed ([`stage3_target`]). The loop and the
    /// gate's check both make their targets here.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn target(
        &self,
        model: Option<(
            &extranerf_diffusion::pipeline::Pipeline,
            &burn::tensor::Device,
        )>,
        render: &[f32],
        mask: &[f32],
        w: usize,
        h: usize,
        seed: u64,
    ) -> anyhow::Result<Vec<f32>> {
        let enhanced = match model {
            Some((pipe, device)) => {
                pipe.model
                    .enhance_image(
                        render,
                        Some(mask),
                        w,
                        h,
                        seed,
                        &SampleSettings {
                            strength: f64::from(self.t),
                            steps: self.ddim_steps,
                            guidance: 1.0,
                            keep_known: false,
                        },
                        device,
                    )?
                    .rgb
            }
            None => unsharp(render, w, h, self.unsharp_amount, self.unsharp_radius),
        };
        Ok(stage3_target(
            render,
            &enhanced,
            w,
            h,
            self.anchor_radius,
            self.smooth_radius,
        ))
    }
}

/// The largest `--stage3-anchor` and `--stage3-smooth` radius (a blur wider than this is
/// most of a virtual view).
pub const MAX_RADIUS: usize = 64;

/// Stage 3's colour target of a virtual view from its `render` and the enhancer's output
/// (`[h, w, 3]` each): the enhanced view, colour-anchored when `anchor` > 0 (the render's blur
/// plus the enhanced view's detail above it), then smoothed when `smooth` > 0 (the render's
/// detail plus the blur of what the enhancement changed); see
/// [`crate::inpaint::low_plus_detail`].
pub fn stage3_target(
    render: &[f32],
    enhanced: &[f32],
    w: usize,
    h: usize,
    anchor: usize,
    smooth: usize,
) -> Vec<f32> {
    let mut t = enhanced.to_vec();
    if anchor > 0 {
        t = crate::inpaint::low_plus_detail(render, &t, w, h, anchor);
    }
    if smooth > 0 {
        t = crate::inpaint::low_plus_detail(&t, render, w, h, smooth);
    }
    t
}

/// A virtual view's per-pixel loss weights in stage 3: `weight` (w(t)) where `mask` is a hole
/// (not visible), `weight * visible` elsewhere.
pub fn virtual_weights(mask: &[f32], weight: f32, visible: f32) -> Vec<f32> {
    (0..mask.len())
        .map(|i| {
            if crate::inpaint::is_hole(mask, i) {
                weight
            } else {
                weight * visible
            }
        })
        .collect()
}

/// The data stage's name and folder.
pub const DATA_STAGE: &str = "stage3-data";
/// The enhancer stage's name and folder.
pub const ENHANCER_STAGE: &str = "stage3-enhancer";
/// The triplets' tensors.
pub const TRIPLETS_FILE: &str = "triplets.safetensors";
/// Where each triplet came from.
pub const TRIPLETS_INDEX: &str = "triplets.json";

/// One entry of [`TRIPLETS_INDEX`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TripletEntry {
    /// Key of its tensors (`KEY.render`, `KEY.mask`).
    pub key: String,
    /// The training view (its slot in the split's training list).
    pub slot: usize,
    /// What rendered it: `fresh@STEPS`, `base` or `inpainted@ROUND`.
    pub source: String,
}

/// The training data of the enhancer: per training view its photo and pseudo mask at the
/// virtual views' scale, and the corrupted renders.
#[derive(Clone, Debug)]
pub struct Triplets {
    pub width: usize,
    pub height: usize,
    /// `[h, w, 3]` per training view.
    pub photos: Vec<Vec<f32>>,
    /// `[h, w]` per training view: 1 where no other training camera saw it.
    pub masks: Vec<Vec<f32>>,
    pub entries: Vec<TripletEntry>,
    /// `[h, w, 3]` render and `[h, w]` mask (where the inpainter supervised it) per entry.
    pub renders: Vec<(Vec<f32>, Vec<f32>)>,
}

impl Triplets {
    /// Writes `dir/triplets.safetensors` and `dir/triplets.json`.
    pub fn save(&self, dir: &Path) -> anyhow::Result<()> {
        let (w, h) = (self.width, self.height);
        let mut st = SafeTensors::default();
        let mut put = |name: String, shape: Vec<usize>, data: &[f32]| {
            st.tensors.insert(
                name,
                Tensor {
                    shape,
                    data: data.to_vec(),
                },
            );
        };
        for (i, (p, m)) in self.photos.iter().zip(&self.masks).enumerate() {
            put(format!("photo_{i:03}"), vec![h, w, 3], p);
            put(format!("pseudo_mask_{i:03}"), vec![h, w], m);
        }
        for (e, (r, m)) in self.entries.iter().zip(&self.renders) {
            put(format!("{}.render", e.key), vec![h, w, 3], r);
            put(format!("{}.mask", e.key), vec![h, w], m);
        }
        st.write(&dir.join(TRIPLETS_FILE))?;
        extranerf_nerf::safetensors::write_atomic(
            &dir.join(TRIPLETS_INDEX),
            serde_json::to_string_pretty(&self.entries)?.as_bytes(),
        )?;
        Ok(())
    }

    /// Reads what [`Triplets::save`] wrote.
    pub fn load(dir: &Path) -> anyhow::Result<Triplets> {
        let path = dir.join(TRIPLETS_FILE);
        let index = dir.join(TRIPLETS_INDEX);
        let st = SafeTensors::read(&path)?;
        let entries: Vec<TripletEntry> = serde_json::from_str(
            &std::fs::read_to_string(&index)
                .with_context(|| format!("reading {}", index.display()))?,
        )
        .with_context(|| format!("{}: malformed", index.display()))?;
        let get = |name: &str, want: &[usize]| -> anyhow::Result<Vec<f32>> {
            let t = st
                .tensors
                .get(name)
                .with_context(|| format!("{}: no tensor {name}", path.display()))?;
            if t.shape != want {
                bail!(
                    "{}: {name} has shape {:?}, not {want:?}",
                    path.display(),
                    t.shape
                );
            }
            Ok(t.data.clone())
        };
        let first = st
            .tensors
            .get("photo_000")
            .with_context(|| format!("{}: no photos", path.display()))?;
        let [h, w, 3] = first.shape[..] else {
            bail!("{}: photo_000 is not [h, w, 3]", path.display());
        };
        let mut photos = Vec::new();
        let mut masks = Vec::new();
        while st
            .tensors
            .contains_key(&format!("photo_{:03}", photos.len()))
        {
            let i = photos.len();
            photos.push(get(&format!("photo_{i:03}"), &[h, w, 3])?);
            masks.push(get(&format!("pseudo_mask_{i:03}"), &[h, w])?);
        }
        let mut renders = Vec::new();
        for e in &entries {
            if e.slot >= photos.len() {
                bail!(
                    "{}: triplet {} names training view {} of {}",
                    index.display(),
                    e.key,
                    e.slot,
                    photos.len()
                );
            }
            renders.push((
                get(&format!("{}.render", e.key), &[h, w, 3])?,
                get(&format!("{}.mask", e.key), &[h, w])?,
            ));
        }
        Ok(Triplets {
            width: w,
            height: h,
            photos,
            masks,
            entries,
            renders,
        })
    }

    /// The enhancer's training images: each photo with its corrupted renders.
    pub fn train_images(&self) -> Vec<TrainImage> {
        self.photos
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let mut im = TrainImage::new(self.width, self.height, p.clone());
                im.guides = self
                    .entries
                    .iter()
                    .zip(&self.renders)
                    .filter(|(e, _)| e.slot == i)
                    .map(|(_, (r, m))| Guide {
                        rgb: r.clone(),
                        mask: m.clone(),
                    })
                    .collect();
                im
            })
            .collect()
    }
}

/// The file in the enhancer's folder that holds its [`EnhancerCheck`].
pub const CHECK_FILE: &str = "check.json";

/// What [`Stage3Gate::Check`] measured: corrupted renders of the training views enhanced as
/// stage 3 enhances the virtual views, against their photos.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnhancerCheck {
    /// The enhancement's settings (a check made with other ones is made again), with the
    /// anchoring and smoothing that turn an enhancement into stage 3's target.
    pub t: f32,
    pub ddim_steps: usize,
    pub seed: u64,
    pub anchor_radius: usize,
    pub smooth_radius: usize,
    /// The triplets enhanced (their keys).
    pub triplets: Vec<String>,
    /// Mean PSNR of the renders and of their enhancements against the photos.
    pub psnr_render: f64,
    pub psnr_enhanced: f64,
    /// Mean LPIPS-alex of the same, where the weights loaded and the views are large enough.
    pub lpips_render: Option<f64>,
    pub lpips_enhanced: Option<f64>,
    /// Wall seconds of the check.
    pub seconds: f64,
}

impl EnhancerCheck {
    /// The enhancement brought the renders closer to their photos: LPIPS lowered, or where it
    /// was not measured, PSNR raised.
    pub fn helps(&self) -> bool {
        match (self.lpips_render, self.lpips_enhanced) {
            (Some(r), Some(e)) => e < r,
            _ => self.psnr_enhanced > self.psnr_render,
        }
    }

    /// One line of what it measured.
    pub fn describe(&self) -> String {
        let lpips = match (self.lpips_render, self.lpips_enhanced) {
            (Some(r), Some(e)) => format!("LPIPS-alex {r:.3} -> {e:.3}, "),
            _ => String::new(),
        };
        format!(
            "enhancing {} training-view renders (triplets {}) from t = {} in {} DDIM steps: {lpips}PSNR {:.2} -> {:.2} dB",
            self.triplets.len(),
            self.triplets.join(", "),
            self.t,
            self.ddim_steps,
            self.psnr_render,
            self.psnr_enhanced
        )
    }
}

/// The triplets the check enhances: one per training view, the sources taken in turn (view
/// `v` gets its `v mod n`-th triplet of `n`), which spreads the kinds of corruption over the
/// views at the cost of one enhancement per view (each kind once when every view has the same
/// `n` sources and there are at least `n` views).
pub fn check_triplets(tr: &Triplets) -> Vec<usize> {
    (0..tr.photos.len())
        .filter_map(|v| {
            let mine: Vec<usize> = (0..tr.entries.len())
                .filter(|&k| tr.entries[k].slot == v)
                .collect();
            (!mine.is_empty()).then(|| mine[v % mine.len()])
        })
        .collect()
}

/// The enhancer check of a run ([`Stage3Gate::Check`]): read from the enhancer's folder when
/// it was made there with these settings, otherwise made and written there.
pub fn check_enhancer(
    dir: &RunDir,
    spec: &Stage3Spec,
    pipe: &extranerf_diffusion::pipeline::Pipeline,
    device: &burn::tensor::Device,
    rep: &mut dyn Reporter,
) -> anyhow::Result<EnhancerCheck> {
    let path = EnhancerStage::dir(dir).join(CHECK_FILE);
    let tr = Triplets::load(&dir.root.join(DATA_STAGE))?;
    let (w, h) = (tr.width, tr.height);
    let lp = match lpips_alex(spec.lpips.as_deref()) {
        Ok(l) if (w.min(h) as u32) >= l.net().min_size() => Some(l),
        Ok(_) => {
            rep.note(&format!(
                "enhancer check: {w}x{h} views are below LPIPS's smallest input; scored with PSNR"
            ));
            None
        }
        Err(e) => {
            rep.note(&format!(
                "enhancer check: no LPIPS ({e:#}; default folder {}); scored with PSNR",
                default_lpips_dir().display()
            ));
            None
        }
    };
    // A check made with these settings and the same score is reused; any other (or a file
    // that does not read) is made again: it is only a cache.
    if let Some(c) = std::fs::read_to_string(&path)
        .ok()
        .and_then(|text| serde_json::from_str::<EnhancerCheck>(&text).ok())
    {
        let key = |c: &EnhancerCheck| {
            (
                c.t,
                c.ddim_steps,
                c.seed,
                c.anchor_radius,
                c.smooth_radius,
                c.lpips_render.is_some(),
            )
        };
        let want = (
            spec.t,
            spec.ddim_steps,
            spec.seed,
            spec.anchor_radius,
            spec.smooth_radius,
            lp.is_some(),
        );
        if key(&c) == want {
            return Ok(c);
        }
    }
    let t0 = Instant::now();
    let picks = check_triplets(&tr);
    if picks.is_empty() {
        bail!(
            "{}: no triplets to check the enhancer on",
            dir.root.join(DATA_STAGE).display()
        );
    }
    let (mut pr, mut pe, mut lr, mut le) = (0.0, 0.0, 0.0, 0.0);
    for (n, &k) in picks.iter().enumerate() {
        let (render, mask) = &tr.renders[k];
        let photo = &tr.photos[tr.entries[k].slot];
        // What stage 3 would train on.
        let enhanced = spec
            .target(
                Some((pipe, device)),
                render,
                mask,
                w,
                h,
                spec.seed ^ 0xc4ec_0000 ^ k as u64,
            )
            .with_context(|| format!("enhancing triplet {}", tr.entries[k].key))?;
        pr += psnr(render, photo)?;
        pe += psnr(&enhanced, photo)?;
        if let Some(l) = &lp {
            lr += l.distance(render, photo, w as u32, h as u32)?;
            le += l.distance(&enhanced, photo, w as u32, h as u32)?;
        }
        progress_views(rep, n + 1, picks.len(), &t0);
    }
    let n = picks.len() as f64;
    let c = EnhancerCheck {
        t: spec.t,
        ddim_steps: spec.ddim_steps,
        seed: spec.seed,
        anchor_radius: spec.anchor_radius,
        smooth_radius: spec.smooth_radius,
        triplets: picks.iter().map(|&k| tr.entries[k].key.clone()).collect(),
        psnr_render: pr / n,
        psnr_enhanced: pe / n,
        lpips_render: lp.as_ref().map(|_| lr / n),
        lpips_enhanced: lp.as_ref().map(|_| le / n),
        seconds: t0.elapsed().as_secs_f64(),
    };
    extranerf_nerf::safetensors::write_atomic(&path, serde_json::to_string_pretty(&c)?.as_bytes())?;
    Ok(c)
}

/// The supervision of one training view in the data collector: the captured view with its
/// photo's weight 0 inside the pseudo mask (`mask_full`, the view's resolution), and a
/// virtual view at the same camera (`cam`, the mask's scale `mask`) that carries the
/// inpainter's fill with weight `weight` inside the mask and nothing outside it.
pub fn collector_views(
    captured: &View,
    mask_full: &[f32],
    cam: &Camera,
    fill: &Fill,
    mask: &[f32],
    weight: f32,
) -> (View, View) {
    let mut photo = captured.clone();
    let old = photo.weight.take();
    photo.weight = Some(
        mask_full
            .iter()
            .enumerate()
            .map(|(i, &m)| {
                let w = old.as_ref().map_or(1.0, |o| o[i]);
                if m >= 0.5 {
                    0.0
                } else {
                    w
                }
            })
            .collect(),
    );
    let inside = |m: f32| if m >= 0.5 { 1.0 } else { 0.0 };
    let virt = View {
        camera: cam.clone(),
        image: Image::opaque(cam.width, cam.height, fill.rgb.clone()),
        depth: Some(
            fill.depth
                .iter()
                .zip(mask)
                .map(|(&d, &m)| [d, inside(m)])
                .collect(),
        ),
        weight: Some(mask.iter().map(|&m| weight * inside(m)).collect()),
        kind: ViewKind::Virtual,
    };
    (photo, virt)
}

/// The enhancer's training data.
#[derive(Clone, Debug)]
pub struct EnhancerDataStage {
    pub spec: Stage3Spec,
    /// The inpainter whose supervision corrupts the masked regions.
    pub inpainter: InpainterKind,
    pub diffusion: Option<DiffusionSpec>,
    /// The stage-2 loop (its noise levels and learning rate serve the data rounds).
    pub stage2: Stage2Spec,
    pub virt: VirtualSpec,
    pub vis: VisSettings,
}

fn progress_views(rep: &mut dyn Reporter, step: usize, total: usize, t: &Instant) {
    rep.progress(&Progress {
        unit: Unit::Views,
        step: step as u32,
        total: total as u32,
        loss: 0.0,
        psnr: 0.0,
        samples_per_s: 0.0,
        secs: t.elapsed().as_secs_f64(),
        eta: 0.0,
    });
}

impl Stage for EnhancerDataStage {
    fn name(&self) -> String {
        DATA_STAGE.into()
    }

    fn config(&self) -> Value {
        let s = &self.spec;
        let mut c = json!({
            "inpainter": self.inpainter,
            "data_rounds": s.data_rounds,
            "data_steps_per_round": s.data_steps_per_round,
            "base_checkpoints": s.base_checkpoints,
            "lr": self.stage2.lr,
            "t_start": self.stage2.t_start,
            "t_end": self.stage2.t_end,
            "seed": self.stage2.seed,
            "downscale": self.virt.downscale,
            "visibility": self.vis,
        });
        if self.inpainter.uses_diffusion() {
            c["diffusion"] = json!(self.diffusion.as_ref().map(|d| d.for_kind(self.inpainter)));
        }
        c
    }

    fn inputs(&self) -> Vec<String> {
        vec!["base".into()]
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> anyhow::Result<Value> {
        self.spec.validate()?;
        let out = dir.root.join(DATA_STAGE);
        std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
        let base = BaseField::load(ctx, &dir.base)?;
        let cfg = base.ck.config.clone();
        let samples = cfg.train.samples;
        let train = base.train_cameras();
        let (captured, _) =
            training_views_in(ctx, &cfg.scene, &base.loaded, &cfg.model, &dir.base)?;
        let cams: Vec<Camera> = train
            .iter()
            .map(|c| c.downscaled(self.virt.downscale))
            .collect();
        let (w, h) = (cams[0].width as usize, cams[0].height as usize);
        if cams
            .iter()
            .any(|c| (c.width as usize, c.height as usize) != (w, h))
        {
            bail!("stage 3 needs training views of one size");
        }
        // Pseudo-disocclusion masks: each view against the other training cameras.
        let t = Instant::now();
        let vcfg = self.vis.config(self.vis.rank, samples)?;
        let fv = FieldVisibility::new(ctx, &base.nerf, &train, &self.vis)?;
        let mut masks = Vec::new();
        let mut photos = Vec::new();
        for (i, cam) in cams.iter().enumerate() {
            let m = fv.map(
                ctx,
                &base.nerf,
                cam,
                mask_all_but(train.len(), Some(i)),
                &vcfg,
                self.vis.chunk,
            )?;
            let mask = self.vis.mask(&m);
            write_png(
                &out.join(format!("pseudo_mask_{i:03}.png")),
                cam.width,
                cam.height,
                &mask.iter().flat_map(|&v| [v, v, v]).collect::<Vec<_>>(),
            )?;
            masks.push(mask);
            photos.push(downscale_image(&captured[i].image, cam.width, cam.height).rgb);
            progress_views(rep, i + 1, cams.len(), &t);
        }
        let masked: f64 = masks.iter().flatten().map(|&v| v as f64).sum::<f64>()
            / (masks.len() * w * h).max(1) as f64;
        rep.note(&format!(
            "{DATA_STAGE}: pseudo-disocclusion masks of {} training views, {:.1}% of their pixels",
            cams.len(),
            100.0 * masked
        ));
        let mut entries = Vec::new();
        let mut renders = Vec::new();
        let mut add = |source: String,
                       nerf: &Nerf,
                       fills: Option<&[Vec<f32>]>,
                       entries: &mut Vec<TripletEntry>|
         -> anyhow::Result<()> {
            for (i, cam) in cams.iter().enumerate() {
                let (rgb, _, _) = render(ctx, nerf, cam, samples)?;
                let key = format!("t{:03}", entries.len());
                write_png(
                    &out.join(format!("{key}_view{i:03}_{}.png", source.replace('@', "_"))),
                    cam.width,
                    cam.height,
                    &rgb,
                )?;
                let mask = fills.map_or_else(|| vec![0.0; w * h], |f| f[i].clone());
                renders.push((rgb, mask));
                entries.push(TripletEntry {
                    key,
                    slot: i,
                    source: source.clone(),
                });
            }
            Ok(())
        };
        // An under-fitted field: a fresh one trained with the BaseNeRF's settings.
        let mut fresh_s = 0.0;
        if !self.spec.base_checkpoints.is_empty() {
            let tf = Instant::now();
            let (mut trainer, data) =
                crate::driver::fresh_trainer(ctx, &cfg, &base.loaded, &dir.base)?;
            let prims = Prims::new(ctx)?;
            let mut checkpoints = self.spec.base_checkpoints.clone();
            checkpoints.sort_unstable();
            checkpoints.dedup();
            for &c in &checkpoints {
                let left = c.saturating_sub(trainer.step());
                if left > 0 {
                    train_steps(
                        ctx,
                        &mut trainer,
                        &prims,
                        &data,
                        left,
                        &format!("{DATA_STAGE}: a fresh field"),
                        &out,
                        rep,
                    )?;
                }
                add(format!("fresh@{c}"), trainer.nerf(), None, &mut entries)?;
            }
            fresh_s = tf.elapsed().as_secs_f64();
        }
        add("base".into(), &base.nerf, None, &mut entries)?;
        // The inpainting-supervised field.
        let ti = Instant::now();
        let mut tcfg = cfg.train.clone();
        let total = self.spec.data_rounds * self.spec.data_steps_per_round;
        tcfg.steps = total;
        tcfg.decay_steps = total;
        tcfg.lr_start = self.stage2.lr;
        tcfg.lr_end = self.stage2.lr;
        let moments = base
            .ck
            .moments
            .as_ref()
            .map(|(m, v)| (m.as_slice(), v.as_slice()));
        let nerf = Nerf::new(
            ctx,
            cfg.model.clone(),
            &base.ck.params,
            cfg.train.background,
        )?;
        let mut trainer = Trainer::new(ctx, nerf, tcfg, 0, moments)?;
        let prims = Prims::new(ctx)?;
        let mut inpainter = build_inpainter(ctx, self.inpainter, self.diffusion.as_ref(), rep)?;
        let loop2 = Stage2Spec {
            rounds: self.spec.data_rounds,
            ..self.stage2.clone()
        };
        let masks_full: Vec<Vec<f32>> = captured
            .iter()
            .zip(&masks)
            .map(|(v, m)| resize_mask(m, w, h, v.camera.width as usize, v.camera.height as usize))
            .collect();
        let mut inpaint_s = 0.0;
        for round in 0..self.spec.data_rounds {
            let (t, weight) = (loop2.t(round), loop2.weight(round));
            let mut views = Vec::new();
            for (i, cam) in cams.iter().enumerate() {
                let (rgb, depth, _) = render(ctx, trainer.nerf(), cam, samples)?;
                // Sources: the other training photos (never the view's own).
                let sources: Vec<Source<'_>> = photos
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .map(|(_, p)| Source {
                        width: w,
                        height: h,
                        rgb: p,
                        depth: None,
                    })
                    .collect();
                let ts = Instant::now();
                let fill = if masks[i].iter().all(|&m| m < 0.5) {
                    Fill {
                        rgb: rgb.clone(),
                        depth: depth.clone(),
                    }
                } else {
                    let target = Target::new(w, h, &rgb, &depth, &masks[i], t);
                    let seed = self.stage2.seed ^ 0x5_7a9e_3000 ^ ((round as u64) << 32) ^ i as u64;
                    inpainter
                        .inpaint(&target, &sources, seed)
                        .with_context(|| format!("training view {i}, data round {round}"))?
                };
                inpaint_s += ts.elapsed().as_secs_f64();
                let (photo, virt) =
                    collector_views(&captured[i], &masks_full[i], cam, &fill, &masks[i], weight);
                views.push(photo);
                views.push(virt);
            }
            let data = TrainData::with_sampling(
                ctx,
                &views,
                ViewSampling::VirtualFraction(self.stage2.virtual_fraction),
            )?;
            train_steps(
                ctx,
                &mut trainer,
                &prims,
                &data,
                self.spec.data_steps_per_round,
                &format!("{DATA_STAGE} round {round}"),
                &out,
                rep,
            )?;
            add(
                format!("inpainted@{round}"),
                trainer.nerf(),
                Some(&masks),
                &mut entries,
            )?;
            rep.note(&format!(
                "{DATA_STAGE} round {}/{}: t {t:.2}, {} triplets so far",
                round + 1,
                self.spec.data_rounds,
                entries.len()
            ));
        }
        let triplets = Triplets {
            width: w,
            height: h,
            photos,
            masks,
            entries,
            renders,
        };
        triplets.save(&out)?;
        Ok(json!({
            "triplets": triplets.entries.len(),
            "views": cams.len(),
            "width": w,
            "height": h,
            "masked_fraction": masked,
            "fresh_field_seconds": fresh_s,
            "inpainted_field_seconds": ti.elapsed().as_secs_f64(),
            "inpaint_seconds": inpaint_s,
        }))
    }
}

/// The enhancer, trained on the data stage's triplets.
#[derive(Clone, Debug)]
pub struct EnhancerStage {
    pub spec: Stage3Spec,
}

impl EnhancerStage {
    /// Its folder.
    pub fn dir(dir: &RunDir) -> PathBuf {
        dir.root.join(ENHANCER_STAGE)
    }
}

impl Stage for EnhancerStage {
    fn name(&self) -> String {
        ENHANCER_STAGE.into()
    }

    fn config(&self) -> Value {
        json!({"enhancer": self.spec.enhancer, "backend": self.spec.backend})
    }

    fn inputs(&self) -> Vec<String> {
        vec![DATA_STAGE.into()]
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> anyhow::Result<Value> {
        let triplets = Triplets::load(&dir.root.join(DATA_STAGE))?;
        let e = &self.spec.enhancer;
        if e.crop > triplets.width.min(triplets.height) {
            bail!(
                "--enhancer-crop {} is larger than the {}x{} training views at the virtual views' scale",
                e.crop,
                triplets.width,
                triplets.height
            );
        }
        let (b, device) = extranerf_diffusion::device::diffusion_device(ctx, self.spec.backend)?;
        rep.note(&format!(
            "{ENHANCER_STAGE}: {} on {} triplets of {} views, on {}",
            match &e.base_model {
                Some(m) => format!("LoRA rank {} on {}", e.rank, m.display()),
                None => format!(
                    "a pixel-space U-Net {:?} from scratch (no pretrained weights)",
                    e.channels
                ),
            },
            triplets.entries.len(),
            triplets.photos.len(),
            b.name()
        ));
        let out = Self::dir(dir);
        std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
        // A check of an earlier enhancer in this folder no longer holds.
        let check = out.join(CHECK_FILE);
        if check.exists() {
            std::fs::remove_file(&check)
                .with_context(|| format!("removing {}", check.display()))?;
        }
        let t = Instant::now();
        let rec = enhancer::train_enhancer(&triplets.train_images(), e, &out, &device, &mut |p| {
            let secs = t.elapsed().as_secs_f64();
            rep.progress(&Progress {
                unit: Unit::ModelSteps,
                step: p.step as u32,
                total: p.steps as u32,
                loss: p.loss,
                psnr: 0.0,
                samples_per_s: 0.0,
                secs,
                eta: secs / p.step.max(1) as f64 * p.steps.saturating_sub(p.step) as f64,
            });
        })?;
        Ok(json!({
            "params": rec.params,
            "final_loss": rec.curve.last().map(|c| c.1),
            "train_seconds": rec.seconds,
            "backend": b.name(),
        }))
    }
}

/// Stage 3 of one stage-2 variant.
#[derive(Clone, Debug)]
pub struct EnhanceStage {
    /// The stage-2 variant it continues.
    pub kind: InpainterKind,
    pub spec: Stage3Spec,
    pub virt: VirtualSpec,
    pub vis: VisSettings,
}

impl EnhanceStage {
    fn stage2_name(&self) -> String {
        format!("stage2-{}", self.kind.name())
    }
}

impl Stage for EnhanceStage {
    fn name(&self) -> String {
        format!("stage3-{}", self.kind.name())
    }

    fn config(&self) -> Value {
        let s = &self.spec;
        let mut c = json!({
            "rounds": s.rounds,
            "steps_per_round": s.steps_per_round,
            "t": s.t,
            "ddim_steps": s.ddim_steps,
            "virtual_fraction": s.virtual_fraction,
            "lr": s.lr,
            "seed": s.seed,
        });
        // Recorded only when on, so that runs made before the setting existed still resume.
        if s.anchor_radius > 0 {
            c["anchor_radius"] = json!(s.anchor_radius);
        }
        if s.visible_weight != 1.0 {
            c["visible_weight"] = json!(s.visible_weight);
        }
        if s.smooth_radius > 0 {
            c["smooth_radius"] = json!(s.smooth_radius);
        }
        if s.l1_core > 0.0 {
            c["l1_core"] = json!(s.l1_core);
        }
        match s.enhance {
            // Recorded only when checked: runs made before the gate existed ran stage 3 always.
            Stage3Enhancer::Diffusion if s.gate == Stage3Gate::Check => {
                c["gate"] = json!(s.gate);
            }
            Stage3Enhancer::Diffusion => {}
            // The gate judges a trained enhancer; a fixed filter has none to judge.
            Stage3Enhancer::Unsharp => {
                c["enhance"] = json!(s.enhance);
                c["unsharp_amount"] = json!(s.unsharp_amount);
                c["unsharp_radius"] = json!(s.unsharp_radius);
            }
        }
        c
    }

    fn inputs(&self) -> Vec<String> {
        match self.spec.enhance {
            Stage3Enhancer::Diffusion => vec![self.stage2_name(), ENHANCER_STAGE.into()],
            Stage3Enhancer::Unsharp => vec![self.stage2_name()],
        }
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> anyhow::Result<Value> {
        self.spec.validate()?;
        let out = dir.root.join(self.name());
        std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
        // The diffusion enhancer and where it runs; None: the unsharp mask.
        let model = match self.spec.enhance {
            Stage3Enhancer::Diffusion => {
                let (b, device) =
                    extranerf_diffusion::device::diffusion_device(ctx, self.spec.backend)?;
                let pipe = enhancer::load(&EnhancerStage::dir(dir), &device)?;
                Some((b, device, pipe))
            }
            Stage3Enhancer::Unsharp => None,
        };
        // A stage with rounds done passed its gate when it started (a skipped one writes
        // none); it resumes without judging again.
        let resuming = out.join(crate::pipeline::ROUND_FILE).exists();
        let check = match (&model, self.spec.gate) {
            (Some(_), Stage3Gate::Check) if resuming => {
                rep.note(&format!(
                    "{}: resuming, the enhancer check passed when it started",
                    self.name()
                ));
                None
            }
            (Some((_, device, pipe)), Stage3Gate::Check) => {
                let c = check_enhancer(dir, &self.spec, pipe, device, rep)?;
                rep.note(&format!(
                    "{}: enhancer check, {}",
                    self.name(),
                    c.describe()
                ));
                Some(c)
            }
            _ => None,
        };
        if let Some(c) = check.as_ref().filter(|c| !c.helps()) {
            let why = format!(
                "skipped: the enhancer made the renders of its own training views worse ({}); \
                 the field is {}'s (--stage3-gate off runs stage 3 anyway)",
                c.describe(),
                self.stage2_name()
            );
            rep.note(&format!("{}: {why}", self.name()));
            keep_stage2(&dir.root.join(self.stage2_name()), &out)?;
            return Ok(json!({"rounds": [], "seconds": 0.0, "check": c, "skipped": why}));
        }
        let base = BaseField::load(ctx, &dir.base)?;
        let from = load_checkpoint(&dir.root.join(self.stage2_name()))
            .with_context(|| format!("the {} field", self.stage2_name()))?;
        let cfg: RunConfig = from.config.clone();
        let samples = cfg.train.samples;
        let virt = make_virtual(&self.virt, &base.train_cameras())?;
        let maps_path = dir.visibility().join(MAPS_FILE);
        let st = SafeTensors::read(&maps_path)?;
        let masks: Vec<Vec<f32>> = (0..virt.len())
            .map(|i| {
                Ok(self
                    .vis
                    .mask(&load_map(&st, &maps_path, &format!("virtual_{i:03}"))?))
            })
            .collect::<anyhow::Result<_>>()?;
        let (captured, _) =
            training_views_in(ctx, &cfg.scene, &base.loaded, &cfg.model, &dir.base)?;
        let (start_round, mut seconds, params, moments) = match load_round(&out)? {
            Some((s, ck)) => {
                rep.note(&format!(
                    "{}: resuming after round {}",
                    self.name(),
                    s.rounds_done
                ));
                (s.rounds_done, s.seconds, ck.params, ck.moments)
            }
            None => (0, 0.0, from.params.clone(), from.moments.clone()),
        };
        let mut tcfg = cfg.train.clone();
        let total = self.spec.rounds * self.spec.steps_per_round;
        tcfg.steps = from.step + total;
        tcfg.decay_steps = tcfg.steps;
        tcfg.lr_start = self.spec.lr;
        tcfg.lr_end = self.spec.lr;
        tcfg.virtual_l1_core = self.spec.l1_core;
        let nerf = Nerf::new(ctx, cfg.model.clone(), &params, cfg.train.background)?;
        let moments = moments.as_ref().map(|(m, v)| (m.as_slice(), v.as_slice()));
        let mut trainer = Trainer::new(
            ctx,
            nerf,
            tcfg.clone(),
            from.step + start_round * self.spec.steps_per_round,
            moments,
        )?;
        let prims = Prims::new(ctx)?;
        rep.note(&format!(
            "{}: {}, loss weight {:.3}",
            self.name(),
            match &model {
                Some((b, _, _)) => format!(
                    "enhancer on {}, from t = {} in {} DDIM steps",
                    b.name(),
                    self.spec.t,
                    self.spec.ddim_steps
                ),
                None => format!(
                    "unsharp mask, amount {} radius {}",
                    self.spec.unsharp_amount, self.spec.unsharp_radius
                ),
            },
            self.spec.weight()
        ));
        let weight = self.spec.weight();
        let mut rounds = Vec::new();
        for round in start_round..self.spec.rounds {
            let t0 = Instant::now();
            let round_dir = out.join(format!("round_{round:02}"));
            std::fs::create_dir_all(&round_dir)
                .with_context(|| format!("creating {}", round_dir.display()))?;
            let mut views = captured.clone();
            let (mut render_s, mut enhance_s, mut change) = (0.0, 0.0, 0.0);
            // Detail energy of the renders and of the targets made from them.
            let (mut detail_render, mut detail_target) = (0.0, 0.0);
            for (k, cam) in virt.iter().enumerate() {
                let tr = Instant::now();
                let (rgb, depth, _) = render(ctx, trainer.nerf(), cam, samples)?;
                render_s += tr.elapsed().as_secs_f64();
                let te = Instant::now();
                let (w, h) = (cam.width as usize, cam.height as usize);
                let seed = self.spec.seed ^ 0xe7_4a9c_e000 ^ ((round as u64) << 32) ^ k as u64;
                let target = self
                    .spec
                    .target(
                        model.as_ref().map(|(_, device, pipe)| (pipe, device)),
                        &rgb,
                        &masks[k],
                        w,
                        h,
                        seed,
                    )
                    .with_context(|| format!("enhancing virtual view {k}, round {round}"))?;
                // The anchoring and smoothing are counted too (a blur or two: milliseconds).
                enhance_s += te.elapsed().as_secs_f64();
                detail_render += detail_energy(&rgb, w, h);
                detail_target += detail_energy(&target, w, h);
                change += rgb
                    .iter()
                    .zip(&target)
                    .map(|(a, b)| (a - b).abs() as f64)
                    .sum::<f64>()
                    / rgb.len() as f64;
                write_png(
                    &round_dir.join(format!("virtual_{k:03}_render.png")),
                    cam.width,
                    cam.height,
                    &rgb,
                )?;
                write_png(
                    &round_dir.join(format!("virtual_{k:03}.png")),
                    cam.width,
                    cam.height,
                    &target,
                )?;
                // The enhanced colours with w(t) (times --stage3-visible-weight where seen);
                // the depth loss on the field's own (stage-2 completed) depth keeps the
                // geometry while the colours change.
                views.push(View {
                    camera: cam.clone(),
                    image: Image::opaque(cam.width, cam.height, target),
                    depth: Some(depth.iter().map(|&d| [d, 1.0]).collect()),
                    weight: Some(virtual_weights(&masks[k], weight, self.spec.visible_weight)),
                    kind: ViewKind::Virtual,
                });
            }
            let (last, train_s) = train_round(
                ctx,
                &mut trainer,
                &prims,
                &views,
                self.spec.virtual_fraction,
                self.spec.steps_per_round,
                &format!("{} round {round}", self.name()),
                &RoundSink {
                    out: &out,
                    cfg: &cfg,
                    tcfg: &tcfg,
                },
                (round, t0, &mut seconds),
                rep,
            )?;
            let mean_change = change / virt.len().max(1) as f64;
            let detail_ratio = detail_target / detail_render.max(1e-12);
            rep.note(&format!(
                "{} round {}/{}: render {render_s:.1} s, enhance {enhance_s:.1} s, train {train_s:.1} s; enhancement changed the renders by {mean_change:.4} (mean absolute), detail energy x{detail_ratio:.2}",
                self.name(),
                round + 1,
                self.spec.rounds
            ));
            rounds.push(json!({
                "round": round,
                "render_seconds": render_s,
                "enhance_seconds": enhance_s,
                "train_seconds": train_s,
                "mean_abs_change": mean_change,
                "detail_ratio": detail_ratio,
                "batch_psnr": last.map(|s| s.psnr()),
            }));
        }
        write_test_renders(ctx, trainer.nerf(), &base.loaded, samples, &out)?;
        Ok(json!({"rounds": rounds, "seconds": seconds, "check": check}))
    }
}

/// A skipped stage 3: the stage-2 field and its held-out renders, copied from `from` to `out`
/// (what the fly-through and `eval` read).
fn keep_stage2(from: &Path, out: &Path) -> anyhow::Result<()> {
    let entries = std::fs::read_dir(from).with_context(|| format!("reading {}", from.display()))?;
    for e in entries {
        let e = e.with_context(|| format!("reading {}", from.display()))?;
        let name = e.file_name().to_string_lossy().into_owned();
        let test = name.starts_with("test_") && name.ends_with(".png");
        if test
            || name == extranerf_nerf::run::CHECKPOINT_FILE
            || name == extranerf_nerf::run::CONFIG_FILE
        {
            std::fs::copy(e.path(), out.join(&name))
                .with_context(|| format!("copying {} to {}", e.path().display(), out.display()))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::{
        check_triplets, detail_energy, stage3_target, unsharp, virtual_weights, EnhancerCheck,
        Stage3Enhancer, Stage3Spec, TripletEntry, Triplets,
    };

    #[test]
    fn the_unsharp_mask_overshoots_an_edge_by_the_tent_blur() {
        // A vertical step 0.2 | 0.8 between columns 3 and 4 of an 8x3 image. The tent of
        // radius 1 is [1, 2, 3, 2, 1] / 9: beside the edge the blur is 0.4 (dark side) and 0.6
        // (bright side), so amount 0.5 gives 0.1 and 0.9; two columns away it is 2.4 / 9 and
        // 6.6 / 9, giving 1 / 6 and 5 / 6; three columns away nothing changes.
        let (w, h) = (8, 3);
        let img: Vec<f32> = (0..w * h * 3)
            .map(|i| if (i / 3) % w < 4 { 0.2 } else { 0.8 })
            .collect();
        let out = unsharp(&img, w, h, 0.5, 1);
        let want = [0.2, 0.2, 1.0 / 6.0, 0.1, 0.9, 5.0 / 6.0, 0.8, 0.8];
        for (i, v) in out.iter().enumerate() {
            let x = (i / 3) % w;
            assert!((v - want[x]).abs() < 1e-6, "column {x}: {v}");
        }
        // Clamped to [0, 1]; a constant image is left as it is.
        let strong = unsharp(&img, w, h, 4.0, 1);
        assert!(strong.iter().all(|v| (0.0..=1.0).contains(v)));
        assert_eq!((strong[3 * 3], strong[4 * 3]), (0.0, 1.0));
        let flat = vec![0.37f32; w * h * 3];
        assert!(unsharp(&flat, w, h, 2.0, 2)
            .iter()
            .all(|v| (v - 0.37).abs() < 1e-6));
        // Its settings are checked only when it is chosen.
        let spec = |amount, radius| Stage3Spec {
            enhance: Stage3Enhancer::Unsharp,
            unsharp_amount: amount,
            unsharp_radius: radius,
            ..Stage3Spec::default()
        };
        assert!(spec(0.5, 1).validate().is_ok());
        for (a, r) in [(0.0, 1), (4.5, 1), (f32::NAN, 1), (0.5, 0), (0.5, 65)] {
            let e = spec(a, r).validate().unwrap_err().to_string();
            assert!(e.contains("--stage3-unsharp-amount"), "{e}");
        }
        let diffusion = Stage3Spec {
            unsharp_amount: 0.0,
            ..Stage3Spec::default()
        };
        assert!(diffusion.validate().is_ok());
    }

    #[test]
    fn the_check_judges_by_lpips_and_by_psnr_without_it() {
        let c = EnhancerCheck {
            t: 0.3,
            ddim_steps: 10,
            seed: 0,
            anchor_radius: 0,
            smooth_radius: 0,
            triplets: vec!["t000".into()],
            psnr_render: 25.0,
            psnr_enhanced: 26.0,
            lpips_render: Some(0.20),
            lpips_enhanced: Some(0.25),
            seconds: 1.0,
        };
        // LPIPS rules where measured, even against a better PSNR; an equal LPIPS fails.
        assert!(!c.helps());
        let better = EnhancerCheck {
            lpips_enhanced: Some(0.15),
            psnr_enhanced: 20.0,
            ..c.clone()
        };
        assert!(better.helps());
        assert!(!EnhancerCheck {
            lpips_enhanced: Some(0.20),
            ..c.clone()
        }
        .helps());
        let psnr_only = EnhancerCheck {
            lpips_render: None,
            lpips_enhanced: None,
            ..c.clone()
        };
        assert!(psnr_only.helps());
        assert!(!EnhancerCheck {
            psnr_enhanced: 25.0,
            ..psnr_only.clone()
        }
        .helps());
        assert!(c.describe().contains("LPIPS-alex 0.200 -> 0.250"));
        assert!(!psnr_only.describe().contains("LPIPS"));
    }

    #[test]
    fn the_check_takes_one_triplet_per_view_with_the_sources_in_turn() {
        let entry = |k: usize, slot: usize, source: &str| TripletEntry {
            key: format!("t{k:03}"),
            slot,
            source: source.into(),
        };
        // Three views: view 0 with two triplets, view 1 with none, view 2 with three.
        let entries = vec![
            entry(0, 0, "base"),
            entry(1, 2, "base"),
            entry(2, 0, "inpainted@0"),
            entry(3, 2, "inpainted@0"),
            entry(4, 2, "inpainted@1"),
        ];
        let tr = Triplets {
            width: 1,
            height: 1,
            photos: vec![vec![0.0; 3]; 3],
            masks: vec![vec![0.0]; 3],
            renders: vec![(vec![0.0; 3], vec![0.0]); entries.len()],
            entries,
        };
        // View 0: its 0th (t000); view 1: none; view 2: its 2 mod 3 = 2nd (t004).
        assert_eq!(check_triplets(&tr), [0, 4]);
    }

    /// An `[h, w, 3]` image from a per-pixel function of (x, y), the same in every channel.
    fn image(w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> Vec<f32> {
        (0..w * h).flat_map(|i| [f(i % w, i / w); 3]).collect()
    }

    #[test]
    fn detail_energy_is_the_mean_squared_laplacian() {
        assert_eq!(detail_energy(&image(6, 5, |_, _| 0.3), 6, 5), 0.0);
        // A linear ramp has no Laplacian.
        let ramp = image(7, 6, |x, y| 0.1 * x as f32 + 0.05 * y as f32);
        assert!(detail_energy(&ramp, 7, 6) < 1e-12);
        // A checkerboard of +-a around 0.5: every interior Laplacian is +-8a.
        let a = 0.1f32;
        let board = image(
            8,
            7,
            |x, y| if (x + y) % 2 == 0 { 0.5 + a } else { 0.5 - a },
        );
        let want = 64.0 * f64::from(a) * f64::from(a);
        assert!((detail_energy(&board, 8, 7) - want).abs() < 1e-6 * want);
        // Too small for an interior: 0, not a division by zero.
        assert_eq!(detail_energy(&image(2, 9, |x, _| x as f32), 2, 9), 0.0);
    }

    #[test]
    fn smoothing_keeps_the_enhancements_colour_change_and_drops_its_pixel_noise() {
        let (w, h) = (40, 30);
        // The render: a smooth shading with a sharp edge (detail the targets must keep).
        let render = image(w, h, |x, y| {
            0.3 + 0.004 * x as f32 + 0.003 * y as f32 + if x >= 20 { 0.2 } else { 0.0 }
        });
        // The enhancer: the render brightened by 0.05, plus a +-0.05 checkerboard of noise.
        let noise = |x: usize, y: usize| {
            if (x + y).is_multiple_of(2) {
                0.05
            } else {
                -0.05
            }
        };
        let enhanced: Vec<f32> = render
            .iter()
            .enumerate()
            .map(|(i, &r)| r + 0.05 + noise((i / 3) % w, (i / 3) / w))
            .collect();
        assert_eq!(stage3_target(&render, &enhanced, w, h, 0, 0), enhanced);
        let t = stage3_target(&render, &enhanced, w, h, 0, 2);
        // Away from the borders (where the box blur's window is cut) the target is the render
        // plus the change of colour: the noise is gone, the edge is kept.
        for y in 5..h - 5 {
            for x in 5..w - 5 {
                let i = (y * w + x) * 3;
                let d = t[i] - render[i] - 0.05;
                assert!(d.abs() < 2e-3, "({x}, {y}): {d}");
            }
        }
        assert!(detail_energy(&t, w, h) < 1.2 * detail_energy(&render, w, h));
        assert!(detail_energy(&enhanced, w, h) > 10.0 * detail_energy(&render, w, h));
        // Colour anchoring alone does the opposite: it keeps the noise and drops the colour
        // change; the two together keep neither.
        let a = stage3_target(&render, &enhanced, w, h, 2, 0);
        let both = stage3_target(&render, &enhanced, w, h, 2, 2);
        let i = (15 * w + 10) * 3;
        assert!((a[i] - render[i] - noise(10, 15)).abs() < 2e-3);
        assert!((both[i] - render[i]).abs() < 2e-3);
    }

    #[test]
    fn seen_pixels_of_a_virtual_view_carry_the_visible_weight() {
        let mask = [0.0, 0.49, 0.5, 1.0];
        assert_eq!(virtual_weights(&mask, 0.9, 1.0), [0.9; 4]);
        assert_eq!(virtual_weights(&mask, 0.9, 0.0), [0.0, 0.0, 0.9, 0.9]);
        assert_eq!(virtual_weights(&mask, 0.8, 0.5), [0.4, 0.4, 0.8, 0.8]);
    }
}
