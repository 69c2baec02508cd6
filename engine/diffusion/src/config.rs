//! Model configurations in diffusers' `config.json` format.
//!
//! The field names and defaults are diffusers' (UNet2DConditionModel, AutoencoderKL), so a
//! Stable Diffusion folder's `unet/config.json` and `vae/config.json` load as they are, and the
//! tiny models this project trains itself are written in the same form. Keys that change the
//! architecture in ways this implementation does not model must keep their default values; a
//! key that is neither known nor harmless is refused. Both give an error that names the file and
//! the key, never a silently different network.

use std::path::Path;

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use crate::DiffusionError;

/// One value for every block, or one per block (diffusers accepts both).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum PerBlock {
    /// The same for every block.
    One(usize),
    /// One per down block (up blocks take them reversed).
    Many(Vec<usize>),
}

impl PerBlock {
    /// The value for block `i` of `n`.
    pub fn get(&self, i: usize) -> usize {
        match self {
            PerBlock::One(v) => *v,
            PerBlock::Many(v) => v[i],
        }
    }

    fn len_ok(&self, n: usize) -> bool {
        match self {
            PerBlock::One(_) => true,
            PerBlock::Many(v) => v.len() == n,
        }
    }
}

/// The down block kinds of a U-Net.
pub const CROSS_ATTN_DOWN: &str = "CrossAttnDownBlock2D";
/// A down block of ResNets only.
pub const DOWN: &str = "DownBlock2D";
/// The up block with cross-attention.
pub const CROSS_ATTN_UP: &str = "CrossAttnUpBlock2D";
/// An up block of ResNets only.
pub const UP: &str = "UpBlock2D";

fn unet_class() -> String {
    "UNet2DConditionModel".into()
}
fn vae_class() -> String {
    "AutoencoderKL".into()
}
fn d_sample() -> usize {
    64
}
fn d_four() -> usize {
    4
}
fn d_three() -> usize {
    3
}
fn d_true() -> bool {
    true
}
fn d_one() -> usize {
    1
}
fn d_one_f() -> f64 {
    1.0
}
fn d_silu() -> String {
    "silu".into()
}
fn d_groups() -> usize {
    32
}
fn d_eps() -> f64 {
    1e-5
}
fn d_cross() -> usize {
    1280
}
fn d_heads() -> PerBlock {
    PerBlock::One(8)
}
fn d_tlayers() -> PerBlock {
    PerBlock::One(1)
}
fn d_layers() -> PerBlock {
    PerBlock::One(2)
}
fn d_mid() -> Option<String> {
    Some("UNetMidBlock2DCrossAttn".into())
}
fn d_down() -> Vec<String> {
    vec![
        CROSS_ATTN_DOWN.into(),
        CROSS_ATTN_DOWN.into(),
        CROSS_ATTN_DOWN.into(),
        DOWN.into(),
    ]
}
fn d_up() -> Vec<String> {
    vec![
        UP.into(),
        CROSS_ATTN_UP.into(),
        CROSS_ATTN_UP.into(),
        CROSS_ATTN_UP.into(),
    ]
}
fn d_boc() -> Vec<usize> {
    vec![320, 640, 1280, 1280]
}

