//! Plain-Rust definitions of the NeRF kernels, in f64 where it matters; the tests compare the
//! GPU against these on random inputs.

use crate::field::hash_grid::{HashGridConfig, HashLevel};
use crate::field::mlp::MlpConfig;

fn hg_index(c: [u64; 3], lv: &HashLevel) -> usize {
    if lv.dense != 0 {
        let s = lv.res as u64 + 1;
        return (c[0] + s * (c[1] + s * c[2])) as usize;
    }
    let h = (c[0] as u32).wrapping_mul(1)
        ^ (c[1] as u32).wrapping_mul(2_654_435_761)
        ^ (c[2] as u32).wrapping_mul(805_459_861);
    (h % lv.size) as usize
}

/// The cell corner and fractional position of `x` at a level, computed in f32 as the kernel
/// does (so both pick the same cell), returned as f64.
fn hg_cell(x: [f32; 3], lv: &HashLevel) -> ([u64; 3], [f64; 3]) {
    let res = lv.res as f32;
    let mut c = [0u64; 3];
    let mut f = [0f64; 3];
    for d in 0..3 {
        let p = x[d].clamp(0.0, 1.0) * res;
        let cd = p.floor().min(res - 1.0);
        c[d] = cd as u64;
        f[d] = (p - cd) as f64;
    }
    (c, f)
}

fn corners(c: [u64; 3], f: [f64; 3]) -> impl Iterator<Item = ([u64; 3], f64)> {
    (0..8u64).map(move |k| {
        let b = [k & 1, (k >> 1) & 1, (k >> 2) & 1];
        let w: f64 = (0..3)
            .map(|d| if b[d] == 1 { f[d] } else { 1.0 - f[d] })
            .product();
        ([c[0] + b[0], c[1] + b[1], c[2] + b[2]], w)
    })
}

/// Hash-grid encoding of `positions` (n x 3): n x (L * F) values.
pub fn hash_grid_forward(cfg: &HashGridConfig, table: &[f32], positions: &[f32]) -> Vec<f64> {
    let levels = cfg.level_layout();
    let fdim = cfg.features as usize;
    let mut out = Vec::with_capacity(positions.len() / 3 * levels.len() * fdim);
    for x in positions.chunks_exact(3) {
        let x = [x[0], x[1], x[2]];
        for lv in &levels {
            let mut acc = vec![0f64; fdim];
            if x.iter().all(|v| !v.is_nan()) {
                let (c, f) = hg_cell(x, lv);
                for (corner, w) in corners(c, f) {
                    let e = lv.offset as usize + hg_index(corner, lv) * fdim;
                    for (j, a) in acc.iter_mut().enumerate() {
                        *a += w * table[e + j] as f64;
                    }
                }
            }
            out.extend(acc);
        }
    }
    out
}

/// Gradient of `sum(d_encoded * encoding)` with respect to the table.
pub fn hash_grid_backward(cfg: &HashGridConfig, positions: &[f32], d_encoded: &[f32]) -> Vec<f64> {
    let levels = cfg.level_layout();
    let fdim = cfg.features as usize;
    let mut grad = vec![0f64; cfg.param_count() as usize];
    for (i, x) in positions.chunks_exact(3).enumerate() {
        let x = [x[0], x[1], x[2]];
        if x.iter().any(|v| v.is_nan()) {
            continue;
        }
        for (l, lv) in levels.iter().enumerate() {
            let (c, f) = hg_cell(x, lv);
            for (corner, w) in corners(c, f) {
                let e = lv.offset as usize + hg_index(corner, lv) * fdim;
                for j in 0..fdim {
                    grad[e + j] += w * d_encoded[(i * levels.len() + l) * fdim + j] as f64;
                }
            }
        }
    }
    grad
}

/// MLP forward for every point (rows of `inputs`), in f64: ReLU hidden layers, linear output.
pub fn mlp_forward(cfg: &MlpConfig, weights: &[f32], inputs: &[f32]) -> Vec<f64> {
    let n_in = cfg.dims[0] as usize;
    inputs
        .chunks_exact(n_in)
        .flat_map(|x| mlp_point(cfg, weights, x).0.pop().unwrap_or_default())
        .collect()
}

/// Per-layer activations (the input, then each layer's output) and pre-activations of one point.
fn mlp_point(cfg: &MlpConfig, weights: &[f32], x: &[f32]) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    mlp_point_with(cfg, weights, x, false)
}

/// [`mlp_point`], with every layer's input rounded to f16 when `f16_inputs` (the
/// cooperative-matrix kernels' activations).
fn mlp_point_with(
    cfg: &MlpConfig,
    weights: &[f32],
    x: &[f32],
    f16_inputs: bool,
) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    let round = |v: f64| {
        if f16_inputs {
            round_f16(v as f32) as f64
        } else {
            v
        }
    };
    let mut acts = vec![x.iter().map(|&v| round(v as f64)).collect::<Vec<f64>>()];
    let mut pres = Vec::new();
    for l in 0..cfg.layers() {
        let (ni, no) = (cfg.dims[l] as usize, cfg.dims[l + 1] as usize);
        let w = &weights[cfg.offset(l)..];
        let a = &acts[l];
        let pre: Vec<f64> = (0..no)
            .map(|o| {
                w[no * ni + o] as f64 + (0..ni).map(|j| w[o * ni + j] as f64 * a[j]).sum::<f64>()
            })
            .collect();
        let last = l + 1 == cfg.layers();
        acts.push(
            pre.iter()
                .map(|&z| if last { z } else { round(z.max(0.0)) })
                .collect(),
        );
        pres.push(pre);
    }
    (acts, pres)
}

/// The cooperative-matrix MLP (`common/mlp_coop.wgsl`): the weights (not the biases) and every
/// layer's input are rounded to f16 as the kernels' tiles hold them, the rest is exact: returns
/// the outputs `[n, out]`, the input gradient `[n, in]` and the weight gradient (flat layout),
/// with the ReLU gates of those rounded pre-activations. (The kernels also round the scaled
/// pre-activation gradients to f16: the error the tests bound.)
pub fn mlp_coop_reference(
    cfg: &MlpConfig,
    weights: &[f32],
    inputs: &[f32],
    d_outputs: &[f32],
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut w16 = weights.to_vec();
    for l in 0..cfg.layers() {
        let (ni, no) = (cfg.dims[l] as usize, cfg.dims[l + 1] as usize);
        let off = cfg.offset(l);
        for v in &mut w16[off..off + no * ni] {
            *v = round_f16(*v);
        }
    }
    let n_in = cfg.dims[0] as usize;
    let out = inputs
        .chunks_exact(n_in)
        .flat_map(|x| {
            mlp_point_with(cfg, &w16, x, true)
                .1
                .pop()
                .unwrap_or_default()
        })
        .collect();
    let (d_in, d_w) = mlp_backward_record(cfg, &w16, inputs, d_outputs, false, true);
    (out, d_in, d_w)
}

/// f32 -> f16 -> f32: NaN to 0, clamped to +-65504, rounded to the nearest f16 (ties to even),
/// subnormals below 2^-14 (as `table_to_f16` stores the f16 table).
pub fn round_f16(v: f32) -> f32 {
    if v.is_nan() {
        return 0.0;
    }
    let a = v.abs().min(65504.0);
    // The exponent from the bits (log2 can round up just below a power of two).
    let exp = ((a.to_bits() >> 23) & 0xff) as i32 - 127;
    let quantum = if a < 2f32.powi(-14) {
        2f32.powi(-24)
    } else {
        2f32.powi(exp - 10)
    };
    ((a / quantum).round_ties_even() * quantum).copysign(v)
}

/// One segment of the f16 MLP record (`field/mlp_f16.wgsl`) stored and read back: scaled by
/// 2^-k so that its largest magnitude lies in [2^14, 2^15), rounded to f16, scaled back. With
/// `relu_out`, positive values stay at least 2^-14 after scaling.
pub fn f16_segment(v: &[f64], relu_out: bool) -> Vec<f64> {
    let m = v.iter().fold(0f32, |m, &x| m.max((x as f32).abs()));
    let e = ((m.to_bits() >> 23) & 0xff) as i32 - 127;
    let k = (e - 14).clamp(-126, 126);
    v.iter()
        .map(|&x| {
            let mut s = x as f32 * 2f32.powi(-k);
            if relu_out && s > 0.0 {
                s = s.max(2f32.powi(-14));
            }
            round_f16(s) as f64 * 2f64.powi(k)
        })
        .collect()
}

/// The weight gradient of [`mlp_backward`] from the f16 record: every layer's input and
/// pre-activation gradient pass through [`f16_segment`] before the products are summed (in
/// f64). The input gradient is not affected (the data pass is f32).
pub fn mlp_weight_grad_f16(
    cfg: &MlpConfig,
    weights: &[f32],
    inputs: &[f32],
    d_outputs: &[f32],
) -> Vec<f64> {
    mlp_backward_record(cfg, weights, inputs, d_outputs, true, false).1
}

/// MLP backward in f64: (dL/dinputs, dL/dweights) for `d_outputs`.
pub fn mlp_backward(
    cfg: &MlpConfig,
    weights: &[f32],
    inputs: &[f32],
    d_outputs: &[f32],
) -> (Vec<f64>, Vec<f64>) {
    mlp_backward_record(cfg, weights, inputs, d_outputs, false, false)
}

