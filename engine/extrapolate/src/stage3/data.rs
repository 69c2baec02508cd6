//! The enhancer's training data (`RUN/stage3-data`): triplets of (corrupted render, mask,
//! photo) of the training views.

use std::path::Path;
use std::time::Instant;

use extranerf_gpu::Context;
use extranerf_nerf::data::Camera;
use extranerf_nerf::image_ops::{downscale_image, resize_mask};
use extranerf_nerf::render::visibility::mask_all_but;
use extranerf_nerf::renderer::Nerf;
use extranerf_nerf::run::{training_views_in, write_png};
use extranerf_nerf::train::Reporter;
use extranerf_nerf::trainer::Trainer;
use extranerf_nerf::views::{TrainData, View, ViewSampling};
use extranerf_prims::Prims;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::base::BaseField;
use crate::error::{create_dir, ExtrapolateError, Result};
use crate::inpaint::{build_inpainter, DiffusionSpec, Fill, InpainterKind, Source, Target};
use crate::manifest::{OnResume, Recorded, StageSpec};
use crate::rounds::{fill_view, train_steps, Stage2Spec};
use crate::stage::{progress_views, render, RunDir, Stage, VirtualSpec, DATA_STAGE};
use crate::stage3::spec::Stage3Spec;
use crate::stage3::triplets::{TripletEntry, Triplets};
use crate::visibility::{FieldVisibility, VisSettings};

/// The supervision of one training view in the data collector: the captured view with its
/// photo's weight 0 inside the pseudo mask (`mask_full`, the view's resolution), and a
/// virtual view at the same camera (`cam`, the mask's scale `mask`) that carries the
/// inpainter's fill with weight `weight` inside the mask and nothing outside it.
pub fn collector_views(
    captured: &View,
    mask_full: &[f32],
    cam: &Camera,
    fill: &Fill,
    mask: &[f32],
    weight: f32,
) -> (View, View) {
    let mut photo = captured.clone();
    let old = photo.weight.take();
    photo.weight = Some(
        mask_full
            .iter()
            .enumerate()
            .map(|(i, &m)| {
                let w = old.as_ref().map_or(1.0, |o| o[i]);
                if m >= 0.5 {
                    0.0
                } else {
                    w
                }
            })
            .collect(),
    );
    let inside = |m: f32| if m >= 0.5 { 1.0 } else { 0.0 };
    let virt = fill_view(cam, fill, mask, |m| weight * inside(m), inside);
    (photo, virt)
}

/// The settings of the enhancer's training data, as its manifest record holds them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataSpec {
    /// The inpainter whose supervision corrupts the masked regions.
    pub inpainter: InpainterKind,
    /// [`Stage3Spec`]'s data rounds.
    pub data_rounds: u32,
    pub data_steps_per_round: u32,
    pub base_checkpoints: Vec<u32>,
    /// [`Stage2Spec`]'s learning rate, noise levels and seed.
    pub lr: f32,
    pub t_start: f32,
    pub t_end: f32,
    pub seed: u64,
    /// [`Stage2Spec`]'s share of virtual rays in the data rounds' batches (records before
    /// issue 56 left it out: they read as the default, 0.3).
    #[serde(default = "default_virtual_fraction")]
    pub virtual_fraction: f32,
    /// The virtual views' downscale (the triplets' scale).
    pub downscale: u32,
    /// The pseudo-disocclusion masks' visibility.
    pub visibility: VisSettings,
    /// The diffusion inpainter's model as the inpainter uses it; None for the others.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub diffusion: Option<DiffusionSpec>,
}

fn default_virtual_fraction() -> f32 {
    Stage2Spec::default().virtual_fraction
}

