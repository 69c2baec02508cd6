//! diffusers' `UNet2DConditionModel`: the latent-diffusion (inpainting) U-Net.
//!
//! Structure and parameter names follow diffusers exactly (`conv_in`, `time_embedding.linear_1`,
//! `down_blocks.{i}.resnets.{j}`, `down_blocks.{i}.attentions.{j}`,
//! `down_blocks.{i}.downsamplers.0.conv`, `mid_block`, `up_blocks`, `conv_norm_out`, `conv_out`),
//! so a diffusers checkpoint loads into it and the same code builds SD-1.5/2 inpainting shapes
//! and the tiny models this project trains.

use burn::module::Module;
use burn::nn::GroupNorm;
use burn::tensor::activation::silu;
use burn::tensor::{Device, Tensor};

use crate::blocks::{
    group_norm, timestep_embedding, Downsample2D, ResnetBlock2D, TimestepEmbedding,
    Transformer2DModel, Upsample2D,
};
use crate::config::{UNetConfig, CROSS_ATTN_UP};
use crate::layers::Conv2d;
use crate::DiffusionError;

/// A down block (`CrossAttnDownBlock2D` when `attentions` is not empty, else `DownBlock2D`).
#[derive(Module, Debug)]
pub struct DownBlock {
    /// ResNets.
    pub resnets: Vec<ResnetBlock2D>,
    /// One transformer after each ResNet (empty for DownBlock2D).
    pub attentions: Vec<Transformer2DModel>,
    /// The stride-2 convolution (absent on the last level).
    pub downsamplers: Vec<Downsample2D>,
}

/// An up block (`CrossAttnUpBlock2D` when `attentions` is not empty, else `UpBlock2D`).
#[derive(Module, Debug)]
pub struct UpBlock {
    /// ResNets, each fed the previous output concatenated with one skip.
    pub resnets: Vec<ResnetBlock2D>,
    /// One transformer after each ResNet (empty for UpBlock2D).
    pub attentions: Vec<Transformer2DModel>,
    /// Nearest 2x + convolution (absent on the last level).
    pub upsamplers: Vec<Upsample2D>,
}

/// `UNetMidBlock2DCrossAttn`: ResNet, then (transformer, ResNet) pairs.
#[derive(Module, Debug)]
pub struct MidBlock {
    /// ResNets (one more than attentions).
    pub resnets: Vec<ResnetBlock2D>,
    /// Transformers between them.
    pub attentions: Vec<Transformer2DModel>,
}

/// The conditional U-Net.
#[derive(Module, Debug)]
pub struct UNet2DConditionModel {
    /// 3x3 input convolution.
    pub conv_in: Conv2d,
    /// MLP on the sinusoidal timestep embedding.
    pub time_embedding: TimestepEmbedding,
    /// Down levels.
    pub down_blocks: Vec<DownBlock>,
    /// Middle block (absent when mid_block_type is null).
    pub mid_block: Option<MidBlock>,
    /// Up levels.
    pub up_blocks: Vec<UpBlock>,
    /// Output GroupNorm.
    pub conv_norm_out: GroupNorm,
    /// 3x3 output convolution.
    pub conv_out: Conv2d,
    /// Timestep embedding: [cos, sin] order.
    pub flip_sin_to_cos: bool,
    /// Timestep embedding frequency shift.
    pub freq_shift: usize,
    /// Scale the input by 2x - 1.
    pub center_input_sample: bool,
    /// Conditioning width expected by cross-attention.
    pub cross_attention_dim: usize,
}

