//! `extranerf eval RUN` on an extrapolate run: the comparison table of the BaseNeRF, every
//! stage-2 variant and every stage-3 field on the held-out views, over the whole image, inside the not-visible mask
//! (from the visibility stage) and over the visible rest.
//!
//! Inside the mask: PSNR over the masked pixels; SSIM and LPIPS on the mask's bounding box
//! (grown to LPIPS's smallest input) of an image that is the render inside the mask and the
//! photo outside, against the photo, so only the masked pixels differ. Visible: PSNR over the
//! pixels outside the mask. Each is the mean over the views that have such pixels.
//!
//! KID (Bińkowski et al. 2018) on [`inception`]'s features, two protocols:
//! - full frame: the held-out views' renders against their photos, subsets of (at most) 8;
//!   with 8 views every subset is the whole set, so it is one noisy estimate, comparable only
//!   roughly with the paper's;
//! - patch: a fixed-seed set of square crops (default 500 of 128x128) that cover the
//!   not-visible mask by at least half, spread evenly over the views that have such crops, cut
//!   at the same places from render and photo; 100 subsets of 100. It ranks the variants.
//!
//! Files: [`table`] (the rows and their markdown), [`kid`] (the KID protocols),
//! [`inception`] (the feature network), [`report`] (the HTML page).

pub mod inception;
pub mod kid;
pub mod report;
pub mod table;

pub use kid::{KidEval, KidReport, KidSpec};
pub use table::{Row, Table, TruthMasks, COLUMNS, EXACT_COLUMNS};

use std::path::{Path, PathBuf};

use crate::error::{write_json, ExtrapolateError, Result};
use crate::manifest::StageSpec;
use extranerf_nerf::data::{load_image, Camera, Image};
use extranerf_nerf::image_ops::{bbox, crop, resize_mask};
use extranerf_nerf::metrics::{psnr, ssim, Lpips};
use extranerf_nerf::run::LoadedScene;
use extranerf_nerf::safetensors::SafeTensors;

use crate::manifest::Manifest;
use crate::shown::Shown;
use crate::stage::{DATA_STAGE, ENHANCER_STAGE};
use crate::stages::VisibilityStage;
use crate::visibility::{load_map, VisSettings, MAPS_FILE};
use extranerf_nerf::train::Reporter;

/// The exact visibility mask (true: seen) of the view whose image is `image`, from `dir`
/// (the image's stem as a PNG, white where seen, `w x h`); None when `dir` has none for it.
/// `eval --visibility-masks` reads masks through it, for training runs and extrapolate runs.
pub fn truth_mask(dir: &Path, image: &Path, w: u32, h: u32) -> Result<Option<Vec<bool>>> {
    let stem = image.file_stem().unwrap_or_default();
    let path = dir.join(stem).with_extension("png");
    if !path.exists() {
        return Ok(None);
    }
    let m = load_image(&path)?;
    if (m.width, m.height) != (w, h) {
        return Err(ExtrapolateError::malformed(
            &path,
            format!("a {}x{} mask for a {w}x{h} view", m.width, m.height),
        ));
    }
    Ok(Some(m.rgb.chunks(3).map(|c| c[0] > 0.5).collect()))
}

