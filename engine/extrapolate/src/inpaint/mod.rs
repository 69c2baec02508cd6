//! Inpainters: what fills the pixels of a virtual view that no two training cameras saw, in
//! colour and in depth. Every inpainter implements [`Inpainter`]; `extranerf extrapolate
//! --inpainter` picks one by [`InpainterKind`].
//!
//! Images are `[h, w, 3]` row-major f32 in [0, 1]; depth maps `[h, w]` in the field's ray
//! space (NDC t for forward-facing scenes, view depth otherwise: larger is farther in both);
//! masks `[h, w]` with values >= 0.5 meaning "fill". Pixels outside the mask come back
//! unchanged.

pub mod diffusion;
pub mod exemplar;
pub mod harmonic;

use std::fmt;

use extranerf_nerf::image_ops::blur;

/// Why an inpainting could not be done.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("inpainting: {0}")]
pub struct InpaintError(pub String);

/// Result alias of inpainting.
pub type Result<T, E = InpaintError> = std::result::Result<T, E>;

/// The view to fill.
#[derive(Clone, Copy, Debug)]
pub struct Target<'a> {
    pub width: usize,
    pub height: usize,
    /// The render, `[h, w, 3]`.
    pub rgb: &'a [f32],
    /// The rendered depth, `[h, w]` (larger is farther).
    pub depth: &'a [f32],
    /// `[h, w]`, >= 0.5 where the pixel is to be filled.
    pub mask: &'a [f32],
    /// The round's noise level in [0, 1) (where the diffusion inpainter starts sampling;
    /// the others ignore it).
    pub t: f32,
}

impl<'a> Target<'a> {
    /// The view `width x height` with its render, depth, mask and noise level (checked when an
    /// inpainter runs).
    pub fn new(
        width: usize,
        height: usize,
        rgb: &'a [f32],
        depth: &'a [f32],
        mask: &'a [f32],
        t: f32,
    ) -> Target<'a> {
        Target {
            width,
            height,
            rgb,
            depth,
            mask,
            t,
        }
    }
}

/// A `[h, w]` mask that is 1 inside the rectangle `x` by `y` (pixel ranges) and 0 outside.
pub fn rect_mask(
    w: usize,
    h: usize,
    x: std::ops::Range<usize>,
    y: std::ops::Range<usize>,
) -> Vec<f32> {
    (0..w * h)
        .map(|i| f32::from(x.contains(&(i % w)) && y.contains(&(i / w))))
        .collect()
}

/// An image whose texture an exemplar-based inpainter may copy (an input photo at the target's
/// scale), with its depth when known.
#[derive(Clone, Copy, Debug)]
pub struct Source<'a> {
    pub width: usize,
    pub height: usize,
    pub rgb: &'a [f32],
    pub depth: Option<&'a [f32]>,
}

/// An inpainted view: the target's pixels with the masked ones filled.
#[derive(Clone, Debug, PartialEq)]
pub struct Fill {
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
}

/// Which inpainter.
#[derive(
    Clone,
    Copy,
    Debug,
    PartialEq,
    Eq,
    Hash,
    PartialOrd,
    Ord,
    clap::ValueEnum,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum InpainterKind {
    /// Laplace's equation seeded only from the far side of each hole's boundary (a
    /// disocclusion shows what lies behind the occluder), in colour and depth.
    Harmonic,
    /// Multi-scale PatchMatch with EM voting (Wexler et al. 2007, Barnes et al. 2009): copies
    /// texture from the view's visible part and the input photos; depth follows the same
    /// correspondences.
    Exemplar,
    /// The harmonic fill's low frequencies with the exemplar fill's high frequencies.
    Hybrid,
    /// An inpainting diffusion model (`--diffusion-model`, with its `--diffusion-lora`
    /// adapters when given), from the render noised to the round's t; depth from the
    /// depth-aware harmonic fill.
    Diffusion,
    /// The same diffusion model without the `--diffusion-lora` adapters: the paper's
    /// "un-fine-tuned" ablation row beside `diffusion`'s fine-tuned one.
    #[serde(rename = "diffusion-base")]
    DiffusionBase,
}

impl InpainterKind {
    /// The name on the command line and in run folders.
    pub fn name(self) -> &'static str {
        match self {
            InpainterKind::Harmonic => "harmonic",
            InpainterKind::Exemplar => "exemplar",
            InpainterKind::Hybrid => "hybrid",
            InpainterKind::Diffusion => "diffusion",
            InpainterKind::DiffusionBase => "diffusion-base",
        }
    }

    /// Whether this inpainter is a diffusion model (loaded from `--diffusion-model`).
    pub fn uses_diffusion(self) -> bool {
        matches!(
            self,
            InpainterKind::Diffusion | InpainterKind::DiffusionBase
        )
    }

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

