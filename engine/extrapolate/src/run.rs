//! `extranerf extrapolate`: the ExtraNeRF pipeline as stages over one run folder. This is
//! the one file that knows every stage: it assembles them from the [`Options`] and runs them.
//!
//! - [`BaseStage`]: the BaseNeRF (trained into `RUN/base` under a time budget, or an existing
//!   run reused with `--base`);
//! - [`VisibilityStage`]: virtual cameras beyond the rig, and the visibility of the virtual and
//!   the held-out views against the training cameras (`RUN/visibility`);
//! - [`InpaintStage`]: the stage-2 loop for one inpainter (`RUN/stage2-NAME`): rounds of
//!   render, mask, inpaint and train on the virtual views mixed with the captured ones;
//! - stage 3 ([`crate::stage3`]): the enhancer's training data (`RUN/stage3-data`), the
//!   enhancer (`RUN/stage3-enhancer`), and per stage-2 variant the enhancement loop
//!   (`RUN/stage3-NAME`);
//! - [`FlythroughStage`]: frames along the virtual trajectory, for the BaseNeRF and each
//!   variant (`RUN/flythrough/NAME`), then [`FlythroughVideoStage`]: the video of them side by
//!   side, each labelled (`RUN/flythrough/flythrough.mp4`).
//!
//! Each stage records its resolved configuration in `extrapolate.json` ([`Manifest`]); a
//! resumed run skips the stages done, refuses one asked for with other settings, and continues
//! an unfinished stage 2 from its last finished round.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use extranerf_gpu::files::{remove_stale_temporaries, RunLock};
use extranerf_gpu::Context;
use extranerf_nerf::run::{load_checkpoint, SceneSpec};
use serde_json::Value;

use crate::error::{create_dir, ExtrapolateError, Result};
use crate::inpaint::{DiffusionSpec, InpainterKind};
use crate::manifest::{Manifest, StageRecord};
use crate::rounds::Stage2Spec;
use crate::stage::{FieldRef, RunDir, Stage, VirtualSpec};
use crate::stage3::{EnhanceStage, EnhancerDataStage, EnhancerStage, Stage3Enhancer, Stage3Spec};
use crate::stages::{
    BaseSpec, BaseStage, FlythroughConfig, FlythroughSpec, FlythroughStage, FlythroughVideoStage,
    InpaintSpec, InpaintStage, VisibilityStage,
};
use crate::visibility::VisSettings;
use extranerf_nerf::train::Reporter;

/// Everything `extranerf extrapolate` was asked to do.
#[derive(Clone, Debug)]
pub struct Options {
    /// Run folder.
    pub out: PathBuf,
    /// The scene (ignored with `base.from`, whose scene is used).
    pub scene: Option<SceneSpec>,
    pub base: BaseSpec,
    pub virt: VirtualSpec,
    pub vis: VisSettings,
    pub stage2: Stage2Spec,
    /// One stage-2 variant per inpainter, each from the same BaseNeRF.
    pub inpainters: Vec<InpainterKind>,
    /// The diffusion inpainter's model (needed when `inpainters` holds it).
    pub diffusion: Option<DiffusionSpec>,
    /// Stage 3 (None: stop after stage 2).
    pub stage3: Option<Stage3Spec>,
    /// The fly-through of the BaseNeRF and each variant.
    pub flythrough: FlythroughSpec,
    /// Continue a run folder that holds a manifest.
    pub resume: bool,
    /// Stages to run again from nothing (with `resume`), whatever their record says; their
    /// settings may differ from the recorded ones. The stages that read them run again too.
    pub redo: Vec<String>,
}