/// diffusers' `UNet2DConditionModel` configuration (the fields this implementation models).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UNetConfig {
    /// Always "UNet2DConditionModel".
    #[serde(rename = "_class_name", default = "unet_class")]
    pub class_name: String,
    /// Nominal latent size (informational).
    #[serde(default = "d_sample")]
    pub sample_size: usize,
    /// Input channels: 9 for inpainting (noisy latent 4 + mask 1 + masked-image latent 4).
    #[serde(default = "d_four")]
    pub in_channels: usize,
    /// Output channels (the predicted noise or v).
    #[serde(default = "d_four")]
    pub out_channels: usize,
    /// Scale the input by 2x - 1 first.
    #[serde(default)]
    pub center_input_sample: bool,
    /// Timestep embedding order: [cos, sin] when true.
    #[serde(default = "d_true")]
    pub flip_sin_to_cos: bool,
    /// Timestep embedding frequency shift.
    #[serde(default)]
    pub freq_shift: usize,
    /// Down block kinds, from the input resolution down.
    #[serde(default = "d_down")]
    pub down_block_types: Vec<String>,
    /// Middle block kind ("UNetMidBlock2DCrossAttn", or null for none).
    #[serde(default = "d_mid")]
    pub mid_block_type: Option<String>,
    /// Up block kinds, from the lowest resolution up.
    #[serde(default = "d_up")]
    pub up_block_types: Vec<String>,
    /// Channels of each level.
    #[serde(default = "d_boc")]
    pub block_out_channels: Vec<usize>,
    /// ResNets per down block (up blocks have one more).
    #[serde(default = "d_layers")]
    pub layers_per_block: PerBlock,
    /// Padding of the stride-2 down-sampling convolutions.
    #[serde(default = "d_one")]
    pub downsample_padding: usize,
    /// Output scale of the middle block's ResNets.
    #[serde(default = "d_one_f")]
    pub mid_block_scale_factor: f64,
    /// Activation ("silu").
    #[serde(default = "d_silu")]
    pub act_fn: String,
    /// GroupNorm groups.
    #[serde(default = "d_groups")]
    pub norm_num_groups: usize,
    /// GroupNorm epsilon.
    #[serde(default = "d_eps")]
    pub norm_eps: f64,
    /// Width of the conditioning tokens fed to cross-attention.
    #[serde(default = "d_cross")]
    pub cross_attention_dim: usize,
    /// Transformer blocks per attention layer.
    #[serde(default = "d_tlayers")]
    pub transformer_layers_per_block: PerBlock,
    /// diffusers' historical naming: when `num_attention_heads` is null this is the number of
    /// *heads* (SD 1.x: 8), as diffusers itself reads it.
    #[serde(default = "d_heads")]
    pub attention_head_dim: PerBlock,
    /// Heads per attention layer (overrides `attention_head_dim` when given).
    #[serde(default)]
    pub num_attention_heads: Option<PerBlock>,
    /// Linear instead of 1x1-convolution projections into and out of the transformers (SD 2).
    #[serde(default)]
    pub use_linear_projection: bool,
    /// Computes attention in f32 (all our attention is f32 already).
    #[serde(default)]
    pub upcast_attention: bool,
    /// Every other key of the file, checked by [`UNetConfig::validate`].
    #[serde(flatten)]
    pub other: Map<String, Value>,
}

/// Keys that are harmless whatever their value.
const INFORMATIONAL: &[&str] = &["_diffusers_version", "_name_or_path", "_use_default_values"];

/// Keys whose value must be the default because other values change the network in ways this
/// implementation does not model (name, allowed default values).
fn unet_fixed() -> Vec<(&'static str, Vec<Value>)> {
    use serde_json::json;
    vec![
        ("dropout", vec![json!(0.0), json!(0)]),
        ("only_cross_attention", vec![json!(false)]),
        ("dual_cross_attention", vec![json!(false)]),
        ("class_embed_type", vec![Value::Null]),
        ("addition_embed_type", vec![Value::Null]),
        ("addition_time_embed_dim", vec![Value::Null]),
        ("addition_embed_type_num_heads", vec![json!(64)]),
        ("num_class_embeds", vec![Value::Null]),
        ("class_embeddings_concat", vec![json!(false)]),
        ("projection_class_embeddings_input_dim", vec![Value::Null]),
        ("encoder_hid_dim", vec![Value::Null]),
        ("encoder_hid_dim_type", vec![Value::Null]),
        ("resnet_time_scale_shift", vec![json!("default")]),
        ("resnet_skip_time_act", vec![json!(false)]),
        ("resnet_out_scale_factor", vec![json!(1.0), json!(1)]),
        ("time_embedding_type", vec![json!("positional")]),
        ("time_embedding_dim", vec![Value::Null]),
        ("time_embedding_act_fn", vec![Value::Null]),
        ("timestep_post_act", vec![Value::Null]),
        ("time_cond_proj_dim", vec![Value::Null]),
        ("conv_in_kernel", vec![json!(3)]),
        ("conv_out_kernel", vec![json!(3)]),
        ("attention_type", vec![json!("default")]),
        ("cross_attention_norm", vec![Value::Null]),
        (
            "mid_block_only_cross_attention",
            vec![Value::Null, json!(false)],
        ),
        ("reverse_transformer_layers_per_block", vec![Value::Null]),
    ]
}