impl UNet2DConditionModel {
    /// Builds the network of a validated config (parameters are initialised lazily, so even
    /// SD-1.5's shapes cost no memory until used).
    pub fn new(c: &UNetConfig, device: &Device) -> Result<UNet2DConditionModel, DiffusionError> {
        c.validate().map_err(DiffusionError::InvalidConfig)?;
        let boc = &c.block_out_channels;
        let n = boc.len();
        let temb = 4 * boc[0];
        let g = c.norm_num_groups;
        let eps = c.norm_eps;
        let transformer = |ch: usize, level: usize| {
            Transformer2DModel::new(
                ch,
                c.heads(level),
                c.transformer_layers_per_block.get(level),
                c.cross_attention_dim,
                g,
                c.use_linear_projection,
                device,
            )
        };
        let mut down_blocks = Vec::with_capacity(n);
        let mut out_ch = boc[0];
        for (i, &ch) in boc.iter().enumerate() {
            let in_ch = out_ch;
            out_ch = ch;
            let layers = c.layers_per_block.get(i);
            let attn = c.down_has_attention(i);
            down_blocks.push(DownBlock {
                resnets: (0..layers)
                    .map(|j| {
                        let cin = if j == 0 { in_ch } else { out_ch };
                        ResnetBlock2D::new(cin, out_ch, Some(temb), g, eps, 1.0, device)
                    })
                    .collect(),
                attentions: if attn {
                    (0..layers).map(|_| transformer(out_ch, i)).collect()
                } else {
                    Vec::new()
                },
                downsamplers: if i + 1 < n {
                    vec![Downsample2D::new(out_ch, c.downsample_padding, device)]
                } else {
                    Vec::new()
                },
            });
        }
        let last = boc[n - 1];
        let mid_block = c.has_mid().then(|| MidBlock {
            resnets: (0..2)
                .map(|_| {
                    ResnetBlock2D::new(
                        last,
                        last,
                        Some(temb),
                        g,
                        eps,
                        c.mid_block_scale_factor,
                        device,
                    )
                })
                .collect(),
            attentions: vec![transformer(last, n - 1)],
        });
        let mut up_blocks = Vec::with_capacity(n);
        let mut out_ch = boc[n - 1];
        for i in 0..n {
            let level = n - 1 - i;
            let prev_out = out_ch;
            out_ch = boc[level];
            let in_ch = boc[level.saturating_sub(1)];
            let layers = c.layers_per_block.get(level) + 1;
            let attn = c.up_block_types[i] == CROSS_ATTN_UP;
            up_blocks.push(UpBlock {
                resnets: (0..layers)
                    .map(|j| {
                        let skip = if j == layers - 1 { in_ch } else { out_ch };
                        let cin = if j == 0 { prev_out } else { out_ch };
                        ResnetBlock2D::new(cin + skip, out_ch, Some(temb), g, eps, 1.0, device)
                    })
                    .collect(),
                attentions: if attn {
                    (0..layers).map(|_| transformer(out_ch, level)).collect()
                } else {
                    Vec::new()
                },
                upsamplers: if i + 1 < n {
                    vec![Upsample2D::new(out_ch, device)]
                } else {
                    Vec::new()
                },
            });
        }
        Ok(UNet2DConditionModel {
            conv_in: Conv2d::new(c.in_channels, boc[0], 3, 1, 1, device),
            time_embedding: TimestepEmbedding::new(boc[0], temb, device),
            down_blocks,
            mid_block,
            up_blocks,
            conv_norm_out: group_norm(g, boc[0], eps, device),
            conv_out: Conv2d::new(boc[0], c.out_channels, 3, 1, 1, device),
            flip_sin_to_cos: c.flip_sin_to_cos,
            freq_shift: c.freq_shift,
            center_input_sample: c.center_input_sample,
            cross_attention_dim: c.cross_attention_dim,
        })
    }

    /// Input channels.
    pub fn in_channels(&self) -> usize {
        self.conv_in.dims()[1]
    }

    /// Output channels.
    pub fn out_channels(&self) -> usize {
        self.conv_out.dims()[0]
    }

