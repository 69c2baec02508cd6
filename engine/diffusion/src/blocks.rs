//! The building blocks shared by the U-Net and the VAE, with diffusers' structure and parameter
//! names (`resnets.0.norm1`, `attentions.0.transformer_blocks.0.attn1.to_q`, ...).

use burn::module::Module;
use burn::nn::{GroupNorm, GroupNormConfig, LayerNorm, LayerNormConfig};
use burn::tensor::activation::{gelu, silu};
use burn::tensor::module::{attention, interpolate};
use burn::tensor::ops::{AttentionModuleOptions, InterpolateMode, InterpolateOptions};
use burn::tensor::{Bool, Device, Tensor};

use crate::layers::{Conv2d, Linear};

/// A GroupNorm with diffusers' affine parameters (`weight`/`bias` in the file, `gamma`/`beta`
/// in burn; the store's PyTorch adapter maps the names).
pub fn group_norm(groups: usize, channels: usize, eps: f64, device: &Device) -> GroupNorm {
    GroupNormConfig::new(groups, channels)
        .with_epsilon(eps)
        .init(device)
}

/// MACs of a GroupNorm or LayerNorm are ignored in FLOP counts (a few per element).
fn norm_macs(_elements: usize) -> u64 {
    0
}

/// diffusers' `ResnetBlock2D` (time_embedding_norm "default", no up/down sampling).
#[derive(Module, Debug)]
pub struct ResnetBlock2D {
    /// Input normalisation.
    pub norm1: GroupNorm,
    /// First 3x3 convolution.
    pub conv1: Conv2d,
    /// Projection of the timestep embedding (absent in the VAE).
    pub time_emb_proj: Option<Linear>,
    /// Second normalisation.
    pub norm2: GroupNorm,
    /// Second 3x3 convolution.
    pub conv2: Conv2d,
    /// 1x1 projection of the input when the channel count changes.
    pub conv_shortcut: Option<Conv2d>,
    /// The output is divided by this.
    pub output_scale_factor: f64,
}

impl ResnetBlock2D {
    /// `c_in -> c_out`, with a timestep embedding of `temb` channels when given.
    pub fn new(
        c_in: usize,
        c_out: usize,
        temb: Option<usize>,
        groups: usize,
        eps: f64,
        output_scale_factor: f64,
        device: &Device,
    ) -> ResnetBlock2D {
        ResnetBlock2D {
            norm1: group_norm(groups, c_in, eps, device),
            conv1: Conv2d::new(c_in, c_out, 3, 1, 1, device),
            time_emb_proj: temb.map(|t| Linear::new(t, c_out, true, device)),
            norm2: group_norm(groups, c_out, eps, device),
            conv2: Conv2d::new(c_out, c_out, 3, 1, 1, device),
            conv_shortcut: (c_in != c_out).then(|| Conv2d::new(c_in, c_out, 1, 1, 0, device)),
            output_scale_factor,
        }
    }

    /// `x [n, c_in, h, w]`, `temb [n, temb]` -> `[n, c_out, h, w]`.
    pub fn forward(&self, x: Tensor<4>, temb: Option<&Tensor<2>>) -> Tensor<4> {
        let mut h = self.conv1.forward(silu(self.norm1.forward(x.clone())));
        if let (Some(proj), Some(t)) = (&self.time_emb_proj, temb) {
            let t: Tensor<4> = proj.forward(silu(t.clone())).unsqueeze_dims(&[2, 3]);
            h = h + t;
        }
        let h = self.conv2.forward(silu(self.norm2.forward(h)));
        let skip = match &self.conv_shortcut {
            Some(c) => c.forward(x),
            None => x,
        };
        let out = skip + h;
        if self.output_scale_factor == 1.0 {
            out
        } else {
            out / self.output_scale_factor
        }
    }

    /// Multiply-adds on an `h x w` input (one image).
    pub fn macs(&self, h: usize, w: usize) -> u64 {
        self.conv1.macs(h, w)
            + self.conv2.macs(h, w)
            + self.conv_shortcut.as_ref().map_or(0, |c| c.macs(h, w))
            + self.time_emb_proj.as_ref().map_or(0, |p| p.macs(1))
            + norm_macs(h * w)
    }
}

