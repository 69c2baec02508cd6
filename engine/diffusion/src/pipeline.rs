//! A model folder in diffusers' pipeline layout: `model_index.json`, `unet/`, `vae/` (latent
//! models), `text_encoder/` and `scheduler/scheduler_config.json`.
//!
//! Two kinds load: the models this project trains (pixel-space or latent, conditioned on
//! learned tokens stored in `text_encoder/learned_tokens.safetensors`) and Stable Diffusion
//! inpainting folders (`StableDiffusionInpaintPipeline`). This build has no CLIP text encoder:
//! an SD folder gets fresh learned tokens in place of the prompt embedding, and
//! [`Pipeline::notes`] says so, so every output can report it.

use std::path::Path;

use burn::tensor::Device;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use crate::config::{UNetConfig, VaeConfig};
use crate::inpaint::{Codec, InpaintModel, PixelCodec, Task};
use crate::scheduler::{Schedule, SchedulerConfig};
use crate::text::LearnedTokens;
use crate::unet::UNet2DConditionModel;
use crate::vae::AutoencoderKL;
use crate::{weights, DiffusionError, Result};

/// The pipeline class this project writes.
pub const OWN_CLASS: &str = "ExtraNerfInpaintPipeline";
/// Stable Diffusion's inpainting pipeline class.
pub const SD_INPAINT_CLASS: &str = "StableDiffusionInpaintPipeline";
/// The file beside LoRA adapters that says what they adapt the model to (absent: inpainting).
pub const TASK_FILE: &str = "extranerf_task.json";

/// Writes [`TASK_FILE`] into an adapter folder.
pub fn save_task(dir: &Path, task: Task) -> Result<()> {
    crate::config::write_json(&dir.join(TASK_FILE), &serde_json::json!({ "task": task }))
}

fn read_task(path: &Path, v: &Value) -> Result<Task> {
    match v.get("task") {
        None => Ok(Task::Inpaint),
        Some(t) => serde_json::from_value(t.clone()).map_err(|e| DiffusionError::Config {
            path: path.to_path_buf(),
            problem: format!(
                "\"task\": {e} (known: \"inpaint\", \"enhance\", \"enhance_residual\")"
            ),
        }),
    }
}

/// `model_index.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelIndex {
    /// Pipeline class.
    #[serde(rename = "_class_name")]
    pub class_name: String,
    /// Every other key (component names).
    #[serde(flatten)]
    pub other: Map<String, Value>,
}

/// A loaded pipeline: the model plus the configs it came from.
#[derive(Debug)]
pub struct Pipeline {
    /// The model.
    pub model: InpaintModel,
    /// The U-Net's config.
    pub unet_config: UNetConfig,
    /// The VAE's config (latent models).
    pub vae_config: Option<VaeConfig>,
    /// The noise schedule's config.
    pub scheduler_config: SchedulerConfig,
    /// What the output should say about where the weights came from.
    pub notes: Vec<String>,
}

impl Pipeline {
    /// A fresh (randomly initialised) model of these configs, conditioned on `tokens`
    /// learned tokens.
    pub fn new(
        unet_config: UNetConfig,
        vae_config: Option<VaeConfig>,
        scheduler_config: SchedulerConfig,
        tokens: usize,
        device: &Device,
    ) -> Result<Pipeline> {
        let unet = UNet2DConditionModel::new(&unet_config, device)?;
        let codec = match &vae_config {
            Some(v) => Codec::Vae(AutoencoderKL::new(v, device)?),
            None => Codec::Pixels(PixelCodec),
        };
        let schedule = Schedule::new(&scheduler_config).map_err(DiffusionError::InvalidConfig)?;
        let model = InpaintModel {
            tokens: LearnedTokens::new(tokens.max(1), unet_config.cross_attention_dim, device),
            unet,
            codec,
            schedule,
            task: Task::Inpaint,
        };
        model.validate()?;
        Ok(Pipeline {
            model,
            unet_config,
            vae_config,
            scheduler_config,
            notes: vec!["randomly initialised weights".into()],
        })
    }

    /// Attaches the LoRA adapters in `dir` (from `diffusion finetune`) to the U-Net and, when
    /// the folder holds them, the conditioning tokens fine-tuned with the adapters.
    pub fn with_lora(mut self, dir: &Path, device: &Device) -> Result<Pipeline> {
        let (_, unet) = crate::lora::load(dir, self.model.unet, device)?;
        self.model.unet = unet;
        self.notes
            .push(format!("LoRA adapters from {}", dir.display()));
        let task_path = dir.join(TASK_FILE);
        if task_path.is_file() {
            let v: Value = crate::config::read_json(&task_path)?;
            self.model.task = read_task(&task_path, &v)?;
        }
        let tdir = dir.join("text_encoder");
        if tdir.join(crate::text::TOKENS_FILE).is_file() {
            self.model.tokens = LearnedTokens::load(&tdir, device)?;
            self.notes
                .push(format!("conditioning tokens from {}", tdir.display()));
        }
        Ok(self)
    }