    /// `sample [n, in_channels, h, w]` (h, w multiples of 2^(levels - 1)), one timestep per
    /// item, `context [n, s, cross_attention_dim]` -> `[n, out_channels, h, w]`.
    pub fn forward(&self, sample: Tensor<4>, timesteps: &[f32], context: &Tensor<3>) -> Tensor<4> {
        let device = sample.device();
        let [n, _, _, _] = sample.dims();
        assert_eq!(timesteps.len(), n, "one timestep per batch item");
        let t = timestep_embedding(
            timesteps,
            self.conv_in.dims()[0],
            self.flip_sin_to_cos,
            self.freq_shift,
            &device,
        );
        let emb = self.time_embedding.forward(t);
        let sample = if self.center_input_sample {
            sample * 2.0 - 1.0
        } else {
            sample
        };
        let mut h = self.conv_in.forward(sample);
        let mut skips = vec![h.clone()];
        for block in &self.down_blocks {
            for (j, resnet) in block.resnets.iter().enumerate() {
                h = resnet.forward(h, Some(&emb));
                if let Some(attn) = block.attentions.get(j) {
                    h = attn.forward(h, context);
                }
                skips.push(h.clone());
            }
            for down in &block.downsamplers {
                h = down.forward(h);
                skips.push(h.clone());
            }
        }
        if let Some(mid) = &self.mid_block {
            h = mid.resnets[0].forward(h, Some(&emb));
            for (attn, resnet) in mid.attentions.iter().zip(&mid.resnets[1..]) {
                h = attn.forward(h, context);
                h = resnet.forward(h, Some(&emb));
            }
        }
        for block in &self.up_blocks {
            for (j, resnet) in block.resnets.iter().enumerate() {
                let skip = skips
                    .pop()
                    .unwrap_or_else(|| unreachable!("one skip per up ResNet"));
                h = resnet.forward(Tensor::cat(vec![h, skip], 1), Some(&emb));
                if let Some(attn) = block.attentions.get(j) {
                    h = attn.forward(h, context);
                }
            }
            for up in &block.upsamplers {
                // Upsample to the next skip's size (diffusers' forward_upsample_size).
                let size = skips.last().map(|s| {
                    let d = s.dims();
                    [d[2], d[3]]
                });
                h = up.forward(h, size);
            }
        }
        self.conv_out.forward(silu(self.conv_norm_out.forward(h)))
    }

    /// Multiply-adds of one forward for one item at `h x w` with `s` context tokens.
    pub fn macs(&self, h: usize, w: usize, s: usize) -> u64 {
        let mut total = self.conv_in.macs(h, w)
            + self.time_embedding.linear_1.macs(1)
            + self.time_embedding.linear_2.macs(1);
        let (mut ch, mut cw) = (h, w);
        let mut sizes = vec![(ch, cw)];
        for block in &self.down_blocks {
            for (j, r) in block.resnets.iter().enumerate() {
                total += r.macs(ch, cw);
                if let Some(a) = block.attentions.get(j) {
                    total += a.macs(ch, cw, s);
                }
                sizes.push((ch, cw));
            }
            for d in &block.downsamplers {
                total += d.conv.macs(ch, cw);
                (ch, cw) = d.conv.out_size(ch, cw);
                sizes.push((ch, cw));
            }
        }
        if let Some(mid) = &self.mid_block {
            total += mid.resnets.iter().map(|r| r.macs(ch, cw)).sum::<u64>();
            total += mid
                .attentions
                .iter()
                .map(|a| a.macs(ch, cw, s))
                .sum::<u64>();
        }
        for block in &self.up_blocks {
            for (j, r) in block.resnets.iter().enumerate() {
                sizes.pop();
                total += r.macs(ch, cw);
                if let Some(a) = block.attentions.get(j) {
                    total += a.macs(ch, cw, s);
                }
            }
            for u in &block.upsamplers {
                (ch, cw) = sizes.last().copied().unwrap_or((2 * ch, 2 * cw));
                total += u.conv.macs(ch, cw);
            }
        }
        total + self.conv_out.macs(h, w)
    }
}
