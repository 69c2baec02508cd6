//! Plain-Rust definitions of the NeRF kernels, in f64 where it matters; the tests compare the
//! GPU against these on random inputs.

use crate::field::hash_grid::{HashGridConfig, HashLevel};

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
