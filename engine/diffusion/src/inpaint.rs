//! The inpainting pipeline: an image (a NeRF render) and a mask of what to fill, noised to a
//! strength and denoised in k DDIM steps by the inpainting U-Net, whose input is the noisy
//! latent, the mask and the masked image's latent (diffusers' inpainting layout).
//!
//! The image reaches the U-Net through a VAE (latent diffusion, as Stable Diffusion
//! inpainting) or directly (pixel-space diffusion, for the small scene priors trained here);
//! in both cases the U-Net's input has `2 * latent + 1` channels.

use burn::module::Module;
use burn::tensor::module::max_pool2d;
use burn::tensor::ops::MaxPoolOptions;
use burn::tensor::{Device, Tensor};

use crate::scheduler::{ddim_timesteps, guide, Prediction, Schedule};
use crate::text::LearnedTokens;
use crate::unet::UNet2DConditionModel;
use crate::vae::AutoencoderKL;
use crate::{DiffusionError, Result};

/// How images become the diffusion variable.
#[allow(clippy::large_enum_variant)] // a module tree; burn has no Module for Box
#[derive(Module, Debug)]
pub enum Codec {
    /// Latent diffusion through an autoencoder.
    Vae(AutoencoderKL),
    /// Pixel-space diffusion: the variable is the image in [-1, 1].
    Pixels(PixelCodec),
}

/// The identity codec of pixel-space models (3 channels, factor 1).
#[derive(Module, Debug, Default)]
pub struct PixelCodec;

impl Codec {
    /// Channels of the diffusion variable.
    pub fn channels(&self) -> usize {
        match self {
            Codec::Vae(v) => v.latent_channels(),
            Codec::Pixels(_) => 3,
        }
    }

    /// Spatial factor image -> variable.
    pub fn factor(&self) -> usize {
        match self {
            Codec::Vae(v) => v.factor(),
            Codec::Pixels(_) => 1,
        }
    }

    /// Image in [-1, 1] -> variable (the VAE's posterior mean, scaled).
    pub fn encode(&self, x: Tensor<4>) -> Tensor<4> {
        match self {
            Codec::Vae(v) => v.encode(x, false),
            Codec::Pixels(_) => x,
        }
    }

    /// Variable -> image in about [-1, 1].
    pub fn decode(&self, z: Tensor<4>) -> Tensor<4> {
        match self {
            Codec::Vae(v) => v.decode(z),
            Codec::Pixels(_) => z,
        }
    }

    /// A hole mask `[n, 1, H, W]` at the variable's resolution: a latent cell is a hole when
    /// any of its pixels is, so an unknown pixel is never shown as known (diffusers' pipeline
    /// takes the nearest pixel instead; this is the conservative choice, used in training and
    /// sampling alike). Unchanged for pixel-space models.
    pub fn mask(&self, mask: Tensor<4>) -> Tensor<4> {
        match self {
            Codec::Vae(v) => {
                let f = v.factor();
                max_pool2d(mask, MaxPoolOptions::new([f, f]).with_stride([f, f]))
            }
            Codec::Pixels(_) => mask,
        }
    }
}

/// The U-Net's input: `[noisy (c), mask (1), masked-image variable (c)]` on channels.
pub fn unet_input(noisy: Tensor<4>, mask: Tensor<4>, masked: Tensor<4>) -> Tensor<4> {
    Tensor::cat(vec![noisy, mask, masked], 1)
}

/// What a model of the inpainting architecture was trained to do; it decides the U-Net's
/// guidance input.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Task {
    /// Fill a hole: the guidance is the image with the hole blanked (diffusers' inpainting).
    #[default]
    Inpaint,
    /// Enhance a whole render (ExtraNeRF's stage 3): the guidance is the image itself, not
    /// masked; the mask channel says where an earlier stage filled it in.
    Enhance,
    /// Enhance as [`Task::Enhance`], with the U-Net's output a correction to its guidance: the
    /// predicted clean variable is the guidance plus the output (the schedule's prediction
    /// must be [`crate::scheduler::Prediction::Sample`]). A network whose last convolution
    /// is zero is then the identity, and training starts from there, not from a denoiser that
    /// must first learn to give the render back.
    EnhanceResidual,
}

impl Task {
    /// Its name in `model_index.json`.
    pub fn name(self) -> &'static str {
        match self {
            Task::Inpaint => "inpaint",
            Task::Enhance => "enhance",
            Task::EnhanceResidual => "enhance_residual",
        }
    }

    /// Whether the guidance is the whole image (an enhancer).
    pub fn enhances(self) -> bool {
        matches!(self, Task::Enhance | Task::EnhanceResidual)
    }

    /// Whether the U-Net's output is added to its guidance ([`Task::EnhanceResidual`]).
    pub fn residual(self) -> bool {
        self == Task::EnhanceResidual
    }
}