impl StageSpec for DataSpec {
    const ON_RESUME: &'static [(&'static str, OnResume)] = &[
        ("inpainter", OnResume::Rerun),
        ("data_rounds", OnResume::Rerun),
        ("data_steps_per_round", OnResume::Rerun),
        ("base_checkpoints", OnResume::Rerun),
        ("lr", OnResume::Rerun),
        ("t_start", OnResume::Rerun),
        ("t_end", OnResume::Rerun),
        ("seed", OnResume::Rerun),
        ("virtual_fraction", OnResume::Rerun),
        ("downscale", OnResume::Rerun),
        ("visibility", OnResume::Rerun),
        // Pixels per submission: the same masks in any chunks.
        ("visibility.chunk", OnResume::MayChange),
        ("diffusion", OnResume::Rerun),
        // Where the model runs: the same model on another device.
        ("diffusion.backend", OnResume::MayChange),
    ];
}

/// The enhancer's training data.
#[derive(Clone, Debug)]
pub struct EnhancerDataStage {
    pub spec: Stage3Spec,
    /// The inpainter whose supervision corrupts the masked regions.
    pub inpainter: InpainterKind,
    pub diffusion: Option<DiffusionSpec>,
    /// The stage-2 loop (its noise levels and learning rate serve the data rounds).
    pub stage2: Stage2Spec,
    pub virt: VirtualSpec,
    pub vis: VisSettings,
}

impl Stage for EnhancerDataStage {
    fn name(&self) -> String {
        DATA_STAGE.into()
    }

    fn config(&self) -> Recorded {
        Recorded::of(&DataSpec {
            inpainter: self.inpainter,
            data_rounds: self.spec.data_rounds,
            data_steps_per_round: self.spec.data_steps_per_round,
            base_checkpoints: self.spec.base_checkpoints.clone(),
            lr: self.stage2.lr,
            t_start: self.stage2.t_start,
            t_end: self.stage2.t_end,
            seed: self.stage2.seed,
            virtual_fraction: self.stage2.virtual_fraction,
            downscale: self.virt.downscale,
            visibility: self.vis.clone(),
            diffusion: self
                .diffusion
                .as_ref()
                .filter(|_| self.inpainter.uses_diffusion())
                .map(|d| d.for_kind(self.inpainter)),
        })
    }

    fn inputs(&self) -> Vec<String> {
        vec!["base".into()]
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value> {
        self.spec.validate()?;
        let out = dir.stage3_data();
        create_dir(&out)?;
        let base = BaseField::load(ctx, &dir.base)?;
        let cfg = base.ck.config.clone();
        let (captured, _) =
            training_views_in(ctx, &cfg.scene, &base.loaded, &cfg.model, &dir.base)?;
        let cams: Vec<Camera> = base
            .train_cameras()
            .iter()
            .map(|c| c.downscaled(self.virt.downscale))
            .collect();
        let (w, h) = (cams[0].width as usize, cams[0].height as usize);
        if cams
            .iter()
            .any(|c| (c.width as usize, c.height as usize) != (w, h))
        {
            return Err(ExtrapolateError::usage(
                "stage 3 needs training views of one size",
            ));
        }
        let (masks, photos) = self.pseudo_masks(ctx, &base, &cams, &captured, &out, rep)?;
        let masked: f64 = masks.iter().flatten().map(|&v| v as f64).sum::<f64>()
            / (masks.len() * w * h).max(1) as f64;
        rep.note(&format!(
            "{DATA_STAGE}: pseudo-disocclusion masks of {} training views, {:.1}% of their pixels",
            cams.len(),
            100.0 * masked
        ));
        let mut tr = Triplets {
            width: w,
            height: h,
            photos,
            masks,
            entries: Vec::new(),
            renders: Vec::new(),
        };
        let at = Renders {
            cams: &cams,
            samples: cfg.train.samples,
            out: &out,
        };
        // An under-fitted field: a fresh one trained with the BaseNeRF's settings.
        let mut fresh_s = 0.0;
        if !self.spec.base_checkpoints.is_empty() {
            let tf = Instant::now();
            let (mut trainer, data) =
                extranerf_nerf::train::fresh_trainer(ctx, &cfg, &base.loaded, &dir.base)?;
            let prims = Prims::new(ctx)?;
            let mut checkpoints = self.spec.base_checkpoints.clone();
            checkpoints.sort_unstable();
            checkpoints.dedup();
            for &c in &checkpoints {
                let left = c.saturating_sub(trainer.step());
                if left > 0 {
                    train_steps(
                        ctx,
                        &mut trainer,
                        &prims,
                        &data,
                        left,
                        &format!("{DATA_STAGE}: a fresh field"),
                        &out,
                        rep,
                    )?;
                }
                at.add(ctx, &format!("fresh@{c}"), trainer.nerf(), false, &mut tr)?;
            }
            fresh_s = tf.elapsed().as_secs_f64();
        }
        at.add(ctx, "base", &base.nerf, false, &mut tr)?;
        // The inpainting-supervised field, rendered after each of its rounds.
        let ti = Instant::now();
        let inpaint_s = self.inpainted_rounds(ctx, &base, &captured, &at, &mut tr, rep)?;
        tr.save(&out)?;
        Ok(json!({
            "triplets": tr.entries.len(),
            "views": cams.len(),
            "width": w,
            "height": h,
            "masked_fraction": masked,
            "fresh_field_seconds": fresh_s,
            "inpainted_field_seconds": ti.elapsed().as_secs_f64(),
            "inpaint_seconds": inpaint_s,
        }))
    }
}

/// A `[h, w]` mask.
type Mask = Vec<f32>;
/// An `[h, w, 3]` image.
type Photo = Vec<f32>;

/// Where the data stage's triplets are rendered: the training cameras at the virtual views'
/// scale, the samples per ray, the stage's folder.
struct Renders<'a> {
    cams: &'a [Camera],
    samples: u32,
    out: &'a Path,
}

