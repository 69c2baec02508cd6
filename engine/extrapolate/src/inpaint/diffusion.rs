//! The diffusion inpainter: an inpainting diffusion model (a diffusers folder: Stable Diffusion
//! inpainting when the user has its weights, or the scene prior of `extranerf diffusion prior`,
//! optionally with LoRA adapters from `diffusion finetune`) used as ExtraNeRF uses it. The
//! render is noised to the round's level t and denoised in a few DDIM steps with the mask as
//! "not seen" and the masked render as guidance; the seen pixels are kept. Depth is completed
//! afterwards by the depth-aware harmonic fill (seeded from the far side of each hole).

use std::path::Path;

use burn::tensor::Device;
use extranerf_diffusion::inpaint::SampleSettings;
use extranerf_diffusion::pipeline::Pipeline;

use super::api::{
    check, is_hole, Fill, InpaintError, Inpainter, InpainterKind, Result, Source, Target,
};
use super::harmonic::{far_side_seeds, solve};

/// A loaded inpainting model and how it samples.
pub struct DiffusionInpainter {
    pipe: Pipeline,
    device: Device,
    /// DDIM steps per inpainting (ExtraNeRF: about 10).
    pub steps: usize,
    /// Where the weights came from (for logs).
    pub notes: Vec<String>,
    /// `Diffusion` with adapters, `DiffusionBase` without.
    kind: InpainterKind,
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
    /// Loads the model folder `dir` (and LoRA adapters from `lora`) onto `device`. It is the
    /// `diffusion` inpainter with adapters and `diffusion-base` (the model as it is) without.
    pub fn load(
        dir: &Path,
        lora: Option<&Path>,
        device: Device,
        steps: usize,
    ) -> crate::error::Result<DiffusionInpainter> {
        if steps == 0 {
            return Err(crate::error::ExtrapolateError::usage(
                "the diffusion inpainter needs at least one DDIM step",
            ));
        }
        let mut pipe = Pipeline::load(dir, &device, "")?;
        let mut kind = InpainterKind::DiffusionBase;
        if let Some(l) = lora {
            pipe = pipe.with_lora(l, &device)?;
            kind = InpainterKind::Diffusion;
        }
        let notes = pipe.notes.clone();
        Ok(DiffusionInpainter {
            pipe,
            device,
            steps,
            notes,
            kind,
        })
    }
}

impl Inpainter for DiffusionInpainter {
    fn kind(&self) -> InpainterKind {
        self.kind
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
        let strength = (target.t as f64).clamp(0.02, 1.0);
        let out = self
            .pipe
            .model
            .inpaint_image(
                target.rgb,
                target.mask,
                w,
                h,
                seed,
                &SampleSettings {
                    strength,
                    steps: self.steps,
                    guidance: 1.0,
                    keep_known: true,
                },
                &self.device,
            )
            .map_err(|e| InpaintError(format!("diffusion: {e}")))?;
        let mut filled = target.rgb.to_vec();
        for i in 0..n {
            if is_hole(target.mask, i) {
                filled[3 * i..3 * i + 3].copy_from_slice(&out.rgb[3 * i..3 * i + 3]);
            }
        }
        Ok(Fill { rgb: filled, depth })
    }
}
