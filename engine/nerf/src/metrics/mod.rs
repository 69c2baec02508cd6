//! Image-quality metrics on the host: PSNR, SSIM, LPIPS, and the KID estimator ([`kid`]).
//!
//! Images are interleaved RGB f32 in [0, 1], row-major (`3 * width * height` values), as
//! [`crate::data::load_image`] returns them. PSNR and SSIM follow the NeRF / mip-NeRF evaluation
//! code (SSIM with 'valid' filtering), LPIPS the authors' v0.1 models ([`lpips`]); weights are
//! read from safetensors files ([`crate::safetensors`]).

pub mod error;
pub mod kid;
pub mod lpips;

pub use error::{MetricsError, Result};
pub use lpips::{Lpips, LpipsNet};

use error::{check_images, check_pair};

/// Peak signal-to-noise ratio in dB for data range 1: `-10 log10(mse)`, the MSE taken over all
/// values in f64. Identical images give `f64::INFINITY`.
pub fn psnr(a: &[f32], b: &[f32]) -> Result<f64> {
    check_pair(a, b)?;
    let se: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum();
    let mse = se / a.len() as f64;
    Ok(if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    })
}

/// Squared error summed over chosen pixels of any number of image pairs, for the PSNR of a
/// region pooled over views (every value of a chosen pixel counts once).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PooledError {
    /// Sum of squared differences.
    pub sum: f64,
    /// Values summed.
    pub values: u64,
}

impl PooledError {
    /// Adds the pixels `i` of RGB images `a` and `b` where `chosen[i]`.
    pub fn add(&mut self, a: &[f32], b: &[f32], chosen: &[bool]) -> Result<()> {
        check_pair(a, b)?;
        if a.len() != 3 * chosen.len() {
            return Err(MetricsError::MaskMismatch {
                len: a.len(),
                mask: chosen.len(),
            });
        }
        for (i, _) in chosen.iter().enumerate().filter(|(_, &c)| c) {
            for c in 0..3 {
                self.sum += (a[3 * i + c] as f64 - b[3 * i + c] as f64).powi(2);
            }
            self.values += 3;
        }
        Ok(())
    }

    /// The PSNR of the pooled error (data range 1); `None` when no pixel was chosen.
    pub fn psnr(&self) -> Option<f64> {
        (self.values > 0).then(|| {
            let mse = self.sum / self.values as f64;
            if mse == 0.0 {
                f64::INFINITY
            } else {
                -10.0 * mse.log10()
            }
        })
    }
}

/// Window size of [`ssim`].
pub const SSIM_WINDOW: usize = 11;
const SSIM_SIGMA: f64 = 1.5;

/// The normalised 1D Gaussian of the SSIM window.
fn ssim_kernel() -> [f64; SSIM_WINDOW] {
    let half = (SSIM_WINDOW / 2) as f64;
    let mut k: [f64; SSIM_WINDOW] =
        std::array::from_fn(|i| (-0.5 * ((i as f64 - half) / SSIM_SIGMA).powi(2)).exp());
    let sum: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    k
}