/// Writes `run`'s `eval.json` and `eval.md` from `table` (atomically) and its `report.html`;
/// returns the report's path.
pub fn write_table(run: &Path, table: &Table) -> Result<std::path::PathBuf> {
    write_json(&run.join("eval.json"), table)?;
    extranerf_nerf::safetensors::write_atomic(&run.join("eval.md"), table.markdown().as_bytes())?;
    report::write_report(run, Some(table))
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

/// A held-out view: its scene index, camera, photo and not-visible mask (the visibility
/// stage's, at the photo's size; true: not visible).
type HeldOut = (usize, Camera, Image, Vec<bool>);

pub fn compare(
    dir: &Path,
    lpips: Option<&Lpips>,
    kid_eval: Option<&KidEval<'_>>,
    truth_masks: Option<&Path>,
    rep: &mut dyn Reporter,
) -> Result<Table> {
    let Some(manifest) = Manifest::load(dir)? else {
        return Err(ExtrapolateError::incomplete(dir, "no extrapolate manifest"));
    };
    let loaded = manifest.scene.load()?;
    let (variants, mut notes) = variants(dir, &manifest);
    let shown = Shown::of(&loaded.split);
    if !shown.held_out {
        notes.push(
            "No held-out view: the run's split trains on every view, so the table scores the \
             training views, which says how well each field keeps what the cameras saw, not \
             how it renders a view it has not seen."
                .into(),
        );
    }
    let views = shown.views.clone();
    let truths = held_out(dir, &manifest, &loaded, &shown)?;
    let (exact, truth_report) = exact_masks(truth_masks, &truths)?;
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
            let imgs: Vec<&[f32]> = truths.iter().map(|t| t.2.rgb.as_slice()).collect();
            Some(k.reference(&masks, &imgs, &sizes, rep)?)
        }
    };
    let mut rows = Vec::new();
    for (name, folder, suffix) in variants {
        let (mut row, renders) =
            score_variant(&name, &folder, suffix, &shown, &truths, &exact, lpips)?;
        if let (Some(k), Some(r)) = (kid_eval, &kid_ref) {
            let imgs: Vec<&[f32]> = renders.iter().map(Vec::as_slice).collect();
            let (frame, patch) = k.score(r, &imgs, &sizes, &name, rep)?;
            row.kid = frame.map(|k| k.mean);
            row.kid_std = frame.map(|k| k.std);
            row.kid_patch = patch.map(|k| k.mean);
            row.kid_patch_std = patch.map(|k| k.std);
        }
        rows.push(row);
    }
    Ok(Table {
        views,
        held_out: shown.held_out,
        rows,
        kid: kid_ref.map(|r| r.report),
        notes,
        truth_masks: truth_report,
    })
}

