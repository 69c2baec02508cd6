//! ExtraNeRF's enhancer (stage 3): the inpainting architecture trained to turn a corrupted
//! NeRF render back into the photograph of its view, with the render shown whole as guidance
//! and the mask channel marking where an earlier stage filled it in ([`Task::Enhance`]).
//!
//! Trained on (corrupted render, mask, photo) triplets ([`TrainImage`] with
//! [`crate::train::Guide`]s): LoRA adapters on a user's Stable Diffusion inpainting folder
//! when one is given, otherwise a pixel-space U-Net from scratch on the scene (no pretrained
//! weights exist on these machines). A folder this module writes loads with [`load`].

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::config::UNetConfig;
use crate::inpaint::{Codec, InpaintModel, PixelCodec, Task};
use crate::lora::{self, LoraConfig};
use crate::pipeline::{save_task, Pipeline};
use crate::scheduler::{Prediction, Schedule, SchedulerConfig};
use crate::train::{self, Augment, Progress, TrainImage, TrainSettings, Trainable};
use crate::train_state::{self, Checkpointing};
use crate::{DiffusionError, Result};

/// The file in an enhancer folder that says what it holds.
pub const ENHANCER_FILE: &str = "enhancer.json";

/// What a from-scratch enhancer's U-Net predicts.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum EnhancerOutput {
    /// v (Salimans & Ho), as the scene prior: the enhancer denoises from scratch, and until it
    /// is well trained its error lands on every pixel of its output.
    #[default]
    V,
    /// The clean image's difference from the render it is shown (task `enhance_residual`, the
    /// schedule's `sample` prediction), its last convolution starting at zero: an untrained
    /// enhancer is the identity.
    Residual,
}

impl EnhancerOutput {
    fn is_default(&self) -> bool {
        *self == EnhancerOutput::V
    }
}

/// How the enhancer is made.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnhancerSpec {
    /// A Stable Diffusion inpainting folder (diffusers layout) to adapt with LoRA; None:
    /// train a pixel-space U-Net from scratch.
    pub base_model: Option<PathBuf>,
    /// Channels per level of the from-scratch U-Net.
    pub channels: Vec<usize>,
    /// LoRA rank (with `base_model`).
    pub rank: usize,
    /// Optimiser steps.
    pub steps: usize,
    /// Crops per step.
    pub batch: usize,
    /// Crop side (a multiple of the model's size step).
    pub crop: usize,
    /// AdamW learning rate.
    pub lr: f64,
    /// Colour jitter (applied alike to render and photo).
    pub jitter: f64,
    /// The largest noise strength it is trained for (a fraction of the schedule's
    /// timesteps): stage 3 enhances from a moderate one and never needs the rest.
    pub max_strength: f64,
    /// Seed of the initialisation, crops, timesteps and noise.
    pub seed: u64,
    /// What the from-scratch U-Net predicts (LoRA keeps the base model's prediction).
    /// Recorded only when not v, so the records of earlier runs (all v) read the same.
    #[serde(default, skip_serializing_if = "EnhancerOutput::is_default")]
    pub output: EnhancerOutput,
}

impl Default for EnhancerSpec {
    fn default() -> Self {
        EnhancerSpec {
            base_model: None,
            channels: vec![32, 64, 96],
            rank: 4,
            steps: 600,
            batch: 8,
            crop: 48,
            lr: 2e-3,
            jitter: 0.1,
            max_strength: 0.6,
            seed: 0,
            output: EnhancerOutput::default(),
        }
    }
}

/// What [`ENHANCER_FILE`] records.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnhancerRecord {
    /// The settings it was trained with.
    pub spec: EnhancerSpec,
    /// U-Net parameters (from scratch) or adapter tensors (LoRA).
    pub params: usize,
    /// Loss reports (step, mean loss).
    pub curve: Vec<(usize, f64)>,
    /// Training seconds.
    pub seconds: f64,
}

/// The folder of the full model (from scratch) inside an enhancer folder.
pub fn model_dir(dir: &Path) -> PathBuf {
    dir.join("model")
}