impl Renders<'_> {
    /// Renders every training view from `nerf` as triplets of `source` (their masks: the pseudo
    /// masks when `fills`, where the inpainter supervised the field; none otherwise).
    fn add(
        &self,
        ctx: &Context,
        source: &str,
        nerf: &Nerf,
        fills: bool,
        tr: &mut Triplets,
    ) -> Result<()> {
        for (i, cam) in self.cams.iter().enumerate() {
            let (rgb, _, _) = render(ctx, nerf, cam, self.samples)?;
            let key = format!("t{:03}", tr.entries.len());
            write_png(
                &self
                    .out
                    .join(format!("{key}_view{i:03}_{}.png", source.replace('@', "_"))),
                cam.width,
                cam.height,
                &rgb,
            )?;
            let mask = if fills {
                tr.masks[i].clone()
            } else {
                vec![0.0; tr.width * tr.height]
            };
            tr.renders.push((rgb, mask));
            tr.entries.push(TripletEntry {
                key,
                slot: i,
                source: source.to_string(),
            });
        }
        Ok(())
    }
}

impl EnhancerDataStage {
    /// Each training view's pseudo-disocclusion mask (the view against the other training
    /// cameras, written as `pseudo_mask_NNN.png`) and its photo, at the cameras `cams`.
    fn pseudo_masks(
        &self,
        ctx: &Context,
        base: &BaseField,
        cams: &[Camera],
        captured: &[View],
        out: &Path,
        rep: &mut dyn Reporter,
    ) -> Result<(Vec<Mask>, Vec<Photo>)> {
        let t = Instant::now();
        let train = base.train_cameras();
        let vcfg = self
            .vis
            .config(self.vis.rank, base.ck.config.train.samples)?;
        let fv = FieldVisibility::new(ctx, &base.nerf, &train, &self.vis)?;
        let mut masks = Vec::new();
        let mut photos = Vec::new();
        for (i, cam) in cams.iter().enumerate() {
            let m = fv.map(
                ctx,
                &base.nerf,
                cam,
                mask_all_but(train.len(), Some(i)),
                &vcfg,
                self.vis.chunk,
            )?;
            let mask = self.vis.mask(&m);
            write_png(
                &out.join(format!("pseudo_mask_{i:03}.png")),
                cam.width,
                cam.height,
                &mask.iter().flat_map(|&v| [v, v, v]).collect::<Vec<_>>(),
            )?;
            masks.push(mask);
            photos.push(downscale_image(&captured[i].image, cam.width, cam.height).rgb);
            progress_views(rep, i + 1, cams.len(), &t);
        }
        Ok((masks, photos))
    }