fn vae_fixed() -> Vec<(&'static str, Vec<Value>)> {
    use serde_json::json;
    vec![
        ("shift_factor", vec![Value::Null, json!(0.0)]),
        ("latents_mean", vec![Value::Null]),
        ("latents_std", vec![Value::Null]),
        ("use_quant_conv", vec![json!(true)]),
        ("use_post_quant_conv", vec![json!(true)]),
        ("mid_block_add_attention", vec![json!(true)]),
    ]
}

/// Keys of the VAE that only matter to diffusers' pipelines (precision, tiling).
const VAE_INFORMATIONAL: &[&str] = &["force_upcast", "sample_size"];

fn check_other(
    other: &Map<String, Value>,
    fixed: &[(&str, Vec<Value>)],
    extra_ok: &[&str],
    what: &str,
) -> Result<(), String> {
    for (k, v) in other {
        if INFORMATIONAL.contains(&k.as_str()) || extra_ok.contains(&k.as_str()) {
            continue;
        }
        match fixed.iter().find(|(name, _)| name == k) {
            Some((_, allowed)) if allowed.contains(v) => {}
            Some((_, allowed)) => {
                return Err(format!(
                    "{k} = {v} is not supported by this {what} (supported: {})",
                    allowed
                        .iter()
                        .map(|a| a.to_string())
                        .collect::<Vec<_>>()
                        .join(" or ")
                ))
            }
            None => return Err(format!("unknown key {k:?} for a {what}")),
        }
    }
    Ok(())
}

impl Default for UNetConfig {
    /// Stable Diffusion 1.5's U-Net with 4 input channels (diffusers' defaults).
    fn default() -> Self {
        serde_json::from_str("{}").unwrap_or_else(|_| unreachable!("all fields have defaults"))
    }
}

impl UNetConfig {
    /// Stable Diffusion 1.5 inpainting (runwayml/stable-diffusion-inpainting `unet/config.json`).
    pub fn sd15_inpainting() -> UNetConfig {
        UNetConfig {
            in_channels: 9,
            cross_attention_dim: 768,
            ..UNetConfig::default()
        }
    }

    /// Stable Diffusion 2 inpainting (stabilityai/stable-diffusion-2-inpainting): linear
    /// projections, 1024-wide conditioning, heads of 64 channels.
    pub fn sd2_inpainting() -> UNetConfig {
        UNetConfig {
            in_channels: 9,
            cross_attention_dim: 1024,
            attention_head_dim: PerBlock::Many(vec![5, 10, 20, 20]),
            use_linear_projection: true,
            ..UNetConfig::default()
        }
    }

    /// The pixel-space U-Net this project trains from scratch (the scene prior, the
    /// enhancer): DownBlock2D levels of `channels`, attention (self and cross, `token_dim`
    /// wide context) on the last level and in the middle block, 7 inputs (noisy RGB, mask,
    /// guidance RGB), 3 outputs.
    pub fn pixel_space(channels: &[usize], token_dim: usize) -> Result<UNetConfig, String> {
        let n = channels.len();
        if n < 2 {
            return Err(format!("needs at least two levels, got {channels:?}"));
        }
        let mut down = vec![DOWN.to_string(); n];
        down[n - 1] = CROSS_ATTN_DOWN.into();
        let mut up = vec![UP.to_string(); n];
        up[0] = CROSS_ATTN_UP.into();
        let c = UNetConfig {
            sample_size: 48,
            in_channels: 7,
            out_channels: 3,
            down_block_types: down,
            up_block_types: up,
            block_out_channels: channels.to_vec(),
            layers_per_block: PerBlock::One(1),
            norm_num_groups: 8,
            cross_attention_dim: token_dim,
            attention_head_dim: PerBlock::One(4),
            ..UNetConfig::default()
        };
        c.validate()?;
        Ok(c)
    }

    /// A tiny inpainting U-Net with the same structure (two levels, one ResNet each, 2-head
    /// attention), for tests and the benches' small row.
    pub fn tiny_inpainting() -> UNetConfig {
        UNetConfig {
            sample_size: 16,
            in_channels: 9,
            down_block_types: vec![CROSS_ATTN_DOWN.into(), DOWN.into()],
            up_block_types: vec![UP.into(), CROSS_ATTN_UP.into()],
            block_out_channels: vec![32, 64],
            layers_per_block: PerBlock::One(1),
            norm_num_groups: 8,
            cross_attention_dim: 32,
            attention_head_dim: PerBlock::One(2),
            ..UNetConfig::default()
        }
    }

