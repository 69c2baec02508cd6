//! `extranerf eval RUN` on an extrapolate run: the comparison table of the BaseNeRF, every
//! stage-2 variant and every stage-3 field on the held-out views, over the whole image, inside the not-visible mask
//! (from the visibility stage) and over the visible rest.
//!
//! Inside the mask: PSNR over the masked pixels; SSIM and LPIPS on the mask's bounding box
//! (grown to LPIPS's smallest input) of an image that is the render inside the mask and the
//! photo outside, against the photo, so only the masked pixels differ. Visible: PSNR over the
//! pixels outside the mask. Each is the mean over the views that have such pixels.
//!
//! KID (Bińkowski et al. 2018) on [`crate::inception`]'s features, two protocols:
//! - full frame: the held-out views' renders against their photos, subsets of (at most) 8;
//!   with 8 views every subset is the whole set, so it is one noisy estimate, comparable only
//!   roughly with the paper's;
//! - patch: a fixed-seed set of square crops (default 500 of 128x128) that cover the
//!   not-visible mask by at least half, spread evenly over the views that have such crops, cut
//!   at the same places from render and photo; 100 subsets of 100. It ranks the variants.

use std::path::Path;

use anyhow::{bail, Context as _};
use extranerf_nerf::data::load_image;
use extranerf_nerf::image_ops::{bbox, crop, resize_mask};
use extranerf_nerf::metrics::kid::{kid, masked_crops, max_coverage, KidConfig};
use extranerf_nerf::metrics::{psnr, ssim, Lpips};
use extranerf_nerf::safetensors::SafeTensors;
use serde::Serialize;

use crate::driver::Reporter;
use crate::inception::{ImageRef, Inception, FEATURES};
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
    /// Full-frame KID (mean and standard deviation over subsets).
    pub kid: Option<f64>,
    pub kid_std: Option<f64>,
    /// Patch KID on crops over the not-visible mask.
    pub kid_patch: Option<f64>,
    pub kid_patch_std: Option<f64>,
    /// Mean share of each view's pixels in the mask.
    pub masked_fraction: f64,
    /// With exact visibility masks ([`compare`]'s `truth_masks`): PSNR over the pixels that
    /// no two training cameras truly see, and over those they do (means over the views with
    /// a mask that has such pixels).
    pub psnr_not_visible_exact: Option<f64>,
    pub psnr_visible_exact: Option<f64>,
}

/// The table of an extrapolate run.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Table {
    pub views: Vec<usize>,
    pub rows: Vec<Row>,
    /// How KID was measured (absent when it was not).
    pub kid: Option<KidReport>,
    /// What the run's stages said of a row (a stage 3 that its gate skipped).
    pub notes: Vec<String>,
    /// The exact visibility masks the table was also scored with, if any.
    pub truth_masks: Option<TruthMasks>,
}

/// Exact visibility masks of the held-out views (`../shared/data/synth2/gt_visibility`, or the
/// demo scene's): where they come from and how much of the views they mark unseen.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TruthMasks {
    pub dir: std::path::PathBuf,
    /// Held-out views that have a mask.
    pub views: Vec<usize>,
    /// Mean share of those views' pixels that is not visible.
    pub not_visible_fraction: f64,
}

impl TruthMasks {
    /// One line for the table's readers.
    pub fn describe(&self) -> String {
        format!(
            "Exact visibility from {} ({} of the held-out views; {:.1}% of their pixels not visible to two training cameras): `PSNR not visible (exact)` and `PSNR visible (exact)`.",
            self.dir.display(),
            self.views.len(),
            100.0 * self.not_visible_fraction
        )
    }
}

/// The exact visibility mask (true: seen) of the view whose image is `image`, from `dir`
/// (the image's stem as a PNG, white where seen, `w x h`); None when `dir` has none for it.
/// `eval --visibility-masks` reads masks through it, for training runs and extrapolate runs.
pub fn truth_mask(dir: &Path, image: &Path, w: u32, h: u32) -> anyhow::Result<Option<Vec<bool>>> {
    let stem = image.file_stem().unwrap_or_default();
    let path = dir.join(stem).with_extension("png");
    if !path.exists() {
        return Ok(None);
    }
    let m = load_image(&path)?;
    if (m.width, m.height) != (w, h) {
        bail!(
            "{}: a {}x{} mask for a {w}x{h} view",
            path.display(),
            m.width,
            m.height
        );
    }
    Ok(Some(m.rgb.chunks(3).map(|c| c[0] > 0.5).collect()))
}