/// An inpainting model: U-Net, codec, conditioning and noise schedule.
#[derive(Debug)]
pub struct InpaintModel {
    /// The U-Net (`2 * codec.channels() + 1` inputs).
    pub unet: UNet2DConditionModel,
    /// Image <-> diffusion variable.
    pub codec: Codec,
    /// Conditioning tokens.
    pub tokens: LearnedTokens,
    /// The noise process.
    pub schedule: Schedule,
    /// Inpainter or enhancer.
    pub task: Task,
}

/// How to sample.
#[derive(Clone, Debug, PartialEq)]
pub struct SampleSettings {
    /// Noise strength of the starting point in (0, 1] (1 = start from pure noise).
    pub strength: f64,
    /// DDIM steps (ExtraNeRF: about 10 per visit).
    pub steps: usize,
    /// Classifier-free guidance scale (1 = off: no unconditional pass).
    pub guidance: f64,
    /// Keep the known pixels of the input in the output.
    pub keep_known: bool,
}

impl Default for SampleSettings {
    fn default() -> Self {
        SampleSettings {
            strength: 1.0,
            steps: 10,
            guidance: 1.0,
            keep_known: true,
        }
    }
}

/// What a sampling run returns.
#[derive(Debug)]
pub struct Inpainted {
    /// `[n, 3, H, W]` in [0, 1].
    pub image: Tensor<4>,
    /// The starting training timestep.
    pub t_start: usize,
    /// Its noise level sqrt(1 - alpha_bar) (for a w(t)-weighted NeRF loss).
    pub noise_level: f64,
}

/// [`InpaintModel::inpaint_image`]'s result.
#[derive(Clone, Debug, PartialEq)]
pub struct InpaintedImage {
    /// `[h, w, 3]` in [0, 1]: the model's output (with `keep_known`, the known pixels are the
    /// input's).
    pub rgb: Vec<f32>,
    /// The starting training timestep.
    pub t_start: usize,
    /// Its noise level sqrt(1 - alpha_bar).
    pub noise_level: f64,
}

/// `v` (`[h, w, c]`) padded to `pw x ph` by repeating its last column and row.
fn pad_edge(v: &[f32], w: usize, h: usize, c: usize, pw: usize, ph: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(pw * ph * c);
    for y in 0..ph {
        let sy = y.min(h - 1);
        for x in 0..pw {
            let sx = x.min(w - 1);
            out.extend_from_slice(&v[(sy * w + sx) * c..(sy * w + sx + 1) * c]);
        }
    }
    out
}

/// Standard-normal noise from a seed, generated on the host (identical on every backend) and
/// uploaded once.
pub fn seeded_noise(shape: [usize; 4], seed: u64, device: &Device) -> Tensor<4> {
    let n: usize = shape.iter().product();
    let mut rng = SplitMix(seed ^ 0x9e37_79b9_7f4a_7c15);
    let mut v = Vec::with_capacity(n);
    while v.len() < n {
        // Box-Muller on two uniforms in (0, 1].
        let u1 = ((rng.next_u64() >> 11) as f64 + 1.0) / (1u64 << 53) as f64;
        let u2 = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        let r = (-2.0 * u1.ln()).sqrt();
        let a = 2.0 * std::f64::consts::PI * u2;
        v.push((r * a.cos()) as f32);
        if v.len() < n {
            v.push((r * a.sin()) as f32);
        }
    }
    Tensor::<1>::from_floats(v.as_slice(), device).reshape(shape)
}

/// SplitMix64: a small seeded generator for host-side noise, masks and crops.
#[derive(Clone, Debug)]
pub struct SplitMix(pub u64);

impl SplitMix {
    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform integer in [0, n).
    pub fn below(&mut self, n: usize) -> usize {
        ((self.unit() * n as f64) as usize).min(n.saturating_sub(1))
    }
}

impl InpaintModel {
    /// Checks that the parts fit together.
    pub fn validate(&self) -> Result<()> {
        let c = self.codec.channels();
        if self.unet.in_channels() != 2 * c + 1 || self.unet.out_channels() != c {
            return Err(DiffusionError::Input(format!(
                "the U-Net takes {} channels and gives {}, but an inpainting U-Net on a {c}-channel variable takes {} and gives {c}",
                self.unet.in_channels(),
                self.unet.out_channels(),
                2 * c + 1
            )));
        }
        if self.task.residual() && self.schedule.prediction() != Prediction::Sample {
            return Err(DiffusionError::Input(format!(
                "a residual enhancer (task \"{}\") predicts the clean image, but its scheduler's prediction_type is {:?} (want \"sample\")",
                self.task.name(),
                self.schedule.prediction()
            )));
        }
        let [_, d] = self.tokens.dims();
        if d != self.unet.cross_attention_dim {
            return Err(DiffusionError::Input(format!(
                "conditioning tokens are {d} wide but the U-Net's cross_attention_dim is {}",
                self.unet.cross_attention_dim
            )));
        }
        Ok(())
    }

