//! Training the inpainting model: from scratch (the scene prior) or LoRA fine-tuning
//! (DreamBooth-style, on the input views with their pseudo-disocclusion masks plus random
//! masks).
//!
//! Every step draws a batch on the host (random crops, flips, colour jitter, random hole masks,
//! the given masks), uploads it once, and runs forward, backward and AdamW on the device. The
//! loss is the diffusion loss (noise or v) averaged over the cells whose pixels are all known:
//! pixels marked unknown (held out, or outside a view) are always inside the hole the model is
//! shown and never enter the loss, so a model never sees what it is later scored on.

use burn::optim::{AdamWConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor};

use crate::inpaint::{seeded_noise, unet_input, Codec, SplitMix};
use crate::scheduler::Schedule;
use crate::train_state::{self, Checkpointing, Snapshot};
use crate::{DiffusionError, Result};

pub use crate::train_spec::{Augment, Guide, TrainImage, TrainSettings, Trainable};

/// One progress report.
#[derive(Clone, Debug, PartialEq)]
pub struct Progress {
    /// Steps done.
    pub step: usize,
    /// Of.
    pub steps: usize,
    /// Mean loss over the steps since the last report.
    pub loss: f64,
    /// Seconds since the start.
    pub elapsed: f64,
}

/// A batch in host memory.
#[derive(Clone, Debug)]
pub struct Batch {
    /// Crops.
    pub n: usize,
    /// Side.
    pub size: usize,
    /// `[n, 3, s, s]` in [0, 1] (unknown pixels 0.5).
    pub image: Vec<f32>,
    /// `[n, 1, s, s]`: 1 = hole shown to the model (includes every unknown pixel).
    pub hole: Vec<f32>,
    /// `[n, 1, s, s]`: 1 = known (enters the loss).
    pub known: Vec<f32>,
    /// An enhancer's batch: `[n, 3, s, s]` in [0, 1], the corrupted images shown whole as
    /// guidance (`hole` is then their fill masks).
    pub guide: Option<Vec<f32>>,
}

fn paint_rect(m: &mut [f32], s: usize, rng: &mut SplitMix, max_frac: f64) {
    let side = |rng: &mut SplitMix| {
        let f = 0.15 + rng.unit() * (max_frac.sqrt() - 0.15).max(0.0);
        ((f * s as f64) as usize).clamp(1, s)
    };
    let (w, h) = (side(rng), side(rng));
    let (x0, y0) = (rng.below(s - w + 1), rng.below(s - h + 1));
    for y in y0..y0 + h {
        for x in x0..x0 + w {
            m[y * s + x] = 1.0;
        }
    }
}

fn paint_stroke(m: &mut [f32], s: usize, rng: &mut SplitMix) {
    let mut x = rng.unit() * s as f64;
    let mut y = rng.unit() * s as f64;
    let r = 1.0 + rng.unit() * s as f64 / 12.0;
    let mut angle = rng.unit() * std::f64::consts::TAU;
    for _ in 0..(4 + rng.below(6)) {
        angle += (rng.unit() - 0.5) * 2.0;
        let len = (0.1 + rng.unit() * 0.3) * s as f64;
        let steps = (len / (r * 0.5)).ceil() as usize;
        for _ in 0..steps {
            x = (x + angle.cos() * r * 0.5).clamp(0.0, s as f64 - 1.0);
            y = (y + angle.sin() * r * 0.5).clamp(0.0, s as f64 - 1.0);
            let (lo_y, hi_y) = ((y - r).max(0.0) as usize, ((y + r) as usize).min(s - 1));
            let (lo_x, hi_x) = ((x - r).max(0.0) as usize, ((x + r) as usize).min(s - 1));
            for py in lo_y..=hi_y {
                for px in lo_x..=hi_x {
                    let (dx, dy) = (px as f64 - x, py as f64 - y);
                    if dx * dx + dy * dy <= r * r {
                        m[py * s + px] = 1.0;
                    }
                }
            }
        }
    }
}

/// Random hole masks of side `s`: one to three rectangles or strokes, never the whole crop.
pub fn random_hole(s: usize, rng: &mut SplitMix, max_frac: f64) -> Vec<f32> {
    let mut m = vec![0.0f32; s * s];
    for _ in 0..(1 + rng.below(3)) {
        if rng.unit() < 0.5 {
            paint_rect(&mut m, s, rng, max_frac);
        } else {
            paint_stroke(&mut m, s, rng);
        }
    }
    let covered = m.iter().filter(|v| **v > 0.5).count();
    if covered == s * s {
        // Keep a known border so the model always has context.
        for y in 0..s {
            for x in 0..s {
                if x < s / 8 || y < s / 8 {
                    m[y * s + x] = 0.0;
                }
            }
        }
    }
    m
}