/// [`mlp_backward`], with the weight gradient's record through [`f16_segment`] when `f16`, and
/// every layer's input rounded to f16 when `f16_inputs` ([`mlp_point_with`]).
fn mlp_backward_record(
    cfg: &MlpConfig,
    weights: &[f32],
    inputs: &[f32],
    d_outputs: &[f32],
    f16: bool,
    f16_inputs: bool,
) -> (Vec<f64>, Vec<f64>) {
    let (n_in, n_out) = (cfg.dims[0] as usize, cfg.dims[cfg.layers()] as usize);
    let mut d_in = Vec::with_capacity(inputs.len());
    let mut d_w = vec![0f64; cfg.param_count()];
    for (x, dy) in inputs.chunks_exact(n_in).zip(d_outputs.chunks_exact(n_out)) {
        let (acts, pres) = mlp_point_with(cfg, weights, x, f16_inputs);
        let mut g: Vec<f64> = dy.iter().map(|&v| v as f64).collect();
        for l in (0..cfg.layers()).rev() {
            let (ni, no) = (cfg.dims[l] as usize, cfg.dims[l + 1] as usize);
            let off = cfg.offset(l);
            let last = l + 1 == cfg.layers();
            let delta: Vec<f64> = (0..no)
                .map(|o| if last || pres[l][o] > 0.0 { g[o] } else { 0.0 })
                .collect();
            let (dq, xq) = if f16 {
                (f16_segment(&delta, false), f16_segment(&acts[l], l > 0))
            } else {
                (delta.clone(), acts[l].clone())
            };
            for o in 0..no {
                for j in 0..ni {
                    d_w[off + o * ni + j] += dq[o] * xq[j];
                }
                d_w[off + no * ni + o] += dq[o];
            }
            g = (0..ni)
                .map(|j| {
                    (0..no)
                        .map(|o| weights[off + o * ni + j] as f64 * delta[o])
                        .sum()
                })
                .collect();
        }
        d_in.extend(g);
    }
    (d_in, d_w)
}

/// Per-sample weights of one ray in f64: w_i = T_i (1 - exp(-sigma_i dt_i)), and the final
/// transmittance. Non-positive sigma or dt contribute nothing.
pub fn ray_weights(sigma: &[f32], dt: &[f32]) -> (Vec<f64>, f64) {
    let mut tau = 0f64;
    let w = sigma
        .iter()
        .zip(dt)
        .map(|(&s, &d)| {
            let x = if s > 0.0 && d > 0.0 {
                s as f64 * d as f64
            } else {
                0.0
            };
            let w = (-tau).exp() * -(-x).exp_m1();
            tau += x;
            w
        })
        .collect();
    (w, (-tau).exp())
}

/// Compositing of one ray in f64: (r, g, b, opacity, depth).
pub fn composite_forward(
    sigma: &[f32],
    rgb: &[[f32; 4]],
    t_dt: &[[f32; 2]],
    background: [f32; 3],
) -> [f64; 5] {
    let dt: Vec<f32> = t_dt.iter().map(|v| v[1]).collect();
    let (w, t_end) = ray_weights(sigma, &dt);
    let mut out = [0f64; 5];
    for i in 0..w.len() {
        for c in 0..3 {
            out[c] += w[i] * rgb[i][c] as f64;
        }
        out[3] += w[i];
        out[4] += w[i] * t_dt[i][0] as f64;
    }
    for c in 0..3 {
        out[c] += t_end * background[c] as f64;
    }
    out
}

/// Backward of [`composite_forward`] for one ray in f64: (dL/dsigma, dL/drgb) per sample, given
/// dL/d(r, g, b, opacity), dL/ddepth and an extra dL/dweight per sample; with `grad_scaling`
/// each sample's gradients are multiplied by min(1, t^2) (Floaters No More).
#[allow(clippy::too_many_arguments)] // mirrors the kernel's operands
pub fn composite_backward(
    sigma: &[f32],
    rgb: &[[f32; 4]],
    t_dt: &[[f32; 2]],
    background: [f32; 3],
    d_rgba: [f32; 4],
    d_depth: f32,
    d_weight: &[f32],
    grad_scaling: bool,
) -> (Vec<f64>, Vec<[f64; 3]>) {
    let n = sigma.len();
    let dt: Vec<f32> = t_dt.iter().map(|v| v[1]).collect();
    let (w, t_end) = ray_weights(sigma, &dt);
    let u: Vec<f64> = (0..n)
        .map(|i| {
            (0..3)
                .map(|c| rgb[i][c] as f64 * d_rgba[c] as f64)
                .sum::<f64>()
                + t_dt[i][0] as f64 * d_depth as f64
                + d_rgba[3] as f64
                + d_weight[i] as f64
        })
        .collect();
    let bg: f64 = t_end
        * (0..3)
            .map(|c| background[c] as f64 * d_rgba[c] as f64)
            .sum::<f64>();
    let mut tau = 0f64;
    let mut d_sigma = vec![0f64; n];
    for i in 0..n {
        let x = if sigma[i] > 0.0 && dt[i] > 0.0 {
            sigma[i] as f64 * dt[i] as f64
        } else {
            0.0
        };
        tau += x;
        let suffix: f64 = (i + 1..n).map(|j| w[j] * u[j]).sum();
        let dx = (-tau).exp() * u[i] - suffix - bg;
        d_sigma[i] = if dt[i] > 0.0 && sigma[i] >= 0.0 {
            dt[i] as f64 * dx
        } else {
            0.0
        };
    }
    let scale = |i: usize| {
        if grad_scaling {
            (t_dt[i][0] as f64 * t_dt[i][0] as f64).min(1.0)
        } else {
            1.0
        }
    };
    let d_sigma = d_sigma
        .iter()
        .enumerate()
        .map(|(i, d)| d * scale(i))
        .collect();
    let d_rgb = (0..n)
        .map(|i| [0, 1, 2].map(|c| scale(i) * w[i] * d_rgba[c] as f64))
        .collect();
    (d_sigma, d_rgb)
}

/// Distortion loss of one ray from its weights, midpoints and widths (the O(N^2) definition).
pub fn distortion_from_weights(w: &[f64], m: &[f64], ds: &[f64]) -> f64 {
    let mut l = 0.0;
    for i in 0..w.len() {
        for j in 0..w.len() {
            l += w[i] * w[j] * (m[i] - m[j]).abs();
        }
        l += w[i] * w[i] * ds[i] / 3.0;
    }
    l
}

/// Distortion loss of one ray (weights from sigma and dt) and dL/dw per sample, in f64.
pub fn distortion(
    sigma: &[f32],
    t_dt: &[[f32; 2]],
    s_ds: &[[f32; 2]],
    lambda: f32,
) -> (f64, Vec<f64>) {
    let dt: Vec<f32> = t_dt.iter().map(|v| v[1]).collect();
    let (w, _) = ray_weights(sigma, &dt);
    let m: Vec<f64> = s_ds.iter().map(|v| v[0] as f64).collect();
    let ds: Vec<f64> = s_ds.iter().map(|v| v[1] as f64).collect();
    let l = lambda as f64 * distortion_from_weights(&w, &m, &ds);
    let grad = (0..w.len())
        .map(|i| {
            lambda as f64
                * (2.0
                    * (0..w.len())
                        .map(|j| w[j] * (m[i] - m[j]).abs())
                        .sum::<f64>()
                    + 2.0 / 3.0 * w[i] * ds[i])
        })
        .collect();
    (l, grad)
}

/// One Adam step in f64 on (params, m, v), as the kernel defines it (non-finite gradients count
/// as zero, weight decay added to the gradient).
#[allow(clippy::too_many_arguments)] // mirrors the kernel's parameter block
pub fn adam_step(
    p: &mut [f64],
    m: &mut [f64],
    v: &mut [f64],
    g: &[f32],
    lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
    step: u32,
    grad_scale: f64,
    weight_decay: f64,
) {
    let (b1, b2) = (1.0 - beta1.powi(step as i32), 1.0 - beta2.powi(step as i32));
    for i in 0..p.len() {
        let gi = g[i] as f64 * grad_scale;
        let gi = if gi.is_finite() && (g[i] * grad_scale as f32).is_finite() {
            gi
        } else {
            0.0
        } + weight_decay * p[i];
        m[i] = beta1 * m[i] + (1.0 - beta1) * gi;
        v[i] = beta2 * v[i] + (1.0 - beta2) * gi * gi;
        p[i] -= lr * (m[i] / b1) / ((v[i] / b2).sqrt() + eps);
    }
}

/// [`adam_step`] with `cfg`'s settings at update `step`: its scheduled learning rate, betas,
/// eps and weight decay.
pub fn adam_step_with(
    p: &mut [f64],
    m: &mut [f64],
    v: &mut [f64],
    g: &[f32],
    cfg: &crate::optim::AdamConfig,
    step: u32,
    grad_scale: f64,
) {
    adam_step(
        p,
        m,
        v,
        g,
        cfg.lr_at(step) as f64,
        cfg.beta1 as f64,
        cfg.beta2 as f64,
        cfg.eps as f64,
        step,
        grad_scale,
        cfg.weight_decay as f64,
    );
}

/// Contraction into [0, 1]^3 in f64 (see `field::encodings::Contraction`).
pub fn contract(x: [f32; 3], scene: &crate::field::encodings::SceneBox) -> [f64; 3] {
    use crate::field::encodings::Contraction;
    let u: Vec<f64> = (0..3)
        .map(|d| ((x[d] as f64 - scene.center[d] as f64) / scene.radius as f64).clamp(-1e37, 1e37))
        .collect();
    let c: Vec<f64> = match scene.contraction {
        Contraction::None => return [0, 1, 2].map(|d| (u[d] * 0.5 + 0.5).clamp(0.0, 1.0)),
        Contraction::L2 | Contraction::LInf => {
            let n = if scene.contraction == Contraction::L2 {
                u.iter().map(|v| v * v).sum::<f64>().sqrt()
            } else {
                u.iter().fold(0.0, |m: f64, v| m.max(v.abs()))
            };
            if n > 1.0 {
                u.iter().map(|v| (2.0 - 1.0 / n) * v / n).collect()
            } else {
                u
            }
        }
    };
    [0, 1, 2].map(|d| (c[d] * 0.25 + 0.5).clamp(0.0, 1.0))
}