    /// Parses and validates a `config.json`.
    pub fn from_file(path: &Path) -> Result<UNetConfig, DiffusionError> {
        let c: UNetConfig = read_json(path)?;
        c.validate().map_err(|problem| DiffusionError::Config {
            path: path.to_path_buf(),
            problem,
        })?;
        Ok(c)
    }

    /// Writes `config.json` (diffusers format).
    pub fn save(&self, path: &Path) -> Result<(), DiffusionError> {
        write_json(path, self)
    }

    /// Number of levels.
    pub fn levels(&self) -> usize {
        self.block_out_channels.len()
    }

    /// Heads of the attention layers of level `i`.
    pub fn heads(&self, i: usize) -> usize {
        self.num_attention_heads
            .as_ref()
            .unwrap_or(&self.attention_head_dim)
            .get(i)
    }

    /// Whether down level `i` has attention.
    pub fn down_has_attention(&self, i: usize) -> bool {
        self.down_block_types[i] == CROSS_ATTN_DOWN
    }

    /// Whether the middle block exists.
    pub fn has_mid(&self) -> bool {
        self.mid_block_type.is_some()
    }

    /// Checks every field against what the implementation models; the message names the key.
    pub fn validate(&self) -> Result<(), String> {
        if self.class_name != "UNet2DConditionModel" {
            return Err(format!(
                "_class_name is {:?}, expected \"UNet2DConditionModel\"",
                self.class_name
            ));
        }
        check_other(&self.other, &unet_fixed(), &[], "UNet2DConditionModel")?;
        let n = self.levels();
        if n == 0 {
            return Err("block_out_channels is empty".into());
        }
        if self.down_block_types.len() != n || self.up_block_types.len() != n {
            return Err(format!(
                "down_block_types ({}) and up_block_types ({}) must have one entry per block_out_channels ({n})",
                self.down_block_types.len(),
                self.up_block_types.len()
            ));
        }
        for (i, t) in self.down_block_types.iter().enumerate() {
            if t != CROSS_ATTN_DOWN && t != DOWN {
                return Err(format!("down_block_types[{i}] = {t:?} is not supported (supported: {CROSS_ATTN_DOWN}, {DOWN})"));
            }
        }
        for (i, t) in self.up_block_types.iter().enumerate() {
            if t != CROSS_ATTN_UP && t != UP {
                return Err(format!(
                    "up_block_types[{i}] = {t:?} is not supported (supported: {CROSS_ATTN_UP}, {UP})"
                ));
            }
            // Up block i mirrors down block n - 1 - i.
            let mirrored = self.down_has_attention(n - 1 - i);
            if (t == CROSS_ATTN_UP) != mirrored {
                return Err(format!(
                    "up_block_types[{i}] = {t:?} does not mirror down_block_types[{}] = {:?}",
                    n - 1 - i,
                    self.down_block_types[n - 1 - i]
                ));
            }
        }
        match self.mid_block_type.as_deref() {
            None | Some("UNetMidBlock2DCrossAttn") => {}
            Some(t) => {
                return Err(format!(
                    "mid_block_type = {t:?} is not supported (supported: UNetMidBlock2DCrossAttn or null)"
                ))
            }
        }
        if self.act_fn != "silu" {
            return Err(format!(
                "act_fn = {:?} is not supported (supported: silu)",
                self.act_fn
            ));
        }
        for (name, p) in [
            ("layers_per_block", &self.layers_per_block),
            ("attention_head_dim", &self.attention_head_dim),
            (
                "transformer_layers_per_block",
                &self.transformer_layers_per_block,
            ),
        ] {
            if !p.len_ok(n) {
                return Err(format!("{name} must be one number or one per block ({n})"));
            }
        }
        if self.num_attention_heads.is_some() {
            // diffusers' UNet2DConditionModel refuses it too (attention_head_dim is the head
            // count there, for historical reasons).
            return Err(
                "num_attention_heads must be null for UNet2DConditionModel (diffusers reads the head count from attention_head_dim)".into(),
            );
        }
        if self.in_channels == 0 || self.out_channels == 0 || self.cross_attention_dim == 0 {
            return Err("in_channels, out_channels and cross_attention_dim must be > 0".into());
        }
        if self.block_out_channels[0] < 2 {
            return Err(
                "block_out_channels[0] must be at least 2 (the timestep embedding width)".into(),
            );
        }
        for (i, &c) in self.block_out_channels.iter().enumerate() {
            let g = self.norm_num_groups;
            if c == 0 {
                return Err(format!("block_out_channels[{i}] is 0"));
            }
            if g == 0 || c % g != 0 {
                return Err(format!(
                    "block_out_channels[{i}] = {c} is not a multiple of norm_num_groups = {g}"
                ));
            }
            let layers = self.layers_per_block.get(i);
            if layers == 0 {
                return Err(format!("layers_per_block[{i}] must be > 0"));
            }
            let uses_attention = self.down_has_attention(i) || (i == n - 1 && self.has_mid());
            if uses_attention {
                let h = self.heads(i);
                if h == 0 || c % h != 0 {
                    return Err(format!(
                        "block_out_channels[{i}] = {c} is not a multiple of the {h} attention heads"
                    ));
                }
                if self.transformer_layers_per_block.get(i) == 0 {
                    return Err(format!("transformer_layers_per_block[{i}] must be > 0"));
                }
            }
        }
        if self.freq_shift > 0 && self.block_out_channels[0] / 2 <= self.freq_shift {
            return Err("freq_shift must be below half of block_out_channels[0]".into());
        }
        if !(self.norm_eps.is_finite() && self.norm_eps > 0.0) {
            return Err("norm_eps must be > 0".into());
        }
        Ok(())
    }