/// Writes `run`'s `eval.json` and `eval.md` from `table` (atomically) and its `report.html`;
/// returns the report's path.
pub fn write_table(run: &Path, table: &Table) -> anyhow::Result<std::path::PathBuf> {
    let json = serde_json::to_string_pretty(table)? + "\n";
    extranerf_nerf::safetensors::write_atomic(&run.join("eval.json"), json.as_bytes())?;
    extranerf_nerf::safetensors::write_atomic(&run.join("eval.md"), table.markdown().as_bytes())?;
    crate::report::write_report(run, Some(table))
}

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
fn patch_places(
    masks: &[(Vec<bool>, u32, u32)],
    spec: &KidSpec,
) -> anyhow::Result<Vec<(usize, u32, u32)>> {
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
    ) -> anyhow::Result<(Vec<f32>, Vec<f32>)> {
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

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Scores the BaseNeRF and each finished stage-2 and stage-3 variant of the run in `dir`; KID
/// too when `kid` is given, and over the exact visible and not-visible pixels when
/// `truth_masks` names a folder of masks (see [`TruthMasks`]; an error when it holds none for
/// the held-out views). Progress goes to `rep`.
pub fn compare(
    dir: &Path,
    lpips: Option<&Lpips>,
    kid_eval: Option<&KidEval<'_>>,
    truth_masks: Option<&Path>,
    rep: &mut dyn Reporter,
) -> anyhow::Result<Table> {
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
    let mut notes = vec![format!(
        "BaseNeRF depth targets: {}",
        manifest.scene.depth_label()
    )];
    for s in &manifest.stages {
        if let (true, Some(why)) = (s.done, s.report["skipped"].as_str()) {
            notes.push(format!("{}: {why}", s.name));
        }
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
        let mask: Vec<bool> = resize_mask(
            &settings.mask(&m),
            m.width as usize,
            m.height as usize,
            cam.width as usize,
            cam.height as usize,
        )
        .iter()
        .map(|&v| v >= 0.5)
        .collect();
        truths.push((i, cam.clone(), img, mask));
    }
    // The exact masks (true: seen), per held-out view where the folder has one.
    let exact: Vec<Option<Vec<bool>>> = match truth_masks {
        None => vec![None; truths.len()],
        Some(d) => {
            if !d.is_dir() {
                bail!("{}: no such folder of visibility masks", d.display());
            }
            truths
                .iter()
                .map(|(_, c, _, _)| truth_mask(d, &c.image, c.width, c.height))
                .collect::<anyhow::Result<_>>()?
        }
    };
    let truth_report = match truth_masks {
        None => None,
        Some(d) => {
            let with: Vec<(usize, &Vec<bool>)> = truths
                .iter()
                .zip(&exact)
                .filter_map(|(t, m)| m.as_ref().map(|m| (t.0, m)))
                .collect();
            if with.is_empty() {
                bail!(
                    "{}: no visibility mask for any held-out view (want PNGs named as their images, e.g. {})",
                    d.display(),
                    truths
                        .first()
                        .and_then(|t| t.1.image.file_stem())
                        .map(|s| format!("{}.png", s.to_string_lossy()))
                        .unwrap_or_default()
                );
            }
            let frac: Vec<f64> = with
                .iter()
                .map(|(_, m)| m.iter().filter(|&&v| !v).count() as f64 / m.len() as f64)
                .collect();
            Some(TruthMasks {
                dir: d.to_path_buf(),
                views: with.iter().map(|w| w.0).collect(),
                not_visible_fraction: mean(&frac).unwrap_or(0.0),
            })
        }
    };
    let sizes: Vec<(usize, usize)> = truths
        .iter()
        .map(|(_, c, _, _)| (c.width as usize, c.height as usize))
        .collect();
    // KID's ground-truth features, once for all variants.
    let kid_ref = match kid_eval {
        None => None,
        Some(k) => {
            let masks: Vec<(Vec<bool>, u32, u32)> = truths
                .iter()
                .map(|(_, c, _, m)| (m.clone(), c.width, c.height))
                .collect();
            let places = patch_places(&masks, &k.spec)?;
            let mut crops_per_view = vec![0; truths.len()];
            for p in &places {
                crops_per_view[p.0] += 1;
            }
            let pm = k.spec.subset_size.min(places.len());
            let report = KidReport {
                spec: k.spec.clone(),
                crops_per_view,
                frame_subset_size: k.spec.frame_subset_size.min(truths.len()),
                patch_subset_size: (pm >= 2).then_some(pm),
                max_coverage: masks
                    .iter()
                    .map(|(m, w, h)| max_coverage(m, *w, *h, k.spec.crop_size))
                    .fold(0.0, f64::max),
            };
            let t0 = std::time::Instant::now();
            let imgs: Vec<&[f32]> = truths.iter().map(|t| t.2.rgb.as_slice()).collect();
            let (full, patches) = k.features(&imgs, &sizes, &places)?;
            rep.note(&format!(
                "KID: Inception features of {} photos and {} crops in {:.0} s",
                imgs.len(),
                places.len(),
                t0.elapsed().as_secs_f64()
            ));
            Some((report, places, full, patches))
        }
    };
    let mut rows = Vec::new();
    for (name, folder, suffix) in variants {
        let (mut p, mut s, mut l) = (vec![], vec![], vec![]);
        let (mut pm, mut sm, mut lm, mut pv, mut frac) = (vec![], vec![], vec![], vec![], vec![]);
        let (mut pn_exact, mut pv_exact) = (vec![], vec![]);
        let mut renders = Vec::new();
        for ((i, cam, truth, mask), seen) in truths.iter().zip(&exact) {
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
            if let Some(seen) = seen {
                if let Some(m) = mse_where(&r.rgb, &truth.rgb, seen, false) {
                    pn_exact.push(to_psnr(m));
                }
                if let Some(m) = mse_where(&r.rgb, &truth.rgb, seen, true) {
                    pv_exact.push(to_psnr(m));
                }
            }
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
            renders.push(r.rgb);
        }
        let (mut kid_frame, mut kid_patch) = (None, None);
        if let (Some(k), Some((report, places, full_t, patch_t))) = (kid_eval, &kid_ref) {
            let t0 = std::time::Instant::now();
            let imgs: Vec<&[f32]> = renders.iter().map(Vec::as_slice).collect();
            let (full, patches) = k.features(&imgs, &sizes, places)?;
            let cfg = |subset_size| KidConfig {
                subsets: k.spec.subsets,
                subset_size,
                seed: k.spec.seed,
            };
            let m = report.frame_subset_size;
            kid_frame = Some(kid(full_t, &full, FEATURES, &cfg(m))?);
            if let Some(pm) = report.patch_subset_size {
                kid_patch = Some(kid(patch_t, &patches, FEATURES, &cfg(pm))?);
            }
            rep.note(&format!(
                "KID of {name}: {} frames and {} crops in {:.0} s",
                imgs.len(),
                places.len(),
                t0.elapsed().as_secs_f64()
            ));
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
            kid: kid_frame.map(|k| k.mean),
            kid_std: kid_frame.map(|k| k.std),
            kid_patch: kid_patch.map(|k| k.mean),
            kid_patch_std: kid_patch.map(|k| k.std),
            masked_fraction: mean(&frac).unwrap_or(0.0),
            psnr_not_visible_exact: mean(&pn_exact),
            psnr_visible_exact: mean(&pv_exact),
        });
    }
    Ok(Table {
        views,
        rows,
        kid: kid_ref.map(|r| r.0),
        notes,
        truth_masks: truth_report,
    })
}

