//! Inpainters: what fills the pixels of a virtual view that no two training cameras saw, in
//! colour and in depth. Every inpainter implements [`Inpainter`]; `extranerf extrapolate
//! --inpainter` picks one by [`InpainterKind`].
//!
//! Images are `[h, w, 3]` row-major f32 in [0, 1]; depth maps `[h, w]` in the field's ray
//! space (NDC t for forward-facing scenes, view depth otherwise: larger is farther in both);
//! masks `[h, w]` with values >= 0.5 meaning "fill". Pixels outside the mask come back
//! unchanged.

pub mod api;
pub mod diffusion;
pub mod exemplar;
pub mod harmonic;
pub mod hybrid;

pub use api::{
    check, is_hole, low_plus_detail, rect_mask, Fill, InpaintError, Inpainter, InpainterKind,
    Result, Source, Target,
};
pub use hybrid::Hybrid;

use std::path::PathBuf;

use extranerf_gpu::Context;
use serde::{Deserialize, Serialize};

use extranerf_nerf::train::Reporter;

impl InpainterKind {
    /// The inpainter with its default settings; None for `diffusion` and `diffusion-base`,
    /// which need a model ([`diffusion::DiffusionInpainter::load`]).
    pub fn build(self) -> Option<Box<dyn Inpainter>> {
        match self {
            InpainterKind::Harmonic => Some(Box::new(harmonic::Harmonic::default())),
            InpainterKind::Exemplar => Some(Box::new(exemplar::Exemplar::default())),
            InpainterKind::Hybrid => Some(Box::new(Hybrid::default())),
            InpainterKind::Diffusion | InpainterKind::DiffusionBase => None,
        }
    }
}

/// The diffusion inpainter's model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionSpec {
    /// A diffusers inpainting folder.
    pub model: PathBuf,
    /// LoRA adapters (`diffusion finetune`).
    pub lora: Option<PathBuf>,
    /// DDIM steps per inpainting.
    pub steps: usize,
    /// burn backend.
    pub backend: extranerf_diffusion::device::Backend,
}

impl DiffusionSpec {
    /// What the inpainter `kind` uses of it: `diffusion-base` leaves the adapters out.
    pub fn for_kind(&self, kind: InpainterKind) -> DiffusionSpec {
        DiffusionSpec {
            lora: if kind == InpainterKind::DiffusionBase {
                None
            } else {
                self.lora.clone()
            },
            ..self.clone()
        }
    }
}

