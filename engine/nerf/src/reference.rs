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
    let mut acts = vec![x.iter().map(|&v| v as f64).collect::<Vec<f64>>()];
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
                .map(|&z| if last { z } else { z.max(0.0) })
                .collect(),
        );
        pres.push(pre);
    }
    (acts, pres)
}

/// MLP backward in f64: (dL/dinputs, dL/dweights) for `d_outputs`.
pub fn mlp_backward(
    cfg: &MlpConfig,
    weights: &[f32],
    inputs: &[f32],
    d_outputs: &[f32],
) -> (Vec<f64>, Vec<f64>) {
    let (n_in, n_out) = (cfg.dims[0] as usize, cfg.dims[cfg.layers()] as usize);
    let mut d_in = Vec::with_capacity(inputs.len());
    let mut d_w = vec![0f64; cfg.param_count()];
    for (x, dy) in inputs.chunks_exact(n_in).zip(d_outputs.chunks_exact(n_out)) {
        let (acts, pres) = mlp_point(cfg, weights, x);
        let mut g: Vec<f64> = dy.iter().map(|&v| v as f64).collect();
        for l in (0..cfg.layers()).rev() {
            let (ni, no) = (cfg.dims[l] as usize, cfg.dims[l + 1] as usize);
            let off = cfg.offset(l);
            let last = l + 1 == cfg.layers();
            let delta: Vec<f64> = (0..no)
                .map(|o| if last || pres[l][o] > 0.0 { g[o] } else { 0.0 })
                .collect();
            for o in 0..no {
                for j in 0..ni {
                    d_w[off + o * ni + j] += delta[o] * acts[l][j];
                }
                d_w[off + no * ni + o] += delta[o];
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