/// Runs the pipeline: the base, the visibility stage, one stage-2 variant per inpainter, then
/// stage 3 (its data from the first inpainter's supervision, the enhancer, and one stage-3
/// field per variant) and the fly-throughs, skipping the stages a resumed run has done.
pub fn extrapolate(ctx: &Context, o: &Options, rep: &mut dyn Reporter) -> Result<Manifest> {
    if o.inpainters.is_empty() {
        return Err(ExtrapolateError::usage("give at least one --inpainter"));
    }
    o.stage2.validate()?;
    // The folder is this process's until it returns (a second run into it is refused, naming
    // this one).
    let _lock = RunLock::acquire(&o.out)?;
    let existing = Manifest::load(&o.out)?;
    if existing.is_some() && !o.resume {
        return Err(ExtrapolateError::resume(
            &o.out,
            "already holds an extrapolate run; pass --resume to continue it or choose another --out",
        ));
    }
    if existing.is_none() && o.resume {
        return Err(ExtrapolateError::resume(
            &o.out,
            format!(
                "--resume: it holds no {}; drop --resume to start a run there",
                crate::manifest::MANIFEST_FILE
            ),
        ));
    }
    let base_dir = o.base.from.clone().unwrap_or_else(|| o.out.join("base"));
    let scene = match (&o.base.from, &o.scene) {
        (Some(from), _) => load_checkpoint(from)?.config.scene,
        (None, Some(s)) => s.clone(),
        (None, None) => {
            return Err(ExtrapolateError::usage(
                "give --scene, or --base with a trained run",
            ))
        }
    };
    let mut manifest = match existing {
        Some(m) => {
            m.check_scene(&o.out, &scene)?;
            m
        }
        None => Manifest::new(scene.clone()),
    };
    // The scene's identity: its cameras and images, which a resumed run must find as they were.
    let cams = scene.load()?.scene.cameras;
    let key = extranerf_nerf::mvs_depth::views_key(&scene.dir, &cams)?;
    manifest.check_scene_content(&o.out, &key)?;
    create_dir(&o.out)?;
    // What writes killed before their rename left (the lock says no live writer's are here).
    let stale = remove_stale_temporaries(&o.out)
        .map_err(|e| ExtrapolateError::io("cleaning", &o.out, e))?;
    if !stale.is_empty() {
        rep.note(&format!(
            "removed {} temporary file(s) an interrupted write left in {}",
            stale.len(),
            o.out.display()
        ));
    }
    let dir = RunDir {
        root: o.out.clone(),
        base: base_dir,
    };
    let stages = stages(o, scene)?;
    let names: Vec<String> = stages.iter().map(|s| s.name()).collect();
    check_redo(&o.redo, &names, o.base.from.is_some())?;
    // Every stage's settings are checked before anything runs (a stage to redo may differ).
    for s in &stages {
        if !o.redo.contains(&s.name()) {
            manifest.stage(&o.out, &s.name(), &s.config())?;
        }
    }
    let mut ran: Vec<String> = Vec::new();
    for s in &stages {
        run_stage(ctx, o, &dir, s.as_ref(), &mut manifest, &mut ran, rep)?;
    }
    Ok(manifest)
}

/// The stages `o` asks for, in the order they run.
fn stages(o: &Options, scene: SceneSpec) -> Result<Vec<Box<dyn Stage>>> {
    let mut stages: Vec<Box<dyn Stage>> = vec![
        Box::new(BaseStage {
            spec: o.base.clone(),
            scene,
            virt: o.virt.clone(),
        }),
        Box::new(VisibilityStage {
            virt: o.virt.clone(),
            vis: o.vis.clone(),
        }),
    ];
    for &kind in &o.inpainters {
        stages.push(Box::new(InpaintStage {
            spec: InpaintSpec::new(kind, o.stage2.clone(), o.diffusion.as_ref()),
            virt: o.virt.clone(),
            vis: o.vis.clone(),
        }));
    }
    if let Some(s3) = &o.stage3 {
        s3.validate()?;
        // A fixed filter needs no training data and no model.
        if s3.enhance == Stage3Enhancer::Diffusion {
            stages.push(Box::new(EnhancerDataStage {
                spec: s3.clone(),
                inpainter: o.inpainters[0],
                diffusion: o.diffusion.clone(),
                stage2: o.stage2.clone(),
                virt: o.virt.clone(),
                vis: o.vis.clone(),
            }));
            stages.push(Box::new(EnhancerStage { spec: s3.clone() }));
        }
        for &kind in &o.inpainters {
            stages.push(Box::new(EnhanceStage {
                kind,
                spec: s3.clone(),
                virt: o.virt.clone(),
                vis: o.vis.clone(),
            }));
        }
    }
    if o.flythrough.frames > 0 {
        let mut fields = vec![FieldRef::Base];
        fields.extend(o.inpainters.iter().map(|&k| FieldRef::Stage2(k)));
        if o.stage3.is_some() {
            fields.extend(o.inpainters.iter().map(|&k| FieldRef::Stage3(k)));
        }
        let config = FlythroughConfig {
            virt: o.virt.clone(),
            spec: o.flythrough.clone(),
        };
        for &field in &fields {
            stages.push(Box::new(FlythroughStage {
                field,
                config: config.clone(),
            }));
        }
        stages.push(Box::new(FlythroughVideoStage { fields, config }));
    }
    Ok(stages)
}