/// Degree-4 real spherical harmonics (16 values) of a unit direction, in f64.
#[allow(clippy::excessive_precision)] // the constants as published, digit for digit
pub fn sh4(d: [f64; 3]) -> [f64; 16] {
    let [x, y, z] = d;
    let (x2, y2, z2) = (x * x, y * y, z * z);
    [
        0.28209479177387814,
        -0.48860251190291987 * y,
        0.48860251190291987 * z,
        -0.48860251190291987 * x,
        1.0925484305920792 * x * y,
        -1.0925484305920792 * y * z,
        0.94617469575755997 * z2 - 0.31539156525251999,
        -1.0925484305920792 * x * z,
        0.54627421529603959 * (x2 - y2),
        0.59004358992664352 * y * (-3.0 * x2 + y2),
        2.8906114426405538 * x * y * z,
        0.45704579946446572 * y * (1.0 - 5.0 * z2),
        0.3731763325901154 * z * (5.0 * z2 - 3.0),
        0.45704579946446572 * x * (1.0 - 5.0 * z2),
        1.4453057213202769 * z * (x2 - y2),
        0.59004358992664352 * x * (-x2 + 3.0 * y2),
    ]
}

/// World-space ray through pixel coordinates `px` (centres at +0.5) in f64: origin and
/// direction with unit depth along the viewing axis.
pub fn camera_ray(cam: &crate::data::Camera, px: [f64; 2]) -> ([f64; 3], [f64; 3]) {
    let dc = glam::DVec3::new((px[0] - cam.cx) / cam.fx, -(px[1] - cam.cy) / cam.fy, -1.0);
    let d = glam::DMat3::from_mat4(cam.c2w) * dc;
    let o = cam.c2w.w_axis.truncate();
    (o.to_array(), d.to_array())
}

/// NeRF's `ndc_rays` in f64 (directions parallel to the near plane nudged as the kernel does).
pub fn ndc_ray(
    cam: &crate::data::Camera,
    o: [f64; 3],
    d: [f64; 3],
    near: f64,
) -> ([f64; 3], [f64; 3]) {
    let mut d = d;
    if d[2].abs() < 1e-12 {
        d[2] = -1e-12;
    }
    let t = -(near + o[2]) / d[2];
    let o = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    let ax = -2.0 * (cam.fx as f32) as f64 / cam.width as f64;
    let ay = -2.0 * (cam.fy as f32) as f64 / cam.height as f64;
    (
        [ax * o[0] / o[2], ay * o[1] / o[2], 1.0 + 2.0 * near / o[2]],
        [
            ax * (d[0] / d[2] - o[0] / o[2]),
            ay * (d[1] / d[2] - o[1] / o[2]),
            -2.0 * near / o[2],
        ],
    )
}

/// Per-ray loss (before the 1/n of the batch mean) and its gradients (d_rgb, d_depth), in f64.
/// `target[3]` is the signed colour weight (common/ray_loss.wgsl): w >= 0 scales the configured
/// loss, w < 0 means L1 scaled by -w (smooth L1 with `cfg.l1_core` > 0).
pub fn ray_loss(
    rendered: [f32; 4],
    depth: f32,
    target: [f32; 4],
    target_depth: [f32; 2],
    cfg: &crate::render::loss::LossConfig,
) -> (f64, [f64; 3], f64) {
    use crate::render::loss::RgbLoss;
    let e = [0, 1, 2].map(|c| rendered[c] as f64 - target[c] as f64);
    let w = (target[3] as f64).abs();
    let core = cfg.l1_core as f64;
    let (l, g) = if target[3] < 0.0 && core > 0.0 {
        let l = e
            .iter()
            .map(|v| {
                if v.abs() <= core {
                    0.5 * v * v / core
                } else {
                    v.abs() - 0.5 * core
                }
            })
            .sum::<f64>()
            / 3.0;
        (
            l,
            e.map(|v| if v.abs() <= core { v / core } else { v.signum() } / 3.0),
        )
    } else if target[3] < 0.0 {
        (
            e.iter().map(|v| v.abs()).sum::<f64>() / 3.0,
            e.map(|v| if v == 0.0 { 0.0 } else { v.signum() } / 3.0),
        )
    } else {
        match cfg.rgb {
            RgbLoss::L2 => (
                e.iter().map(|v| v * v).sum::<f64>() / 3.0,
                e.map(|v| 2.0 * v / 3.0),
            ),
            RgbLoss::Huber(d) => {
                let d = d as f64;
                let l = e
                    .iter()
                    .map(|v| {
                        if v.abs() <= d {
                            0.5 * v * v
                        } else {
                            d * (v.abs() - 0.5 * d)
                        }
                    })
                    .sum::<f64>()
                    / 3.0;
                (
                    l,
                    e.map(|v| if v.abs() <= d { v } else { d * v.signum() } / 3.0),
                )
            }
        }
    };
    let mut l = w * l;
    let g = g.map(|v| w * v);
    let mut gd = 0.0;
    if target_depth[1] > 0.0 {
        let de = depth as f64 - target_depth[0] as f64;
        l += cfg.depth_lambda as f64 * target_depth[1] as f64 * de * de;
        gd = 2.0 * cfg.depth_lambda as f64 * target_depth[1] as f64 * de;
    }
    (l, g, gd)
}

/// Hash decay in f64: (lambda * sum over levels of mean(V_l^2), gradient).
pub fn hash_decay(cfg: &HashGridConfig, table: &[f32], lambda: f32) -> (f64, Vec<f64>) {
    let mut loss = 0.0;
    let mut grad = vec![0f64; table.len()];
    for lv in cfg.level_layout() {
        let count = lv.size as usize * cfg.features as usize;
        let scale = lambda as f64 / count as f64;
        for i in lv.offset as usize..lv.offset as usize + count {
            loss += scale * table[i] as f64 * table[i] as f64;
            grad[i] = 2.0 * scale * table[i] as f64;
        }
    }
    (loss, grad)
}

pub use crate::render::composite::{pcg_hash, rand01, ray_background};

/// Occupancy cell of a scene-normalised point (f32 arithmetic as the kernel), or `None`
/// outside the grid; the flag is true when the point lies within 1e-4 cells of a cell face,
/// where fused and unfused f32 arithmetic may disagree.
pub fn occ_cell(u: [f32; 3], res: u32, cascades: u32) -> (Option<u32>, bool) {
    if u.iter().any(|v| v.is_nan()) {
        return (None, false);
    }
    let m = u.iter().fold(0f32, |m, v| m.max(v.abs()));
    let c = if m <= 1.0 {
        0
    } else if m <= 2f32.powi(cascades as i32 - 1) {
        (m as f64).log2().ceil() as u32
    } else {
        return (None, false);
    };
    let r = res as f32;
    let mut q = [0u32; 3];
    let mut edge = false;
    for d in 0..3 {
        let p = ((u[d] * 2f32.powi(-(c as i32))) * 0.5 + 0.5) * r;
        let pc = p.clamp(0.0, r - 1.0);
        q[d] = pc as u32;
        let exact = ((u[d] as f64 / 2f64.powi(c as i32)) * 0.5 + 0.5) * res as f64;
        edge |= (exact - exact.round()).abs() < 1e-4;
    }
    (Some(((c * res + q[2]) * res + q[1]) * res + q[0]), edge)
}

/// The jittered sample position of an occupancy cell, as `occ_sample` computes it.
pub fn occ_cell_point(cell: u32, seed: u32, res: u32, cascades: u32) -> [f32; 3] {
    let per = res * res * res;
    let total = per * cascades;
    let h = seed
        .wrapping_mul(3)
        .wrapping_mul(total)
        .wrapping_add(cell.wrapping_mul(3));
    let j = [
        rand01(h),
        rand01(h.wrapping_add(1)),
        rand01(h.wrapping_add(2)),
    ];
    let (c, i) = (cell / per, cell % per);
    let q = [i % res, (i / res) % res, i / (res * res)];
    [0, 1, 2].map(|d| ((q[d] as f32 + j[d]) / res as f32 * 2.0 - 1.0) * 2f32.powi(c as i32))
}

/// Activation value and derivative in f64 (see `field::activation`).
pub fn activation(kind: crate::field::activation::Activation, x: f32) -> (f64, f64) {
    use crate::field::activation::Activation;
    let x = x as f64;
    match kind {
        Activation::TruncExp => {
            let y = x.min(15.0).exp();
            (y, y)
        }
        Activation::Sigmoid => {
            let y = 1.0 / (1.0 + (-x).exp());
            let e = (-x.abs()).exp();
            (y, e / ((1.0 + e) * (1.0 + e)))
        }
    }
}

/// The stratified samples of ray `r` in f64: (t, dt, s, ds) per sample, as `stratified` places
/// them (jitter from the same hash).
pub fn stratified(
    r: u32,
    near: f32,
    far: f32,
    k: u32,
    disparity: bool,
    seed: Option<u32>,
) -> Vec<[f64; 4]> {
    let t_of = |s: f64| t_at(s, near, far, disparity);
    (0..k)
        .map(|i| {
            let u = stratum_jitter(r, i, seed);
            let (s0, s1) = (i as f64 / k as f64, (i + 1) as f64 / k as f64);
            let s = s0 + (s1 - s0) * u;
            [t_of(s), t_of(s1) - t_of(s0), s, 1.0 / k as f64]
        })
        .collect()
}

/// Distance at normalised position s (linear in t, or in disparity).
fn t_at(s: f64, near: f32, far: f32, disparity: bool) -> f64 {
    if disparity {
        1.0 / ((1.0 - s) / near as f64 + s / far as f64)
    } else {
        near as f64 + s * (far as f64 - near as f64)
    }
}

/// Position of sample i of ray r inside its stratum (0.5 without a seed).
fn stratum_jitter(r: u32, i: u32, seed: Option<u32>) -> f64 {
    seed.map_or(0.5, |sd| {
        rand01(pcg_hash(sd ^ pcg_hash(r)).wrapping_add(i)) as f64
    })
}

