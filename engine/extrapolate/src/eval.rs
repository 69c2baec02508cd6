//! `extranerf eval RUN` on an extrapolate run: the comparison table of the BaseNeRF, every
//! stage-2 variant and every stage-3 field on the held-out views, over the whole image, inside the not-visible mask
//! (from the visibility stage) and over the visible rest.
//!
//! Inside the mask: PSNR over the masked pixels; SSIM and LPIPS on the mask's bounding box
//! (grown to LPIPS's smallest input) of an image that is the render inside the mask and the
//! photo outside, against the photo, so only the masked pixels differ. Visible: PSNR over the
//! pixels outside the mask. Each is the mean over the views that have such pixels.

use std::path::Path;

use anyhow::{bail, Context as _};
use extranerf_nerf::data::load_image;
use extranerf_nerf::metrics::{psnr, ssim, Lpips};
use extranerf_nerf::safetensors::SafeTensors;
use serde::Serialize;

use crate::manifest::Manifest;
use crate::pipeline::{load_map, MAPS_FILE};
use crate::visibility::VisSettings;

/// One row of the table.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Row {
    pub variant: String,
    pub psnr: f64,
    pub ssim: f64,
    pub lpips: Option<f64>,
    pub psnr_masked: Option<f64>,
    pub ssim_masked: Option<f64>,
    pub lpips_masked: Option<f64>,
    pub psnr_visible: Option<f64>,
    /// Mean share of each view's pixels in the mask.
    pub masked_fraction: f64,
}

/// The table of an extrapolate run.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Table {
    pub views: Vec<usize>,
    pub rows: Vec<Row>,
}

fn mse_where(a: &[f32], b: &[f32], mask: &[bool], inside: bool) -> Option<f64> {
    let (mut se, mut n) = (0f64, 0usize);
    for (i, &m) in mask.iter().enumerate() {
        if m == inside {
            for c in 0..3 {
                se += (a[3 * i + c] as f64 - b[3 * i + c] as f64).powi(2);
            }
            n += 3;
        }
    }
    (n > 0).then(|| se / n as f64)
}

fn to_psnr(mse: f64) -> f64 {
    if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

/// The mask's bounding box grown to at least `min` pixels a side (within the image).
fn bbox(mask: &[bool], w: usize, h: usize, min: usize) -> Option<(usize, usize, usize, usize)> {
    let (mut x0, mut x1, mut y0, mut y1) = (w, 0, h, 0);
    for (i, &m) in mask.iter().enumerate() {
        if m {
            let (x, y) = (i % w, i / w);
            (x0, x1, y0, y1) = (x0.min(x), x1.max(x + 1), y0.min(y), y1.max(y + 1));
        }
    }
    if x1 == 0 {
        return None;
    }
    let grow = |lo: usize, hi: usize, size: usize| {
        let want = min.min(size);
        if hi - lo >= want {
            return (lo, hi);
        }
        let lo = lo.saturating_sub((want - (hi - lo)).div_ceil(2));
        let lo = lo.min(size - want);
        (lo, lo + want)
    };
    let (x0, x1) = grow(x0, x1, w);
    let (y0, y1) = grow(y0, y1, h);
    Some((x0, x1, y0, y1))
}

fn crop(img: &[f32], w: usize, b: (usize, usize, usize, usize)) -> Vec<f32> {
    let mut v = Vec::new();
    for y in b.2..b.3 {
        v.extend_from_slice(&img[3 * (y * w + b.0)..3 * (y * w + b.1)]);
    }
    v
}

/// A `sw x sh` mask resized to `w x h` by nearest neighbour.
fn upsample(mask: &[f32], sw: usize, sh: usize, w: usize, h: usize) -> Vec<bool> {
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let (sx, sy) = ((x * sw / w).min(sw - 1), (y * sh / h).min(sh - 1));
            mask[sy * sw + sx] >= 0.5
        })
        .collect()
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Scores the BaseNeRF and each finished stage-2 variant of the run in `dir`.
pub fn compare(dir: &Path, lpips: Option<&Lpips>) -> anyhow::Result<Table> {
    let Some(manifest) = Manifest::load(dir)? else {
        bail!("{}: no extrapolate manifest", dir.display());
    };
    let loaded = manifest.scene.load()?;
    let vis_rec = manifest
        .stages
        .iter()
        .find(|s| s.name == "visibility" && s.done)
        .with_context(|| format!("{}: the visibility stage has not finished", dir.display()))?;
    let settings: VisSettings = serde_json::from_value(vis_rec.config["settings"].clone())
        .with_context(|| format!("{}: the visibility stage's settings", dir.display()))?;
    let maps_path = dir.join("visibility").join(MAPS_FILE);
    let st = SafeTensors::read(&maps_path)?;
    let mut variants = vec![("base".to_string(), dir.join("visibility"), "_base")];
    for s in &manifest.stages {
        let stage3 = s.name.starts_with("stage3-")
            && s.name != crate::stage3::DATA_STAGE
            && s.name != crate::stage3::ENHANCER_STAGE;
        if s.done && (s.name.starts_with("stage2-") || stage3) {
            variants.push((s.name.clone(), dir.join(&s.name), ""));
        }
    }
    let views = loaded.split.test.clone();
    let mut truths = Vec::new();
    for &i in &views {
        let cam = &loaded.scene.cameras[i];
        let img = load_image(&cam.image)?;
        let m = load_map(&st, &maps_path, &format!("test_{i:03}"))?;
        let mask = upsample(
            &settings.mask(&m),
            m.width as usize,
            m.height as usize,
            cam.width as usize,
            cam.height as usize,
        );
        truths.push((i, cam.clone(), img, mask));
    }
    let mut rows = Vec::new();
    for (name, folder, suffix) in variants {
        let (mut p, mut s, mut l) = (vec![], vec![], vec![]);
        let (mut pm, mut sm, mut lm, mut pv, mut frac) = (vec![], vec![], vec![], vec![], vec![]);
        for (i, cam, truth, mask) in &truths {
            let path = folder.join(format!("test_{i:03}{suffix}.png"));
            let r = load_image(&path).with_context(|| format!("variant {name}"))?;
            if (r.width, r.height) != (cam.width, cam.height) {
                bail!("{}: not the size of held-out view {i}", path.display());
            }
            let (w, h) = (cam.width as usize, cam.height as usize);
            p.push(psnr(&r.rgb, &truth.rgb)?);
            s.push(ssim(&r.rgb, &truth.rgb, cam.width, cam.height)?);
            if let Some(lp) = lpips {
                l.push(lp.distance(&r.rgb, &truth.rgb, cam.width, cam.height)?);
            }
            frac.push(mask.iter().filter(|&&m| m).count() as f64 / mask.len() as f64);
            if let Some(m) = mse_where(&r.rgb, &truth.rgb, mask, false) {
                pv.push(to_psnr(m));
            }
            if let Some(m) = mse_where(&r.rgb, &truth.rgb, mask, true) {
                pm.push(to_psnr(m));
                let mut comp = truth.rgb.clone();
                for (k, &inside) in mask.iter().enumerate() {
                    if inside {
                        comp[3 * k..3 * k + 3].copy_from_slice(&r.rgb[3 * k..3 * k + 3]);
                    }
                }
                let min = lpips.map_or(16, |lp| lp.net().min_size() as usize).max(16);
                if let Some(b) = bbox(mask, w, h, min) {
                    let (bw, bh) = ((b.1 - b.0) as u32, (b.3 - b.2) as u32);
                    let (cr, ct) = (crop(&comp, w, b), crop(&truth.rgb, w, b));
                    sm.push(ssim(&cr, &ct, bw, bh)?);
                    if let Some(lp) = lpips {
                        lm.push(lp.distance(&cr, &ct, bw, bh)?);
                    }
                }
            }
        }
        rows.push(Row {
            variant: name,
            psnr: mean(&p).unwrap_or(f64::NAN),
            ssim: mean(&s).unwrap_or(f64::NAN),
            lpips: mean(&l),
            psnr_masked: mean(&pm),
            ssim_masked: mean(&sm),
            lpips_masked: mean(&lm),
            psnr_visible: mean(&pv),
            masked_fraction: mean(&frac).unwrap_or(0.0),
        });
    }
    Ok(Table { views, rows })
}

