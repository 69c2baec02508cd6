//! The visibility stage (`RUN/visibility`): the virtual cameras beyond the rig, and the
//! visibility maps and inpainting masks of the virtual and the held-out views against the
//! training cameras.

use std::time::Instant;

use extranerf_gpu::Context;
use extranerf_nerf::cameras::write_transforms;
use extranerf_nerf::data::Camera;
use extranerf_nerf::demo::{demo_seen, DEMO_MARKER};
use extranerf_nerf::image_ops::grey_to_rgb;
use extranerf_nerf::render::visibility::mask_all_but;
use extranerf_nerf::run::write_png;
use extranerf_nerf::train::{Progress, Reporter, Unit};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::base::BaseField;
use crate::error::{create_dir, Result};
use crate::manifest::{OnResume, Recorded, StageSpec};
use crate::stage::{make_virtual, render, RunDir, Stage, VirtualSpec};
use crate::visibility::{save_maps, FieldVisibility, MaskScore, VisSettings, MAPS_FILE};

/// The virtual cameras and the visibility maps; the stage is its own spec.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VisibilityStage {
    #[serde(rename = "virtual")]
    pub virt: VirtualSpec,
    #[serde(rename = "settings")]
    pub vis: VisSettings,
}

impl StageSpec for VisibilityStage {
    const ON_RESUME: &'static [(&'static str, OnResume)] = &[
        ("virtual", OnResume::Rerun),
        ("settings", OnResume::Rerun),
        // Pixels per submission: the maps are the same in any chunks.
        ("settings.chunk", OnResume::MayChange),
    ];
}

/// The scene index of a held-out view's map name (`test_NNN`).
fn test_index(name: &str) -> Option<usize> {
    name.strip_prefix("test_")?.parse().ok()
}

impl Stage for VisibilityStage {
    fn name(&self) -> String {
        "visibility".into()
    }

    fn config(&self) -> Recorded {
        Recorded::of(self)
    }

    /// It measures the BaseNeRF.
    fn inputs(&self) -> Vec<String> {
        vec!["base".into()]
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value> {
        let out = dir.visibility();
        create_dir(&out)?;
        let base = BaseField::load(ctx, &dir.base)?;
        let train = base.train_cameras();
        let virt = make_virtual(&self.virt, &train)?;
        write_transforms(&out.join("virtual.json"), &virt)?;
        let cfg = self
            .vis
            .config(self.vis.rank, base.ck.config.train.samples)?;
        let t = Instant::now();
        let fv = FieldVisibility::new(ctx, &base.nerf, &train, &self.vis)?;
        let volume_s = t.elapsed().as_secs_f64();
        let all = mask_all_but(train.len(), None);
        // Virtual views, and the held-out views (the training views where the split holds
        // none out; mapped at the virtual views' scale, their BaseNeRF renders at full size for
        // `eval`).
        let mut views: Vec<(String, Camera, Camera)> = virt
            .iter()
            .enumerate()
            .map(|(i, c)| (format!("virtual_{i:03}"), c.clone(), c.clone()))
            .collect();
        let shown = crate::shown::Shown::of(&base.loaded.split);
        for &i in &shown.views {
            let full = base.loaded.scene.cameras[i].clone();
            let c = full.downscaled(self.virt.downscale);
            views.push((shown.name(i), c, full));
        }
        let mut maps = Vec::new();
        let mut rows = Vec::new();
        let total = views.len() as u32;
        // The demo scene's generator knows what each rig camera sees: score the held-out
        // views' masks against it.
        let demo = base.ck.config.scene.dir.join(DEMO_MARKER).exists();
        let mut exact: Vec<MaskScore> = Vec::new();
        for (k, (name, cam, full)) in views.iter().enumerate() {
            let t = Instant::now();
            let m = fv.map(ctx, &base.nerf, cam, all, &cfg, self.vis.chunk)?;
            let mask = self.vis.mask(&m);
            write_png(
                &out.join(format!("{name}_vis.png")),
                m.width,
                m.height,
                &grey_to_rgb(&m.visibility),
            )?;
            write_png(
                &out.join(format!("{name}_mask.png")),
                m.width,
                m.height,
                &grey_to_rgb(&mask),
            )?;
            let (rgb, _, _) = render(ctx, &base.nerf, full, cfg.samples)?;
            write_png(
                &out.join(format!("{name}_base.png")),
                full.width,
                full.height,
                &rgb,
            )?;
            let masked = mask.iter().map(|&v| v as f64).sum::<f64>() / mask.len().max(1) as f64;
            let mut row = json!({
                "view": name,
                "width": m.width,
                "height": m.height,
                "mean_visibility": m.mean(),
                "mean_opacity": m.mean_opacity(),
                "masked_fraction": masked,
                "seconds": t.elapsed().as_secs_f64(),
            });
            if let (true, Some(i)) = (demo, test_index(name)) {
                let unseen: Vec<bool> = demo_seen(i, m.width, m.height, cfg.rank as usize)
                    .into_iter()
                    .map(|s| !s)
                    .collect();
                let s = MaskScore::new(&mask, &unseen);
                row["exact"] = json!(s);
                exact.push(s);
            }
            rows.push(row);
            rep.progress(&Progress {
                unit: Unit::Views,
                step: k as u32 + 1,
                total,
                loss: masked,
                psnr: 0.0,
                samples_per_s: 0.0,
                secs: 0.0,
                eta: 0.0,
            });
            rep.note(&format!(
                "{name}: {}x{}, {:.1}% to inpaint (mean opacity {:.3})",
                m.width,
                m.height,
                100.0 * masked,
                m.mean_opacity()
            ));
            maps.push((name.clone(), m));
        }
        save_maps(&out.join(MAPS_FILE), &maps)?;
        let exact_mean = (!exact.is_empty()).then(|| MaskScore::mean(&exact));
        if let Some(e) = &exact_mean {
            rep.note(&format!(
                "masks against the demo's exact visibility: IoU {:.3}, accuracy {:.3} ({:.1}% masked, {:.1}% truly unseen)",
                e.iou,
                e.accuracy,
                100.0 * e.masked,
                100.0 * e.unseen
            ));
        }
        let doc = json!({
            "exact_mean": exact_mean,
            "training_views": base.loaded.split.train,
            "settings": self.vis,
            "virtual": self.virt,
            "volume_seconds": volume_s,
            "views": rows,
        });
        crate::error::write_json(&out.join("visibility.json"), &doc)?;
        Ok(json!({"volume_seconds": volume_s, "views": rows.len(), "exact_mean": exact_mean}))
    }
}
