//! The two weight layers every model here is built from, with optional LoRA factors.
//!
//! They keep PyTorch's parameter names (`weight`, `bias`) so that diffusers checkpoints map onto
//! them directly; [`Linear`] stores its weight in burn's `[in, out]` layout, which
//! burn-store's PyTorch adapter transposes on load and save (it matches the struct name
//! `Linear`). LoRA factors use PEFT's layout and names (`lora_A` `[r, in(, kh, kw)]`, `lora_B`
//! `[out, r(, 1, 1)]`) so adapters need no transposition: the effective weight is
//! `W + (alpha / r) * B A`, with B initialised to zero so that a fresh adapter changes nothing.

use burn::module::{Module, Param};
use burn::nn::Initializer;
use burn::tensor::module::{conv2d, linear};
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor};

/// PyTorch's default initialiser for Linear and Conv2d (Kaiming uniform with a = sqrt 5).
fn torch_default() -> Initializer {
    Initializer::KaimingUniform {
        gain: 1.0 / 3f64.sqrt(),
        fan_out_only: false,
    }
}

/// A fully connected layer `y = x W + b (+ LoRA)`.
#[derive(Module, Debug)]
pub struct Linear {
    /// `[in, out]` (burn layout; the file holds PyTorch's `[out, in]`).
    pub weight: Param<Tensor<2>>,
    /// `[out]`.
    pub bias: Option<Param<Tensor<1>>>,
    /// LoRA down factor `[r, in]` (PEFT `lora_A`).
    pub lora_a: Option<Param<Tensor<2>>>,
    /// LoRA up factor `[out, r]` (PEFT `lora_B`), zero when created.
    pub lora_b: Option<Param<Tensor<2>>>,
    /// alpha / r.
    pub lora_scale: f64,
}

impl Linear {
    /// A layer with PyTorch's default initialisation (lazy: nothing is allocated until used).
    pub fn new(d_in: usize, d_out: usize, bias: bool, device: &Device) -> Linear {
        let init = torch_default();
        Linear {
            weight: init.init_with([d_in, d_out], Some(d_in), Some(d_out), device),
            bias: bias.then(|| init.init_with([d_out], Some(d_in), Some(d_out), device)),
            lora_a: None,
            lora_b: None,
            lora_scale: 0.0,
        }
    }

    /// Input width.
    pub fn d_in(&self) -> usize {
        self.weight.lazy_shape()[0]
    }

    /// Output width.
    pub fn d_out(&self) -> usize {
        self.weight.lazy_shape()[1]
    }

    /// `[..., in] -> [..., out]`.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let base = linear(
            x.clone(),
            self.weight.val(),
            self.bias.as_ref().map(|b| b.val()),
        );
        match (&self.lora_a, &self.lora_b) {
            (Some(a), Some(b)) => {
                let h = linear(x, a.val().transpose(), None);
                base + linear(h, b.val().transpose(), None) * self.lora_scale
            }
            _ => base,
        }
    }

    /// Adds rank-`rank` LoRA factors (A Kaiming-uniform, B zero) scaled by alpha / rank.
    pub fn add_lora(&mut self, rank: usize, alpha: f64, device: &Device) {
        let (d_in, d_out) = (self.d_in(), self.d_out());
        self.lora_a = Some(torch_default().init_with([rank, d_in], Some(d_in), Some(rank), device));
        self.lora_b = Some(Initializer::Zeros.init([d_out, rank], device));
        self.lora_scale = alpha / rank as f64;
    }

    /// Multiply-adds of one forward over `rows` input rows.
    pub fn macs(&self, rows: usize) -> u64 {
        (rows * self.d_in() * self.d_out()) as u64
    }
}

/// A 2-D convolution, NCHW, PyTorch weight layout `[out, in, kh, kw]`.
#[derive(Module, Debug)]
pub struct Conv2d {
    /// `[out, in, kh, kw]`.
    pub weight: Param<Tensor<4>>,
    /// `[out]`.
    pub bias: Option<Param<Tensor<1>>>,
    /// LoRA down convolution `[r, in, kh, kw]` (same stride and padding as the base).
    pub lora_a: Option<Param<Tensor<4>>>,
    /// LoRA up projection `[out, r, 1, 1]`, zero when created.
    pub lora_b: Option<Param<Tensor<4>>>,
    /// alpha / r.
    pub lora_scale: f64,
    /// Stride in both directions.
    pub stride: usize,
    /// Zero padding (top, left, bottom, right).
    pub padding: [usize; 4],
}