/// The table's column headers.
pub const COLUMNS: [&str; 9] = [
    "variant",
    "PSNR",
    "SSIM",
    "LPIPS-alex",
    "PSNR masked",
    "SSIM masked",
    "LPIPS masked",
    "PSNR visible",
    "masked",
];

impl Row {
    /// The row's cells as the tables print them (`-` where a value is missing).
    pub fn cells(&self) -> [String; 9] {
        let f = |v: Option<f64>, d: usize| v.map_or("-".into(), |x| format!("{x:.d$}"));
        [
            self.variant.clone(),
            format!("{:.2}", self.psnr),
            format!("{:.3}", self.ssim),
            f(self.lpips, 3),
            f(self.psnr_masked, 2),
            f(self.ssim_masked, 3),
            f(self.lpips_masked, 3),
            f(self.psnr_visible, 2),
            format!("{:.1}%", 100.0 * self.masked_fraction),
        ]
    }
}

impl Table {
    /// The table in Markdown.
    pub fn markdown(&self) -> String {
        let mut s = format!("| {} |\n|{}\n", COLUMNS.join(" | "), "---|".repeat(9));
        for r in &self.rows {
            s += &format!("| {} |\n", r.cells().join(" | "));
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn boxes_grow_to_the_smallest_input_inside_the_image() {
        let (w, h) = (40, 30);
        let mut mask = vec![false; w * h];
        assert_eq!(bbox(&mask, w, h, 16), None);
        mask[2 * w + 1] = true;
        let b = bbox(&mask, w, h, 16).unwrap();
        assert_eq!((b.1 - b.0, b.3 - b.2), (16, 16));
        assert!(b.0 <= 1 && b.1 > 1 && b.2 <= 2 && b.3 > 2);
        mask[29 * w + 39] = true;
        assert_eq!(bbox(&mask, w, h, 16), Some((1, 40, 2, 30)));
        // Larger than the image: the whole image.
        assert_eq!(bbox(&mask, w, h, 100), Some((0, 40, 0, 30)));
    }

    #[test]
    fn masked_and_visible_errors_split_the_image() {
        let a = vec![0.5f32; 4 * 3];
        let mut b = a.clone();
        b[0] = 0.6;
        let mask = [true, false, false, false];
        let m = mse_where(&a, &b, &mask, true).unwrap();
        assert!((m - 0.01 / 3.0).abs() < 1e-7, "{m}");
        assert_eq!(mse_where(&a, &b, &mask, false), Some(0.0));
        assert_eq!(mse_where(&a, &b, &[false; 4], true), None);
        let up = upsample(&[1.0, 0.0], 2, 1, 4, 2);
        assert_eq!(up, [true, true, false, false, true, true, false, false]);
    }
}