/// Draws a batch of augmented crops with holes.
pub fn draw_batch(
    images: &[TrainImage],
    aug: &Augment,
    n: usize,
    rng: &mut SplitMix,
) -> Result<Batch> {
    let s = aug.crop;
    if images.is_empty() {
        return Err(DiffusionError::Input("no training images".into()));
    }
    if let Some((i, im)) = images
        .iter()
        .enumerate()
        .find(|(_, im)| im.width < s || im.height < s)
    {
        return Err(DiffusionError::Input(format!(
            "training image {i} is {}x{}, smaller than the {s}-pixel crop",
            im.width, im.height
        )));
    }
    let enhancer = images.iter().any(|im| !im.guides.is_empty());
    if let Some(i) = images
        .iter()
        .position(|im| enhancer && im.guides.is_empty())
    {
        return Err(DiffusionError::Input(format!(
            "training image {i} has no corrupted version, but others do: an enhancer needs one for every image"
        )));
    }
    let mut image = vec![0.5f32; n * 3 * s * s];
    let mut hole = vec![0.0f32; n * s * s];
    let mut known = vec![0.0f32; n * s * s];
    let mut guide = enhancer.then(|| vec![0.5f32; n * 3 * s * s]);
    for b in 0..n {
        let im = &images[rng.below(images.len())];
        let (x0, y0) = (rng.below(im.width - s + 1), rng.below(im.height - s + 1));
        let flip = aug.flip && rng.unit() < 0.5;
        let j = aug.jitter;
        let bright = 1.0 + (rng.unit() * 2.0 - 1.0) * j;
        let contrast = 1.0 + (rng.unit() * 2.0 - 1.0) * j;
        let sat = 1.0 + (rng.unit() * 2.0 - 1.0) * j;
        let own = (!im.masks.is_empty() && rng.unit() < aug.own_mask_probability)
            .then(|| &im.masks[rng.below(im.masks.len())]);
        let random = random_hole(s, rng, aug.max_hole_fraction);
        let g = enhancer.then(|| &im.guides[rng.below(im.guides.len())]);
        let jitter = |px: [f64; 3], c: usize| {
            let grey = (px[0] + px[1] + px[2]) / 3.0;
            let v = grey + (px[c] - grey) * sat;
            (((v - 0.5) * contrast + 0.5) * bright).clamp(0.0, 1.0) as f32
        };
        for y in 0..s {
            for x in 0..s {
                let sx = if flip { x0 + s - 1 - x } else { x0 + x };
                let si = (y0 + y) * im.width + sx;
                let di = y * s + x;
                let k = im.known[si] >= 0.5;
                let mut h = match (g, own) {
                    (Some(g), _) => g.mask[si] >= 0.5,
                    (None, Some(m)) => m[si] >= 0.5,
                    (None, None) => random[di] >= 0.5,
                };
                if !k {
                    h = true;
                }
                hole[b * s * s + di] = if h { 1.0 } else { 0.0 };
                known[b * s * s + di] = if k { 1.0 } else { 0.0 };
                if k {
                    let px: [f64; 3] = std::array::from_fn(|c| im.rgb[3 * si + c] as f64);
                    for c in 0..3 {
                        image[b * 3 * s * s + c * s * s + di] = jitter(px, c);
                    }
                }
                // The corrupted version goes through the same crop, flip and jitter, all of
                // it (its unknown pixels are no less its input).
                if let (Some(g), Some(out)) = (g, guide.as_mut()) {
                    let px: [f64; 3] = std::array::from_fn(|c| g.rgb[3 * si + c] as f64);
                    for c in 0..3 {
                        out[b * 3 * s * s + c * s * s + di] = jitter(px, c);
                    }
                }
            }
        }
    }
    Ok(Batch {
        n,
        size: s,
        image,
        hole,
        known,
        guide,
    })
}

/// The diffusion loss of one batch (on the device; nothing is read back), over every
/// timestep.
pub fn batch_loss(
    model: &Trainable,
    codec: &Codec,
    schedule: &Schedule,
    batch: &Batch,
    cond_dropout: f64,
    rng: &mut SplitMix,
    device: &Device,
) -> Tensor<1> {
    batch_loss_upto(
        model,
        codec,
        schedule,
        batch,
        cond_dropout,
        1.0,
        false,
        rng,
        device,
    )
}