/// The folder of the adapters (LoRA) inside an enhancer folder.
pub fn lora_dir(dir: &Path) -> PathBuf {
    dir.join("lora")
}

/// Trains an enhancer on `images` (each with its corrupted versions) into `out`, resuming a
/// killed training there (`out/train_state`). `device` is a plain device; training runs on
/// its autodiff twin.
pub fn train_enhancer(
    images: &[TrainImage],
    spec: &EnhancerSpec,
    out: &Path,
    device: &Device,
    on_progress: &mut dyn FnMut(&Progress),
) -> Result<EnhancerRecord> {
    if images.is_empty() || images.iter().any(|im| im.guides.is_empty()) {
        return Err(DiffusionError::Input(
            "an enhancer needs training images, each with at least one corrupted version".into(),
        ));
    }
    if spec.base_model.is_some() && spec.rank == 0 {
        return Err(DiffusionError::Input(
            "the enhancer's LoRA rank must be at least 1".into(),
        ));
    }
    let identity = serde_json::to_value(spec).map_err(|e| DiffusionError::Input(e.to_string()))?;
    let state_dir = out.join("train_state");
    // A state from other triplets or settings is this folder's stale work (its data were
    // collected again): it is dropped. The same training resumes.
    let resume = match train_state::peek(&state_dir)? {
        Some(st) if st.images == train_state::images_hash(images) && st.identity == identity => {
            true
        }
        Some(_) => {
            std::fs::remove_dir_all(&state_dir).map_err(|e| DiffusionError::io(&state_dir, e))?;
            false
        }
        None => false,
    };
    let ck = Checkpointing {
        dir: state_dir,
        every: 50.min(spec.steps.max(1)),
        resume,
        identity,
    };
    let ad = device.clone().autodiff();
    ad.seed(spec.seed);
    let residual = spec.base_model.is_none() && spec.output == EnhancerOutput::Residual;
    let settings = TrainSettings {
        residual,
        steps: spec.steps,
        batch: spec.batch,
        lr: spec.lr,
        token_lr: spec.lr,
        seed: spec.seed,
        log_every: 25.min(spec.steps.max(1)),
        cond_dropout: 0.0,
        max_strength: spec.max_strength,
        ..TrainSettings::default()
    };
    let aug = Augment {
        crop: spec.crop,
        flip: true,
        jitter: spec.jitter,
        ..Augment::default()
    };
    let t = std::time::Instant::now();
    // The one training call of both branches (from scratch, LoRA).
    let mut run = |model: Trainable, codec: &Codec, schedule: &Schedule| {
        train::train(
            model,
            codec,
            schedule,
            images,
            &aug,
            &settings,
            &ad,
            Some(&ck),
            on_progress,
        )
    };
    let (params, curve) = match &spec.base_model {
        None => {
            let cfg = UNetConfig::pixel_space(&spec.channels, 64)
                .map_err(|e| DiffusionError::InvalidConfig(format!("enhancer channels: {e}")))?;
            let (prediction, task) = if residual {
                (Prediction::Sample, Task::EnhanceResidual)
            } else {
                (Prediction::V, Task::Enhance)
            };
            let sched = SchedulerConfig::pixel_space(prediction);
            let mut pipe = Pipeline::new(cfg.clone(), None, sched.clone(), 4, &ad)?;
            if residual {
                // The identity to start from: the output (added to the guidance) is zero.
                pipe.model.unet.conv_out.zero(&ad);
            }
            let params = pipe.model.unet.num_params();
            let schedule = pipe.model.schedule.clone();
            let (model, curve) = run(
                Trainable {
                    unet: pipe.model.unet,
                    tokens: pipe.model.tokens,
                },
                &pipe.model.codec,
                &schedule,
            )?;
            let model = model.valid();
            Pipeline {
                model: InpaintModel {
                    unet: model.unet,
                    tokens: model.tokens,
                    codec: Codec::Pixels(PixelCodec),
                    schedule,
                    task,
                },
                unet_config: cfg,
                vae_config: None,
                scheduler_config: sched,
                notes: Vec::new(),
            }
            .save(&model_dir(out))?;
            (params, curve)
        }
        Some(base) => {
            let pipe = Pipeline::load(base, &ad, "")?;
            let cfg = LoraConfig::attention(spec.rank, spec.rank as f64);
            let unet = lora::apply(pipe.model.unet, &cfg, &ad)?;
            let params = lora::count_lora(&unet);
            let schedule = pipe.model.schedule.clone();
            let codec = pipe.model.codec.no_grad();
            let (model, curve) = run(
                Trainable {
                    unet,
                    tokens: pipe.model.tokens,
                },
                &codec,
                &schedule,
            )?;
            let dir = lora_dir(out);
            lora::save(&dir, &model.unet, &cfg)?;
            model.tokens.save(&dir.join("text_encoder"))?;
            save_task(&dir, Task::Enhance)?;
            (params, curve)
        }
    };
    let rec = EnhancerRecord {
        spec: spec.clone(),
        params,
        curve,
        seconds: t.elapsed().as_secs_f64(),
    };
    crate::config::write_json(&out.join(ENHANCER_FILE), &rec)?;
    Ok(rec)
}