/// Occupancy-aware stratified samples (`stratified_occupied`): `occupied[j]` tells whether
/// probe interval j of [0, 1] (in s) is occupied; the k strata tile the occupied intervals
/// (all of them when none is). `[t, dt, s, ds]` per sample, dt the t-length of the stratum's
/// occupied part.
pub fn stratified_occupied(
    r: u32,
    near: f32,
    far: f32,
    k: u32,
    disparity: bool,
    seed: Option<u32>,
    occupied: &[bool],
) -> Vec<[f64; 4]> {
    let m = occupied.len() as f64;
    let mut runs: Vec<usize> = (0..occupied.len()).filter(|&j| occupied[j]).collect();
    if runs.is_empty() {
        runs = (0..occupied.len()).collect();
    }
    let count = runs.len();
    let per = count as f64 / k as f64;
    let t_of = |s: f64| t_at(s, near, far, disparity);
    // s at occupied measure c (in probe intervals).
    let s_at = |c: f64| {
        let q = (c.floor() as usize).min(count - 1);
        (runs[q] as f64 + c - q as f64) / m
    };
    (0..k)
        .map(|i| {
            let (c0, c1) = (i as f64 * per, (i + 1) as f64 * per);
            let s = s_at(c0 + (c1 - c0) * stratum_jitter(r, i, seed));
            let mut dt = 0.0;
            let (q0, q1) = (c0.floor() as usize, (c1.ceil() as usize).min(count));
            for (q, &run) in runs.iter().enumerate().take(q1).skip(q0) {
                let (a, b) = (c0.max(q as f64), c1.min(q as f64 + 1.0));
                if b > a {
                    let j = run as f64;
                    dt += t_of((j + b - q as f64) / m) - t_of((j + a - q as f64) / m);
                }
            }
            [t_of(s), dt, s, per / m]
        })
        .collect()
}

/// Index of the source bin holding s for sorted `edges` (bins `[edges[i], edges[i + 1])`,
/// the last closed): the count of interior edges at or below s.
fn bin_of(edges: &[f64], s: f64) -> usize {
    edges[1..edges.len() - 1]
        .iter()
        .filter(|&&e| e <= s)
        .count()
}

/// The proposal sampler's resampling of one ray in f64 (`render/proposal.wgsl`'s `resample`):
/// from the source bins (sorted `src_edges`, one more than `src_w`) and their weights, a
/// piecewise-constant density in s proportional to `w + pad` per bin; `k + 1` new edges at
/// its inverse CDF of `u_j = (j + jitter[j]) / (k + 1)`, or `u_j = j / k` without jitter.
pub fn proposal_resample(
    src_edges: &[f64],
    src_w: &[f64],
    pad: f64,
    k: usize,
    jitter: Option<&[f64]>,
) -> Vec<f64> {
    let n = src_w.len();
    let mass: Vec<f64> = src_w.iter().map(|w| w.max(0.0) + pad).collect();
    let total: f64 = mass.iter().sum();
    let mut cdf = vec![0f64; n + 1];
    for i in 0..n {
        cdf[i + 1] = cdf[i] + mass[i] / total;
    }
    (0..=k)
        .map(|j| {
            let u = match jitter {
                Some(jit) => (j as f64 + jit[j]) / (k + 1) as f64,
                None => j as f64 / k as f64,
            };
            // The bin whose CDF interval holds u (the last one for u = 1).
            let i = (0..n).rfind(|&i| cdf[i] <= u).unwrap_or(0);
            let f = ((u - cdf[i]) / (cdf[i + 1] - cdf[i])).clamp(0.0, 1.0);
            src_edges[i] + f * (src_edges[i + 1] - src_edges[i])
        })
        .collect()
}

/// The main samples of bins with sorted `edges` in s, in f64, as `resample` writes them:
/// `[t, dt, s, ds]` per bin, s at the bin's middle and dt, ds its lengths in t and s.
pub fn bin_samples(edges: &[f64], near: f32, far: f32, disparity: bool) -> Vec<[f64; 4]> {
    let t_of = |s: f64| t_at(s, near, far, disparity);
    edges
        .windows(2)
        .map(|e| {
            let s = 0.5 * (e[0] + e[1]);
            [t_of(s), t_of(e[1]) - t_of(e[0]), s, e[1] - e[0]]
        })
        .collect()
}

/// The interlevel loss of one ray in f64 (Mip-NeRF 360's, `render/proposal.wgsl`'s
/// `interlevel`): for each bin `[a, b]` of `edges` with weight `w` (held constant), the bound
/// is the summed weight of the source bins from the one holding a to the one holding b (see
/// `bin_of`; at least the first); the loss is the sum of `max(0, w - bound)^2 / (w + eps)`.
/// Returns the loss and its gradient with respect to each source weight.
pub fn interlevel(
    src_edges: &[f64],
    src_w: &[f64],
    edges: &[f64],
    w: &[f64],
    eps: f64,
) -> (f64, Vec<f64>) {
    let mut loss = 0.0;
    let mut grad = vec![0f64; src_w.len()];
    for j in 0..w.len() {
        let lo = bin_of(src_edges, edges[j]);
        // Bins up to the one whose interval (p_i, p_i+1] holds b.
        let hi = src_edges[1..src_edges.len() - 1]
            .iter()
            .filter(|&&e| e < edges[j + 1])
            .count()
            + 1;
        let hi = hi.max(lo + 1);
        let bound: f64 = src_w[lo..hi].iter().sum();
        let excess = (w[j] - bound).max(0.0);
        loss += excess * excess / (w[j] + eps);
        for g in &mut grad[lo..hi] {
            *g -= 2.0 * excess / (w[j] + eps);
        }
    }
    (loss, grad)
}

/// The BaseNeRF field (see `model::Field`) per sample: `(sigma, rgb)`; sample i looks along
/// `dirs[i / per_ray]`. Each stage runs in f64 on the previous stage's output rounded to f32
/// (the stages' own references take f32 inputs).
pub fn field_forward(
    cfg: &crate::model::ModelConfig,
    params: &[f32],
    positions: &[f32],
    dirs: &[[f32; 3]],
    per_ray: usize,
) -> Vec<(f64, [f64; 3])> {
    let lay = crate::model::ParamLayout::new(cfg);
    let scene = cfg.scene_box();
    let table = &params[lay.table.0..lay.table.0 + lay.table.1];
    let wd = &params[lay.density.0..lay.density.0 + lay.density.1];
    let wc = &params[lay.color.0..lay.color.0 + lay.color.1];
    let contracted: Vec<f32> = positions
        .chunks_exact(3)
        .flat_map(|p| contract([p[0], p[1], p[2]], &scene).map(|v| v as f32))
        .collect();
    let enc: Vec<f32> = hash_grid_forward(&cfg.grid(), table, &contracted)
        .iter()
        .map(|&v| v as f32)
        .collect();
    let dens = mlp_forward(&cfg.density_mlp(), wd, &enc);
    let g = cfg.geo_dims as usize;
    let n = positions.len() / 3;
    let mut color_in = Vec::with_capacity(n * (g + 16));
    for i in 0..n {
        color_in.extend(dens[i * g..(i + 1) * g].iter().map(|&v| v as f32));
        let d = dirs[i / per_ray].map(|v| v as f64);
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let u = if len > 0.0 && len.is_finite() {
            d.map(|v| v / len)
        } else {
            [0.0, 0.0, 1.0]
        };
        color_in.extend(sh4(u).iter().map(|&v| v as f32));
    }
    let col = mlp_forward(&cfg.color_mlp(), wc, &color_in);
    let sig = |x: f64| 1.0 / (1.0 + (-x).exp());
    (0..n)
        .map(|i| {
            (
                dens[i * g].min(15.0).exp(),
                [sig(col[3 * i]), sig(col[3 * i + 1]), sig(col[3 * i + 2])],
            )
        })
        .collect()
}

/// The fused march (`render/march.wgsl`) for one pixel in f64: the camera ray (NDC when the
/// model's space is "ndc", near plane 1), `samples` stratum midpoints (linear in t, or in
/// disparity for world space), the field per sample ([`field_forward`]) and compositing.
/// Samples where `occupied(u)` is false, for u the sample's scene-normalised position, are
/// skipped. Returns (r, g, b, opacity, depth).
pub fn march_pixel(
    cfg: &crate::model::ModelConfig,
    params: &[f32],
    cam: &crate::data::Camera,
    pixel: u32,
    samples: u32,
    background: [f32; 3],
    occupied: &dyn Fn([f32; 3]) -> bool,
) -> [f64; 5] {
    let px = [
        (pixel % cam.width) as f64 + 0.5,
        (pixel / cam.width) as f64 + 0.5,
    ];
    let (wo, wd) = camera_ray(cam, px);
    let ndc = cfg.space == crate::model::Space::Ndc;
    let (o, d) = if ndc {
        ndc_ray(cam, wo, wd, 1.0)
    } else {
        (wo, wd)
    };
    let (near, far) = (cfg.near as f64, cfg.far as f64);
    let t_of = |s: f64| {
        if ndc {
            near + (far - near) * s
        } else {
            1.0 / (1.0 / near + (1.0 / far - 1.0 / near) * s)
        }
    };
    let k = samples as f64;
    let mut pos = Vec::new();
    let mut t_dt = Vec::new();
    for j in 0..samples {
        let (s0, s1) = (j as f64 / k, (j + 1) as f64 / k);
        let t = t_of(0.5 * (s0 + s1));
        let p = [0, 1, 2].map(|a| (o[a] + t * d[a]) as f32);
        let u = [0, 1, 2].map(|a| (p[a] - cfg.center[a]) / cfg.radius);
        if occupied(u) {
            pos.extend(p);
            t_dt.push([t as f32, (t_of(s1) - t_of(s0)) as f32]);
        }
    }
    if t_dt.is_empty() {
        return [
            background[0] as f64,
            background[1] as f64,
            background[2] as f64,
            0.0,
            0.0,
        ];
    }
    let dir = [wd[0] as f32, wd[1] as f32, wd[2] as f32];
    let field = field_forward(cfg, params, &pos, &[dir], t_dt.len());
    let sigma: Vec<f32> = field.iter().map(|f| f.0 as f32).collect();
    let rgb: Vec<[f32; 4]> = field
        .iter()
        .map(|f| [f.1[0] as f32, f.1[1] as f32, f.1[2] as f32, 0.0])
        .collect();
    composite_forward(&sigma, &rgb, &t_dt, background)
}