/// [`batch_loss`] with the timesteps drawn from the first `max_strength` of the schedule,
/// and with `residual`, the U-Net's output added to its guidance
/// ([`crate::inpaint::Task::EnhanceResidual`]).
#[allow(clippy::too_many_arguments)] // each is a distinct operand
pub fn batch_loss_upto(
    model: &Trainable,
    codec: &Codec,
    schedule: &Schedule,
    batch: &Batch,
    cond_dropout: f64,
    max_strength: f64,
    residual: bool,
    rng: &mut SplitMix,
    device: &Device,
) -> Tensor<1> {
    let (n, s) = (batch.n, batch.size);
    let image = Tensor::<1>::from_floats(batch.image.as_slice(), device).reshape([n, 3, s, s]);
    let hole = Tensor::<1>::from_floats(batch.hole.as_slice(), device).reshape([n, 1, s, s]);
    let known = Tensor::<1>::from_floats(batch.known.as_slice(), device).reshape([n, 1, s, s]);
    let x = image * 2.0 - 1.0;
    // Unknown pixels are 0 in [-1, 1] (grey) and never enter the loss.
    let x = x * known.clone();
    let keep = hole.clone().neg() + 1.0;
    let z0 = codec.encode(x.clone()).detach();
    // The guidance: the image with its hole blanked, or an enhancer's corrupted image whole.
    let masked = match &batch.guide {
        Some(g) => {
            let g = Tensor::<1>::from_floats(g.as_slice(), device).reshape([n, 3, s, s]);
            codec.encode(g * 2.0 - 1.0).detach()
        }
        None => codec.encode(x * keep).detach(),
    };
    let mask_z = codec.mask(hole);
    let valid = codec.mask(known.neg() + 1.0).neg() + 1.0;
    let t_max = ((schedule.len() as f64 * max_strength).ceil() as usize).clamp(1, schedule.len());
    let t: Vec<usize> = (0..n).map(|_| rng.below(t_max)).collect();
    let noise = seeded_noise(z0.dims(), rng.next_u64(), device);
    let zt = schedule.add_noise(z0.clone(), noise.clone(), &t);
    let target = schedule.target(z0, noise, &t);
    let ts: Vec<f32> = t.iter().map(|&t| t as f32).collect();
    // Conditioning dropout: some items see the null context, so that guidance has a trained
    // unconditional branch.
    let keep: Vec<f32> = (0..n)
        .map(|_| if rng.unit() < cond_dropout { 0.0 } else { 1.0 })
        .collect();
    let context = if keep.iter().all(|k| *k == 1.0) {
        model.tokens.forward(n)
    } else {
        let k = Tensor::<1>::from_floats(keep.as_slice(), device).reshape([n, 1, 1]);
        model.tokens.forward(n) * k.clone() + model.tokens.null(n, device) * (k.neg() + 1.0)
    };
    let mut pred = model
        .unet
        .forward(unet_input(zt, mask_z, masked.clone()), &ts, &context);
    if residual {
        pred = pred + masked;
    }
    let c = pred.dims()[1] as f64;
    let err = (pred - target).powi_scalar(2) * valid.clone();
    err.sum() / (valid.sum() * c + 1e-6)
}

