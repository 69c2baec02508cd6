//! Stage 2 of one inpainter (`RUN/stage2-NAME`): rounds of rendering the virtual views,
//! inpainting what no two training cameras saw, and training on them mixed with the captured
//! views.

use std::path::Path;
use std::time::Instant;

use extranerf_gpu::Context;
use extranerf_nerf::data::Camera;
use extranerf_nerf::image_ops::{downscale_image, grey_to_rgb};
use extranerf_nerf::run::{training_views_in, write_png};
use extranerf_nerf::train::Reporter;
use extranerf_nerf::views::View;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::base::BaseField;
use crate::error::{create_dir, ExtrapolateError, Result};
use crate::inpaint::{build_inpainter, DiffusionSpec, Fill, InpainterKind, Source, Target};
use crate::manifest::{OnResume, Recorded, StageSpec};
use crate::rounds::{fill_view, write_test_renders, Rounds, Stage2Spec};
use crate::stage::{make_virtual, progress_views, render, RunDir, Stage, VirtualSpec};
use crate::visibility::{virtual_masks, VisSettings};

/// One stage-2 variant.
#[derive(Clone, Debug)]
pub struct InpaintStage {
    /// Its settings (what its manifest record holds).
    pub spec: InpaintSpec,
    /// The virtual views and their masks (the visibility stage's settings, recorded there).
    pub virt: VirtualSpec,
    pub vis: VisSettings,
}

/// A stage-2 variant's settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InpaintSpec {
    pub inpainter: InpainterKind,
    /// The loop.
    #[serde(rename = "loop")]
    pub stage2: Stage2Spec,
    /// The diffusion inpainter's model as the inpainter uses it ([`DiffusionSpec::for_kind`]);
    /// None for the other inpainters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub diffusion: Option<DiffusionSpec>,
}

impl InpaintSpec {
    /// The settings of `inpainter`'s variant: the model only where the inpainter uses one.
    pub fn new(
        inpainter: InpainterKind,
        stage2: Stage2Spec,
        diffusion: Option<&DiffusionSpec>,
    ) -> InpaintSpec {
        InpaintSpec {
            inpainter,
            stage2,
            diffusion: diffusion
                .filter(|_| inpainter.uses_diffusion())
                .map(|d| d.for_kind(inpainter)),
        }
    }
}

impl StageSpec for InpaintSpec {
    const ON_RESUME: &'static [(&'static str, OnResume)] = &[
        ("inpainter", OnResume::Rerun),
        ("loop", OnResume::Rerun),
        ("diffusion", OnResume::Rerun),
        // Where the model runs: the same model on another device.
        ("diffusion.backend", OnResume::MayChange),
    ];
}

/// Fills of earlier views, reprojected into `cam`: per pixel, the nearest reprojected colour
/// and its ray-space depth in `cam`.
pub fn reproject(
    earlier: &[(Camera, Fill, Vec<f32>)],
    cam: &Camera,
    ndc: bool,
) -> Vec<Option<([f32; 3], f32)>> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut best: Vec<Option<([f32; 3], f32, f64)>> = vec![None; w * h];
    for (src, fill, filled) in earlier {
        let sw = src.width as usize;
        for (i, &f) in filled.iter().enumerate() {
            if f < 0.5 {
                continue;
            }
            let (x, y) = ((i % sw) as f64 + 0.5, (i / sw) as f64 + 0.5);
            let Some(p) = src.ray_point(x, y, fill.depth[i] as f64, ndc) else {
                continue;
            };
            let (px, py, z) = cam.project(p);
            if !(z > 0.0 && px >= 0.0 && py >= 0.0 && px < w as f64 && py < h as f64) {
                continue;
            }
            let j = py as usize * w + px as usize;
            if best[j].is_some_and(|b| b.2 <= z) {
                continue;
            }
            // Ray-space depth in this camera: NDC t = 1 + 1 / z_world, else view depth.
            let t = if ndc {
                let pz = p.z;
                if pz >= -1.0 {
                    continue;
                }
                1.0 + 1.0 / pz
            } else {
                z
            };
            best[j] = Some((
                [fill.rgb[3 * i], fill.rgb[3 * i + 1], fill.rgb[3 * i + 2]],
                t as f32,
                z,
            ));
        }
    }
    best.into_iter()
        .map(|b| b.map(|(c, t, _)| (c, t)))
        .collect()
}