/// Edge-aware depth completion (`depth_completion`) in f64: `iterations` Jacobi steps; known
/// pixels keep their depth, others take the colour-weighted mean of their 4 neighbours,
/// w = exp(-|c_i - c_j|^2 / sigma^2).
pub fn depth_complete(
    width: usize,
    height: usize,
    depth: &[f32],
    known: &[u32],
    guide: &[[f32; 4]],
    sigma: f32,
    iterations: u32,
) -> Vec<f64> {
    let inv = 1.0 / (sigma as f64 * sigma as f64);
    let mut d: Vec<f64> = depth.iter().map(|&v| v as f64).collect();
    for _ in 0..iterations {
        let mut next = d.clone();
        for y in 0..height {
            for x in 0..width {
                let i = y * width + x;
                if known[i] != 0 {
                    continue;
                }
                let mut sum = 0.0;
                let mut wsum = 0.0;
                let nb = [
                    (x as i64 - 1, y as i64),
                    (x as i64 + 1, y as i64),
                    (x as i64, y as i64 - 1),
                    (x as i64, y as i64 + 1),
                ];
                for (nx, ny) in nb {
                    if nx < 0 || ny < 0 || nx >= width as i64 || ny >= height as i64 {
                        continue;
                    }
                    let j = ny as usize * width + nx as usize;
                    let c2: f64 = (0..3)
                        .map(|c| (guide[j][c] as f64 - guide[i][c] as f64).powi(2))
                        .sum();
                    let w = (-c2 * inv).exp();
                    sum += w * d[j];
                    wsum += w;
                }
                if wsum > 1e-30 {
                    next[i] = sum / wsum;
                }
            }
        }
        d = next;
    }
    d
}

/// Settings of [`visibility_pixel`] (the kernel's `VisibilityConfig` plus the field's space).
#[derive(Clone, Copy, Debug)]
pub struct VisibilitySetup {
    /// The field lives in NDC (near plane 1); otherwise world space, t linear in disparity.
    pub ndc: bool,
    /// Sampling range of camera rays.
    pub near: f64,
    /// See `near`.
    pub far: f64,
    /// Samples per camera ray.
    pub samples: u32,
    /// Samples per segment toward a training camera.
    pub vis_samples: u32,
    /// Which largest transmittance counts.
    pub rank: u32,
    /// Training cameras used (bit k: camera k).
    pub mask: u32,
    /// Absolute transmittance, or relative to the pixel ray's own in front of the sample.
    pub measure: crate::render::visibility::VisibilityMeasure,
}

/// The camera ray of `pixel` (continuous pixel coordinates) in the field's space (NDC with
/// near plane 1 when `ndc`).
fn field_ray(cam: &crate::data::Camera, px: [f64; 2], ndc: bool) -> (glam::DVec3, glam::DVec3) {
    let (wo, wd) = camera_ray(cam, px);
    let (o, d) = if ndc {
        ndc_ray(cam, wo, wd, 1.0)
    } else {
        (wo, wd)
    };
    (glam::DVec3::from(o), glam::DVec3::from(d))
}

/// The distance along a camera ray of `s` at sampling parameter `u` in [0, 1]: linear in NDC,
/// in disparity in world space (the kernels' `t_of`).
pub fn sample_t(s: &VisibilitySetup, u: f64) -> f64 {
    if s.ndc {
        s.near + (s.far - s.near) * u
    } else {
        1.0 / (1.0 / s.near + (1.0 / s.far - 1.0 / s.near) * u)
    }
}

/// A camera's NDC frame (near plane 1; the kernel's f32 intrinsics): field space <-> world.
struct Frame {
    ndc: bool,
    ax: f64,
    ay: f64,
}

impl Frame {
    fn new(cam: &crate::data::Camera, ndc: bool) -> Frame {
        Frame {
            ndc,
            ax: -2.0 * (cam.fx as f32) as f64 / cam.width as f64,
            ay: -2.0 * (cam.fy as f32) as f64 / cam.height as f64,
        }
    }

    fn to_world(&self, x: glam::DVec3) -> glam::DVec3 {
        if !self.ndc {
            return x;
        }
        let z = 2.0 / (x.z - 1.0);
        glam::DVec3::new(x.x * z / self.ax, x.y * z / self.ay, z)
    }

    fn to_field(&self, p: glam::DVec3) -> glam::DVec3 {
        if !self.ndc {
            return p;
        }
        glam::DVec3::new(self.ax * p.x / p.z, self.ay * p.y / p.z, 1.0 + 2.0 / p.z)
    }
}

/// Pixel coordinates (u, v) of world point p in camera c when it is in front of c and inside its
/// image (edges included).
fn in_image(c: &crate::data::Camera, p: glam::DVec3) -> Option<(f64, f64, f64)> {
    let r = glam::DMat3::from_mat4(c.c2w).transpose() * (p - c.centre());
    if r.z >= 0.0 {
        return None;
    }
    let u = c.fx * r.x / -r.z + c.cx;
    let v = -c.fy * r.y / -r.z + c.cy;
    ((0.0..=c.width as f64).contains(&u) && (0.0..=c.height as f64).contains(&v))
        .then_some((u, v, -r.z))
}

/// The part both visibility references share: march the pixel's ray (stratum midpoints, exact
/// alpha); for each weighted sample at field point x (world p) whose previous sample sits at
/// field point xs (world ps), `transmittance(k, x, p, xs, ps)` gives selected camera k's
/// transmittance (divided by the ray's own in front of the sample and capped at 1 for the
/// relative measure); the rank-th largest, weighted, sums to the visibility. Returns (visibility,
/// opacity, depth).
fn visibility_march(
    density: &dyn Fn([f64; 3]) -> f64,
    cam: &crate::data::Camera,
    pixel: u32,
    n_train: usize,
    s: &VisibilitySetup,
    given: Option<&[[f64; 2]]>,
    transmittance: &dyn Fn(usize, glam::DVec3, glam::DVec3, glam::DVec3, glam::DVec3) -> f64,
) -> [f64; 3] {
    let px = [
        (pixel % cam.width) as f64 + 0.5,
        (pixel / cam.width) as f64 + 0.5,
    ];
    let (o, d) = field_ray(cam, px, s.ndc);
    let frame = Frame::new(cam, s.ndc);
    let k = s.samples as f64;
    let (mut tau, mut vis, mut opacity, mut depth) = (0.0f64, 0.0, 0.0, 0.0);
    for j in 0..s.samples {
        let (s0, s1) = (j as f64 / k, (j + 1) as f64 / k);
        // Every segment starts at the previous sample (the near end for the first).
        let (t, dt, t_prev) = match given {
            Some(g) => (
                g[j as usize][0],
                g[j as usize][1],
                match j {
                    0 => sample_t(s, 0.0),
                    _ => g[j as usize - 1][0],
                },
            ),
            None => (
                sample_t(s, 0.5 * (s0 + s1)),
                sample_t(s, s1) - sample_t(s, s0),
                match j {
                    0 => sample_t(s, 0.0),
                    _ => sample_t(s, s0 - 0.5 / k),
                },
            ),
        };
        let x = o + t * d;
        let xo = (density(x.to_array()).max(0.0) * dt).max(0.0);
        let own = (-tau).exp();
        let w = own * (1.0 - (-xo).exp());
        tau += xo;
        opacity += w;
        depth += w * t;
        let xs = o + t_prev * d;
        let (p, ps) = (frame.to_world(x), frame.to_world(xs));
        if w.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
            || !p.is_finite()
            || !ps.is_finite()
        {
            continue;
        }
        let mut ts: Vec<f64> = (0..n_train.min(32))
            .filter(|&c| (s.mask >> c) & 1 == 1)
            .map(|c| {
                let t = transmittance(c, x, p, xs, ps);
                match s.measure {
                    crate::render::visibility::VisibilityMeasure::Absolute => t,
                    crate::render::visibility::VisibilityMeasure::Relative => (t / own).min(1.0),
                }
            })
            .collect();
        ts.sort_by(|a, b| b.total_cmp(a));
        vis += w
            * (s.rank as usize)
                .checked_sub(1)
                .and_then(|r| ts.get(r))
                .copied()
                .unwrap_or(0.0);
    }
    [vis, opacity, depth]
}

/// Multi-view transmittance visibility (`render/visibility.wgsl`, no cuts, no occupancy) of
/// one pixel in f64, for a density given in the field's space: each segment from the previous
/// sample to a camera (clipped where the sampled range starts in NDC, at t = `near`, or `near`
/// before a world-space camera)
/// marched with `vis_samples` midpoints. Returns (visibility, opacity, depth).
pub fn visibility_pixel(
    density: &dyn Fn([f64; 3]) -> f64,
    cam: &crate::data::Camera,
    pixel: u32,
    train: &[crate::data::Camera],
    s: &VisibilitySetup,
) -> [f64; 3] {
    visibility_pixel_given(density, cam, pixel, train, s, None)
}

