//! KID on Inception features ([`super::inception`]): the full-frame and the patch protocols.

use extranerf_nerf::image_ops::crop;
use extranerf_nerf::metrics::kid::{kid, masked_crops, max_coverage, Kid, KidConfig};
use serde::Serialize;

use extranerf_nerf::train::Reporter;

use crate::error::Result;
use crate::eval::inception::{ImageRef, Inception, FEATURES};

/// KID's protocols (`extranerf eval --kid-*`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct KidSpec {
    /// Patch crops in all (spread over the views).
    pub crops: usize,
    /// Their side in pixels.
    pub crop_size: u32,
    /// Share of each crop's pixels that the not-visible mask must cover.
    pub min_fraction: f64,
    /// Subsets of the patch protocol and rows per subset.
    pub subsets: usize,
    pub subset_size: usize,
    /// Rows per subset of the full-frame protocol (capped at the number of views).
    pub frame_subset_size: usize,
    /// Seed of the crops and the subsets.
    pub seed: u64,
    /// Images per Inception batch.
    pub batch: usize,
}

impl Default for KidSpec {
    fn default() -> Self {
        KidSpec {
            crops: 500,
            crop_size: 128,
            min_fraction: 0.5,
            subsets: 100,
            subset_size: 100,
            frame_subset_size: 8,
            seed: 0,
            batch: 8,
        }
    }
}

/// What the table's KID columns were measured with.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct KidReport {
    pub spec: KidSpec,
    /// Crops taken per view (views without a crop that covers the mask enough get none).
    pub crops_per_view: Vec<usize>,
    /// Subset sizes used: full frame, patch (capped at the rows available).
    pub frame_subset_size: usize,
    pub patch_subset_size: Option<usize>,
    /// The largest share of a crop that the mask covers, over every view and position (what
    /// `min_fraction` can ask).
    pub max_coverage: f64,
}

impl KidReport {
    /// One line on how KID was measured.
    pub fn describe(&self) -> String {
        let crops: usize = self.crops_per_view.iter().sum();
        format!(
            "KID (TF-FID Inception-v3 pool features, cubic kernel, unbiased): full frame over \
             the {} held-out views, {} subsets of {}; patch: {crops} crops of {s}x{s} covering \
             the not-visible mask by at least {:.0}% (per view {:?}; the best crop covers \
             {:.0}%), {}.",
            self.crops_per_view.len(),
            self.spec.subsets,
            self.frame_subset_size,
            100.0 * self.spec.min_fraction,
            self.crops_per_view,
            100.0 * self.max_coverage,
            match self.patch_subset_size {
                Some(m) => format!("{} subsets of {m}", self.spec.subsets),
                None => "too few crops for a patch KID".into(),
            },
            s = self.spec.crop_size,
        )
    }
}

/// The crops of every view: `(view slot, x, y)`, spread evenly over the views that have a crop
/// covering the mask by `min_fraction`.
fn patch_places(masks: &[(Vec<bool>, u32, u32)], spec: &KidSpec) -> Result<Vec<(usize, u32, u32)>> {
    let ok: Vec<usize> = (0..masks.len())
        .filter(|&v| {
            let (m, w, h) = &masks[v];
            masked_crops(m, *w, *h, spec.crop_size, 1, spec.min_fraction, 0).is_ok()
        })
        .collect();
    let mut out = Vec::new();
    for (k, &v) in ok.iter().enumerate() {
        // Even shares; the first views take the remainder.
        let n = spec.crops / ok.len() + usize::from(k < spec.crops % ok.len());
        let (m, w, h) = &masks[v];
        let seed = spec.seed.wrapping_mul(0x9E37_79B9).wrapping_add(v as u64);
        for (x, y) in masked_crops(m, *w, *h, spec.crop_size, n, spec.min_fraction, seed)? {
            out.push((v, x, y));
        }
    }
    Ok(out)
}

fn cut(img: &[f32], w: usize, x: u32, y: u32, s: u32) -> Vec<f32> {
    let (x, y, s) = (x as usize, y as usize, s as usize);
    crop(img, w, (x, x + s, y, y + s))
}

/// The KID evaluator: the network and the protocols.
#[derive(Debug)]
pub struct KidEval<'a> {
    pub net: &'a Inception,
    pub spec: KidSpec,
}

impl KidEval<'_> {
    /// Features of full frames and of the crops at `places`.
    fn features(
        &self,
        imgs: &[&[f32]],
        sizes: &[(usize, usize)],
        places: &[(usize, u32, u32)],
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let frames: Vec<ImageRef> = imgs
            .iter()
            .zip(sizes)
            .map(|(rgb, &(width, height))| ImageRef { rgb, width, height })
            .collect();
        let full = self.net.features(&frames, self.spec.batch)?;
        let s = self.spec.crop_size;
        let crops: Vec<Vec<f32>> = places
            .iter()
            .map(|&(v, x, y)| cut(imgs[v], sizes[v].0, x, y, s))
            .collect();
        let refs: Vec<ImageRef> = crops
            .iter()
            .map(|c| ImageRef {
                rgb: c,
                width: s as usize,
                height: s as usize,
            })
            .collect();
        let patches = self.net.features(&refs, self.spec.batch)?;
        Ok((full, patches))
    }
}

