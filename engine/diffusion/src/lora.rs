//! LoRA: rank-r adapters with alpha / r scaling and B initialised to zero, on the U-Net's
//! attention projections (q, k, v, out) and optionally its convolutions, with the base frozen.
//!
//! Adapters are saved apart from the model in diffusers' LoRA layout: a
//! `pytorch_lora_weights.safetensors` with PEFT names (`unet.<module>.lora_A.weight`,
//! `unet.<module>.lora_B.weight`; PyTorch layouts, so no transposition) and an
//! `adapter_config.json` (r, lora_alpha, target_modules).

use std::path::Path;

use burn::module::{Module, ModuleVisitor, Param};
use burn::store::{ModuleSnapshot, SafetensorsStore};
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::blocks::{Attention, ResnetBlock2D, Transformer2DModel};
use crate::unet::UNet2DConditionModel;
use crate::weights::is_lora_path;
use crate::{DiffusionError, Result};

/// The adapter file name diffusers writes and reads.
pub const LORA_WEIGHTS: &str = "pytorch_lora_weights.safetensors";
/// The adapter settings file (PEFT's name).
pub const LORA_CONFIG: &str = "adapter_config.json";

/// Where adapters go and how large they are.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoraConfig {
    /// Rank r.
    pub r: usize,
    /// alpha (the update is scaled by alpha / r).
    pub lora_alpha: f64,
    /// PEFT-style target names: any of to_q, to_k, to_v, to_out.0 (attention), conv1, conv2
    /// (ResNet convolutions), proj_in, proj_out (transformer projections).
    pub target_modules: Vec<String>,
    /// Always "LORA" (PEFT).
    #[serde(default = "lora_type")]
    pub peft_type: String,
}

fn lora_type() -> String {
    "LORA".into()
}

const ATTENTION_TARGETS: [&str; 4] = ["to_q", "to_k", "to_v", "to_out.0"];
const ALL_TARGETS: [&str; 8] = [
    "to_q", "to_k", "to_v", "to_out.0", "conv1", "conv2", "proj_in", "proj_out",
];

impl LoraConfig {
    /// Rank `r` on the attention projections q, k, v and out (the usual choice).
    pub fn attention(r: usize, alpha: f64) -> LoraConfig {
        LoraConfig {
            r,
            lora_alpha: alpha,
            target_modules: ATTENTION_TARGETS.iter().map(|s| s.to_string()).collect(),
            peft_type: lora_type(),
        }
    }

    /// Checks the rank, alpha and target names.
    pub fn validate(&self) -> std::result::Result<(), String> {
        if self.r == 0 {
            return Err("LoRA rank r must be at least 1".into());
        }
        if !(self.lora_alpha.is_finite() && self.lora_alpha > 0.0) {
            return Err(format!(
                "lora_alpha = {} must be finite and > 0",
                self.lora_alpha
            ));
        }
        if self.peft_type != "LORA" {
            return Err(format!("peft_type {:?} is not LORA", self.peft_type));
        }
        if self.target_modules.is_empty() {
            return Err("target_modules is empty".into());
        }
        for t in &self.target_modules {
            if !ALL_TARGETS.contains(&t.as_str()) {
                return Err(format!(
                    "target module {t:?} is not supported (supported: {})",
                    ALL_TARGETS.join(", ")
                ));
            }
        }
        Ok(())
    }

    fn has(&self, t: &str) -> bool {
        self.target_modules.iter().any(|m| m == t)
    }

    /// Reads `adapter_config.json`.
    pub fn from_file(path: &Path) -> Result<LoraConfig> {
        let c: LoraConfig = crate::config::read_json(path)?;
        c.validate().map_err(|problem| DiffusionError::Config {
            path: path.to_path_buf(),
            problem,
        })?;
        Ok(c)
    }
}

fn each_transformer(unet: &mut UNet2DConditionModel, f: &mut dyn FnMut(&mut Transformer2DModel)) {
    for b in &mut unet.down_blocks {
        b.attentions.iter_mut().for_each(&mut *f);
    }
    if let Some(m) = &mut unet.mid_block {
        m.attentions.iter_mut().for_each(&mut *f);
    }
    for b in &mut unet.up_blocks {
        b.attentions.iter_mut().for_each(&mut *f);
    }
}

fn each_resnet(unet: &mut UNet2DConditionModel, f: &mut dyn FnMut(&mut ResnetBlock2D)) {
    for b in &mut unet.down_blocks {
        b.resnets.iter_mut().for_each(&mut *f);
    }
    if let Some(m) = &mut unet.mid_block {
        m.resnets.iter_mut().for_each(&mut *f);
    }
    for b in &mut unet.up_blocks {
        b.resnets.iter_mut().for_each(&mut *f);
    }
}

