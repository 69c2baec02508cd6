//! diffusers' `AutoencoderKL`: the encoder and decoder between images and latents.
//!
//! Parameter names follow diffusers (`encoder.down_blocks.{i}.resnets.{j}`,
//! `encoder.mid_block.attentions.0.to_q`, `quant_conv`, `post_quant_conv`, `decoder.up_blocks`,
//! ...). Latents are scaled by `scaling_factor` (SD: 0.18215) on the way into diffusion.

use burn::module::Module;
use burn::nn::GroupNorm;
use burn::tensor::activation::silu;
use burn::tensor::{Device, Distribution, Tensor};

use crate::blocks::{group_norm, Attention, Downsample2D, ResnetBlock2D, Upsample2D};
use crate::config::VaeConfig;
use crate::layers::Conv2d;
use crate::DiffusionError;

const EPS: f64 = 1e-6;

/// `DownEncoderBlock2D`.
#[derive(Module, Debug)]
pub struct EncoderBlock {
    /// ResNets without timestep embedding.
    pub resnets: Vec<ResnetBlock2D>,
    /// Stride-2 convolution with (0, 1, 0, 1) padding (absent on the last level).
    pub downsamplers: Vec<Downsample2D>,
}

/// `UpDecoderBlock2D`.
#[derive(Module, Debug)]
pub struct DecoderBlock {
    /// ResNets without timestep embedding.
    pub resnets: Vec<ResnetBlock2D>,
    /// Nearest 2x + convolution (absent on the last level).
    pub upsamplers: Vec<Upsample2D>,
}

/// `UNetMidBlock2D` of the VAE: ResNet, single-head attention, ResNet.
#[derive(Module, Debug)]
pub struct VaeMidBlock {
    /// Two ResNets.
    pub resnets: Vec<ResnetBlock2D>,
    /// One spatial attention.
    pub attentions: Vec<Attention>,
}

impl VaeMidBlock {
    fn new(c: usize, groups: usize, device: &Device) -> VaeMidBlock {
        VaeMidBlock {
            resnets: (0..2)
                .map(|_| ResnetBlock2D::new(c, c, None, groups, EPS, 1.0, device))
                .collect(),
            attentions: vec![Attention::vae(c, groups, EPS, device)],
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let mut h = self.resnets[0].forward(x, None);
        for (a, r) in self.attentions.iter().zip(&self.resnets[1..]) {
            h = r.forward(a.forward_spatial(h), None);
        }
        h
    }

    fn macs(&self, h: usize, w: usize) -> u64 {
        self.resnets.iter().map(|r| r.macs(h, w)).sum::<u64>()
            + self
                .attentions
                .iter()
                .map(|a| a.macs(h * w, h * w))
                .sum::<u64>()
    }
}

/// The encoder: image -> (mean, log-variance) of the latent.
#[derive(Module, Debug)]
pub struct Encoder {
    /// 3x3 input convolution.
    pub conv_in: Conv2d,
    /// Down levels.
    pub down_blocks: Vec<EncoderBlock>,
    /// Middle block.
    pub mid_block: VaeMidBlock,
    /// Output GroupNorm.
    pub conv_norm_out: GroupNorm,
    /// 3x3 output convolution to 2 * latent channels.
    pub conv_out: Conv2d,
}

/// The decoder: latent -> image.
#[derive(Module, Debug)]
pub struct Decoder {
    /// 3x3 input convolution.
    pub conv_in: Conv2d,
    /// Middle block.
    pub mid_block: VaeMidBlock,
    /// Up levels.
    pub up_blocks: Vec<DecoderBlock>,
    /// Output GroupNorm.
    pub conv_norm_out: GroupNorm,
    /// 3x3 output convolution to image channels.
    pub conv_out: Conv2d,
}

/// The autoencoder.
#[derive(Module, Debug)]
pub struct AutoencoderKL {
    /// Image -> moments.
    pub encoder: Encoder,
    /// Latent -> image.
    pub decoder: Decoder,
    /// 1x1 on the moments.
    pub quant_conv: Conv2d,
    /// 1x1 on the latent before decoding.
    pub post_quant_conv: Conv2d,
    /// Latent scale factor.
    pub scaling_factor: f64,
}

impl AutoencoderKL {
    /// Builds the network of a validated config (lazy parameters).
    pub fn new(c: &VaeConfig, device: &Device) -> Result<AutoencoderKL, DiffusionError> {
        c.validate().map_err(DiffusionError::InvalidConfig)?;
        let boc = &c.block_out_channels;
        let n = boc.len();
        let g = c.norm_num_groups;
        let lat = c.latent_channels;
        let mut down_blocks = Vec::with_capacity(n);
        let mut out_ch = boc[0];
        for (i, &ch) in boc.iter().enumerate() {
            let in_ch = out_ch;
            out_ch = ch;
            down_blocks.push(EncoderBlock {
                resnets: (0..c.layers_per_block)
                    .map(|j| {
                        let cin = if j == 0 { in_ch } else { out_ch };
                        ResnetBlock2D::new(cin, out_ch, None, g, EPS, 1.0, device)
                    })
                    .collect(),
                downsamplers: if i + 1 < n {
                    vec![Downsample2D::new(out_ch, 0, device)]
                } else {
                    Vec::new()
                },
            });
        }
        let top = boc[n - 1];
        let encoder = Encoder {
            conv_in: Conv2d::new(c.in_channels, boc[0], 3, 1, 1, device),
            down_blocks,
            mid_block: VaeMidBlock::new(top, g, device),
            conv_norm_out: group_norm(g, top, EPS, device),
            conv_out: Conv2d::new(top, 2 * lat, 3, 1, 1, device),
        };
        let mut up_blocks = Vec::with_capacity(n);
        let mut out_ch = top;
        for i in 0..n {
            let prev = out_ch;
            out_ch = boc[n - 1 - i];
            up_blocks.push(DecoderBlock {
                resnets: (0..c.layers_per_block + 1)
                    .map(|j| {
                        let cin = if j == 0 { prev } else { out_ch };
                        ResnetBlock2D::new(cin, out_ch, None, g, EPS, 1.0, device)
                    })
                    .collect(),
                upsamplers: if i + 1 < n {
                    vec![Upsample2D::new(out_ch, device)]
                } else {
                    Vec::new()
                },
            });
        }
        let decoder = Decoder {
            conv_in: Conv2d::new(lat, top, 3, 1, 1, device),
            mid_block: VaeMidBlock::new(top, g, device),
            up_blocks,
            conv_norm_out: group_norm(g, boc[0], EPS, device),
            conv_out: Conv2d::new(boc[0], c.out_channels, 3, 1, 1, device),
        };
        Ok(AutoencoderKL {
            encoder,
            decoder,
            quant_conv: Conv2d::new(2 * lat, 2 * lat, 1, 1, 0, device),
            post_quant_conv: Conv2d::new(lat, lat, 1, 1, 0, device),
            scaling_factor: c.scaling_factor,
        })
    }