/// The inpainter of `kind` (the diffusion one loaded from `diffusion`).
pub fn build_inpainter(
    ctx: &Context,
    kind: InpainterKind,
    diffusion: Option<&DiffusionSpec>,
    rep: &mut dyn Reporter,
) -> crate::error::Result<Box<dyn Inpainter>> {
    if let Some(i) = kind.build() {
        return Ok(i);
    }
    let Some(d) = diffusion.map(|d| d.for_kind(kind)) else {
        return Err(crate::error::ExtrapolateError::usage(format!(
            "--inpainter {kind} needs --diffusion-model DIR (a diffusers inpainting folder, or \
             `extranerf diffusion prior`'s model)"
        )));
    };
    let (b, device) = extranerf_diffusion::device::diffusion_device(ctx, d.backend)?;
    let inp = diffusion::DiffusionInpainter::load(&d.model, d.lora.as_deref(), device, d.steps)?;
    rep.note(&format!(
        "{kind} inpainter on {}: {}",
        b.name(),
        inp.notes.join("; ")
    ));
    Ok(Box::new(inp))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `[h, w, 3]` image from a formula.
    fn image(w: usize, h: usize, f: impl Fn(usize, usize, usize) -> f32) -> Vec<f32> {
        (0..h * w * 3)
            .map(|i| f(i / 3 % w, i / 3 / w, i % 3))
            .collect()
    }

    #[test]
    fn low_plus_detail_removes_a_colour_drift_and_keeps_the_detail() {
        let (w, h) = (24, 18);
        let render = image(w, h, |x, y, c| {
            0.2 + 0.01 * x as f32 + 0.01 * y as f32 + 0.05 * c as f32
        });
        // A pure colour drift (a constant per channel) is removed exactly.
        let drift = [0.08f32, -0.05, 0.02];
        let drifted: Vec<f32> = render
            .iter()
            .enumerate()
            .map(|(i, &v)| v + drift[i % 3])
            .collect();
        let out = low_plus_detail(&render, &drifted, w, h, 3);
        let worst = out
            .iter()
            .zip(&render)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-5, "a colour drift left {worst}");
        // Drift plus a fine checkerboard: the drift goes, the checkerboard stays.
        let detail = |x: usize, y: usize| {
            if (x + y).is_multiple_of(2) {
                0.1f32
            } else {
                -0.1
            }
        };
        let sharpened: Vec<f32> = drifted
            .iter()
            .enumerate()
            .map(|(i, &v)| v + detail(i / 3 % w, i / 3 / w))
            .collect();
        let out = low_plus_detail(&render, &sharpened, w, h, 3);
        let n = out.len() as f32;
        let kept = out
            .iter()
            .enumerate()
            .map(|(i, &v)| (v - render[i]) * detail(i / 3 % w, i / 3 / w).signum())
            .sum::<f32>()
            / n;
        let mean_shift = out.iter().zip(&render).map(|(a, b)| a - b).sum::<f32>() / n;
        assert!(kept > 0.09, "detail kept {kept} of 0.1");
        assert!(mean_shift.abs() < 0.01, "mean colour moved by {mean_shift}");
        // Clamped to [0, 1] at the extremes.
        let white = vec![1.0f32; w * h * 3];
        let out = low_plus_detail(&white, &sharpened, w, h, 1);
        assert!(out.iter().all(|v| (0.0..=1.0).contains(v)));
    }

    #[test]
    fn the_un_fine_tuned_diffusion_row_has_its_own_name_everywhere() {
        use clap::ValueEnum as _;
        let k = InpainterKind::DiffusionBase;
        assert_eq!(k.name(), "diffusion-base");
        assert_eq!(k.to_string(), "diffusion-base");
        assert_eq!(
            serde_json::to_string(&k).unwrap_or_default(),
            "\"diffusion-base\""
        );
        assert_eq!(InpainterKind::from_str("diffusion-base", false), Ok(k));
        assert!(k.uses_diffusion() && InpainterKind::Diffusion.uses_diffusion());
        assert!(!InpainterKind::Hybrid.uses_diffusion());
        assert!(k.build().is_none());
        // The adapters are left out of its model, kept for `diffusion`.
        let d = DiffusionSpec {
            model: "m".into(),
            lora: Some("l".into()),
            steps: 10,
            backend: extranerf_diffusion::device::Backend::Cpu,
        };
        assert_eq!(d.for_kind(k).lora, None);
        assert_eq!(d.for_kind(InpainterKind::Diffusion), d);
    }

    #[test]
    fn mis_sized_and_non_finite_inputs_are_refused() {
        let rgb = vec![0.5f32; 4 * 4 * 3];
        let depth = vec![1.0f32; 16];
        let mask = vec![0.0f32; 15];
        let t = Target::new(4, 4, &rgb, &depth, &mask, 0.5);
        for kind in [
            InpainterKind::Harmonic,
            InpainterKind::Exemplar,
            InpainterKind::Hybrid,
        ] {
            let e = kind.build().unwrap().inpaint(&t, &[], 0).unwrap_err();
            assert!(e.0.contains("16 mask values"), "{kind}: {e}");
        }
        let mut mask = vec![0.0f32; 16];
        mask[3] = f32::NAN;
        let t = Target { mask: &mask, ..t };
        let e = harmonic::Harmonic::default()
            .inpaint(&t, &[], 0)
            .unwrap_err();
        assert!(e.0.contains("NaN"), "{e}");
        let bad = Source {
            width: 2,
            height: 2,
            rgb: &rgb[..5],
            depth: None,
        };
        let mask = vec![0.0f32; 16];
        let t = Target { mask: &mask, ..t };
        let e = exemplar::Exemplar::default()
            .inpaint(&t, &[bad], 0)
            .unwrap_err();
        assert!(e.0.contains("source image 0"), "{e}");
    }

    #[test]
    fn an_empty_mask_is_a_no_op_and_a_full_one_an_error() {
        let (w, h) = (8, 6);
        let rgb: Vec<f32> = (0..w * h * 3).map(|i| (i % 7) as f32 / 7.0).collect();
        let depth: Vec<f32> = (0..w * h).map(|i| 0.5 + (i % 5) as f32 * 0.1).collect();
        let empty = vec![0.0f32; w * h];
        let full = vec![1.0f32; w * h];
        for kind in [
            InpainterKind::Harmonic,
            InpainterKind::Exemplar,
            InpainterKind::Hybrid,
        ] {
            let t = Target::new(w, h, &rgb, &depth, &empty, 0.5);
            let f = kind.build().unwrap().inpaint(&t, &[], 1).unwrap();
            assert_eq!(f.rgb, rgb, "{kind}");
            assert_eq!(f.depth, depth, "{kind}");
            let t = Target { mask: &full, ..t };
            let e = kind.build().unwrap().inpaint(&t, &[], 1).unwrap_err();
            assert!(e.0.contains("whole view"), "{kind}: {e}");
        }
    }

    #[test]
    fn hybrid_keeps_the_harmonic_low_frequencies_on_a_ramp() {
        // On a linear ramp both fills are close to the ramp, so the hybrid is too.
        let (w, h) = (40, 30);
        let rgb: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                [x / w as f32, y / h as f32, 0.5]
            })
            .collect();
        let depth = vec![1.0f32; w * h];
        let mask: Vec<f32> = rect_mask(w, h, 15..25, 10..20);
        let t = Target::new(w, h, &rgb, &depth, &mask, 0.5);
        let f = Hybrid::default().inpaint(&t, &[], 3).unwrap();
        let mut worst = 0f32;
        for i in 0..w * h {
            if mask[i] > 0.5 {
                for c in 0..3 {
                    worst = worst.max((f.rgb[3 * i + c] - rgb[3 * i + c]).abs());
                }
            }
        }
        assert!(worst < 0.08, "largest error {worst}");
    }
}