/// [`visibility_pixel`] at the pixel ray's samples `given` (`(t, dt)`, `s.samples` of them,
/// sorted along the ray; each segment starts at the previous given sample, the first at the
/// near end) in place of the strata, or at the strata for `None`.
///
/// # Panics
/// When `given` holds fewer than `s.samples` samples (a test's own mistake: the reference
/// takes no user input).
pub fn visibility_pixel_given(
    density: &dyn Fn([f64; 3]) -> f64,
    cam: &crate::data::Camera,
    pixel: u32,
    train: &[crate::data::Camera],
    s: &VisibilitySetup,
    given: Option<&[[f64; 2]]>,
) -> [f64; 3] {
    let frame = Frame::new(cam, s.ndc);
    let segment = |k: usize, _x, p, xs: glam::DVec3, ps: glam::DVec3| -> f64 {
        let c = &train[k];
        if in_image(c, p).is_none() {
            return 0.0;
        }
        let centre = c.centre();
        let end = if s.ndc {
            // The plane where the sampled range starts: NDC t = near, world z = -1 / (1 - near).
            let zn = -1.0 / (1.0 - s.near);
            let mut e = centre;
            if centre.z > zn {
                e = ps + (zn - ps.z) / (centre.z - ps.z) * (centre - ps);
                e.z = zn;
            }
            frame.to_field(e)
        } else {
            let len = (centre - ps).length();
            if len <= s.near {
                return 1.0;
            }
            ps + (centre - ps) * ((len - s.near) / len)
        };
        let scale = if s.ndc { 0.5 } else { 1.0 };
        let seg = end - xs;
        let len = seg.length();
        if len <= 0.0 {
            return 1.0;
        }
        let dir = seg / len;
        let step = len / s.vis_samples as f64;
        let od: f64 = (0..s.vis_samples)
            .map(|m| {
                let y = xs + dir * ((m as f64 + 0.5) * step);
                density(y.to_array()).max(0.0) * step * scale
            })
            .sum();
        (-od).exp()
    };
    visibility_march(density, cam, pixel, train.len(), s, given, &segment)
}

/// Transmittance volumes (`render/visibility.wgsl`'s `transmittance_volume`) in f64: per
/// camera, row and column of a `w` x `h` grid of ray cells, T at the `d + 1` boundaries of `d`
/// strata (densities at the strata midpoints).
pub fn transmittance_volume(
    density: &dyn Fn([f64; 3]) -> f64,
    train: &[crate::data::Camera],
    size: [u32; 3],
    s: &VisibilitySetup,
) -> Vec<f64> {
    let [w, h, d] = size;
    let mut out = Vec::new();
    for c in train {
        for y in 0..h {
            for x in 0..w {
                let px = [
                    (x as f64 + 0.5) / w as f64 * c.width as f64,
                    (y as f64 + 0.5) / h as f64 * c.height as f64,
                ];
                let (o, dir) = field_ray(c, px, s.ndc);
                let mut tau = 0.0;
                out.push(1.0);
                for m in 0..d {
                    let (s0, s1) = (m as f64 / d as f64, (m + 1) as f64 / d as f64);
                    let t = sample_t(s, 0.5 * (s0 + s1));
                    let dt = sample_t(s, s1) - sample_t(s, s0);
                    tau += density((o + t * dir).to_array()).max(0.0) * dt;
                    out.push((-tau).exp());
                }
            }
        }
    }
    out
}

/// Visibility of one pixel with transmittances looked up in `volume` (laid out as
/// [`transmittance_volume`] returns it): 0 for a sample outside camera k's image or behind
/// it; else k's T at the previous sample's world position, bilinear across rays (clamped to
/// the grid), at the near boundary of the stratum that holds it.
///
/// # Panics
/// When `size` has a zero or `volume` holds fewer than `train.len() * w * h * (d + 1)` values
/// (a test's own mistake: the reference takes no user input).
pub fn visibility_pixel_volume(
    density: &dyn Fn([f64; 3]) -> f64,
    cam: &crate::data::Camera,
    pixel: u32,
    train: &[crate::data::Camera],
    s: &VisibilitySetup,
    volume: &[f64],
    size: [u32; 3],
) -> [f64; 3] {
    let [w, h, d] = size;
    assert!(
        w > 0 && h > 0 && d > 0 && volume.len() >= train.len() * (w * h * (d + 1)) as usize,
        "visibility_pixel_volume: a {w}x{h}x{d} volume for {} cameras needs more than {} values",
        train.len(),
        volume.len()
    );
    let lookup = |k: usize, _x, p, _xs, ps: glam::DVec3| -> f64 {
        let c = &train[k];
        if in_image(c, p).is_none() {
            return 0.0;
        }
        let r = glam::DMat3::from_mat4(c.c2w).transpose() * (ps - c.centre());
        if r.z >= 0.0 {
            return 1.0;
        }
        let u = c.fx * r.x / -r.z + c.cx;
        let v = -c.fy * r.y / -r.z + c.cy;
        let t = if s.ndc { 1.0 + 1.0 / ps.z } else { -r.z };
        let sp = if s.ndc {
            (t - s.near) / (s.far - s.near)
        } else {
            (1.0 / t - 1.0 / s.near) / (1.0 / s.far - 1.0 / s.near)
        }
        .clamp(0.0, 1.0);
        let fx = (u / c.width as f64 * w as f64 - 0.5).clamp(0.0, (w - 1) as f64);
        let fy = (v / c.height as f64 * h as f64 - 0.5).clamp(0.0, (h - 1) as f64);
        let z0 = ((sp * d as f64) as u32).min(d - 1);
        let (x0, y0) = ((fx as u32).min(w - 1), (fy as u32).min(h - 1));
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
        let at = |x: u32, y: u32| volume[(((k as u32 * h + y) * w + x) * (d + 1) + z0) as usize];
        let top = at(x0, y0) * (1.0 - tx) + at(x1, y0) * tx;
        let bottom = at(x0, y1) * (1.0 - tx) + at(x1, y1) * tx;
        top * (1.0 - ty) + bottom * ty
    };
    visibility_march(density, cam, pixel, train.len(), s, None, &lookup)
}

/// Plane-sweep stereo (`depth/mvs.wgsl`'s `mvs_sweep`) of reference pixel (x, y) of view `r`
/// against every other view, in f64. Returns (depth, confidence, cost per plane); depth 0 when
/// no plane had enough voting sources or the window is textureless (no costs then).
pub fn mvs_pixel(
    cams: &[crate::data::Camera],
    grey: &[Vec<f32>],
    r: usize,
    cfg: &crate::mvs::MvsConfig,
    x: u32,
    y: u32,
) -> (f64, f64, Vec<f64>) {
    use glam::DVec3;
    let (w, h) = (cams[r].width as i64, cams[r].height as i64);
    let rad = cfg.radius as i64;
    let side = 2 * rad + 1;
    let count = (side * side) as f64;
    let sample = |v: usize, q: [f64; 2]| {
        let fx = (q[0] - 0.5).clamp(0.0, (w - 1) as f64);
        let fy = (q[1] - 0.5).clamp(0.0, (h - 1) as f64);
        let (x0, y0) = ((fx as i64).min(w - 1), (fy as i64).min(h - 1));
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (ax, ay) = (fx - x0 as f64, fy - y0 as f64);
        let g = |xx: i64, yy: i64| grey[v][(yy * w + xx) as usize] as f64;
        let top = g(x0, y0) * (1.0 - ax) + g(x1, y0) * ax;
        let bottom = g(x0, y1) * (1.0 - ax) + g(x1, y1) * ax;
        top * (1.0 - ay) + bottom * ay
    };
    let mut win = Vec::new();
    let mut dirs = Vec::new();
    for k in 0..side * side {
        let qx = (x as i64 + k % side - rad).clamp(0, w - 1);
        let qy = (y as i64 + k / side - rad).clamp(0, h - 1);
        win.push(grey[r][(qy * w + qx) as usize] as f64);
        dirs.push(DVec3::from(
            camera_ray(&cams[r], [qx as f64 + 0.5, qy as f64 + 0.5]).1,
        ));
    }
    let sa: f64 = win.iter().sum();
    let saa: f64 = win.iter().map(|v| v * v).sum();
    let var_a = saa - sa * sa / count;
    if var_a <= 1e-6 * count {
        return (0.0, 0.0, Vec::new());
    }
    let o = cams[r].centre();
    let depth_of = |m: f64| {
        let s = m / (cfg.planes as f64 - 1.0).max(1.0);
        1.0 / (1.0 / cfg.near as f64 + (1.0 / cfg.far as f64 - 1.0 / cfg.near as f64) * s)
    };
    let kb = cfg.best_k.clamp(1, 8) as usize;
    let mut costs = Vec::new();
    for m in 0..cfg.planes {
        let d = depth_of(m as f64);
        let mut src = Vec::new();
        for (s, c) in cams.iter().enumerate() {
            if s == r || s >= 32 {
                continue;
            }
            let mut b = Vec::new();
            for dir in &dirs {
                let (u, v, z) = c.project(o + d * *dir);
                if !(z > 0.0 && u >= 0.0 && v >= 0.0 && u <= w as f64 && v <= h as f64) {
                    break;
                }
                b.push(sample(s, [u, v]));
            }
            if b.len() < win.len() {
                continue;
            }
            let sb: f64 = b.iter().sum();
            let sbb: f64 = b.iter().map(|v| v * v).sum();
            let sab: f64 = b.iter().zip(&win).map(|(p, q)| p * q).sum();
            let var_b = sbb - sb * sb / count;
            let ncc = if var_b > 1e-6 * count {
                ((sab - sa * sb / count) / (var_a * var_b).sqrt()).clamp(-1.0, 1.0)
            } else {
                -1.0
            };
            src.push(1.0 - ncc);
        }
        src.sort_by(f64::total_cmp);
        costs.push(if src.len() >= kb {
            src[..kb].iter().sum::<f64>() / kb as f64
        } else {
            2.0
        });
    }
    let (best_m, best) =
        costs.iter().enumerate().fold(
            (0, 3.0),
            |acc, (m, &c)| if c < acc.1 { (m, c) } else { acc },
        );
    if best >= 2.0 {
        return (0.0, 0.0, costs);
    }
    let mut delta = 0.0;
    if best_m > 0 && best_m + 1 < costs.len() {
        let (cb, ca) = (costs[best_m - 1], costs[best_m + 1]);
        let den = cb - 2.0 * best + ca;
        if den > 1e-12 {
            delta = (0.5 * (cb - ca) / den).clamp(-0.5, 0.5);
        }
    }
    (
        depth_of(best_m as f64 + delta),
        (1.0 - best).clamp(0.0, 1.0),
        costs,
    )
}