    /// Latent channels.
    pub fn latent_channels(&self) -> usize {
        self.post_quant_conv.dims()[0]
    }

    /// Image -> latent down-sampling factor.
    pub fn factor(&self) -> usize {
        1 << self
            .encoder
            .down_blocks
            .iter()
            .filter(|b| !b.downsamplers.is_empty())
            .count()
    }

    /// `image [n, 3, h, w]` in [-1, 1] -> (mean, log-variance clamped to [-30, 20]), each
    /// `[n, latent, h / f, w / f]`, unscaled.
    pub fn encode_moments(&self, image: Tensor<4>) -> (Tensor<4>, Tensor<4>) {
        let e = &self.encoder;
        let mut h = e.conv_in.forward(image);
        for b in &e.down_blocks {
            for r in &b.resnets {
                h = r.forward(h, None);
            }
            for d in &b.downsamplers {
                h = d.forward(h);
            }
        }
        let h = e.mid_block.forward(h);
        let h = e.conv_out.forward(silu(e.conv_norm_out.forward(h)));
        let moments = self.quant_conv.forward(h);
        let mut parts = moments.chunk(2, 1);
        let logvar = parts
            .pop()
            .unwrap_or_else(|| unreachable!("chunk(2) gives 2"))
            .clamp(-30.0, 20.0);
        let mean = parts
            .pop()
            .unwrap_or_else(|| unreachable!("chunk(2) gives 2"));
        (mean, logvar)
    }

    /// Image in [-1, 1] -> *scaled* latent: the mean (`sample = false`) or a draw from the
    /// posterior, times `scaling_factor`.
    pub fn encode(&self, image: Tensor<4>, sample: bool) -> Tensor<4> {
        let (mean, logvar) = self.encode_moments(image);
        let z = if sample {
            let std = (logvar * 0.5).exp();
            let eps = mean.random_like(Distribution::Normal(0.0, 1.0));
            mean + std * eps
        } else {
            mean
        };
        z * self.scaling_factor
    }

    /// *Scaled* latent -> image in about [-1, 1].
    pub fn decode(&self, latent: Tensor<4>) -> Tensor<4> {
        let d = &self.decoder;
        let z = self.post_quant_conv.forward(latent / self.scaling_factor);
        let mut h = d.mid_block.forward(d.conv_in.forward(z));
        for b in &d.up_blocks {
            for r in &b.resnets {
                h = r.forward(h, None);
            }
            for u in &b.upsamplers {
                h = u.forward(h, None);
            }
        }
        d.conv_out.forward(silu(d.conv_norm_out.forward(h)))
    }

    /// Multiply-adds of encode + decode of one `h x w` image.
    pub fn macs(&self, h: usize, w: usize) -> u64 {
        let e = &self.encoder;
        let mut total = e.conv_in.macs(h, w);
        let (mut ch, mut cw) = (h, w);
        for b in &e.down_blocks {
            total += b.resnets.iter().map(|r| r.macs(ch, cw)).sum::<u64>();
            for d in &b.downsamplers {
                total += d.conv.macs(ch, cw);
                (ch, cw) = d.conv.out_size(ch, cw);
            }
        }
        total += e.mid_block.macs(ch, cw) + e.conv_out.macs(ch, cw);
        total += self.quant_conv.macs(ch, cw) + self.post_quant_conv.macs(ch, cw);
        let d = &self.decoder;
        total += d.conv_in.macs(ch, cw) + d.mid_block.macs(ch, cw);
        for b in &d.up_blocks {
            total += b.resnets.iter().map(|r| r.macs(ch, cw)).sum::<u64>();
            for u in &b.upsamplers {
                (ch, cw) = (2 * ch, 2 * cw);
                total += u.conv.macs(ch, cw);
            }
        }
        total + d.conv_out.macs(ch, cw)
    }
}