impl Stage for InpaintStage {
    fn name(&self) -> String {
        format!("stage2-{}", self.spec.inpainter.name())
    }

    fn config(&self) -> Recorded {
        Recorded::of(&self.spec)
    }

    /// It trains on from the BaseNeRF, inpainting where the visibility stage's masks say.
    fn inputs(&self) -> Vec<String> {
        vec!["base".into(), "visibility".into()]
    }

    fn run(&self, ctx: &Context, dir: &RunDir, rep: &mut dyn Reporter) -> Result<Value> {
        self.spec.stage2.validate()?;
        let out = dir.stage2(self.spec.inpainter);
        create_dir(&out)?;
        let base = BaseField::load(ctx, &dir.base)?;
        let cfg = base.ck.config.clone();
        let samples = cfg.train.samples;
        let virt = make_virtual(&self.virt, &base.train_cameras())?;
        let masks = virtual_masks(&dir.visibility(), &virt, &self.vis)?;
        let (captured, _) =
            training_views_in(ctx, &cfg.scene, &base.loaded, &cfg.model, &dir.base)?;
        // Exemplar sources: the training photos at the virtual views' scale, with the
        // BaseNeRF's depth.
        let mut sources = Vec::new();
        for v in &captured {
            let cam = v.camera.downscaled(self.virt.downscale);
            let img = downscale_image(&v.image, cam.width, cam.height);
            let (_, depth, _) = render(ctx, &base.nerf, &cam, samples)?;
            sources.push((cam, img.rgb, depth));
        }
        let total_steps = self.spec.stage2.rounds * self.spec.stage2.steps_per_round;
        let mut tcfg = cfg.train.clone();
        tcfg.steps = total_steps;
        tcfg.decay_steps = total_steps;
        tcfg.lr_start = self.spec.stage2.lr;
        tcfg.lr_end = self.spec.stage2.lr;
        let mut r = Rounds::open(
            ctx,
            &out,
            &self.name(),
            &cfg,
            tcfg,
            &base.ck,
            0,
            self.spec.stage2.steps_per_round,
            rep,
        )?;
        let mut inpainter =
            build_inpainter(ctx, self.spec.inpainter, self.spec.diffusion.as_ref(), rep)?;
        let fixed = Fixed {
            virt: &virt,
            masks: &masks,
            sources: &sources,
            ndc: base.ndc(),
            samples,
        };
        let mut rounds = Vec::new();
        for round in r.start..self.spec.stage2.rounds {
            let t0 = Instant::now();
            let (filled, f) =
                self.fill_round(ctx, &r, inpainter.as_mut(), &fixed, (round, t0), &out, rep)?;
            // Train on the captured views and this round's virtual views.
            let mut views = captured.clone();
            views.extend(
                filled
                    .iter()
                    .map(|(cam, fill, mask)| self.virtual_view(cam, fill, mask, round)),
            );
            let (last, train_s) = r.train(
                ctx,
                &views,
                self.spec.stage2.virtual_fraction,
                self.spec.stage2.steps_per_round,
                &format!("{} round {round}", self.name()),
                (round, t0),
                rep,
            )?;
            let t = self.spec.stage2.t(round);
            rep.note(&format!(
                "{} round {}/{}: t {t:.2}, render {:.1} s, inpaint {:.1} s, train {train_s:.1} s; {} pixels reprojected",
                self.name(),
                round + 1,
                self.spec.stage2.rounds,
                f.render_s,
                f.inpaint_s,
                f.reprojected
            ));
            rounds.push(json!({
                "round": round,
                "t": t,
                "weight": self.spec.stage2.weight(round),
                "render_seconds": f.render_s,
                "inpaint_seconds": f.inpaint_s,
                "train_seconds": train_s,
                "reprojected_pixels": f.reprojected,
                "batch_psnr": last.map(|s| s.psnr()),
            }));
        }
        // The held-out views' renders, for `eval`.
        write_test_renders(ctx, r.trainer.nerf(), &base.loaded, samples, &out)?;
        Ok(json!({"rounds": rounds, "seconds": r.seconds}))
    }
}

/// A filled virtual view: its camera, the fill, and its inpainting mask.
type Filled = (Camera, Fill, Vec<f32>);

/// What a round's fills measured: render and inpainting seconds, and the pixels reprojected
/// from earlier views of the round.
struct RoundFigures {
    render_s: f64,
    inpaint_s: f64,
    reprojected: usize,
}

