//! The gate of stage 3 ([`crate::stage3::Stage3Gate::Check`]): corrupted renders of the training views
//! enhanced as stage 3 would enhance the virtual views, against their photos.

use std::time::Instant;

use extranerf_nerf::metrics::psnr;
use serde::{Deserialize, Serialize};

use crate::error::{write_json, ExtrapolateError, Result};
use crate::stage::{progress_views, RunDir};
use crate::stage3::spec::Stage3Spec;
use crate::stage3::triplets::Triplets;
use extranerf_nerf::train::{default_lpips_dir, lpips_alex, Reporter};

/// The file in the enhancer's folder that holds its [`EnhancerCheck`].
pub const CHECK_FILE: &str = "check.json";

/// What [`crate::stage3::Stage3Gate::Check`] measured: corrupted renders of the training views enhanced as
/// stage 3 enhances the virtual views, against their photos.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnhancerCheck {
    /// The enhancement's settings (a check made with other ones is made again), with the
    /// anchoring and smoothing that turn an enhancement into stage 3's target.
    pub t: f32,
    pub ddim_steps: usize,
    pub seed: u64,
    pub anchor_radius: usize,
    pub smooth_radius: usize,
    /// The triplets enhanced (their keys).
    pub triplets: Vec<String>,
    /// Mean PSNR of the renders and of their enhancements against the photos.
    pub psnr_render: f64,
    pub psnr_enhanced: f64,
    /// Mean LPIPS-alex of the same, where the weights loaded and the views are large enough.
    pub lpips_render: Option<f64>,
    pub lpips_enhanced: Option<f64>,
    /// Wall seconds of the check.
    pub seconds: f64,
}

impl EnhancerCheck {
    /// The enhancement brought the renders closer to their photos: LPIPS lowered, or where it
    /// was not measured, PSNR raised.
    pub fn helps(&self) -> bool {
        match (self.lpips_render, self.lpips_enhanced) {
            (Some(r), Some(e)) => e < r,
            _ => self.psnr_enhanced > self.psnr_render,
        }
    }

    /// One line of what it measured.
    pub fn describe(&self) -> String {
        let lpips = match (self.lpips_render, self.lpips_enhanced) {
            (Some(r), Some(e)) => format!("LPIPS-alex {r:.3} -> {e:.3}, "),
            _ => String::new(),
        };
        format!(
            "enhancing {} training-view renders (triplets {}) from t = {} in {} DDIM steps: {lpips}PSNR {:.2} -> {:.2} dB",
            self.triplets.len(),
            self.triplets.join(", "),
            self.t,
            self.ddim_steps,
            self.psnr_render,
            self.psnr_enhanced
        )
    }
}

/// The triplets the check enhances: one per training view, the sources taken in turn (view
/// `v` gets its `v mod n`-th triplet of `n`), which spreads the kinds of corruption over the
/// views at the cost of one enhancement per view (each kind once when every view has the same
/// `n` sources and there are at least `n` views).
pub fn check_triplets(tr: &Triplets) -> Vec<usize> {
    (0..tr.photos.len())
        .filter_map(|v| {
            let mine: Vec<usize> = (0..tr.entries.len())
                .filter(|&k| tr.entries[k].slot == v)
                .collect();
            (!mine.is_empty()).then(|| mine[v % mine.len()])
        })
        .collect()
}

/// The enhancer check of a run ([`crate::stage3::Stage3Gate::Check`]): read from the enhancer's folder when
/// it was made there with these settings, otherwise made and written there.
pub fn check_enhancer(
    dir: &RunDir,
    spec: &Stage3Spec,
    pipe: &extranerf_diffusion::pipeline::Pipeline,
    device: &burn::tensor::Device,
    rep: &mut dyn Reporter,
) -> Result<EnhancerCheck> {
    let path = dir.enhancer().join(CHECK_FILE);
    let tr = Triplets::load(&dir.stage3_data())?;
    let (w, h) = (tr.width, tr.height);
    let lp = match lpips_alex(spec.lpips.as_deref()) {
        Ok(l) if (w.min(h) as u32) >= l.net().min_size() => Some(l),
        Ok(_) => {
            rep.note(&format!(
                "enhancer check: {w}x{h} views are below LPIPS's smallest input; scored with PSNR"
            ));
            None
        }
        Err(e) => {
            rep.note(&format!(
                "enhancer check: no LPIPS ({e:#}; default folder {}); scored with PSNR",
                default_lpips_dir().display()
            ));
            None
        }
    };
    // A check made with these settings and the same score is reused; any other (or a file
    // that does not read) is made again: it is only a cache.
    if let Some(c) = std::fs::read_to_string(&path)
        .ok()
        .and_then(|text| serde_json::from_str::<EnhancerCheck>(&text).ok())
    {
        let key = |c: &EnhancerCheck| {
            (
                c.t,
                c.ddim_steps,
                c.seed,
                c.anchor_radius,
                c.smooth_radius,
                c.lpips_render.is_some(),
            )
        };
        let want = (
            spec.t,
            spec.ddim_steps,
            spec.seed,
            spec.anchor_radius,
            spec.smooth_radius,
            lp.is_some(),
        );
        if key(&c) == want {
            return Ok(c);
        }
    }
    let t0 = Instant::now();
    let picks = check_triplets(&tr);
    if picks.is_empty() {
        return Err(ExtrapolateError::malformed(
            &dir.stage3_data(),
            "no triplets to check the enhancer on",
        ));
    }
    let (mut pr, mut pe, mut lr, mut le) = (0.0, 0.0, 0.0, 0.0);
    for (n, &k) in picks.iter().enumerate() {
        let (render, mask) = &tr.renders[k];
        let photo = &tr.photos[tr.entries[k].slot];
        // What stage 3 would train on.
        let enhanced = spec
            .target(
                Some((pipe, device)),
                render,
                mask,
                w,
                h,
                spec.seed ^ 0xc4ec_0000 ^ k as u64,
            )
            .map_err(|e| e.in_view(format!("enhancing triplet {}", tr.entries[k].key)))?;
        pr += psnr(render, photo)?;
        pe += psnr(&enhanced, photo)?;
        if let Some(l) = &lp {
            lr += l.distance(render, photo, w as u32, h as u32)?;
            le += l.distance(&enhanced, photo, w as u32, h as u32)?;
        }
        progress_views(rep, n + 1, picks.len(), &t0);
    }
    let n = picks.len() as f64;
    let c = EnhancerCheck {
        t: spec.t,
        ddim_steps: spec.ddim_steps,
        seed: spec.seed,
        anchor_radius: spec.anchor_radius,
        smooth_radius: spec.smooth_radius,
        triplets: picks.iter().map(|&k| tr.entries[k].key.clone()).collect(),
        psnr_render: pr / n,
        psnr_enhanced: pe / n,
        lpips_render: lp.as_ref().map(|_| lr / n),
        lpips_enhanced: lp.as_ref().map(|_| le / n),
        seconds: t0.elapsed().as_secs_f64(),
    };
    write_json(&path, &c)?;
    Ok(c)
}