/// The table's column headers (the two exact-visibility columns only where the table was
/// scored with exact masks, [`Table::columns`]).
pub const COLUMNS: [&str; 11] = [
    "variant",
    "PSNR",
    "SSIM",
    "LPIPS-alex",
    "PSNR masked",
    "SSIM masked",
    "LPIPS masked",
    "PSNR visible",
    "KID",
    "patch KID",
    "masked",
];

/// The headers of the exact-visibility columns.
pub const EXACT_COLUMNS: [&str; 2] = ["PSNR not visible (exact)", "PSNR visible (exact)"];

impl Row {
    /// The row's cells as the tables print them (`-` where a value is missing); with `exact`,
    /// the exact-visibility cells too.
    pub fn cells(&self, exact: bool) -> Vec<String> {
        let f = |v: Option<f64>, d: usize| v.map_or("-".into(), |x| format!("{x:.d$}"));
        let mut c = vec![
            self.variant.clone(),
            format!("{:.2}", self.psnr),
            format!("{:.3}", self.ssim),
            f(self.lpips, 3),
            f(self.psnr_masked, 2),
            f(self.ssim_masked, 3),
            f(self.lpips_masked, 3),
            f(self.psnr_visible, 2),
            f(self.kid, 4),
            f(self.kid_patch, 4),
            format!("{:.1}%", 100.0 * self.masked_fraction),
        ];
        if exact {
            c.push(f(self.psnr_not_visible_exact, 2));
            c.push(f(self.psnr_visible_exact, 2));
        }
        c
    }
}

impl Table {
    /// The column headers of this table.
    pub fn columns(&self) -> Vec<&'static str> {
        let mut c = COLUMNS.to_vec();
        if self.truth_masks.is_some() {
            c.extend(EXACT_COLUMNS);
        }
        c
    }

    /// Each row's cells, as [`Table::columns`] names them.
    pub fn cells(&self) -> Vec<Vec<String>> {
        let exact = self.truth_masks.is_some();
        self.rows.iter().map(|r| r.cells(exact)).collect()
    }

    /// The table in Markdown.
    pub fn markdown(&self) -> String {
        let cols = self.columns();
        let mut s = format!("| {} |\n|{}\n", cols.join(" | "), "---|".repeat(cols.len()));
        for r in self.cells() {
            s += &format!("| {} |\n", r.join(" | "));
        }
        if let Some(t) = &self.truth_masks {
            s += &format!("\n{}\n", t.describe());
        }
        if let Some(k) = &self.kid {
            s += &format!("\n{}\n", k.describe());
        }
        for n in &self.notes {
            s += &format!("\n{n}\n");
        }
        s
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
    }
}
