//! Weights in diffusers' folder layout: `unet/`, `vae/` and `text_encoder/`, each with a
//! `config.json` and a safetensors file (`diffusion_pytorch_model.safetensors`, or
//! `model.safetensors` for the text encoder), PyTorch tensor layouts and names.
//!
//! Loading goes through burn-store's `SafetensorsStore` with the PyTorch adapter (Linear weights
//! transposed, norm `weight`/`bias` to `gamma`/`beta`) and a cast to f32 (fp16 checkpoints load
//! too). It is strict: a tensor the model needs but the file lacks, a tensor of the wrong shape,
//! and a tensor the file has but the model does not use are all errors that name the file and
//! the tensors, so a checkpoint of another architecture never loads into a silently different
//! network. LoRA factors are never part of these files (see [`crate::lora`]).

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::store::{
    BurnToPyTorchAdapter, FloatCastAdapter, ModuleAdapter, ModuleSnapshot, PyTorchToBurnAdapter,
    SafetensorsStore,
};
use burn::tensor::{DType, Device};

use crate::config::{UNetConfig, VaeConfig};
use crate::unet::UNet2DConditionModel;
use crate::vae::AutoencoderKL;
use crate::{DiffusionError, Result};

/// File name of U-Net and VAE weights in diffusers folders.
pub const DIFFUSERS_WEIGHTS: &str = "diffusion_pytorch_model.safetensors";

fn not_lora(path: &str, _container: &str) -> bool {
    !is_lora_path(path)
}

/// Whether a module path is a LoRA factor.
pub fn is_lora_path(path: &str) -> bool {
    path.ends_with(".lora_a") || path.ends_with(".lora_b")
}