impl Conv2d {
    /// A `k x k` convolution with symmetric padding `pad`, PyTorch's default initialisation.
    pub fn new(
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        pad: usize,
        device: &Device,
    ) -> Conv2d {
        let init = torch_default();
        let fan_in = c_in * k * k;
        let fan_out = c_out * k * k;
        Conv2d {
            weight: init.init_with([c_out, c_in, k, k], Some(fan_in), Some(fan_out), device),
            bias: Some(init.init_with([c_out], Some(fan_in), Some(fan_out), device)),
            lora_a: None,
            lora_b: None,
            lora_scale: 0.0,
            stride,
            padding: [pad; 4],
        }
    }

    /// The same layer with explicit (top, left, bottom, right) padding.
    pub fn with_padding(self, padding: [usize; 4]) -> Conv2d {
        Conv2d { padding, ..self }
    }

    /// Sets the weight and bias to zero (trainable, on `device`): the layer outputs zeros,
    /// as a residual enhancer's last convolution starts.
    pub fn zero(&mut self, device: &Device) {
        self.weight = Param::from_tensor(Tensor::zeros(self.dims(), device));
        if let Some(b) = &self.bias {
            self.bias = Some(Param::from_tensor(Tensor::zeros(b.dims(), device)));
        }
    }

    /// `[out, in, kh, kw]`.
    pub fn dims(&self) -> [usize; 4] {
        let s = self.weight.lazy_shape();
        [s[0], s[1], s[2], s[3]]
    }

    fn options(&self) -> ConvOptions<2> {
        let [t, l, b, r] = self.padding;
        ConvOptions::new_with_padding([self.stride; 2], [(t, b), (l, r)], [1, 1], 1)
    }

    /// `[n, in, h, w] -> [n, out, h', w']`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let opts = self.options();
        let base = conv2d(
            x.clone(),
            self.weight.val(),
            self.bias.as_ref().map(|b| b.val()),
            opts.clone(),
        );
        match (&self.lora_a, &self.lora_b) {
            (Some(a), Some(b)) => {
                let h = conv2d(x, a.val(), None, opts);
                let up = conv2d(
                    h,
                    b.val(),
                    None,
                    ConvOptions::new([1, 1], [0, 0], [1, 1], 1),
                );
                base + up * self.lora_scale
            }
            _ => base,
        }
    }

    /// Adds rank-`rank` LoRA factors: a `k x k` down convolution (Kaiming-uniform) and a zero
    /// 1x1 up projection, scaled by alpha / rank.
    pub fn add_lora(&mut self, rank: usize, alpha: f64, device: &Device) {
        let [c_out, c_in, kh, kw] = self.dims();
        let fan_in = c_in * kh * kw;
        self.lora_a = Some(torch_default().init_with(
            [rank, c_in, kh, kw],
            Some(fan_in),
            Some(rank * kh * kw),
            device,
        ));
        self.lora_b = Some(Initializer::Zeros.init([c_out, rank, 1, 1], device));
        self.lora_scale = alpha / rank as f64;
    }

    /// Output size for an input of `h x w`.
    pub fn out_size(&self, h: usize, w: usize) -> (usize, usize) {
        let [_, _, kh, kw] = self.dims();
        let [t, l, b, r] = self.padding;
        (
            (h + t + b - kh) / self.stride + 1,
            (w + l + r - kw) / self.stride + 1,
        )
    }

    /// Multiply-adds of one forward on an `h x w` input (one image).
    pub fn macs(&self, h: usize, w: usize) -> u64 {
        let [c_out, c_in, kh, kw] = self.dims();
        let (oh, ow) = self.out_size(h, w);
        (c_out * c_in * kh * kw * oh * ow) as u64
    }
}