/// diffusers' `Downsample2D` with a convolution (`downsamplers.0.conv`): a stride-2 3x3
/// convolution; the VAE's pads (0, 1, 0, 1) first (`padding = 0`).
#[derive(Module, Debug)]
pub struct Downsample2D {
    /// The stride-2 convolution.
    pub conv: Conv2d,
}

impl Downsample2D {
    /// `padding` as diffusers' `downsample_padding`: 1 (U-Net) or 0 (VAE, asymmetric pad).
    pub fn new(channels: usize, padding: usize, device: &Device) -> Downsample2D {
        let conv = Conv2d::new(channels, channels, 3, 2, padding, device);
        let conv = if padding == 0 {
            conv.with_padding([0, 0, 1, 1])
        } else {
            conv
        };
        Downsample2D { conv }
    }

    /// `[n, c, h, w] -> [n, c, h / 2, w / 2]` (rounded up).
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.conv.forward(x)
    }
}

/// diffusers' `Upsample2D` with a convolution (`upsamplers.0.conv`): nearest 2x, then 3x3.
#[derive(Module, Debug)]
pub struct Upsample2D {
    /// The 3x3 convolution after the nearest-neighbour upsampling.
    pub conv: Conv2d,
}

impl Upsample2D {
    /// Keeps the channel count.
    pub fn new(channels: usize, device: &Device) -> Upsample2D {
        Upsample2D {
            conv: Conv2d::new(channels, channels, 3, 1, 1, device),
        }
    }

    /// `[n, c, h, w] -> [n, c, size]` (`size` = twice the input when None).
    pub fn forward(&self, x: Tensor<4>, size: Option<[usize; 2]>) -> Tensor<4> {
        let [_, _, h, w] = x.dims();
        let size = size.unwrap_or([2 * h, 2 * w]);
        let x = interpolate(
            x,
            InterpolateOptions::new(InterpolateMode::Nearest).with_output_size(size),
        );
        self.conv.forward(x)
    }
}

/// An identity placeholder where diffusers has a zero-probability Dropout (keeps the index
/// in `ff.net.2` and `to_out.0` paths).
#[derive(Module, Debug, Default)]
pub struct NoDropout;

/// diffusers' `Attention` (multi-head, `to_q/to_k/to_v/to_out.0`); self-attention when the
/// context is None.
#[derive(Module, Debug)]
pub struct Attention {
    /// Query projection.
    pub to_q: Linear,
    /// Key projection (from the context width).
    pub to_k: Linear,
    /// Value projection (from the context width).
    pub to_v: Linear,
    /// Output projection (diffusers' `to_out.0`; `to_out.1` is a Dropout).
    pub to_out: Vec<Linear>,
    /// The VAE's `group_norm` before the projections (absent in transformer blocks).
    pub group_norm: Option<GroupNorm>,
    /// Heads.
    pub heads: usize,
}

impl Attention {
    /// Transformer attention: `query_dim -> heads * dim_head`, no q/k/v bias.
    pub fn new(
        query_dim: usize,
        context_dim: Option<usize>,
        heads: usize,
        dim_head: usize,
        device: &Device,
    ) -> Attention {
        let inner = heads * dim_head;
        let ctx = context_dim.unwrap_or(query_dim);
        Attention {
            to_q: Linear::new(query_dim, inner, false, device),
            to_k: Linear::new(ctx, inner, false, device),
            to_v: Linear::new(ctx, inner, false, device),
            to_out: vec![Linear::new(inner, query_dim, true, device)],
            group_norm: None,
            heads,
        }
    }

    /// The VAE's single-head spatial self-attention with biases and a GroupNorm.
    pub fn vae(channels: usize, groups: usize, eps: f64, device: &Device) -> Attention {
        Attention {
            to_q: Linear::new(channels, channels, true, device),
            to_k: Linear::new(channels, channels, true, device),
            to_v: Linear::new(channels, channels, true, device),
            to_out: vec![Linear::new(channels, channels, true, device)],
            group_norm: Some(group_norm(groups, channels, eps, device)),
            heads: 1,
        }
    }