/// The consistency check (`mvs_consistency`) of reference pixel (x, y) of view `r` in f64,
/// given every view's winner-take-all depth and confidence: (kept depth, kept confidence).
pub fn mvs_consistency_pixel(
    cams: &[crate::data::Camera],
    depths: &[Vec<f32>],
    confs: &[Vec<f32>],
    r: usize,
    cfg: &crate::mvs::MvsConfig,
    x: u32,
    y: u32,
) -> (f64, f64) {
    use glam::DVec3;
    let (w, h) = (cams[r].width, cams[r].height);
    let i = (y * w + x) as usize;
    let d = depths[r][i] as f64;
    if d <= 0.0 {
        return (0.0, 0.0);
    }
    let px = [x as f64 + 0.5, y as f64 + 0.5];
    let p = cams[r].centre() + d * DVec3::from(camera_ray(&cams[r], px).1);
    let mut agree = 0;
    for (s, c) in cams.iter().enumerate() {
        if s == r || s >= 32 {
            continue;
        }
        let (u, v, z) = c.project(p);
        if !(z > 0.0 && u >= 0.0 && v >= 0.0 && u < w as f64 && v < h as f64) {
            continue;
        }
        let (sx, sy) = ((u as u32).min(w - 1), (v as u32).min(h - 1));
        let ds = depths[s][(sy * w + sx) as usize] as f64;
        if ds <= 0.0 {
            continue;
        }
        let dir = DVec3::from(camera_ray(c, [sx as f64 + 0.5, sy as f64 + 0.5]).1);
        let (bu, bv, bz) = cams[r].project(c.centre() + ds * dir);
        if bz > 0.0
            && ((bu - px[0]).powi(2) + (bv - px[1]).powi(2)).sqrt() <= cfg.px_tol as f64
            && (bz - d).abs() <= cfg.rel_tol as f64 * d
        {
            agree += 1;
        }
    }
    if agree >= cfg.min_agree {
        (d, confs[r][i] as f64)
    } else {
        (0.0, 0.0)
    }
}