/// Freezes every parameter of `unet` and adds fresh adapters where `config` says. Create the
/// model on an autodiff device to train them.
pub fn apply(
    unet: UNet2DConditionModel,
    config: &LoraConfig,
    device: &Device,
) -> Result<UNet2DConditionModel> {
    config.validate().map_err(DiffusionError::InvalidConfig)?;
    let mut unet = unet.no_grad();
    let (r, alpha) = (config.r, config.lora_alpha);
    let attn = |a: &mut Attention| {
        if config.has("to_q") {
            a.to_q.add_lora(r, alpha, device);
        }
        if config.has("to_k") {
            a.to_k.add_lora(r, alpha, device);
        }
        if config.has("to_v") {
            a.to_v.add_lora(r, alpha, device);
        }
        if config.has("to_out.0") {
            a.to_out[0].add_lora(r, alpha, device);
        }
    };
    each_transformer(&mut unet, &mut |t| {
        for b in &mut t.transformer_blocks {
            attn(&mut b.attn1);
            attn(&mut b.attn2);
        }
        for (name, p) in [("proj_in", &mut t.proj_in), ("proj_out", &mut t.proj_out)] {
            if config.has(name) {
                match p {
                    crate::blocks::Projection::Conv(c) => c.add_lora(r, alpha, device),
                    crate::blocks::Projection::Linear(l) => l.add_lora(r, alpha, device),
                }
            }
        }
    });
    if config.has("conv1") || config.has("conv2") {
        each_resnet(&mut unet, &mut |res| {
            if config.has("conv1") {
                res.conv1.add_lora(r, alpha, device);
            }
            if config.has("conv2") {
                res.conv2.add_lora(r, alpha, device);
            }
        });
    }
    Ok(unet)
}

fn not_lora_err(path: &Path, problem: impl Into<String>) -> DiffusionError {
    DiffusionError::Weights {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

fn lora_only(path: &str, _container: &str) -> bool {
    is_lora_path(path)
}

/// Writes the adapters of `unet` (and `config`) into `dir`, atomically per file.
pub fn save(dir: &Path, unet: &UNet2DConditionModel, config: &LoraConfig) -> Result<()> {
    let file = dir.join(LORA_WEIGHTS);
    let mut store = SafetensorsStore::from_bytes(None)
        .skip_enum_variants(true)
        .with_predicate(lora_only)
        .with_key_remapping(r"^(.*)\.lora_a$", "unet.$1.lora_A.weight")
        .with_key_remapping(r"^(.*)\.lora_b$", "unet.$1.lora_B.weight")
        .metadata("format", "pt");
    unet.save_into(&mut store)
        .map_err(|e| not_lora_err(&file, e.to_string()))?;
    let bytes = store
        .get_bytes()
        .map_err(|e| not_lora_err(&file, e.to_string()))?;
    if count_lora(unet) == 0 {
        return Err(not_lora_err(
            &file,
            "the model has no LoRA adapters to save",
        ));
    }
    crate::write_atomic(&file, &bytes)?;
    crate::config::write_json(&dir.join(LORA_CONFIG), config)
}

/// Reads `dir/adapter_config.json`, attaches adapters of that shape to `unet` (freezing it)
/// and loads their values; every adapter tensor must be present with its shape.
pub fn load(
    dir: &Path,
    unet: UNet2DConditionModel,
    device: &Device,
) -> Result<(LoraConfig, UNet2DConditionModel)> {
    let config = LoraConfig::from_file(&dir.join(LORA_CONFIG))?;
    let mut unet = apply(unet, &config, device)?;
    let file = dir.join(LORA_WEIGHTS);
    let bytes = std::fs::read(&file).map_err(|e| DiffusionError::io(&file, e))?;
    let mut store = SafetensorsStore::from_bytes(Some(bytes))
        .skip_enum_variants(true)
        .with_predicate(lora_only)
        .with_key_remapping(r"^unet\.(.*)\.lora_A\.weight$", "$1.lora_a")
        .with_key_remapping(r"^unet\.(.*)\.lora_B\.weight$", "$1.lora_b")
        .allow_partial(true)
        .validate(true);
    let res = unet
        .load_from(&mut store)
        .map_err(|e| not_lora_err(&file, e.to_string()))?;
    let missing: Vec<&String> = res
        .missing
        .iter()
        .map(|(p, _)| p)
        .filter(|p| is_lora_path(p))
        .collect();
    if !res.errors.is_empty() || !res.unused.is_empty() || !missing.is_empty() {
        return Err(not_lora_err(
            &file,
            format!(
                "adapters do not match {}: missing {:?}, errors {:?}, unused {:?}",
                LORA_CONFIG,
                missing.iter().take(4).collect::<Vec<_>>(),
                res.errors.iter().take(4).collect::<Vec<_>>(),
                res.unused.iter().take(4).collect::<Vec<_>>()
            ),
        ));
    }
    Ok((config, unet))
}

/// Number of LoRA factor tensors in a module.
pub fn count_lora<M: Module>(m: &M) -> usize {
    params_by_kind(m).0.len()
}

/// (LoRA factor params, other params) of a module: paths with lazy shapes.
pub fn params_by_kind<M: Module>(m: &M) -> (Vec<String>, Vec<String>) {
    #[derive(Default)]
    struct V {
        path: Vec<String>,
        lora: Vec<String>,
        base: Vec<String>,
    }
    impl ModuleVisitor for V {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, _p: &Param<Tensor<D>>) {
            let p = self.path.join(".");
            if is_lora_path(&p) {
                self.lora.push(p);
            } else {
                self.base.push(p);
            }
        }
    }
    let mut v = V::default();
    m.visit(&mut v);
    (v.lora, v.base)
}

/// (path, is LoRA, got a gradient) for every float parameter after a backward pass.
pub fn gradients_reached<M: Module>(
    m: &M,
    grads: &burn::tensor::Gradients,
) -> Vec<(String, bool, bool)> {
    struct V<'a> {
        path: Vec<String>,
        grads: &'a burn::tensor::Gradients,
        out: Vec<(String, bool, bool)>,
    }
    impl ModuleVisitor for V<'_> {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            let path = self.path.join(".");
            let has = p.val().grad(self.grads).is_some();
            self.out.push((path.clone(), is_lora_path(&path), has));
        }
    }
    let mut v = V {
        path: Vec::new(),
        grads,
        out: Vec::new(),
    };
    m.visit(&mut v);
    v.out
}
