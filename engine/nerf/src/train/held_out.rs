//! Held-out evaluations during training (`train --eval-every`, `curve.jsonl`), and the LPIPS
//! weights they (and the pipeline's checks) score with.

use std::io::Write;
use std::path::{Path, PathBuf};

use extranerf_gpu::Context;

use super::report::Reporter;
use super::view_set::ViewSet;
use super::{Result, TrainError};
use crate::data::{load_image_over, Camera};
use crate::metrics::{psnr, ssim, Lpips, LpipsNet};
use crate::run::LoadedScene;
use crate::trainer::{StepStats, Trainer};

/// Held-out evaluations during training (`train --eval-every`): each renders the chosen views
/// at the training samples per ray, as `render` would ([`crate::renderer::Nerf::default_march`]: the fused march,
/// or the proposal sampler's samples when the field has one), and appends one line to
/// `curve.jsonl`.
pub struct HeldOut {
    views: Vec<(usize, Camera, Vec<f32>)>,
    lpips: Option<Lpips>,
    log: std::fs::File,
    path: PathBuf,
}

impl std::fmt::Debug for HeldOut {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HeldOut")
            .field("views", &self.views.iter().map(|v| v.0).collect::<Vec<_>>())
            .field("lpips", &self.lpips.is_some())
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

impl HeldOut {
    /// The views `which` of `loaded` (ground truth composited over the renders' `background`),
    /// with LPIPS when its weights are found, appending to `out/curve.jsonl` (replaced when
    /// `start` is 0).
    pub fn new(
        loaded: &LoadedScene,
        which: &ViewSet,
        out: &Path,
        start: u32,
        background: [f32; 3],
        rep: &mut dyn Reporter,
    ) -> Result<HeldOut> {
        let indices = which.indices(&loaded.split, loaded.scene.cameras.len(), "--eval-views")?;
        if indices.is_empty() {
            return Err(TrainError::Usage(
                "--eval-every: the split holds no held-out view to evaluate".into(),
            ));
        }
        let mut views = Vec::new();
        for i in indices {
            let cam = loaded.scene.cameras[i].clone();
            let truth = load_image_over(&cam.image, background)?;
            views.push((i, cam, truth.rgb));
        }
        let lpips = match lpips_alex(None) {
            Ok(l) => Some(l),
            Err(e) => {
                rep.note(&format!("--eval-every: no LPIPS in the curve ({e:#})"));
                None
            }
        };
        std::fs::create_dir_all(out).map_err(|e| TrainError::io("creating", out, e))?;
        let path = out.join("curve.jsonl");
        let log = super::open_step_log(&path, start)?;
        Ok(HeldOut {
            views,
            lpips,
            log,
            path,
        })
    }

    /// Renders the views from the trainer's current field and appends their means.
    pub fn evaluate(
        &mut self,
        ctx: &Context,
        trainer: &Trainer,
        stats: &StepStats,
        train_secs: f64,
        rep: &mut dyn Reporter,
    ) -> Result<()> {
        let samples = trainer.config().samples;
        let (mut p, mut s, mut l, mut o) = (0.0, 0.0, 0.0, 0.0);
        for (_, cam, truth) in &self.views {
            let nerf = trainer.nerf();
            let (rgb, _, opacity) =
                nerf.render_with(ctx, cam, 8192, samples, nerf.default_march())?;
            p += psnr(&rgb, truth)?;
            s += ssim(&rgb, truth, cam.width, cam.height)?;
            if let Some(lp) = &self.lpips {
                l += lp.distance(&rgb, truth, cam.width, cam.height)?;
            }
            o += opacity.iter().map(|&v| v as f64).sum::<f64>() / opacity.len().max(1) as f64;
        }
        let n = self.views.len() as f64;
        let line = serde_json::json!({
            "step": trainer.step(),
            "train_seconds": train_secs,
            "test_psnr": p / n,
            "test_ssim": s / n,
            "test_lpips_alex": self.lpips.as_ref().map(|_| l / n),
            "test_opacity": o / n,
            "batch_psnr": stats.psnr(),
            "views": self.views.iter().map(|v| v.0).collect::<Vec<_>>(),
        });
        rep.note(&format!(
            "held-out at step {} ({train_secs:.1} s of training): PSNR {:.2} SSIM {:.3} LPIPS-alex {} opacity {:.3}",
            trainer.step(),
            p / n,
            s / n,
            self.lpips
                .as_ref()
                .map_or("-".to_string(), |_| format!("{:.3}", l / n)),
            o / n
        ));
        writeln!(self.log, "{line}").map_err(|e| TrainError::io("writing", &self.path, e))?;
        Ok(())
    }
}

/// Where LPIPS weights are looked for by default: `$EXTRANERF_MODELS/lpips`, else
/// `../shared/models/lpips` (the project's shared folder beside the checkout).
pub fn default_lpips_dir() -> PathBuf {
    std::env::var_os("EXTRANERF_MODELS")
        .map(|m| PathBuf::from(m).join("lpips"))
        .unwrap_or_else(|| PathBuf::from("../shared/models/lpips"))
}

/// The AlexNet LPIPS from `dir` (default [`default_lpips_dir`]), the error naming the folder.
pub fn lpips_alex(dir: Option<&Path>) -> Result<Lpips> {
    let dir = dir.map(PathBuf::from).unwrap_or_else(default_lpips_dir);
    Lpips::load(&dir.join("lpips_alex_v0.1.safetensors"), LpipsNet::Alex)
        .map_err(|error| TrainError::Lpips { dir, error })
}