/// 'Valid' separable Gaussian filter of a `w` x `h` plane: `(w - 10) x (h - 10)` values.
fn filter_valid(x: &[f64], w: usize, h: usize, k: &[f64; SSIM_WINDOW]) -> Vec<f64> {
    let (ow, oh) = (w + 1 - SSIM_WINDOW, h + 1 - SSIM_WINDOW);
    let mut rows = Vec::with_capacity(ow * h);
    for row in x.chunks_exact(w) {
        rows.extend(row.windows(SSIM_WINDOW).map(|win| dot(win, k)));
    }
    let mut out = vec![0.0; ow * oh];
    for (y, orow) in out.chunks_exact_mut(ow).enumerate() {
        for (i, &kv) in k.iter().enumerate() {
            let src = &rows[(y + i) * ow..][..ow];
            orow.iter_mut().zip(src).for_each(|(o, s)| *o += kv * s);
        }
    }
    out
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Structural similarity (Wang et al. 2004) as the NeRF / RegNeRF / ExtraNeRF evaluations compute
/// it (mip-NeRF's `compute_ssim`): 11x11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03,
/// data range 1, 'valid' filtering (no padding), variances clamped at 0 and the covariance at
/// their geometric mean; the SSIM map is averaged over channels and pixels. f64 throughout.
pub fn ssim(a: &[f32], b: &[f32], width: u32, height: u32) -> Result<f64> {
    check_images(a, b, width, height, SSIM_WINDOW as u32, "SSIM")?;
    let (w, h) = (width as usize, height as usize);
    let k = ssim_kernel();
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let mut sum = 0.0;
    let mut count = 0usize;
    for ch in 0..3 {
        let plane = |img: &[f32]| -> Vec<f64> {
            img.iter().skip(ch).step_by(3).map(|&v| v as f64).collect()
        };
        let (x, y) = (plane(a), plane(b));
        let prod =
            |p: &[f64], q: &[f64]| -> Vec<f64> { p.iter().zip(q).map(|(u, v)| u * v).collect() };
        let f = |p: &[f64]| filter_valid(p, w, h, &k);
        let (mx, my) = (f(&x), f(&y));
        let (sxx, syy, sxy) = (f(&prod(&x, &x)), f(&prod(&y, &y)), f(&prod(&x, &y)));
        for i in 0..mx.len() {
            let (mx, my) = (mx[i], my[i]);
            let vx = (sxx[i] - mx * mx).max(0.0);
            let vy = (syy[i] - my * my).max(0.0);
            let cxy = sxy[i] - mx * my;
            let cxy = cxy.signum() * (vx * vy).sqrt().min(cxy.abs());
            sum += (2.0 * mx * my + c1) * (2.0 * cxy + c2)
                / ((mx * mx + my * my + c1) * (vx + vy + c2));
        }
        count += mx.len();
    }
    Ok(sum / count as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values in [0, 1).
    pub(crate) fn noise(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 40) as f32 / (1u64 << 24) as f32
            })
            .collect()
    }

    #[test]
    fn pooled_error_counts_only_chosen_pixels() {
        let a = [0.0f32, 0.0, 0.0, 1.0, 1.0, 1.0, 0.5, 0.5, 0.5];
        let b = [0.1f32, 0.1, 0.1, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5];
        let mut e = PooledError::default();
        assert_eq!(e.psnr(), None);
        e.add(&a, &b, &[true, false, true]).unwrap();
        // Squared error 0.01 in 3 of the 6 values chosen (the third pixel's are 0): 0.005.
        let want = -10.0 * (3.0 * (0.1f32 as f64).powi(2) / 6.0).log10();
        assert!((e.psnr().unwrap() - want).abs() < 1e-9);
        e.add(&a, &a, &[true; 3]).unwrap();
        assert_eq!(e.values, 15);
        assert!(matches!(
            e.add(&a, &b, &[true]),
            Err(MetricsError::MaskMismatch { len: 9, mask: 1 })
        ));
        let mut same = PooledError::default();
        same.add(&a, &a, &[true; 3]).unwrap();
        assert_eq!(same.psnr(), Some(f64::INFINITY));
    }

    #[test]
    fn psnr_of_known_mse() {
        let a = vec![0.5f32; 300];
        let b: Vec<f32> = a
            .iter()
            .enumerate()
            .map(|(i, v)| if i % 2 == 0 { v + 0.1 } else { v - 0.1 })
            .collect();
        // mse = 0.01 (up to f32 rounding of 0.6 and 0.4) -> 20 dB
        assert!((psnr(&a, &b).unwrap() - 20.0).abs() < 1e-5);
        assert_eq!(psnr(&a, &a).unwrap(), f64::INFINITY);
    }

    #[test]
    fn psnr_rejects_bad_input() {
        let e = psnr(&[0.0; 6], &[0.0; 3]).unwrap_err();
        assert!(matches!(e, MetricsError::LengthMismatch { a: 6, b: 3 }));
        assert_eq!(e.to_string(), "the images differ in size: 6 vs 3 values");
        assert!(matches!(psnr(&[], &[]), Err(MetricsError::Empty)));
    }

    #[test]
    fn ssim_of_identical_images_is_one() {
        let a = noise(3 * 20 * 13, 1);
        assert!((ssim(&a, &a, 20, 13).unwrap() - 1.0).abs() < 1e-12);
    }

    /// The SSIM map by a direct double loop over the 2D window.
    fn ssim_direct(a: &[f32], b: &[f32], w: usize, h: usize) -> f64 {
        let k = ssim_kernel();
        let (c1, c2) = (1e-4, 9e-4);
        let mut sum = 0.0;
        let mut n = 0;
        for ch in 0..3 {
            for y in 0..=h - 11 {
                for x in 0..=w - 11 {
                    let [mut mx, mut my, mut sxx, mut syy, mut sxy] = [0f64; 5];
                    for i in 0..11 {
                        for j in 0..11 {
                            let wt = k[i] * k[j];
                            let idx = 3 * ((y + i) * w + x + j) + ch;
                            let (p, q) = (a[idx] as f64, b[idx] as f64);
                            mx += wt * p;
                            my += wt * q;
                            sxx += wt * p * p;
                            syy += wt * q * q;
                            sxy += wt * p * q;
                        }
                    }
                    let (vx, vy, cxy) = (sxx - mx * mx, syy - my * my, sxy - mx * my);
                    sum += (2.0 * mx * my + c1) * (2.0 * cxy + c2)
                        / ((mx * mx + my * my + c1) * (vx + vy + c2));
                    n += 1;
                }
            }
        }
        sum / n as f64
    }

    #[test]
    fn ssim_matches_direct_window_sum() {
        let (w, h) = (16, 14);
        let a = noise(3 * w * h, 2);
        let b: Vec<f32> = a
            .iter()
            .zip(noise(3 * w * h, 3))
            .map(|(x, n)| 0.7 * x + 0.3 * n)
            .collect();
        let s = ssim(&a, &b, w as u32, h as u32).unwrap();
        let d = ssim_direct(&a, &b, w, h);
        assert!((s - d).abs() < 1e-12, "{s} vs {d}");
        assert!(s > 0.3 && s < 0.99, "{s}");
    }

    #[test]
    fn ssim_hand_computed_constant_images() {
        // Constant planes: variances vanish, SSIM = (2 m1 m2 + c1) / (m1^2 + m2^2 + c1).
        let (a, b) = (vec![0.25f32; 3 * 11 * 11], vec![0.75f32; 3 * 11 * 11]);
        let want = (2.0 * 0.25 * 0.75 + 1e-4) / (0.0625 + 0.5625 + 1e-4);
        assert!((ssim(&a, &b, 11, 11).unwrap() - want).abs() < 1e-12);
    }

    #[test]
    fn ssim_rejects_bad_input() {
        let a = noise(3 * 10 * 20, 4);
        let e = ssim(&a, &a, 10, 20).unwrap_err();
        assert!(matches!(e, MetricsError::TooSmall { min: 11, .. }), "{e}");
        assert_eq!(
            e.to_string(),
            "a 10x20 image is too small for SSIM: at least 11x11 is needed"
        );
        let e = ssim(&a, &a, 20, 20).unwrap_err();
        assert!(
            matches!(e, MetricsError::SizeMismatch { len: 600, .. }),
            "{e}"
        );
        assert!(matches!(
            ssim(&a, &a[1..], 10, 20),
            Err(MetricsError::LengthMismatch { .. })
        ));
    }
}