/// Runs stage `s` unless the manifest says it is done with these settings and the stages it
/// reads are as they were when it ran: their fingerprints equal those its record holds, and
/// none of them ran in this invocation (`ran`, which it joins when it runs). Its record is
/// saved before it runs (not done, with the fingerprints of its inputs) and after (with its
/// own).
fn run_stage(
    ctx: &Context,
    o: &Options,
    dir: &RunDir,
    s: &dyn Stage,
    manifest: &mut Manifest,
    ran: &mut Vec<String>,
    rep: &mut dyn Reporter,
) -> Result<()> {
    let name = s.name();
    let config = s.config();
    let redo = o.redo.contains(&name);
    let prior = if redo {
        None
    } else {
        manifest.stage(&o.out, &name, &config)?.cloned()
    };
    // The fingerprints of the stages it reads, now.
    let mut declared: Vec<String> = Vec::new();
    for i in s.inputs() {
        if !declared.contains(&i) {
            declared.push(i);
        }
    }
    let inputs: BTreeMap<String, String> = declared
        .iter()
        .filter_map(|i| manifest.fingerprint(i).map(|f| (i.clone(), f)))
        .collect();
    // The stages it reads that were made again since it ran (in this invocation, or in an
    // earlier one that stopped before this stage): its output is stale.
    let rerun: Vec<String> = declared
        .into_iter()
        .filter(|i| {
            ran.contains(i)
                || prior
                    .as_ref()
                    .and_then(|r| r.inputs.as_ref())
                    .is_some_and(|rec| rec.get(i) != inputs.get(i))
        })
        .collect();
    let stale = !rerun.is_empty();
    if let Some(p) = prior.as_ref().filter(|r| r.done && !stale) {
        // (Read only here: a stage about to run is identified once it has.)
        let identity = s.identity(dir)?;
        match (&identity, &p.output) {
            // Its output was replaced outside this run (the reused BaseNeRF trained on, or
            // `--base` another run): recorded anew, and what reads it runs again.
            (Some(now), Some(then)) if now != then => {
                rep.note(&format!(
                    "stage {name}: its output changed since this run recorded it (SHA-256 {} -> {}); the stages that read it run again",
                    &then[..12.min(then.len())],
                    &now[..12.min(now.len())]
                ));
                let mut rec = p.clone();
                rec.config = config.value.clone();
                rec.output = identity;
                manifest.record(rec);
                manifest.save(&o.out)?;
                ran.push(name);
                return Ok(());
            }
            _ => {
                rep.note(&format!("stage {name}: done, skipped"));
                return Ok(());
            }
        }
    }
    ran.push(name.clone());
    rep.stage(&name);
    // Its state from an earlier run was made from other inputs or settings: start over.
    let prior = if redo || stale {
        // (A stage that never ran before has nothing to discard, and says nothing.)
        if redo || prior.is_some() {
            rep.note(&format!(
                "stage {name}: {}, its earlier output discarded",
                if redo {
                    "redone (--redo)".to_string()
                } else {
                    format!("runs again after {}", rerun.join(", "))
                }
            ));
        }
        s.reset(dir)?;
        None
    } else {
        prior
    };
    let before = prior.as_ref().map_or(0.0, |r| r.seconds);
    manifest.record(StageRecord {
        name: name.clone(),
        config: config.value.clone(),
        done: false,
        seconds: before,
        report: Value::Null,
        inputs: Some(inputs.clone()),
        output: None,
    });
    manifest.save(&o.out)?;
    let t = Instant::now();
    let report = s.run(ctx, dir, rep).map_err(|e| e.in_stage(&name))?;
    let seconds = before + t.elapsed().as_secs_f64();
    rep.note(&format!("stage {name}: done in {seconds:.1} s"));
    // Its output: the identity of the file that holds it, else its record and this moment
    // (a stage made again is new output, even with the same settings).
    let output = match s.identity(dir)? {
        Some(id) => id,
        None => {
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos());
            extranerf_nerf::mvs_depth::sha256_hex(
                serde_json::json!({
                    "name": name, "config": config.value, "report": report,
                    "finished": format!("{now}-{}", std::process::id())
                })
                .to_string()
                .as_bytes(),
            )
        }
    };
    manifest.record(StageRecord {
        name,
        config: config.value,
        done: true,
        seconds,
        report,
        inputs: Some(inputs),
        output: Some(output),
    });
    manifest.save(&o.out)?;
    Ok(())
}