/// Trains `model` (parameters on an autodiff device; frozen ones get no update) and returns it
/// with the loss curve (step, mean loss per report). `on_progress` sees every report. With
/// `checkpoint`, the state is saved at its interval and at the last step, and a resume
/// continues from it (see [`crate::train_state`]): the result is the one an uninterrupted run
/// gives.
#[allow(clippy::too_many_arguments)] // each is a distinct input of the loop
pub fn train(
    mut model: Trainable,
    codec: &Codec,
    schedule: &Schedule,
    images: &[TrainImage],
    aug: &Augment,
    s: &TrainSettings,
    device: &Device,
    checkpoint: Option<&Checkpointing>,
    on_progress: &mut dyn FnMut(&Progress),
) -> Result<(Trainable, Vec<(usize, f64)>)> {
    if !device.is_autodiff() {
        return Err(DiffusionError::Input(
            "training needs an autodiff device (Device::autodiff)".into(),
        ));
    }
    for (i, im) in images.iter().enumerate() {
        im.check(i)?;
    }
    let m = codec.factor() * (1 << (model.unet.down_blocks.len() - 1));
    if aug.crop == 0 || !aug.crop.is_multiple_of(m) {
        return Err(DiffusionError::Input(format!(
            "crop {} must be a positive multiple of {m} for this model",
            aug.crop
        )));
    }
    if s.steps == 0
        || s.batch == 0
        || !(s.lr.is_finite() && s.lr > 0.0)
        || !(s.token_lr.is_finite() && s.token_lr >= 0.0)
        || !(0.0..1.0).contains(&s.cond_dropout)
        || !(s.max_strength > 0.0 && s.max_strength <= 1.0)
    {
        return Err(DiffusionError::Input(format!(
            "steps {} and batch {} must be > 0, lr {} > 0, token lr {} >= 0, conditioning dropout {} in [0, 1) and the largest strength {} in (0, 1]",
            s.steps, s.batch, s.lr, s.token_lr, s.cond_dropout, s.max_strength
        )));
    }
    let adam = || {
        let c = AdamWConfig::new()
            .with_beta_2(0.999)
            .with_epsilon(1e-8)
            .with_weight_decay(0.0);
        let c = if s.clip > 0.0 {
            c.with_grad_clipping(Some(burn::grad_clipping::GradientClippingConfig::Norm(
                s.clip as f32,
            )))
        } else {
            c
        };
        c.init()
    };
    if let Some(ck) = checkpoint {
        if ck.every == 0 {
            return Err(DiffusionError::Input(
                "the checkpoint interval must be at least one step".into(),
            ));
        }
    }
    let hash = train_state::images_hash(images);
    let mut opt_unet: ModuleOptimizer = adam();
    let mut opt_tokens: ModuleOptimizer = adam();
    let mut rng = SplitMix(s.seed);
    let mut curve = Vec::new();
    let mut pending: Option<Tensor<1>> = None;
    let mut since = 0usize;
    let mut first = 1;
    let mut earlier = 0.0;
    match checkpoint {
        Some(ck) if ck.resume => {
            let r = train_state::load(ck, model, opt_unet, opt_tokens, s, aug, &hash)?;
            model = r.model;
            opt_unet = r.opt_unet;
            opt_tokens = r.opt_tokens;
            rng = SplitMix(r.state.rng);
            curve = r.state.curve;
            let (sum, n) = r.state.pending;
            if n > 0 {
                pending = Some(Tensor::<1>::from_floats([sum as f32], device));
            }
            since = n;
            first = r.state.step + 1;
            earlier = r.state.seconds;
        }
        Some(ck) => {
            if let Some(st) = train_state::peek(&ck.dir)? {
                return Err(DiffusionError::Input(format!(
                    "{} holds an unfinished training (step {}); resume it or choose another folder",
                    ck.dir.display(),
                    st.step
                )));
            }
        }
        None => {}
    }
    let start = std::time::Instant::now();
    for step in first..=s.steps {
        let batch = draw_batch(images, aug, s.batch, &mut rng)?;
        let loss = batch_loss_upto(
            &model,
            codec,
            schedule,
            &batch,
            s.cond_dropout,
            s.max_strength,
            s.residual,
            &mut rng,
            device,
        );
        let mut grads = loss.backward();
        let warm = if s.warmup > 0 {
            (step as f64 / s.warmup as f64).min(1.0)
        } else {
            1.0
        };
        let g_unet = GradientsParams::from_module(&mut grads, &model.unet);
        let g_tokens = GradientsParams::from_module(&mut grads, &model.tokens);
        let Trainable { unet, tokens } = model;
        let unet = opt_unet.step(s.lr * warm, unet, g_unet);
        let tokens = if s.token_lr > 0.0 {
            opt_tokens.step(s.token_lr * warm, tokens, g_tokens)
        } else {
            tokens
        };
        model = Trainable { unet, tokens };
        let l = loss.detach();
        pending = Some(match pending {
            Some(p) => p + l,
            None => l,
        });
        since += 1;
        if step % s.log_every.max(1) == 0 || step == s.steps {
            let sum = pending
                .take()
                .map(|p| p.into_scalar::<f32>() as f64)
                .unwrap_or(0.0);
            let mean = sum / since as f64;
            since = 0;
            if !mean.is_finite() {
                return Err(DiffusionError::Diverged(format!(
                    "the diffusion loss became {mean} by step {step} (lower --lr or raise --clip)"
                )));
            }
            curve.push((step, mean));
            on_progress(&Progress {
                step,
                steps: s.steps,
                loss: mean,
                elapsed: earlier + start.elapsed().as_secs_f64(),
            });
        }
        if let Some(ck) = checkpoint {
            if step % ck.every == 0 || step == s.steps {
                // The unreported losses are read back (one wait for the device) so that a
                // resumed run reports the same means.
                let sum = match pending.take() {
                    Some(p) => {
                        let v = p.into_scalar::<f32>();
                        pending = Some(Tensor::<1>::from_floats([v], device));
                        f64::from(v)
                    }
                    None => 0.0,
                };
                train_state::save(
                    ck,
                    &Snapshot {
                        step,
                        rng: rng.0,
                        curve: &curve,
                        pending: (sum, since),
                        seconds: earlier + start.elapsed().as_secs_f64(),
                        settings: s,
                        augment: aug,
                        images: &hash,
                    },
                    &model,
                    &opt_unet,
                    &opt_tokens,
                )?;
            }
        }
    }
    Ok((model, curve))
}