    /// The image side must be a multiple of this.
    pub fn size_multiple(&self) -> usize {
        self.codec.factor() * (1 << (self.unet.down_blocks.len() - 1))
    }

    /// Inpaints one image on `device`: `rgb` `[h, w, 3]` in [0, 1], `mask` `[h, w]` (at least 0.5:
    /// to be filled), noise from `seed`. Sides that are not multiples of
    /// [`InpaintModel::size_multiple`] are padded by repeating the last row and column, and
    /// the result is cropped back.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn inpaint_image(
        &self,
        rgb: &[f32],
        mask: &[f32],
        w: usize,
        h: usize,
        seed: u64,
        s: &SampleSettings,
        device: &Device,
    ) -> Result<InpaintedImage> {
        let mut out = self.inpaint_images(&[(rgb, mask)], w, h, seed, s, device)?;
        Ok(out.remove(0))
    }

    /// Enhances one render (an enhancer's [`Task::Enhance`]): `rgb` `[h, w, 3]` in [0, 1] is
    /// noised to `s.strength` and denoised with itself as guidance; `mask` `[h, w]` marks what
    /// an earlier stage filled in (None: nothing). Every pixel may change (`s.keep_known` is
    /// ignored).
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn enhance_image(
        &self,
        rgb: &[f32],
        mask: Option<&[f32]>,
        w: usize,
        h: usize,
        seed: u64,
        s: &SampleSettings,
        device: &Device,
    ) -> Result<InpaintedImage> {
        if !self.task.enhances() {
            return Err(DiffusionError::Input(
                "this model was trained to inpaint, not to enhance (train an enhancer: `extranerf extrapolate` stage 3, or LoRA adapters written by it)".into(),
            ));
        }
        let zeros = vec![0f32; w * h];
        let s = SampleSettings {
            keep_known: false,
            ..s.clone()
        };
        self.inpaint_image(rgb, mask.unwrap_or(&zeros), w, h, seed, &s, device)
    }

    /// [`InpaintModel::inpaint_image`] for a batch of same-sized images sampled together (one
    /// noise tensor of the batch's shape from `seed`).
    pub fn inpaint_images(
        &self,
        images: &[(&[f32], &[f32])],
        w: usize,
        h: usize,
        seed: u64,
        s: &SampleSettings,
        device: &Device,
    ) -> Result<Vec<InpaintedImage>> {
        let n = images.len();
        if n == 0 || w == 0 || h == 0 {
            return Err(DiffusionError::Input(format!(
                "inpaint: {n} images of {w}x{h}: need at least one non-empty image"
            )));
        }
        let m = self.size_multiple();
        let (pw, ph) = (w.div_ceil(m) * m, h.div_ceil(m) * m);
        let plane = pw * ph;
        let mut chw = Vec::with_capacity(n * 3 * plane);
        let mut masks = Vec::with_capacity(n * plane);
        for (k, (rgb, mask)) in images.iter().enumerate() {
            if rgb.len() != w * h * 3 || mask.len() != w * h {
                return Err(DiffusionError::Input(format!(
                    "inpaint: image {k} of {w}x{h} needs {} colour values and {} mask values, not {} and {}",
                    w * h * 3,
                    w * h,
                    rgb.len(),
                    mask.len()
                )));
            }
            let prgb = pad_edge(rgb, w, h, 3, pw, ph);
            for c in 0..3 {
                chw.extend((0..plane).map(|i| prgb[3 * i + c]));
            }
            masks.extend(
                pad_edge(mask, w, h, 1, pw, ph)
                    .into_iter()
                    .map(|v| f32::from(v >= 0.5)),
            );
        }
        let img = Tensor::<1>::from_floats(chw.as_slice(), device).reshape([n, 3, ph, pw]);
        let mk = Tensor::<1>::from_floats(masks.as_slice(), device).reshape([n, 1, ph, pw]);
        let c = self.codec.channels();
        let f = self.codec.factor();
        let noise = seeded_noise([n, c, ph / f, pw / f], seed, device);
        let out = self.inpaint(img, mk, noise, s)?;
        let res: Vec<f32> =
            out.image.into_data().try_to_vec_as::<f32>().map_err(|e| {
                DiffusionError::Input(format!("reading the inpainted images: {e:?}"))
            })?;
        Ok((0..n)
            .map(|k| {
                let img = &res[k * 3 * plane..(k + 1) * 3 * plane];
                let mut rgb = vec![0f32; w * h * 3];
                for y in 0..h {
                    for x in 0..w {
                        for ch in 0..3 {
                            rgb[3 * (y * w + x) + ch] =
                                img[ch * plane + y * pw + x].clamp(0.0, 1.0);
                        }
                    }
                }
                InpaintedImage {
                    rgb,
                    t_start: out.t_start,
                    noise_level: out.noise_level,
                }
            })
            .collect())
    }

    /// Inpaints `image [n, 3, H, W]` (in [0, 1]) where `mask [n, 1, H, W]` is 1, starting from
    /// the image noised to `s.strength` with `noise` (standard normal, the variable's shape;
    /// see [`seeded_noise`]). Everything stays on the device; nothing is read back.
    pub fn inpaint(
        &self,
        image: Tensor<4>,
        mask: Tensor<4>,
        noise: Tensor<4>,
        s: &SampleSettings,
    ) -> Result<Inpainted> {
        self.validate()?;
        let [n, c, h, w] = image.dims();
        let m = self.size_multiple();
        if c != 3 || h % m != 0 || w % m != 0 || mask.dims() != [n, 1, h, w] {
            return Err(DiffusionError::Input(format!(
                "inpaint: image {:?} and mask {:?}: want [n, 3, H, W] with H and W multiples of {m} and a [n, 1, H, W] mask",
                image.dims(),
                mask.dims()
            )));
        }
        if !(s.strength > 0.0 && s.strength <= 1.0)
            || s.steps == 0
            || !(s.guidance.is_finite() && s.guidance >= 1.0)
        {
            return Err(DiffusionError::Input(format!(
                "sampling: strength {} must be in (0, 1], steps {} > 0, guidance {} >= 1",
                s.strength, s.steps, s.guidance
            )));
        }
        let x = image.clone() * 2.0 - 1.0;
        let keep = mask.clone().neg() + 1.0;
        let z0 = self.codec.encode(x.clone());
        // The guidance: the image with its hole blanked, or (an enhancer) all of it.
        let masked = match self.task {
            Task::Inpaint => self.codec.encode(x * keep.clone()),
            Task::Enhance | Task::EnhanceResidual => z0.clone(),
        };
        let mask_z = self.codec.mask(mask.clone());
        if noise.dims() != z0.dims() {
            return Err(DiffusionError::Input(format!(
                "noise {:?} must have the variable's shape {:?}",
                noise.dims(),
                z0.dims()
            )));
        }
        let steps = ddim_timesteps(&self.schedule, s.strength, s.steps);
        let t_start = steps[0];
        let mut z = self.schedule.add_noise(z0, noise, &vec![t_start; n]);
        let cond = self.tokens.forward(n);
        let guided = s.guidance > 1.0;
        let device = image.device();
        let (context, mask_in, masked_in) = if guided {
            (
                Tensor::cat(vec![cond, self.tokens.null(n, &device)], 0),
                Tensor::cat(vec![mask_z.clone(), mask_z], 0),
                Tensor::cat(vec![masked.clone(), masked], 0),
            )
        } else {
            (cond, mask_z, masked)
        };
        for (i, &t) in steps.iter().enumerate() {
            let zin = if guided {
                Tensor::cat(vec![z.clone(), z.clone()], 0)
            } else {
                z.clone()
            };
            let inp = unet_input(zin, mask_in.clone(), masked_in.clone());
            let ts = vec![t as f32; inp.dims()[0]];
            let mut out = self.unet.forward(inp, &ts, &context);
            if self.task.residual() {
                out = out + masked_in.clone();
            }
            if guided {
                let mut halves = out.chunk(2, 0);
                let u = halves.pop().unwrap_or_else(|| unreachable!("two halves"));
                let c = halves.pop().unwrap_or_else(|| unreachable!("two halves"));
                out = guide(c, u, s.guidance);
            }
            z = self
                .schedule
                .ddim_step(out, z, t, steps.get(i + 1).copied());
        }
        let mut result = ((self.codec.decode(z) + 1.0) * 0.5).clamp(0.0, 1.0);
        if s.keep_known {
            result = image * keep + result * mask;
        }
        Ok(Inpainted {
            image: result,
            t_start,
            noise_level: self.schedule.noise_level(t_start),
        })
    }
}