/// One step of the sparse Adam (`optim/adam_sparse.wgsl`, tiny-cuda-nn's rule) in f64: floats
/// `0..table` (a hash table) are updated only in the vec4s whose bit is set in `touched` (bit
/// i of word w: vec4 32 w + i), the others keep their parameter and moments; floats `rest..`
/// are updated densely; floats between the two are left alone. `g` holds the gradient with
/// any decay terms already added, as [`adam_step_with`] takes it.
#[allow(clippy::too_many_arguments)] // mirrors the kernel's operands
pub fn adam_step_sparse(
    p: &mut [f64],
    m: &mut [f64],
    v: &mut [f64],
    g: &[f32],
    touched: &[u32],
    table: usize,
    rest: usize,
    cfg: &crate::optim::AdamConfig,
    step: u32,
    grad_scale: f64,
) {
    let on = |i: usize| touched[i / 128] >> ((i / 4) % 32) & 1 == 1;
    let pick: Vec<usize> = (0..table).filter(|&i| on(i)).chain(rest..p.len()).collect();
    let (mut ps, mut ms, mut vs): (Vec<f64>, Vec<f64>, Vec<f64>) = (
        pick.iter().map(|&i| p[i]).collect(),
        pick.iter().map(|&i| m[i]).collect(),
        pick.iter().map(|&i| v[i]).collect(),
    );
    let gs: Vec<f32> = pick.iter().map(|&i| g[i]).collect();
    adam_step_with(&mut ps, &mut ms, &mut vs, &gs, cfg, step, grad_scale);
    for (k, &i) in pick.iter().enumerate() {
        p[i] = ps[k];
        m[i] = ms[k];
        v[i] = vs[k];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The reference backward is the gradient of the reference forward (finite differences:
    /// the encoding is linear in the table, so central differences are exact up to rounding).
    #[test]
    fn backward_is_the_gradient_of_forward() {
        let cfg = HashGridConfig {
            levels: 3,
            features: 2,
            log2_table: 6,
            min_res: 2,
            max_res: 9,
        };
        let n = cfg.param_count() as usize;
        let mut table: Vec<f32> = (0..n)
            .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
            .collect();
        let positions = [
            0.1f32, 0.7, 0.33, 0.999, 0.0, 0.5, 1.0, 1.0, 1.0, -3.0, 0.25, 2.0,
        ];
        let out_dim = positions.len() / 3 * 6;
        let d: Vec<f32> = (0..out_dim).map(|i| (i as f32 * 0.37).sin()).collect();
        let grad = hash_grid_backward(&cfg, &positions, &d);
        let loss = |t: &[f32]| -> f64 {
            hash_grid_forward(&cfg, t, &positions)
                .iter()
                .zip(&d)
                .map(|(a, &b)| a * b as f64)
                .sum()
        };
        for e in 0..n {
            let h = 0.5f32;
            let orig = table[e];
            table[e] = orig + h;
            let up = loss(&table);
            table[e] = orig - h;
            let down = loss(&table);
            table[e] = orig;
            let fd = (up - down) / (2.0 * h as f64);
            assert!(
                (fd - grad[e]).abs() < 1e-6,
                "entry {e}: finite difference {fd} vs {}",
                grad[e]
            );
        }
    }

    /// The reference MLP backward matches central finite differences of the forward (f64).
    #[test]
    fn mlp_backward_is_the_gradient_of_forward() {
        let cfg = MlpConfig {
            dims: vec![5, 7, 6, 3],
        };
        let mut w: Vec<f32> = (0..cfg.param_count())
            .map(|i| ((i * 53 % 97) as f32 / 48.0) - 1.0)
            .collect();
        let mut x: Vec<f32> = (0..10)
            .map(|i| ((i * 29 % 31) as f32 / 15.0) - 1.0)
            .collect();
        let dy: Vec<f32> = (0..6).map(|i| (i as f32 * 0.71).cos()).collect();
        let (d_in, d_w) = mlp_backward(&cfg, &w, &x, &dy);
        let loss = |w: &[f32], x: &[f32]| -> f64 {
            mlp_forward(&cfg, w, x)
                .iter()
                .zip(&dy)
                .map(|(a, &b)| a * b as f64)
                .sum()
        };
        let h = 1e-3f32;
        for e in 0..w.len() {
            let orig = w[e];
            w[e] = orig + h;
            let up = loss(&w, &x);
            w[e] = orig - h;
            let down = loss(&w, &x);
            w[e] = orig;
            let fd = (up - down) / (2.0 * h as f64);
            assert!(
                (fd - d_w[e]).abs() < 1e-3 * (1.0 + fd.abs()),
                "weight {e}: {fd} vs {}",
                d_w[e]
            );
        }
        for e in 0..x.len() {
            let orig = x[e];
            x[e] = orig + h;
            let up = loss(&w, &x);
            x[e] = orig - h;
            let down = loss(&w, &x);
            x[e] = orig;
            let fd = (up - down) / (2.0 * h as f64);
            assert!(
                (fd - d_in[e]).abs() < 1e-3 * (1.0 + fd.abs()),
                "input {e}: {fd} vs {}",
                d_in[e]
            );
        }
    }

    /// Compositing backward and distortion gradient against central finite differences.
    #[test]
    fn composite_and_distortion_gradients_match_finite_differences() {
        let n = 12;
        let mut sigma: Vec<f32> = (0..n).map(|i| ((i * 7 % 11) as f32) * 0.9 + 0.05).collect();
        sigma[3] = 0.0;
        let rgb: Vec<[f32; 4]> = (0..n)
            .map(|i| {
                [
                    ((i * 3 % 7) as f32) / 7.0,
                    0.3,
                    ((i * 5 % 9) as f32) / 9.0,
                    0.0,
                ]
            })
            .collect();
        let t_dt: Vec<[f32; 2]> = (0..n).map(|i| [1.0 + 0.1 * i as f32, 0.1]).collect();
        let bg = [0.2f32, 0.9, 0.4];
        let g = [0.3f32, -0.7, 0.5, 0.25];
        let gd = -0.4f32;
        let dw: Vec<f32> = (0..n).map(|i| (i as f32 * 0.3).sin() * 0.2).collect();
        let (d_sigma, d_rgb) = composite_backward(&sigma, &rgb, &t_dt, bg, g, gd, &dw, false);
        // Gradient scaling only rescales per sample.
        let (scaled, _) = composite_backward(&sigma, &rgb, &t_dt, bg, g, gd, &dw, true);
        for i in 0..n {
            let t = t_dt[i][0] as f64;
            assert!((scaled[i] - d_sigma[i] * (t * t).min(1.0)).abs() < 1e-12);
        }
        let dt: Vec<f32> = t_dt.iter().map(|v| v[1]).collect();
        let loss = |s: &[f32], c: &[[f32; 4]]| -> f64 {
            let o = composite_forward(s, c, &t_dt, bg);
            let (w, _) = ray_weights(s, &dt);
            (0..4).map(|k| o[k] * g[k] as f64).sum::<f64>()
                + o[4] * gd as f64
                + w.iter().zip(&dw).map(|(a, &b)| a * b as f64).sum::<f64>()
        };
        let h = 1e-3f32;
        for i in 0..n {
            let mut s = sigma.clone();
            s[i] = sigma[i] + h;
            let up = loss(&s, &rgb);
            // One-sided at sigma = 0 (the density cannot go below 0).
            let (down, span) = if sigma[i] > h {
                s[i] = sigma[i] - h;
                (loss(&s, &rgb), 2.0 * h as f64)
            } else {
                (loss(&sigma, &rgb), h as f64)
            };
            let fd = (up - down) / span;
            assert!(
                (fd - d_sigma[i]).abs() < 1e-4,
                "sigma {i}: {fd} vs {}",
                d_sigma[i]
            );
            for c in 0..3 {
                let mut col = rgb.clone();
                col[i][c] += h;
                let fd = (loss(&sigma, &col) - loss(&sigma, &rgb)) / h as f64;
                assert!(
                    (fd - d_rgb[i][c]).abs() < 1e-5,
                    "rgb {i}.{c}: {fd} vs {}",
                    d_rgb[i][c]
                );
            }
        }
        // Distortion: dL/dw by finite differences of the O(N^2) definition in w.
        let s_ds: Vec<[f32; 2]> = (0..n).map(|i| [0.05 + 0.08 * i as f32, 0.08]).collect();
        let (_, grad) = distortion(&sigma, &t_dt, &s_ds, 0.5);
        let (w, _) = ray_weights(&sigma, &dt);
        let m: Vec<f64> = s_ds.iter().map(|v| v[0] as f64).collect();
        let ds: Vec<f64> = s_ds.iter().map(|v| v[1] as f64).collect();
        for i in 0..n {
            let mut wp = w.clone();
            wp[i] += 1e-6;
            let mut wm = w.clone();
            wm[i] -= 1e-6;
            let fd = 0.5
                * (distortion_from_weights(&wp, &m, &ds) - distortion_from_weights(&wm, &m, &ds))
                / 2e-6;
            assert!(
                (fd - grad[i]).abs() < 1e-6,
                "distortion w {i}: {fd} vs {}",
                grad[i]
            );
        }
    }

    /// The SH basis is orthonormal over the sphere (quadrature on a Fibonacci sphere), which
    /// checks every constant independently of the formulas' transcription.
    #[test]
    fn sh_basis_is_orthonormal() {
        let n = 40_000;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let mut gram = [[0f64; 16]; 16];
        for i in 0..n {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let (s, c) = (golden * i as f64).sin_cos();
            let y = sh4([r * c, r * s, z]);
            for (row, ya) in gram.iter_mut().zip(y) {
                for (g, yb) in row.iter_mut().zip(y) {
                    *g += ya * yb * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for (a, row) in gram.iter().enumerate() {
            for (b, g) in row.iter().enumerate() {
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((g - want).abs() < 1e-3, "<Y{a}, Y{b}> = {g}");
            }
        }
    }

    #[test]
    fn contraction_is_continuous_and_bounded() {
        use crate::field::encodings::{Contraction, SceneBox};
        for contraction in [Contraction::L2, Contraction::LInf] {
            let s = SceneBox {
                center: [1.0, 2.0, 3.0],
                radius: 2.0,
                contraction,
            };
            // Continuous across the unit sphere / cube (radius 2 around the centre).
            let a = contract([3.0 - 1e-4, 2.0, 3.0], &s);
            let b = contract([3.0 + 1e-4, 2.0, 3.0], &s);
            assert!((a[0] - b[0]).abs() < 1e-4);
            // The centre maps to the middle; far points approach the boundary of radius 2.
            assert_eq!(contract([1.0, 2.0, 3.0], &s), [0.5, 0.5, 0.5]);
            let far = contract([1e30, 2.0, 3.0], &s);
            assert!((far[0] - 1.0).abs() < 1e-12 && (far[1] - 0.5).abs() < 1e-12);
        }
    }

    /// Ray losses and hash decay against central finite differences.
    #[test]
    fn loss_gradients_match_finite_differences() {
        use crate::render::loss::{LossConfig, RgbLoss};
        // Colour weights: the configured loss at full and partial weight, L1 (negative; plain,
        // and smooth with a core that holds two of the three channels' errors) and none (zero,
        // which must leave no colour gradient). The core changes nothing for w >= 0.
        for (rgb, w, core) in [
            (RgbLoss::L2, 1.0f32, 0.0f32),
            (RgbLoss::L2, 0.4, 0.0),
            (RgbLoss::L2, 0.4, 0.1),
            (RgbLoss::Huber(0.1), 1.0, 0.0),
            (RgbLoss::Huber(0.1), 0.4, 0.1),
            (RgbLoss::L2, -0.7, 0.0),
            (RgbLoss::Huber(0.1), -1.0, 0.0),
            (RgbLoss::L2, -0.7, 0.1),
            (RgbLoss::Huber(0.1), -1.0, 0.03),
            (RgbLoss::L2, 0.0, 0.1),
        ] {
            let cfg = LossConfig {
                rgb,
                depth_lambda: 0.3,
                l1_core: core,
            };
            let (r, d, t, td) = (
                [0.9f32, 0.2, 0.55, 1.0],
                2.5f32,
                [0.1f32, 0.25, 0.5, w],
                [2.0f32, 0.7],
            );
            let (_, g, gd) = ray_loss(r, d, t, td, &cfg);
            let h = 1e-3f32;
            for c in 0..3 {
                let (mut up, mut dn) = (r, r);
                up[c] += h;
                dn[c] -= h;
                let fd = (ray_loss(up, d, t, td, &cfg).0 - ray_loss(dn, d, t, td, &cfg).0)
                    / (2.0 * h as f64);
                assert!(
                    (fd - g[c]).abs() < 1e-4,
                    "{rgb:?} weight {w} channel {c}: {fd} vs {}",
                    g[c]
                );
                assert_eq!(g[c] == 0.0, w == 0.0, "{rgb:?} weight {w} channel {c}");
            }
            let fd = (ray_loss(r, d + h, t, td, &cfg).0 - ray_loss(r, d - h, t, td, &cfg).0)
                / (2.0 * h as f64);
            assert!((fd - gd).abs() < 1e-4, "depth: {fd} vs {gd}");
            assert_eq!(
                ray_loss(r, d, t, [2.0, 0.0], &cfg).2,
                0.0,
                "no target, no depth gradient"
            );
        }
        // L1 is |e| summed over the channels / 3, times the weight; smooth L1 with a core of
        // 0.1 is |e| - 0.05 for the error of 0.8 and e^2 / 0.2 for the two of 0.05.
        let mut cfg = LossConfig {
            rgb: RgbLoss::L2,
            depth_lambda: 0.0,
            l1_core: 0.0,
        };
        let l1 = |cfg: &LossConfig| {
            ray_loss(
                [0.9, 0.2, 0.55, 1.0],
                0.0,
                [0.1, 0.25, 0.5, -0.5],
                [0.0; 2],
                cfg,
            )
        };
        let plain = l1(&cfg).0;
        assert!(
            (plain - 0.5 * (0.8 + 0.05 + 0.05) / 3.0).abs() < 1e-7,
            "{plain}"
        );
        cfg.l1_core = 0.1;
        let (smooth, g, _) = l1(&cfg);
        let want = 0.5 * (0.75 + 2.0 * 0.0025 / 0.2) / 3.0;
        assert!((smooth - want).abs() < 1e-7, "{smooth} vs {want}");
        // Inside the core the gradient is e / core, not the sign: here half of it.
        assert!((g[1] - 0.5 * -0.5 / 3.0).abs() < 1e-6, "{g:?}");
        assert!((g[0] - 0.5 / 3.0).abs() < 1e-7, "{g:?}");
        let hg = HashGridConfig {
            levels: 3,
            features: 2,
            log2_table: 6,
            min_res: 2,
            max_res: 8,
        };
        let mut table: Vec<f32> = (0..hg.param_count() as usize)
            .map(|i| ((i * 13 % 17) as f32 - 8.0) / 8.0)
            .collect();
        let (_, grad) = hash_decay(&hg, &table, 0.5);
        for i in (0..table.len()).step_by(7) {
            let orig = table[i];
            table[i] = orig + 1e-3;
            let up = hash_decay(&hg, &table, 0.5).0;
            table[i] = orig - 1e-3;
            let dn = hash_decay(&hg, &table, 0.5).0;
            table[i] = orig;
            assert!(((up - dn) / 2e-3 - grad[i]).abs() < 1e-6, "entry {i}");
        }
    }

    #[test]
    fn activation_derivatives_match_finite_differences() {
        use crate::field::activation::Activation;
        for kind in [Activation::TruncExp, Activation::Sigmoid] {
            for x in [-30.0f32, -3.0, -0.5, 0.0, 0.7, 4.0, 14.0] {
                let h = 1e-3f64;
                let f = |v: f64| {
                    let v = v as f32 as f64;
                    match kind {
                        Activation::TruncExp => v.min(15.0).exp(),
                        Activation::Sigmoid => 1.0 / (1.0 + (-v).exp()),
                    }
                };
                let fd = (f(x as f64 + h) - f(x as f64 - h)) / (2.0 * h);
                let (_, d) = activation(kind, x);
                assert!(
                    (fd - d).abs() <= 1e-3 * d.abs() + 1e-12,
                    "{kind:?} at {x}: {fd} vs {d}"
                );
            }
        }
    }

    #[test]
    fn layout_dense_then_hashed() {
        let cfg = HashGridConfig {
            levels: 4,
            features: 2,
            log2_table: 10,
            min_res: 4,
            max_res: 32,
        };
        let l = cfg.level_layout();
        assert_eq!(
            l.iter().map(|l| l.res).collect::<Vec<_>>(),
            vec![4, 8, 16, 32]
        );
        assert_eq!((l[0].dense, l[0].size), (1, 125));
        assert_eq!((l[1].dense, l[1].size), (1, 729));
        assert_eq!((l[2].dense, l[2].size), (0, 1024));
        assert_eq!(l[1].offset, 250);
        assert_eq!(cfg.param_count(), 2 * (125 + 729 + 1024 + 1024));
    }
}