    /// The latent side must be a multiple of this (one halving per level but the last).
    pub fn size_multiple(&self) -> usize {
        1 << (self.levels() - 1)
    }
}

/// diffusers' `AutoencoderKL` configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VaeConfig {
    /// Always "AutoencoderKL".
    #[serde(rename = "_class_name", default = "vae_class")]
    pub class_name: String,
    /// Image channels in.
    #[serde(default = "d_three")]
    pub in_channels: usize,
    /// Image channels out.
    #[serde(default = "d_three")]
    pub out_channels: usize,
    /// "DownEncoderBlock2D" per level.
    #[serde(default = "vae_down")]
    pub down_block_types: Vec<String>,
    /// "UpDecoderBlock2D" per level.
    #[serde(default = "vae_up")]
    pub up_block_types: Vec<String>,
    /// Channels per level.
    #[serde(default = "vae_boc")]
    pub block_out_channels: Vec<usize>,
    /// ResNets per encoder level (decoder levels have one more).
    #[serde(default = "d_one")]
    pub layers_per_block: usize,
    /// Activation ("silu").
    #[serde(default = "d_silu")]
    pub act_fn: String,
    /// Latent channels.
    #[serde(default = "d_four")]
    pub latent_channels: usize,
    /// GroupNorm groups.
    #[serde(default = "d_groups")]
    pub norm_num_groups: usize,
    /// Latents are multiplied by this before diffusion (SD: 0.18215).
    #[serde(default = "d_scaling")]
    pub scaling_factor: f64,
    /// Every other key, checked by [`VaeConfig::validate`].
    #[serde(flatten)]
    pub other: Map<String, Value>,
}

// diffusers' AutoencoderKL defaults (one level of 64 channels); SD's are VaeConfig::sd().
fn vae_down() -> Vec<String> {
    vec!["DownEncoderBlock2D".into()]
}
fn vae_up() -> Vec<String> {
    vec!["UpDecoderBlock2D".into()]
}
fn vae_boc() -> Vec<usize> {
    vec![64]
}
fn d_scaling() -> f64 {
    0.18215
}

impl Default for VaeConfig {
    /// diffusers' AutoencoderKL defaults (what a config.json that omits a key means).
    fn default() -> Self {
        serde_json::from_str("{}").unwrap_or_else(|_| unreachable!("all fields have defaults"))
    }
}