    /// `x [b, l, query_dim]`, context `[b, s, context_dim]` -> `[b, l, query_dim]`.
    pub fn forward(&self, x: Tensor<3>, context: Option<&Tensor<3>>) -> Tensor<3> {
        let ctx = context.cloned().unwrap_or_else(|| x.clone());
        let q = self.to_q.forward(x);
        let k = self.to_k.forward(ctx.clone());
        let v = self.to_v.forward(ctx);
        self.to_out[0].forward(multi_head_attention(q, k, v, self.heads, None))
    }

    /// The VAE's spatial form: `[n, c, h, w] -> [n, c, h, w]` with the residual added.
    pub fn forward_spatial(&self, x: Tensor<4>) -> Tensor<4> {
        let [n, c, h, w] = x.dims();
        let y = match &self.group_norm {
            Some(g) => g.forward(x.clone()),
            None => x.clone(),
        };
        let y = y.reshape([n, c, h * w]).swap_dims(1, 2);
        let y = self.forward(y, None);
        let y = y.swap_dims(1, 2).reshape([n, c, h, w]);
        x + y
    }

    /// Multiply-adds for `l` queries over `s` context tokens (one item).
    pub fn macs(&self, l: usize, s: usize) -> u64 {
        let inner = self.to_q.d_out() as u64;
        self.to_q.macs(l)
            + self.to_k.macs(s)
            + self.to_v.macs(s)
            + self.to_out[0].macs(l)
            + 2 * (l as u64) * (s as u64) * inner
    }
}

/// softmax(q k^T / sqrt(d_head)) v per head: `q [b, l, heads * d_head]`, `k`, `v`
/// `[b, s, heads * d_head]` -> `[b, l, heads * d_head]`; `mask [b, heads, l, s]` is true where
/// a query must not see a key.
pub fn multi_head_attention(
    q: Tensor<3>,
    k: Tensor<3>,
    v: Tensor<3>,
    heads: usize,
    mask: Option<Tensor<4, Bool>>,
) -> Tensor<3> {
    let [b, l, inner] = q.dims();
    let s = k.dims()[1];
    let dh = inner / heads;
    let split =
        |t: Tensor<3>, n: usize| -> Tensor<4> { t.reshape([b, n, heads, dh]).swap_dims(1, 2) };
    let o = attention(
        split(q, l),
        split(k, s),
        split(v, s),
        mask,
        None,
        AttentionModuleOptions::default(),
    );
    o.swap_dims(1, 2).reshape([b, l, inner])
}

/// diffusers' GEGLU (`ff.net.0`): `proj` to twice the width, value * gelu(gate).
#[derive(Module, Debug)]
pub struct Geglu {
    /// `dim -> 2 * inner`.
    pub proj: Linear,
}

/// diffusers' `FeedForward` with GEGLU: `net.0` (GEGLU), `net.1` (Dropout), `net.2` (Linear).
#[derive(Module, Debug)]
pub struct FeedForward {
    /// (GEGLU, Dropout, output Linear), as diffusers' ModuleList.
    pub net: (Geglu, NoDropout, Linear),
}

impl FeedForward {
    /// Width `dim`, inner width 4 * dim.
    pub fn new(dim: usize, device: &Device) -> FeedForward {
        let inner = 4 * dim;
        FeedForward {
            net: (
                Geglu {
                    proj: Linear::new(dim, 2 * inner, true, device),
                },
                NoDropout,
                Linear::new(inner, dim, true, device),
            ),
        }
    }

    /// `[b, l, dim] -> [b, l, dim]`.
    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        let h = self.net.0.proj.forward(x);
        let mut halves = h.chunk(2, 2);
        let gate = halves
            .pop()
            .unwrap_or_else(|| unreachable!("chunk(2) gives 2"));
        let value = halves
            .pop()
            .unwrap_or_else(|| unreachable!("chunk(2) gives 2"));
        self.net.2.forward(value * gelu(gate))
    }

    /// Multiply-adds over `l` tokens.
    pub fn macs(&self, l: usize) -> u64 {
        self.net.0.proj.macs(l) + self.net.2.macs(l)
    }
}