/// The fields of a run that `compare` scores (name, folder, suffix of its held-out renders),
/// and the table's notes (the BaseNeRF's depth targets, the stages that were skipped).
fn variants(
    dir: &Path,
    manifest: &Manifest,
) -> (Vec<(String, PathBuf, &'static str)>, Vec<String>) {
    let mut variants = vec![("base".to_string(), dir.join("visibility"), "_base")];
    let mut notes = vec![format!(
        "BaseNeRF depth targets: {}",
        manifest.scene.depth_label()
    )];
    for s in &manifest.stages {
        if let (true, Some(why)) = (s.done, s.report["skipped"].as_str()) {
            notes.push(format!("{}: {why}", s.name));
        }
        let stage3 =
            s.name.starts_with("stage3-") && s.name != DATA_STAGE && s.name != ENHANCER_STAGE;
        if s.done && (s.name.starts_with("stage2-") || stage3) {
            variants.push((s.name.clone(), dir.join(&s.name), ""));
        }
    }
    (variants, notes)
}

/// The views `eval` scores ([`Shown`]) with their photos and the visibility stage's masks.
fn held_out(
    dir: &Path,
    manifest: &Manifest,
    loaded: &LoadedScene,
    shown: &Shown,
) -> Result<Vec<HeldOut>> {
    let vis_rec = manifest
        .stages
        .iter()
        .find(|s| s.name == "visibility" && s.done)
        .ok_or_else(|| {
            ExtrapolateError::incomplete(dir, "the visibility stage has not finished")
        })?;
    let settings: VisSettings = VisibilityStage::from_record(&vis_rec.config)
        .map_err(|e| {
            ExtrapolateError::malformed(
                &Manifest::path(dir),
                format!("the visibility stage's settings: {e}"),
            )
        })?
        .vis;
    let maps_path = dir.join("visibility").join(MAPS_FILE);
    let st = SafeTensors::read(&maps_path)?;
    let mut truths = Vec::new();
    for &i in &shown.views {
        let cam = &loaded.scene.cameras[i];
        let img = load_image(&cam.image)?;
        let m = load_map(&st, &maps_path, &shown.name(i))?;
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
    Ok(truths)
}

/// The exact masks (true: seen) of the held-out views that the folder `truth_masks` has one
/// for, and what they cover.
#[allow(clippy::type_complexity)] // a mask per view, and the summary
fn exact_masks(
    truth_masks: Option<&Path>,
    truths: &[HeldOut],
) -> Result<(Vec<Option<Vec<bool>>>, Option<TruthMasks>)> {
    let Some(d) = truth_masks else {
        return Ok((vec![None; truths.len()], None));
    };
    if !d.is_dir() {
        return Err(ExtrapolateError::usage(format!(
            "{}: no such folder of visibility masks",
            d.display()
        )));
    }
    let exact: Vec<Option<Vec<bool>>> = truths
        .iter()
        .map(|(_, c, _, _)| truth_mask(d, &c.image, c.width, c.height))
        .collect::<Result<_>>()?;
    let with: Vec<(usize, &Vec<bool>)> = truths
        .iter()
        .zip(&exact)
        .filter_map(|(t, m)| m.as_ref().map(|m| (t.0, m)))
        .collect();
    if with.is_empty() {
        return Err(ExtrapolateError::malformed(d, format!("no visibility mask for any held-out view (want PNGs named as their images, e.g. {})",
            truths
                .first()
                .and_then(|t| t.1.image.file_stem())
                .map(|s| format!("{}.png", s.to_string_lossy()))
                .unwrap_or_default())));
    }
    let frac: Vec<f64> = with
        .iter()
        .map(|(_, m)| m.iter().filter(|&&v| !v).count() as f64 / m.len() as f64)
        .collect();
    let report = TruthMasks {
        dir: d.to_path_buf(),
        views: with.iter().map(|w| w.0).collect(),
        not_visible_fraction: mean(&frac).unwrap_or(0.0),
    };
    Ok((exact, Some(report)))
}

/// One field's row (without KID) from its renders of the scored views,
/// `folder/test_NNN{suffix}.png` (or `train_NNN`, [`Shown::name`]), and the renders.
fn score_variant(
    name: &str,
    folder: &Path,
    suffix: &str,
    shown: &Shown,
    truths: &[HeldOut],
    exact: &[Option<Vec<bool>>],
    lpips: Option<&Lpips>,
) -> Result<(Row, Vec<Vec<f32>>)> {
    let (mut p, mut s, mut l) = (vec![], vec![], vec![]);
    let (mut pm, mut sm, mut lm, mut pv, mut frac) = (vec![], vec![], vec![], vec![], vec![]);
    let (mut pn_exact, mut pv_exact) = (vec![], vec![]);
    let mut renders = Vec::new();
    for ((i, cam, truth, mask), seen) in truths.iter().zip(exact) {
        let path = folder.join(format!("{}{suffix}.png", shown.name(*i)));
        let r = load_image(&path)?;
        if (r.width, r.height) != (cam.width, cam.height) {
            return Err(ExtrapolateError::malformed(
                &path,
                format!("not the size of view {i} (variant {name})"),
            ));
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
    let row = Row {
        variant: name.to_string(),
        psnr: mean(&p).unwrap_or(f64::NAN),
        ssim: mean(&s).unwrap_or(f64::NAN),
        lpips: mean(&l),
        psnr_masked: mean(&pm),
        ssim_masked: mean(&sm),
        lpips_masked: mean(&lm),
        psnr_visible: mean(&pv),
        kid: None,
        kid_std: None,
        kid_patch: None,
        kid_patch_std: None,
        masked_fraction: mean(&frac).unwrap_or(0.0),
        psnr_not_visible_exact: mean(&pn_exact),
        psnr_visible_exact: mean(&pv_exact),
    };
    Ok((row, renders))
}

#[cfg(test)]
mod tests {
    use super::*;

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