impl VaeConfig {
    /// Stable Diffusion's VAE (f = 8, 4 latent channels, 128/256/512/512).
    pub fn sd() -> VaeConfig {
        VaeConfig {
            down_block_types: vec!["DownEncoderBlock2D".into(); 4],
            up_block_types: vec!["UpDecoderBlock2D".into(); 4],
            block_out_channels: vec![128, 256, 512, 512],
            layers_per_block: 2,
            ..VaeConfig::default()
        }
    }

    /// A tiny VAE with the same structure (f = 4: three levels of 16/32/32 channels, 4
    /// latent channels), for tests and benches.
    pub fn tiny() -> VaeConfig {
        VaeConfig {
            down_block_types: vec!["DownEncoderBlock2D".into(); 3],
            up_block_types: vec!["UpDecoderBlock2D".into(); 3],
            block_out_channels: vec![16, 32, 32],
            layers_per_block: 1,
            norm_num_groups: 8,
            ..VaeConfig::sd()
        }
    }

    /// Parses and validates a `config.json`.
    pub fn from_file(path: &Path) -> Result<VaeConfig, DiffusionError> {
        let c: VaeConfig = read_json(path)?;
        c.validate().map_err(|problem| DiffusionError::Config {
            path: path.to_path_buf(),
            problem,
        })?;
        Ok(c)
    }

    /// Writes `config.json` (diffusers format).
    pub fn save(&self, path: &Path) -> Result<(), DiffusionError> {
        write_json(path, self)
    }

    /// Spatial down-sampling factor image -> latent.
    pub fn factor(&self) -> usize {
        1 << (self.block_out_channels.len() - 1)
    }

    /// Checks every field; the message names the key.
    pub fn validate(&self) -> Result<(), String> {
        if self.class_name != "AutoencoderKL" {
            return Err(format!(
                "_class_name is {:?}, expected \"AutoencoderKL\"",
                self.class_name
            ));
        }
        check_other(
            &self.other,
            &vae_fixed(),
            VAE_INFORMATIONAL,
            "AutoencoderKL",
        )?;
        let n = self.block_out_channels.len();
        if n == 0 {
            return Err("block_out_channels is empty".into());
        }
        if self.down_block_types.len() != n || self.up_block_types.len() != n {
            return Err(format!(
                "down_block_types and up_block_types must have {n} entries"
            ));
        }
        if let Some(t) = self
            .down_block_types
            .iter()
            .find(|t| *t != "DownEncoderBlock2D")
        {
            return Err(format!(
                "down block {t:?} is not supported (supported: DownEncoderBlock2D)"
            ));
        }
        if let Some(t) = self
            .up_block_types
            .iter()
            .find(|t| *t != "UpDecoderBlock2D")
        {
            return Err(format!(
                "up block {t:?} is not supported (supported: UpDecoderBlock2D)"
            ));
        }
        if self.act_fn != "silu" {
            return Err(format!(
                "act_fn = {:?} is not supported (supported: silu)",
                self.act_fn
            ));
        }
        if self.layers_per_block == 0
            || self.latent_channels == 0
            || self.in_channels == 0
            || self.out_channels == 0
        {
            return Err(
                "layers_per_block, latent_channels, in_channels and out_channels must be > 0"
                    .into(),
            );
        }
        for (i, &c) in self.block_out_channels.iter().enumerate() {
            if c == 0 {
                return Err(format!("block_out_channels[{i}] is 0"));
            }
            if self.norm_num_groups == 0 || c % self.norm_num_groups != 0 {
                return Err(format!(
                    "block_out_channels[{i}] = {c} is not a multiple of norm_num_groups = {}",
                    self.norm_num_groups
                ));
            }
        }
        if !(self.scaling_factor.is_finite() && self.scaling_factor > 0.0) {
            return Err("scaling_factor must be finite and > 0".into());
        }
        Ok(())
    }
}

pub(crate) fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, DiffusionError> {
    let text = std::fs::read_to_string(path).map_err(|e| DiffusionError::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| DiffusionError::Config {
        path: path.to_path_buf(),
        problem: e.to_string(),
    })
}

pub(crate) fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), DiffusionError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| DiffusionError::Config {
        path: path.to_path_buf(),
        problem: e.to_string(),
    })?;
    crate::write_atomic(path, text.as_bytes())
}