impl fmt::Display for InpainterKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Fills the masked pixels of a view.
pub trait Inpainter {
    /// Which inpainter this is.
    fn kind(&self) -> InpainterKind;
    /// Fills `target`'s masked pixels; `sources` are extra images to copy from, `seed` makes
    /// randomised inpainters repeatable. An empty mask returns the target unchanged; a mask
    /// that leaves nothing to start from is an error.
    fn inpaint(&mut self, target: &Target<'_>, sources: &[Source<'_>], seed: u64) -> Result<Fill>;
}

/// Checks the sizes of a target and its sources.
pub fn check(target: &Target<'_>, sources: &[Source<'_>]) -> Result<()> {
    let n = target.width * target.height;
    if n == 0 {
        return Err(InpaintError(format!(
            "the view is {}x{}; it has no pixels",
            target.width, target.height
        )));
    }
    if target.rgb.len() != 3 * n || target.depth.len() != n || target.mask.len() != n {
        return Err(InpaintError(format!(
            "a {}x{} view needs {} colour values, {n} depths and {n} mask values; got {}, {} and {}",
            target.width,
            target.height,
            3 * n,
            target.rgb.len(),
            target.depth.len(),
            target.mask.len()
        )));
    }
    if target
        .rgb
        .iter()
        .chain(target.depth)
        .chain(target.mask)
        .any(|v| !v.is_finite())
    {
        return Err(InpaintError(
            "the view's colour, depth or mask holds NaN or infinity".into(),
        ));
    }
    for (i, s) in sources.iter().enumerate() {
        let m = s.width * s.height;
        if m == 0
            || s.rgb.len() != 3 * m
            || s.depth.is_some_and(|d| d.len() != m)
            || s.rgb.iter().any(|v| !v.is_finite())
        {
            return Err(InpaintError(format!(
                "source image {i} ({}x{}) has {} colour values{}; want {} finite ones",
                s.width,
                s.height,
                s.rgb.len(),
                s.depth
                    .map(|d| format!(" and {} depths", d.len()))
                    .unwrap_or_default(),
                3 * m
            )));
        }
    }
    Ok(())
}

/// Whether pixel `i` is to be filled.
pub fn is_hole(mask: &[f32], i: usize) -> bool {
    mask[i] >= 0.5
}

/// `low`'s low frequencies plus `detail`'s high frequencies: the box blur (radius `r`, applied
/// twice) of `low`, plus `detail` minus its own blur, clamped to [0, 1]; `[h, w, 3]` images. A
/// constant colour shift between `detail` and `low` cancels exactly. The hybrid inpainter's
/// fill, and stage 3's colour anchoring (`--stage3-anchor`).
pub fn low_plus_detail(low: &[f32], detail: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let low_blur = blur(low, w, h, 3, r);
    let detail_blur = blur(detail, w, h, 3, r);
    low_blur
        .iter()
        .zip(detail.iter().zip(&detail_blur))
        .map(|(&lb, (&d, &db))| (lb + d - db).clamp(0.0, 1.0))
        .collect()
}

/// The hybrid inpainter: the harmonic fill's low frequencies (its colour blurred) plus the
/// exemplar fill's high frequencies (the exemplar fill minus its blur), depth from the
/// harmonic fill.
#[derive(Clone, Debug)]
pub struct Hybrid {
    pub harmonic: harmonic::Harmonic,
    pub exemplar: exemplar::Exemplar,
    /// Box-blur radius (applied twice) that separates low from high frequencies, in pixels.
    pub radius: usize,
}

impl Default for Hybrid {
    fn default() -> Self {
        Hybrid {
            harmonic: harmonic::Harmonic::default(),
            exemplar: exemplar::Exemplar::default(),
            radius: 3,
        }
    }
}

impl Inpainter for Hybrid {
    fn kind(&self) -> InpainterKind {
        InpainterKind::Hybrid
    }

    fn inpaint(&mut self, target: &Target<'_>, sources: &[Source<'_>], seed: u64) -> Result<Fill> {
        let low = self.harmonic.inpaint(target, sources, seed)?;
        let ex = self.exemplar.inpaint(target, sources, seed)?;
        let (w, h) = (target.width, target.height);
        let mixed = low_plus_detail(&low.rgb, &ex.rgb, w, h, self.radius);
        let mut rgb = target.rgb.to_vec();
        for i in 0..w * h {
            if is_hole(target.mask, i) {
                rgb[3 * i..3 * i + 3].copy_from_slice(&mixed[3 * i..3 * i + 3]);
            }
        }
        Ok(Fill {
            rgb,
            depth: low.depth,
        })
    }
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
        let d = crate::pipeline::DiffusionSpec {
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