/// diffusers' `BasicTransformerBlock`: self-attention, cross-attention, GEGLU feed-forward,
/// each after a LayerNorm and with a residual.
#[derive(Module, Debug)]
pub struct BasicTransformerBlock {
    /// Before self-attention.
    pub norm1: LayerNorm,
    /// Self-attention.
    pub attn1: Attention,
    /// Before cross-attention.
    pub norm2: LayerNorm,
    /// Cross-attention to the conditioning tokens.
    pub attn2: Attention,
    /// Before the feed-forward.
    pub norm3: LayerNorm,
    /// Feed-forward.
    pub ff: FeedForward,
}

impl BasicTransformerBlock {
    /// Width `dim` = heads * dim_head.
    pub fn new(
        dim: usize,
        heads: usize,
        dim_head: usize,
        context_dim: usize,
        device: &Device,
    ) -> BasicTransformerBlock {
        let ln = || LayerNormConfig::new(dim).with_epsilon(1e-5).init(device);
        BasicTransformerBlock {
            norm1: ln(),
            attn1: Attention::new(dim, None, heads, dim_head, device),
            norm2: ln(),
            attn2: Attention::new(dim, Some(context_dim), heads, dim_head, device),
            norm3: ln(),
            ff: FeedForward::new(dim, device),
        }
    }

    /// `[b, l, dim]`, context `[b, s, context_dim]` -> `[b, l, dim]`.
    pub fn forward(&self, x: Tensor<3>, context: &Tensor<3>) -> Tensor<3> {
        let x = self.attn1.forward(self.norm1.forward(x.clone()), None) + x;
        let x = self
            .attn2
            .forward(self.norm2.forward(x.clone()), Some(context))
            + x;
        self.ff.forward(self.norm3.forward(x.clone())) + x
    }

    /// Multiply-adds for `l` tokens and `s` context tokens.
    pub fn macs(&self, l: usize, s: usize) -> u64 {
        self.attn1.macs(l, l) + self.attn2.macs(l, s) + self.ff.macs(l)
    }
}

/// The projection into or out of a transformer: a 1x1 convolution (SD 1.x) or a Linear
/// (`use_linear_projection`, SD 2). Saved without the variant name (`proj_in.weight`).
#[derive(Module, Debug)]
pub enum Projection {
    /// 1x1 convolution on the NCHW map.
    Conv(Conv2d),
    /// Linear on the token sequence.
    Linear(Linear),
}

impl Projection {
    fn new(c_in: usize, c_out: usize, linear: bool, device: &Device) -> Projection {
        if linear {
            Projection::Linear(Linear::new(c_in, c_out, true, device))
        } else {
            Projection::Conv(Conv2d::new(c_in, c_out, 1, 1, 0, device))
        }
    }

    fn macs(&self, tokens: usize) -> u64 {
        match self {
            Projection::Conv(c) => {
                let [o, i, _, _] = c.dims();
                (o * i * tokens) as u64
            }
            Projection::Linear(l) => l.macs(tokens),
        }
    }
}

/// diffusers' `Transformer2DModel` for continuous inputs: GroupNorm, projection in, transformer
/// blocks over the h*w tokens, projection out, residual.
#[derive(Module, Debug)]
pub struct Transformer2DModel {
    /// GroupNorm (eps 1e-6).
    pub norm: GroupNorm,
    /// Into the transformer width.
    pub proj_in: Projection,
    /// The blocks.
    pub transformer_blocks: Vec<BasicTransformerBlock>,
    /// Back to the channel count.
    pub proj_out: Projection,
}

impl Transformer2DModel {
    /// `channels` wide, `heads` heads of `channels / heads`.
    pub fn new(
        channels: usize,
        heads: usize,
        layers: usize,
        context_dim: usize,
        groups: usize,
        linear_projection: bool,
        device: &Device,
    ) -> Transformer2DModel {
        let dim_head = channels / heads;
        let inner = heads * dim_head;
        Transformer2DModel {
            norm: group_norm(groups, channels, 1e-6, device),
            proj_in: Projection::new(channels, inner, linear_projection, device),
            transformer_blocks: (0..layers)
                .map(|_| BasicTransformerBlock::new(inner, heads, dim_head, context_dim, device))
                .collect(),
            proj_out: Projection::new(inner, channels, linear_projection, device),
        }
    }

