//! The diffusion inpainter: an inpainting diffusion model (a diffusers folder: Stable Diffusion
//! inpainting when the user has its weights, or the scene prior of `extranerf diffusion prior`,
//! optionally with LoRA adapters from `diffusion finetune`) used as ExtraNeRF uses it. The
//! render is noised to the round's level t and denoised in a few DDIM steps with the mask as
//! "not seen" and the masked render as guidance; the seen pixels are kept. Depth is completed
//! afterwards by the depth-aware harmonic fill (seeded from the far side of each hole).

use std::path::Path;

use burn::tensor::{Device, Tensor};
use extranerf_diffusion::inpaint::{seeded_noise, SampleSettings};
use extranerf_diffusion::pipeline::Pipeline;

use super::harmonic::{far_side_seeds, solve};
use super::{check, is_hole, Fill, InpaintError, Inpainter, InpainterKind, Result, Source, Target};

/// A loaded inpainting model and how it samples.
pub struct DiffusionInpainter {
    pipe: Pipeline,
    device: Device,
    /// DDIM steps per inpainting (ExtraNeRF: about 10).
    pub steps: usize,
    /// Where the weights came from (for logs).
    pub notes: Vec<String>,
}

impl std::fmt::Debug for DiffusionInpainter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DiffusionInpainter")
            .field("steps", &self.steps)
            .field("notes", &self.notes)
            .finish_non_exhaustive()
    }
}

impl DiffusionInpainter {
    /// Loads the model folder `dir` (and LoRA adapters from `lora`) onto `device`.
    pub fn load(
        dir: &Path,
        lora: Option<&Path>,
        device: Device,
        steps: usize,
    ) -> anyhow::Result<DiffusionInpainter> {
        if steps == 0 {
            anyhow::bail!("the diffusion inpainter needs at least one DDIM step");
        }
        let mut pipe = Pipeline::load(dir, &device, "")?;
        if let Some(l) = lora {
            let (_, unet) = extranerf_diffusion::lora::load(l, pipe.model.unet, &device)?;
            pipe.model.unet = unet;
            pipe.notes
                .push(format!("LoRA adapters from {}", l.display()));
            let tdir = l.join("text_encoder");
            if tdir.join(extranerf_diffusion::text::TOKENS_FILE).is_file() {
                pipe.model.tokens = extranerf_diffusion::text::LearnedTokens::load(&tdir, &device)?;
            }
        }
        let notes = pipe.notes.clone();
        Ok(DiffusionInpainter {
            pipe,
            device,
            steps,
            notes,
        })
    }
}

/// `v` (`[h, w, c]`) padded to `pw x ph` by repeating its last column and row.
fn pad(v: &[f32], w: usize, h: usize, c: usize, pw: usize, ph: usize) -> Vec<f32> {
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

impl Inpainter for DiffusionInpainter {
    fn kind(&self) -> InpainterKind {
        InpainterKind::Diffusion
    }

    fn inpaint(&mut self, target: &Target<'_>, sources: &[Source<'_>], seed: u64) -> Result<Fill> {
        check(target, sources)?;
        let (w, h) = (target.width, target.height);
        let n = w * h;
        // Depth first: it also refuses a mask with nothing seen.
        let (seeds, _) = far_side_seeds(target, 0.1);
        let (_, depth) = solve(target, &seeds, 5000, 1e-5)?;
        if !(0..n).any(|i| is_hole(target.mask, i)) {
            return Ok(Fill {
                rgb: target.rgb.to_vec(),
                depth,
            });
        }
        let m = self.pipe.model.size_multiple();
        let (pw, ph) = (w.div_ceil(m) * m, h.div_ceil(m) * m);
        let rgb = pad(target.rgb, w, h, 3, pw, ph);
        let mask: Vec<f32> = pad(target.mask, w, h, 1, pw, ph)
            .into_iter()
            .map(|v| f32::from(v >= 0.5))
            .collect();
        let mut chw = vec![0f32; 3 * pw * ph];
        for i in 0..pw * ph {
            for c in 0..3 {
                chw[c * pw * ph + i] = rgb[3 * i + c];
            }
        }
        let dev = &self.device;
        let img = Tensor::<1>::from_floats(chw.as_slice(), dev).reshape([1, 3, ph, pw]);
        let mk = Tensor::<1>::from_floats(mask.as_slice(), dev).reshape([1, 1, ph, pw]);
        let c = self.pipe.model.codec.channels();
        let f = self.pipe.model.codec.factor();
        let noise = seeded_noise([1, c, ph / f, pw / f], seed, dev);
        let strength = (target.t as f64).clamp(0.02, 1.0);
        let out = self
            .pipe
            .model
            .inpaint(
                img,
                mk,
                noise,
                &SampleSettings {
                    strength,
                    steps: self.steps,
                    guidance: 1.0,
                    keep_known: true,
                },
            )
            .map_err(|e| InpaintError(format!("diffusion: {e}")))?;
        let res: Vec<f32> = out
            .image
            .into_data()
            .try_to_vec_as::<f32>()
            .map_err(|e| InpaintError(format!("diffusion: reading the result: {e:?}")))?;
        let mut filled = target.rgb.to_vec();
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if is_hole(target.mask, i) {
                    for ch in 0..3 {
                        filled[3 * i + ch] = res[ch * pw * ph + y * pw + x].clamp(0.0, 1.0);
                    }
                }
            }
        }
        Ok(Fill { rgb: filled, depth })
    }
}