    /// The inpainting-supervised field: optimised from the BaseNeRF for the data rounds, each
    /// round inpainting every training view's pseudo mask (from the other training photos) and
    /// training on the fills, then rendering the views as triplets. Returns the inpainting
    /// seconds.
    fn inpainted_rounds(
        &self,
        ctx: &Context,
        base: &BaseField,
        captured: &[View],
        at: &Renders<'_>,
        tr: &mut Triplets,
        rep: &mut dyn Reporter,
    ) -> Result<f64> {
        let cfg = &base.ck.config;
        let (w, h) = (tr.width, tr.height);
        let mut tcfg = cfg.train.clone();
        let total = self.spec.data_rounds * self.spec.data_steps_per_round;
        tcfg.steps = total;
        tcfg.decay_steps = total;
        tcfg.lr_start = self.stage2.lr;
        tcfg.lr_end = self.stage2.lr;
        let moments = base
            .ck
            .moments
            .as_ref()
            .map(|(m, v)| (m.as_slice(), v.as_slice()));
        let nerf = Nerf::new(
            ctx,
            cfg.model.clone(),
            &base.ck.params,
            cfg.train.background,
        )?;
        let mut trainer = Trainer::new(ctx, nerf, tcfg, 0, moments)?;
        let prims = Prims::new(ctx)?;
        let mut inpainter = build_inpainter(ctx, self.inpainter, self.diffusion.as_ref(), rep)?;
        let loop2 = Stage2Spec {
            rounds: self.spec.data_rounds,
            ..self.stage2.clone()
        };
        let masks_full: Vec<Vec<f32>> = captured
            .iter()
            .zip(&tr.masks)
            .map(|(v, m)| resize_mask(m, w, h, v.camera.width as usize, v.camera.height as usize))
            .collect();
        let mut inpaint_s = 0.0;
        for round in 0..self.spec.data_rounds {
            let (t, weight) = (loop2.t(round), loop2.weight(round));
            let mut views = Vec::new();
            for (i, cam) in at.cams.iter().enumerate() {
                let (rgb, depth, _) = render(ctx, trainer.nerf(), cam, at.samples)?;
                // Sources: the other training photos (never the view's own).
                let sources: Vec<Source<'_>> = tr
                    .photos
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .map(|(_, p)| Source {
                        width: w,
                        height: h,
                        rgb: p,
                        depth: None,
                    })
                    .collect();
                let ts = Instant::now();
                let fill = if tr.masks[i].iter().all(|&m| m < 0.5) {
                    Fill {
                        rgb: rgb.clone(),
                        depth: depth.clone(),
                    }
                } else {
                    let target = Target::new(w, h, &rgb, &depth, &tr.masks[i], t);
                    let seed = self.stage2.seed ^ 0x5_7a9e_3000 ^ ((round as u64) << 32) ^ i as u64;
                    inpainter.inpaint(&target, &sources, seed).map_err(|e| {
                        ExtrapolateError::from(e)
                            .in_view(format!("training view {i}, data round {round}"))
                    })?
                };
                inpaint_s += ts.elapsed().as_secs_f64();
                let (photo, virt) = collector_views(
                    &captured[i],
                    &masks_full[i],
                    cam,
                    &fill,
                    &tr.masks[i],
                    weight,
                );
                views.push(photo);
                views.push(virt);
            }
            let data = TrainData::with_sampling(
                ctx,
                &views,
                ViewSampling::VirtualFraction(self.stage2.virtual_fraction),
            )?;
            train_steps(
                ctx,
                &mut trainer,
                &prims,
                &data,
                self.spec.data_steps_per_round,
                &format!("{DATA_STAGE} round {round}"),
                at.out,
                rep,
            )?;
            at.add(ctx, &format!("inpainted@{round}"), trainer.nerf(), true, tr)?;
            rep.note(&format!(
                "{DATA_STAGE} round {}/{}: t {t:.2}, {} triplets so far",
                round + 1,
                self.spec.data_rounds,
                tr.entries.len()
            ));
        }
        Ok(inpaint_s)
    }
}
