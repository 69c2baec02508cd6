//! What every inpainter shares: the view to fill ([`Target`]), the images to copy from
//! ([`Source`]), the fill ([`Fill`]), the [`Inpainter`] trait, the [`InpainterKind`] that names
//! one, and the checks and helpers of the fills.

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