fn weights_err(path: &Path, problem: impl Into<String>) -> DiffusionError {
    DiffusionError::Weights {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

/// The weight file of a component folder: `names` in order of preference.
pub fn find_weights(dir: &Path, names: &[&str]) -> Result<PathBuf> {
    for n in names {
        let p = dir.join(n);
        if p.is_file() {
            return Ok(p);
        }
    }
    let bin = ["diffusion_pytorch_model.bin", "pytorch_model.bin"]
        .iter()
        .map(|n| dir.join(n))
        .find(|p| p.is_file());
    Err(match bin {
        Some(b) => weights_err(
            &b,
            "PyTorch pickle weights are not read (unsafe to unpickle); convert them to safetensors",
        ),
        None => weights_err(
            dir,
            format!("no weight file here (looked for {})", names.join(", ")),
        ),
    })
}

/// Loads `file` into `model` strictly (see the module docs). `remap` renames file keys first
/// (regex, replacement), e.g. for deprecated attention names.
pub fn load_into<M: Module + ModuleSnapshot>(
    model: &mut M,
    file: &Path,
    remap: &[(&str, &str)],
    ignore_unused: &[&str],
) -> Result<()> {
    let bytes = std::fs::read(file).map_err(|e| DiffusionError::io(file, e))?;
    check_header(file, &bytes)?;
    let mut store = SafetensorsStore::from_bytes(Some(bytes))
        .with_from_adapter(PyTorchToBurnAdapter.chain(FloatCastAdapter::to(DType::F32)))
        .skip_enum_variants(true)
        .with_predicate(not_lora)
        // Missing tensors are checked below: burn-store counts a module path the file lacks
        // as missing even when the filter excludes it (LoRA factors).
        .allow_partial(true)
        .validate(true);
    for (from, to) in remap {
        store = store.with_key_remapping(*from, *to);
    }
    let res = model
        .load_from(&mut store)
        .map_err(|e| weights_err(file, e.to_string()))?;
    let missing: Vec<&str> = res
        .missing
        .iter()
        .map(|(p, _)| p.as_str())
        .filter(|p| !is_lora_path(p))
        .collect();
    if !missing.is_empty() {
        return Err(weights_err(
            file,
            format!(
                "{} tensors of the model are missing from the file: {}{}",
                missing.len(),
                missing
                    .iter()
                    .take(8)
                    .copied()
                    .collect::<Vec<_>>()
                    .join(", "),
                if missing.len() > 8 { ", ..." } else { "" }
            ),
        ));
    }
    if !res.errors.is_empty() {
        let list: Vec<String> = res
            .errors
            .iter()
            .take(8)
            .map(|e| format!("{e:?}"))
            .collect();
        return Err(weights_err(
            file,
            format!(
                "{} tensors could not be applied: {}",
                res.errors.len(),
                list.join("; ")
            ),
        ));
    }
    let unused: Vec<&String> = res
        .unused
        .iter()
        .filter(|k| !ignore_unused.iter().any(|i| k.contains(i)))
        .collect();
    if !unused.is_empty() {
        let list: Vec<&str> = unused.iter().take(8).map(|s| s.as_str()).collect();
        return Err(weights_err(
            file,
            format!(
                "{} tensors in the file are not part of this model (another architecture or config?): {}{}",
                unused.len(),
                list.join(", "),
                if unused.len() > 8 { ", ..." } else { "" }
            ),
        ));
    }
    Ok(())
}

/// A safetensors header check before burn-store sees the bytes: a truncated or corrupt file is
/// reported as such, naming the file.
fn check_header(file: &Path, bytes: &[u8]) -> Result<()> {
    if bytes.len() < 8 {
        return Err(weights_err(
            file,
            format!("{} bytes: too short for a safetensors file", bytes.len()),
        ));
    }
    let mut n = [0u8; 8];
    n.copy_from_slice(&bytes[..8]);
    let n = u64::from_le_bytes(n);
    if n > (bytes.len() - 8) as u64 {
        return Err(weights_err(
            file,
            format!(
                "header of {n} bytes but the file has {} (truncated or not safetensors)",
                bytes.len()
            ),
        ));
    }
    let header = &bytes[8..8 + n as usize];
    let v: serde_json::Value = serde_json::from_slice(header)
        .map_err(|e| weights_err(file, format!("malformed safetensors header: {e}")))?;
    let map = v
        .as_object()
        .ok_or_else(|| weights_err(file, "safetensors header is not a JSON object"))?;
    let data_len = (bytes.len() - 8 - n as usize) as u64;
    for (k, t) in map {
        if k == "__metadata__" {
            continue;
        }
        let end = t
            .get("data_offsets")
            .and_then(|o| o.as_array())
            .and_then(|o| o.get(1))
            .and_then(|e| e.as_u64())
            .ok_or_else(|| weights_err(file, format!("tensor {k:?} has no data_offsets")))?;
        if end > data_len {
            return Err(weights_err(
                file,
                format!(
                    "tensor {k:?} ends at byte {end} of a {data_len}-byte data section (truncated)"
                ),
            ));
        }
    }
    Ok(())
}

/// Saves `model`'s parameters (LoRA factors excluded) as a PyTorch-layout safetensors file,
/// atomically.
pub fn save_from<M: Module + ModuleSnapshot>(model: &M, file: &Path) -> Result<()> {
    let mut store = SafetensorsStore::from_bytes(None)
        .with_to_adapter(BurnToPyTorchAdapter)
        .skip_enum_variants(true)
        .with_predicate(not_lora)
        .metadata("format", "pt");
    model
        .save_into(&mut store)
        .map_err(|e| weights_err(file, e.to_string()))?;
    let bytes = store
        .get_bytes()
        .map_err(|e| weights_err(file, e.to_string()))?;
    crate::write_atomic(file, &bytes)
}

/// diffusers' deprecated VAE attention names (query/key/value/proj_attn), as found in older
/// checkpoints such as sd-vae-ft-mse, mapped to the current ones.
pub const VAE_DEPRECATED: &[(&str, &str)] = &[
    (r"\.attentions\.(\d+)\.query\.", ".attentions.$1.to_q."),
    (r"\.attentions\.(\d+)\.key\.", ".attentions.$1.to_k."),
    (r"\.attentions\.(\d+)\.value\.", ".attentions.$1.to_v."),
    (
        r"\.attentions\.(\d+)\.proj_attn\.",
        ".attentions.$1.to_out.0.",
    ),
];

/// Loads `dir/config.json` and `dir/diffusion_pytorch_model.safetensors` (or its fp16 variant).
pub fn load_unet(dir: &Path, device: &Device) -> Result<(UNetConfig, UNet2DConditionModel)> {
    let config = UNetConfig::from_file(&dir.join("config.json"))?;
    let file = find_weights(
        dir,
        &[
            DIFFUSERS_WEIGHTS,
            "diffusion_pytorch_model.fp16.safetensors",
        ],
    )?;
    let mut unet = UNet2DConditionModel::new(&config, device)?;
    load_into(&mut unet, &file, &[], &[])?;
    Ok((config, unet))
}

/// Writes `dir/config.json` and `dir/diffusion_pytorch_model.safetensors`.
pub fn save_unet(dir: &Path, config: &UNetConfig, unet: &UNet2DConditionModel) -> Result<()> {
    save_from(unet, &dir.join(DIFFUSERS_WEIGHTS))?;
    config.save(&dir.join("config.json"))
}

/// Loads a VAE folder (current or deprecated attention names).
pub fn load_vae(dir: &Path, device: &Device) -> Result<(VaeConfig, AutoencoderKL)> {
    let config = VaeConfig::from_file(&dir.join("config.json"))?;
    let file = find_weights(
        dir,
        &[
            DIFFUSERS_WEIGHTS,
            "diffusion_pytorch_model.fp16.safetensors",
        ],
    )?;
    let mut vae = AutoencoderKL::new(&config, device)?;
    load_into(&mut vae, &file, VAE_DEPRECATED, &[])?;
    Ok((config, vae))
}

/// Writes a VAE folder.
pub fn save_vae(dir: &Path, config: &VaeConfig, vae: &AutoencoderKL) -> Result<()> {
    save_from(vae, &dir.join(DIFFUSERS_WEIGHTS))?;
    config.save(&dir.join("config.json"))
}

/// The parameter names and shapes of a module as they appear in a diffusers file (PyTorch
/// names and layouts), LoRA factors excluded. Reads shapes only: a lazily initialised model
/// (even SD-1.5's 860M parameters) stays unallocated.
pub fn parameter_names<M: Module>(model: &M) -> Vec<(String, Vec<usize>)> {
    #[derive(Default)]
    struct Names {
        stack: Vec<(String, String)>,
        out: Vec<(String, Vec<usize>)>,
    }
    impl burn::module::ModuleVisitor for Names {
        fn enter_module(&mut self, name: &str, container: &str) {
            self.stack.push((name.to_string(), container.to_string()));
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.stack.pop();
        }
        fn visit_float<const D: usize>(
            &mut self,
            p: &burn::module::Param<burn::tensor::Tensor<D>>,
        ) {
            let Some((leaf, module)) = self.stack.last() else {
                return;
            };
            let mut shape = p.lazy_shape().to_vec();
            let mut leaf = leaf.clone();
            match module.as_str() {
                "Struct:Linear" if leaf == "weight" && shape.len() == 2 => shape.reverse(),
                "Struct:GroupNorm" | "Struct:LayerNorm" => {
                    leaf = match leaf.as_str() {
                        "gamma" => "weight".into(),
                        "beta" => "bias".into(),
                        _ => leaf,
                    }
                }
                _ => {}
            }
            let mut parts: Vec<&str> = self.stack[..self.stack.len() - 1]
                .iter()
                .filter(|(_, c)| !c.starts_with("Enum:"))
                .map(|(n, _)| n.as_str())
                .collect();
            parts.push(&leaf);
            let name = parts.join(".");
            if !is_lora_path(&name) {
                self.out.push((name, shape));
            }
        }
    }
    let mut v = Names::default();
    model.visit(&mut v);
    v.out
}
