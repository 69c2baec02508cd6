//! The hybrid inpainter: harmonic low frequencies with exemplar detail.

use super::api::{
    is_hole, low_plus_detail, Fill, Inpainter, InpainterKind, Result, Source, Target,
};
use super::exemplar;
use super::harmonic;

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