/// Refuses `--redo` names that are not stages of this run, or the BaseNeRF of another run.
pub fn check_redo(redo: &[String], stages: &[String], base_reused: bool) -> Result<()> {
    for r in redo {
        if !stages.contains(r) {
            return Err(ExtrapolateError::usage(format!(
                "--redo {r}: this run has no such stage (its stages: {})",
                stages.join(", ")
            )));
        }
        if r == "base" && base_reused {
            return Err(ExtrapolateError::usage(
                "--redo base: the BaseNeRF is --base's run, not this one's; retrain it there",
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stage3::Stage3Gate;
    use extranerf_nerf::cameras::Trajectory;

    /// Options that make every kind of stage, with settings away from their defaults.
    fn every_stage(enhance: Stage3Enhancer) -> Options {
        Options {
            out: "run".into(),
            scene: None,
            base: BaseSpec {
                from: Some("base".into()),
                budget: 30.0,
            },
            virt: VirtualSpec {
                trajectory: Trajectory::Outward,
                count: 5,
                range: 1.25,
                downscale: 3,
            },
            vis: VisSettings {
                threshold: 0.3,
                chunk: 512,
                ..VisSettings::default()
            },
            stage2: Stage2Spec {
                rounds: 3,
                lr: 1e-3,
                ..Stage2Spec::default()
            },
            inpainters: vec![InpainterKind::Diffusion, InpainterKind::Exemplar],
            diffusion: Some(DiffusionSpec {
                model: "model".into(),
                lora: Some("lora".into()),
                steps: 7,
                backend: extranerf_diffusion::device::Backend::Cpu,
            }),
            stage3: Some(Stage3Spec {
                enhance,
                gate: Stage3Gate::Check,
                anchor_radius: 2,
                unsharp_amount: 0.75,
                ..Stage3Spec::default()
            }),
            flythrough: FlythroughSpec {
                frames: 5,
                ..FlythroughSpec::default()
            },
            resume: false,
            redo: Vec::new(),
        }
    }

    #[test]
    fn each_stage_records_its_spec_and_declares_every_field() {
        let scene = SceneSpec {
            dir: "scene".into(),
            split: extranerf_nerf::data::split::SplitKind::Extrapolation,
            fewshot_views: 3,
            factor: 8,
            sparse_depth: false,
            depth_dir: None,
            mvs_depth: None,
            capture_depth: false,
        };
        let mut names = Vec::new();
        for enhance in [Stage3Enhancer::Diffusion, Stage3Enhancer::Unsharp] {
            for s in stages(&every_stage(enhance), scene.clone()).unwrap() {
                let r = s.config();
                // The record round-trips through its type unchanged ...
                assert_eq!(r.read(&r.value).unwrap(), r.value, "{}", s.name());
                r.check(std::path::Path::new("run"), &s.name(), &r.value)
                    .unwrap();
                // ... and every field it holds is declared.
                let Value::Object(fields) = &r.value else {
                    panic!("{}: not an object", s.name());
                };
                for k in fields.keys() {
                    assert!(
                        r.rules.iter().any(|(p, _)| p == k),
                        "{}: field `{k}` has no resume rule",
                        s.name()
                    );
                }
                // A rule inside a field names one of its fields (where the field is there).
                for (p, _) in r.rules {
                    let top = p.split('.').next().unwrap();
                    if fields.get(top).is_some_and(|v| !v.is_null()) {
                        assert!(
                            r.value
                                .pointer(&format!("/{}", p.replace('.', "/")))
                                .is_some(),
                            "{}: the rule of `{p}` names no field",
                            s.name()
                        );
                    }
                }
                names.push(s.name());
            }
        }
        for n in [
            "base",
            "visibility",
            "stage2-diffusion",
            "stage2-exemplar",
            "stage3-data",
            "stage3-enhancer",
            "stage3-diffusion",
            "stage3-exemplar",
            "flythrough-base",
            "flythrough-stage3-exemplar",
        ] {
            assert!(names.iter().any(|m| m == n), "{n} not made: {names:?}");
        }
    }

    #[test]
    fn redo_names_a_stage_of_the_run_and_not_a_reused_base() {
        let stages: Vec<String> = ["base", "visibility", "stage2-harmonic"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        assert!(check_redo(&["stage2-harmonic".into()], &stages, true).is_ok());
        assert!(check_redo(&["base".into()], &stages, false).is_ok());
        let e = check_redo(&["stage3-harmonic".into()], &stages, false)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--redo stage3-harmonic: this run has no such stage"),
            "{e}"
        );
        assert!(e.contains("base, visibility, stage2-harmonic"), "{e}");
        let e = check_redo(&["base".into()], &stages, true)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--redo base: the BaseNeRF is --base's run"),
            "{e}"
        );
    }
}