    /// Loads a pipeline folder. `prompt` conditions a Stable Diffusion folder through its CLIP
    /// text encoder (the embedding then becomes the learned tokens fine-tuning adapts; the empty
    /// prompt is the guidance baseline); this project's folders carry their tokens.
    pub fn load(dir: &Path, device: &Device, prompt: &str) -> Result<Pipeline> {
        let index_path = dir.join("model_index.json");
        let index: ModelIndex = crate::config::read_json(&index_path)?;
        let own = match index.class_name.as_str() {
            OWN_CLASS => true,
            SD_INPAINT_CLASS => false,
            other => {
                return Err(DiffusionError::Config {
                    path: index_path,
                    problem: format!(
                        "pipeline {other:?} is not an inpainting pipeline this engine runs (supported: {OWN_CLASS}, {SD_INPAINT_CLASS})"
                    ),
                })
            }
        };
        let (unet_config, unet) = weights::load_unet(&dir.join("unet"), device)?;
        let (vae_config, codec) = if dir.join("vae").is_dir() {
            let (c, v) = weights::load_vae(&dir.join("vae"), device)?;
            (Some(c), Codec::Vae(v))
        } else if own {
            (None, Codec::Pixels(PixelCodec))
        } else {
            return Err(DiffusionError::Config {
                path: dir.join("vae"),
                problem: "a Stable Diffusion pipeline needs its vae/ folder".into(),
            });
        };
        let sched_path = dir.join("scheduler").join("scheduler_config.json");
        let scheduler_config = SchedulerConfig::from_file(&sched_path)?;
        let schedule =
            Schedule::new(&scheduler_config).map_err(|problem| DiffusionError::Config {
                path: sched_path,
                problem,
            })?;
        let mut notes = Vec::new();
        let tokens_dir = dir.join("text_encoder");
        let tokens = if tokens_dir.join(crate::text::TOKENS_FILE).is_file() {
            notes.push(format!(
                "weights from {} (conditioning: learned tokens)",
                dir.display()
            ));
            LearnedTokens::load(&tokens_dir, device)?
        } else if own {
            return Err(DiffusionError::Weights {
                path: tokens_dir.join(crate::text::TOKENS_FILE),
                problem: "missing: this pipeline is conditioned on learned tokens".into(),
            });
        } else if tokens_dir.join("config.json").is_file() && dir.join("tokenizer").is_dir() {
            let (_, clip) = crate::clip::load_text_encoder(&tokens_dir, device)?;
            let tok = crate::clip::ClipTokenizer::load(&dir.join("tokenizer"))?;
            let len = clip.max_len();
            let ids = vec![tok.encode(prompt, len)?, tok.encode("", len)?];
            let e = clip.forward(&ids, device)?;
            let [_, l, d] = e.dims();
            let mut rows = e.chunk(2, 0);
            let empty = rows
                .pop()
                .unwrap_or_else(|| unreachable!("two rows"))
                .reshape([l, d]);
            let cond = rows
                .pop()
                .unwrap_or_else(|| unreachable!("two rows"))
                .reshape([l, d]);
            notes.push(format!(
                "weights from {}; conditioning: CLIP embedding of {prompt:?} (adapted as learned tokens when fine-tuned)",
                dir.display()
            ));
            LearnedTokens::from_embedding(cond.detach(), empty.detach())
        } else {
            notes.push(format!(
                "U-Net and VAE from {}; no text encoder in the folder: conditioning is 8 fresh learned tokens until fine-tuned",
                dir.display()
            ));
            LearnedTokens::new(8, unet_config.cross_attention_dim, device)
        };
        let task = if own {
            read_task(&index_path, &Value::Object(index.other.clone()))?
        } else {
            Task::Inpaint
        };
        let model = InpaintModel {
            unet,
            codec,
            tokens,
            schedule,
            task,
        };
        model.validate().map_err(|e| DiffusionError::Config {
            path: dir.to_path_buf(),
            problem: e.to_string(),
        })?;
        Ok(Pipeline {
            model,
            unet_config,
            vae_config,
            scheduler_config,
            notes,
        })
    }

    /// Writes the pipeline folder (this project's class; each file atomically).
    pub fn save(&self, dir: &Path) -> Result<()> {
        weights::save_unet(&dir.join("unet"), &self.unet_config, &self.model.unet)?;
        if let (Some(c), Codec::Vae(v)) = (&self.vae_config, &self.model.codec) {
            weights::save_vae(&dir.join("vae"), c, v)?;
        }
        self.model.tokens.save(&dir.join("text_encoder"))?;
        self.scheduler_config
            .save(&dir.join("scheduler").join("scheduler_config.json"))?;
        let mut other = Map::new();
        other.insert("_diffusers_version".into(), Value::from("0.31.0"));
        other.insert(
            "codec".into(),
            Value::from(if self.vae_config.is_some() {
                "vae"
            } else {
                "pixels"
            }),
        );
        other.insert("conditioning".into(), Value::from("learned_tokens"));
        other.insert("task".into(), Value::from(self.model.task.name()));
        crate::config::write_json(
            &dir.join("model_index.json"),
            &ModelIndex {
                class_name: OWN_CLASS.into(),
                other,
            },
        )
    }
}