    /// `[n, c, h, w]`, context `[n, s, context_dim]` -> `[n, c, h, w]`.
    pub fn forward(&self, x: Tensor<4>, context: &Tensor<3>) -> Tensor<4> {
        let [n, c, h, w] = x.dims();
        let y = self.norm.forward(x.clone());
        let tokens = |t: Tensor<4>| -> Tensor<3> {
            let ch = t.dims()[1];
            t.permute([0, 2, 3, 1]).reshape([n, h * w, ch])
        };
        let mut y = match &self.proj_in {
            Projection::Conv(conv) => tokens(conv.forward(y)),
            Projection::Linear(lin) => lin.forward(tokens(y)),
        };
        for block in &self.transformer_blocks {
            y = block.forward(y, context);
        }
        let spatial = |t: Tensor<3>| -> Tensor<4> {
            let ch = t.dims()[2];
            t.reshape([n, h, w, ch]).permute([0, 3, 1, 2])
        };
        let y = match &self.proj_out {
            Projection::Conv(conv) => conv.forward(spatial(y)),
            Projection::Linear(lin) => spatial(lin.forward(y)),
        };
        debug_assert_eq!(y.dims()[1], c);
        y + x
    }

    /// Multiply-adds on an `h x w` map with `s` context tokens (one item).
    pub fn macs(&self, h: usize, w: usize, s: usize) -> u64 {
        let l = h * w;
        self.proj_in.macs(l)
            + self.proj_out.macs(l)
            + self
                .transformer_blocks
                .iter()
                .map(|b| b.macs(l, s))
                .sum::<u64>()
    }
}

/// diffusers' sinusoidal timestep embedding (`get_timestep_embedding`, max period 10000),
/// `[n] -> [n, dim]`, `[cos, sin]` order when `flip_sin_to_cos`.
pub fn timestep_embedding(
    timesteps: &[f32],
    dim: usize,
    flip_sin_to_cos: bool,
    freq_shift: usize,
    device: &Device,
) -> Tensor<2> {
    let half = dim / 2;
    let mut out = Vec::with_capacity(timesteps.len() * dim);
    for &t in timesteps {
        let mut sin = Vec::with_capacity(half);
        let mut cos = Vec::with_capacity(half);
        for i in 0..half {
            let exponent = -(10000f64.ln()) * i as f64 / (half as f64 - freq_shift as f64);
            let arg = t as f64 * exponent.exp();
            sin.push(arg.sin() as f32);
            cos.push(arg.cos() as f32);
        }
        if flip_sin_to_cos {
            out.extend(cos);
            out.extend(sin);
        } else {
            out.extend(sin);
            out.extend(cos);
        }
        // Odd widths are zero-padded, as diffusers does.
        out.extend(std::iter::repeat_n(0.0, dim - 2 * half));
    }
    Tensor::<1>::from_floats(out.as_slice(), device).reshape([timesteps.len(), dim])
}

/// diffusers' `TimestepEmbedding`: `linear_1`, SiLU, `linear_2`.
#[derive(Module, Debug)]
pub struct TimestepEmbedding {
    /// `in -> time_embed_dim`.
    pub linear_1: Linear,
    /// `time_embed_dim -> time_embed_dim`.
    pub linear_2: Linear,
}

impl TimestepEmbedding {
    /// `c_in -> dim`.
    pub fn new(c_in: usize, dim: usize, device: &Device) -> TimestepEmbedding {
        TimestepEmbedding {
            linear_1: Linear::new(c_in, dim, true, device),
            linear_2: Linear::new(dim, dim, true, device),
        }
    }

    /// `[n, c_in] -> [n, dim]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        self.linear_2.forward(silu(self.linear_1.forward(x)))
    }
}