/// What every round of a stage-2 variant reads.
struct Fixed<'a> {
    /// The virtual cameras and their inpainting masks.
    virt: &'a [Camera],
    masks: &'a [Vec<f32>],
    /// The exemplar sources: camera, `[h, w, 3]` photo and the BaseNeRF's depth.
    sources: &'a [(Camera, Vec<f32>, Vec<f32>)],
    ndc: bool,
    samples: u32,
}

impl InpaintStage {
    /// Round `round`'s fills: each virtual view rendered from the field, its masked pixels
    /// (those that an earlier view of the round filled reprojected first) inpainted and written
    /// into `out/round_NN` (progress counted from the round's start `t0`). Returns each view's
    /// camera, fill and mask, and what the round measured.
    #[allow(clippy::too_many_arguments)] // each is a distinct input of the round
    fn fill_round(
        &self,
        ctx: &Context,
        r: &Rounds,
        inpainter: &mut dyn crate::inpaint::Inpainter,
        f: &Fixed<'_>,
        (round, t0): (u32, Instant),
        out: &Path,
        rep: &mut dyn Reporter,
    ) -> Result<(Vec<Filled>, RoundFigures)> {
        let t = self.spec.stage2.t(round);
        let round_dir = out.join(format!("round_{round:02}"));
        create_dir(&round_dir)?;
        let mut filled: Vec<Filled> = Vec::new();
        let (mut inpaint_s, mut render_s, mut reprojected) = (0.0, 0.0, 0usize);
        for (k, cam) in f.virt.iter().enumerate() {
            let tr = Instant::now();
            let (mut rgb, mut depth, _) = render(ctx, r.trainer.nerf(), cam, f.samples)?;
            render_s += tr.elapsed().as_secs_f64();
            let mut mask = f.masks[k].clone();
            if self.spec.stage2.reproject && !filled.is_empty() {
                for (j, p) in reproject(&filled, cam, f.ndc).into_iter().enumerate() {
                    if let Some((c, d)) = p {
                        if mask[j] >= 0.5 {
                            rgb[3 * j..3 * j + 3].copy_from_slice(&c);
                            depth[j] = d;
                            mask[j] = 0.0;
                            reprojected += 1;
                        }
                    }
                }
            }
            let sources: Vec<Source<'_>> = f
                .sources
                .iter()
                .map(|(c, img, d)| Source {
                    width: c.width as usize,
                    height: c.height as usize,
                    rgb: img,
                    depth: Some(d),
                })
                .collect();
            let target = Target {
                width: cam.width as usize,
                height: cam.height as usize,
                rgb: &rgb,
                depth: &depth,
                mask: &mask,
                t,
            };
            let ti = Instant::now();
            let seed = self.spec.stage2.seed ^ ((round as u64) << 32) ^ k as u64;
            let fill = if mask.iter().all(|&m| m < 0.5) {
                Fill {
                    rgb: rgb.clone(),
                    depth: depth.clone(),
                }
            } else {
                inpainter.inpaint(&target, &sources, seed).map_err(|e| {
                    ExtrapolateError::from(e).in_view(format!("virtual view {k}, round {round}"))
                })?
            };
            inpaint_s += ti.elapsed().as_secs_f64();
            write_png(
                &round_dir.join(format!("virtual_{k:03}.png")),
                cam.width,
                cam.height,
                &fill.rgb,
            )?;
            write_png(
                &round_dir.join(format!("virtual_{k:03}_mask.png")),
                cam.width,
                cam.height,
                &grey_to_rgb(&f.masks[k]),
            )?;
            filled.push((cam.clone(), fill, f.masks[k].clone()));
            progress_views(rep, k + 1, f.virt.len(), &t0);
        }
        let figures = RoundFigures {
            render_s,
            inpaint_s,
            reprojected,
        };
        Ok((filled, figures))
    }

    /// A filled virtual view as training data: the filled pixels carry w(t), the seen rest
    /// `visible_weight` of it (their colour is the field's own render, which the captured views
    /// supervise); the fill's depth supervises where its colour does.
    fn virtual_view(&self, cam: &Camera, fill: &Fill, mask: &[f32], round: u32) -> View {
        let (weight, visible) = (
            self.spec.stage2.weight(round),
            self.spec.stage2.visible_weight,
        );
        fill_view(
            cam,
            fill,
            mask,
            |m| if m >= 0.5 { weight } else { weight * visible },
            |m| if m >= 0.5 || visible > 0.0 { 1.0 } else { 0.0 },
        )
    }
}
