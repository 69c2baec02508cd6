//! Simple fills that an inpainting model has to beat: the mean colour of the known pixels, the
//! harmonic (diffusion) fill, and an edge-aware diffusion fill (Perona-Malik iterations from
//! the harmonic fill, which carry edges into the hole instead of blurring them).
//!
//! Images are `[h, w, 3]` row-major f32 in [0, 1]; masks are `[h, w]` with 1 = hole (fill) and
//! 0 = known. Known pixels are returned unchanged.

use crate::{DiffusionError, Result};

fn check(img: &[f32], mask: &[f32], w: usize, h: usize) -> Result<()> {
    if img.len() != w * h * 3 || mask.len() != w * h {
        return Err(DiffusionError::Input(format!(
            "fill: image has {} values and mask {} for {w}x{h} (want {} and {})",
            img.len(),
            mask.len(),
            w * h * 3,
            w * h
        )));
    }
    Ok(())
}

fn hole(mask: &[f32], i: usize) -> bool {
    mask[i] >= 0.5
}

/// Every hole pixel set to the mean colour of the known pixels (0.5 grey when none is known).
pub fn mean_fill(img: &[f32], mask: &[f32], w: usize, h: usize) -> Result<Vec<f32>> {
    check(img, mask, w, h)?;
    let mut sum = [0f64; 3];
    let mut n = 0usize;
    for i in 0..w * h {
        if !hole(mask, i) {
            for c in 0..3 {
                sum[c] += img[3 * i + c] as f64;
            }
            n += 1;
        }
    }
    let mean = if n == 0 {
        [0.5; 3]
    } else {
        sum.map(|s| s / n as f64)
    };
    let mut out = img.to_vec();
    for i in 0..w * h {
        if hole(mask, i) {
            for c in 0..3 {
                out[3 * i + c] = mean[c] as f32;
            }
        }
    }
    Ok(out)
}

/// The harmonic fill: the hole solves Laplace's equation with the known pixels as boundary
/// values (reflecting image borders), by successive over-relaxation from the mean fill until
/// the largest update is below `tol` or after `max_iters` sweeps.
pub fn harmonic_fill(
    img: &[f32],
    mask: &[f32],
    w: usize,
    h: usize,
    max_iters: usize,
    tol: f32,
) -> Result<Vec<f32>> {
    let mut u = mean_fill(img, mask, w, h)?;
    let holes: Vec<usize> = (0..w * h).filter(|&i| hole(mask, i)).collect();
    if holes.is_empty() || holes.len() == w * h {
        return Ok(u);
    }
    let omega = 1.9f32;
    for _ in 0..max_iters {
        let mut largest = 0f32;
        for &i in &holes {
            let (x, y) = (i % w, i / w);
            let mut nb = [0usize; 4];
            let mut k = 0;
            if x > 0 {
                nb[k] = i - 1;
                k += 1;
            }
            if x + 1 < w {
                nb[k] = i + 1;
                k += 1;
            }
            if y > 0 {
                nb[k] = i - w;
                k += 1;
            }
            if y + 1 < h {
                nb[k] = i + w;
                k += 1;
            }
            for c in 0..3 {
                let avg = nb[..k].iter().map(|&j| u[3 * j + c]).sum::<f32>() / k as f32;
                let d = omega * (avg - u[3 * i + c]);
                u[3 * i + c] += d;
                largest = largest.max(d.abs());
            }
        }
        if largest < tol {
            break;
        }
    }
    Ok(u)
}

/// The edge-aware diffusion fill: the harmonic fill followed by `iters` Perona-Malik steps in
/// the hole, conductance 1 / (1 + (|grad| / k)^2), so that strong edges entering the hole keep
/// their contrast while flat regions keep diffusing.
pub fn edge_aware_fill(
    img: &[f32],
    mask: &[f32],
    w: usize,
    h: usize,
    iters: usize,
    k: f32,
) -> Result<Vec<f32>> {
    let mut u = harmonic_fill(img, mask, w, h, 2000, 1e-5)?;
    let holes: Vec<usize> = (0..w * h).filter(|&i| hole(mask, i)).collect();
    if holes.is_empty() || holes.len() == w * h || !(k.is_finite() && k > 0.0) {
        return Ok(u);
    }
    let lambda = 0.2f32;
    let g = |d: f32| 1.0 / (1.0 + (d / k) * (d / k));
    for _ in 0..iters {
        let prev = u.clone();
        for &i in &holes {
            let (x, y) = (i % w, i / w);
            let nbs = [
                (x > 0).then(|| i - 1),
                (x + 1 < w).then(|| i + 1),
                (y > 0).then(|| i - w),
                (y + 1 < h).then(|| i + w),
            ];
            // The conductance uses the colour difference's length, shared by the channels.
            for j in nbs.into_iter().flatten() {
                let diff: [f32; 3] = std::array::from_fn(|c| prev[3 * j + c] - prev[3 * i + c]);
                let mag = (diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2]).sqrt();
                let cond = g(mag);
                for c in 0..3 {
                    u[3 * i + c] += lambda * cond * diff[c];
                }
            }
        }
    }
    Ok(u)
}