/// Loads an enhancer folder written by [`train_enhancer`] (its base model, for LoRA, from
/// where the record says).
pub fn load(dir: &Path, device: &Device) -> Result<Pipeline> {
    let path = dir.join(ENHANCER_FILE);
    let rec: EnhancerRecord = crate::config::read_json(&path)?;
    let pipe = match &rec.spec.base_model {
        None => Pipeline::load(&model_dir(dir), device, "")?,
        Some(base) => Pipeline::load(base, device, "")?.with_lora(&lora_dir(dir), device)?,
    };
    if !pipe.model.task.enhances() {
        return Err(DiffusionError::Config {
            path,
            problem: "the folder's model is not an enhancer".into(),
        });
    }
    Ok(pipe)
}

/// Loads a model folder for enhancement: an enhancer folder ([`ENHANCER_FILE`]), or a
/// pipeline folder whose model (with `lora`) was trained to enhance.
pub fn load_any(dir: &Path, lora: Option<&Path>, device: &Device) -> Result<Pipeline> {
    if dir.join(ENHANCER_FILE).is_file() {
        if lora.is_some() {
            return Err(DiffusionError::Input(format!(
                "{} is an enhancer folder with its own adapters; give no --lora",
                dir.display()
            )));
        }
        return load(dir, device);
    }
    let mut pipe = Pipeline::load(dir, device, "")?;
    if let Some(l) = lora {
        pipe = pipe.with_lora(l, device)?;
    }
    if !pipe.model.task.enhances() {
        return Err(DiffusionError::Input(format!(
            "{}{} holds an inpainting model, not an enhancer (stage 3 of `extranerf extrapolate` trains one into RUN/stage3-enhancer)",
            dir.display(),
            lora.map(|l| format!(" with {}", l.display()))
                .unwrap_or_default()
        )));
    }
    Ok(pipe)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(json: serde_json::Value) -> EnhancerSpec {
        match serde_json::from_value(json) {
            Ok(s) => s,
            Err(e) => panic!("{e}"),
        }
    }

    /// Records written before the choice of output existed (no `output` field) trained v and
    /// read back as v; a v spec (the default) writes no field, so it still matches them; a
    /// residual one is written out and read back.
    #[test]
    fn records_without_an_output_trained_v() {
        let json = serde_json::to_value(EnhancerSpec::default()).unwrap_or_default();
        assert!(json.is_object());
        assert!(json.get("output").is_none(), "{json}");
        let back = parse(json);
        assert_eq!(back.output, EnhancerOutput::V);
        let r = EnhancerSpec {
            output: EnhancerOutput::Residual,
            ..EnhancerSpec::default()
        };
        let json = serde_json::to_value(&r).unwrap_or_default();
        assert_eq!(json["output"], "residual", "{json}");
        assert_eq!(parse(json), r);
    }
}