/// KID's ground truth of a run: the report of the protocols and the photos' features (full
/// frames, and crops at `places`).
#[derive(Debug)]
pub(crate) struct KidRef {
    pub report: KidReport,
    pub places: Vec<(usize, u32, u32)>,
    full: Vec<f32>,
    patches: Vec<f32>,
}

impl KidEval<'_> {
    /// The ground truth of the held-out views: `masks` (true: not visible, with the view's size)
    /// place the crops; `photos` are the views' images of `sizes`.
    pub(crate) fn reference(
        &self,
        masks: &[(Vec<bool>, u32, u32)],
        photos: &[&[f32]],
        sizes: &[(usize, usize)],
        rep: &mut dyn Reporter,
    ) -> Result<KidRef> {
        let places = patch_places(masks, &self.spec)?;
        let mut crops_per_view = vec![0; masks.len()];
        for p in &places {
            crops_per_view[p.0] += 1;
        }
        let pm = self.spec.subset_size.min(places.len());
        let report = KidReport {
            spec: self.spec.clone(),
            crops_per_view,
            frame_subset_size: self.spec.frame_subset_size.min(masks.len()),
            patch_subset_size: (pm >= 2).then_some(pm),
            max_coverage: masks
                .iter()
                .map(|(m, w, h)| max_coverage(m, *w, *h, self.spec.crop_size))
                .fold(0.0, f64::max),
        };
        let t0 = std::time::Instant::now();
        let (full, patches) = self.features(photos, sizes, &places)?;
        rep.note(&format!(
            "KID: Inception features of {} photos and {} crops in {:.0} s",
            photos.len(),
            places.len(),
            t0.elapsed().as_secs_f64()
        ));
        Ok(KidRef {
            report,
            places,
            full,
            patches,
        })
    }

    /// The full-frame and the patch KID of the renders `imgs` of field `name` against `r`
    /// (the patch one where there are at least two crops).
    pub(crate) fn score(
        &self,
        r: &KidRef,
        imgs: &[&[f32]],
        sizes: &[(usize, usize)],
        name: &str,
        rep: &mut dyn Reporter,
    ) -> Result<(Option<Kid>, Option<Kid>)> {
        let t0 = std::time::Instant::now();
        let (full, patches) = self.features(imgs, sizes, &r.places)?;
        let cfg = |subset_size| KidConfig {
            subsets: self.spec.subsets,
            subset_size,
            seed: self.spec.seed,
        };
        let frame = kid(&r.full, &full, FEATURES, &cfg(r.report.frame_subset_size))?;
        let patch = match r.report.patch_subset_size {
            Some(pm) => Some(kid(&r.patches, &patches, FEATURES, &cfg(pm))?),
            None => None,
        };
        rep.note(&format!(
            "KID of {name}: {} frames and {} crops in {:.0} s",
            imgs.len(),
            r.places.len(),
            t0.elapsed().as_secs_f64()
        ));
        Ok((Some(frame), patch))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patch_crops_spread_over_the_views_that_have_them() {
        let (w, h) = (40usize, 30usize);
        // View 0: a 20x20 block; view 1: nothing; view 2: a 12x12 block.
        let block = |x0: usize, y0: usize, s: usize| -> Vec<bool> {
            (0..w * h)
                .map(|i| (x0..x0 + s).contains(&(i % w)) && (y0..y0 + s).contains(&(i / w)))
                .collect()
        };
        let masks = vec![
            (block(5, 5, 20), w as u32, h as u32),
            (vec![false; w * h], w as u32, h as u32),
            (block(20, 10, 12), w as u32, h as u32),
        ];
        let spec = KidSpec {
            crops: 11,
            crop_size: 16,
            ..KidSpec::default()
        };
        let p = patch_places(&masks, &spec).unwrap();
        let count = |v| p.iter().filter(|c| c.0 == v).count();
        assert_eq!((count(0), count(1), count(2)), (6, 0, 5));
        for &(v, x, y) in &p {
            let (m, _, _) = &masks[v];
            let (x, y) = (x as usize, y as usize);
            let inside = (0..16 * 16)
                .filter(|k| m[(y + k / 16) * w + x + k % 16])
                .count();
            assert!(
                inside * 2 >= 256,
                "crop ({x}, {y}) of view {v} covers {inside}"
            );
        }
        assert_eq!(p, patch_places(&masks, &spec).unwrap());
        let other = KidSpec {
            seed: 1,
            ..spec.clone()
        };
        assert_ne!(p, patch_places(&masks, &other).unwrap());
        // No view with such a crop: no crops, no error.
        let none = vec![(vec![false; w * h], w as u32, h as u32)];
        assert!(patch_places(&none, &spec).unwrap().is_empty());
    }
}
