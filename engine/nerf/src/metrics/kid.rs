//! The Kernel Inception Distance estimator (Bińkowski et al., "Demystifying MMD GANs", 2018):
//! the unbiased estimate of the squared maximum mean discrepancy between two sets of feature
//! vectors under the cubic polynomial kernel `k(x, y) = (x . y / d + 1)^3` (d: the feature
//! dimension), averaged over random subsets of both sets, as the reference implementations
//! (the authors', torch-fidelity, clean-fid) compute it. For KID proper the features are
//! Inception-v3's 2048-d pool features; this module takes any features.
//!
//! Per subset, `m` rows are drawn without replacement from each set (independently), and
//!
//! ```text
//! MMD^2_u = 1/(m(m-1)) sum_{i != j} k(x_i, x_j) + 1/(m(m-1)) sum_{i != j} k(y_i, y_j)
//!           - 2/m^2 sum_{i, j} k(x_i, y_j)
//! ```
//!
//! whose expectation is exactly the squared MMD (0 when both sets come from one distribution;
//! single estimates may be negative). Everything runs in f64.

use extranerf_prims::reference::Rng;

use super::error::{MetricsError, Result};

/// How the subsets are drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct KidConfig {
    /// Subsets averaged.
    pub subsets: usize,
    /// Rows per subset from each set (at least 2, at most the smaller set's size).
    pub subset_size: usize,
    /// Seed of the draws (the same seed gives the same estimate).
    pub seed: u64,
}

/// A KID estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Kid {
    /// Mean of the subsets' unbiased MMD^2 estimates.
    pub mean: f64,
    /// Their standard deviation (0 for one subset).
    pub std: f64,
    /// Subsets averaged.
    pub subsets: usize,
    /// Rows per subset.
    pub subset_size: usize,
}

/// The cubic polynomial kernel `(x . y / d + 1)^3` of two rows of `d` features.
pub fn polynomial_kernel(x: &[f32], y: &[f32]) -> f64 {
    let d = x.len() as f64;
    let dot: f64 = x.iter().zip(y).map(|(a, b)| *a as f64 * *b as f64).sum();
    (dot / d + 1.0).powi(3)
}

/// Row i of `dim` features.
fn row(a: &[f32], dim: usize, i: usize) -> &[f32] {
    &a[i * dim..(i + 1) * dim]
}

/// The unbiased MMD^2 estimate between the rows `xi` of `x` and `yi` of `y` (row-major,
/// `dim` features per row; at least two rows each, as many of one as of the other).
fn mmd2_unbiased(x: &[f32], y: &[f32], dim: usize, xi: &[usize], yi: &[usize]) -> f64 {
    let m = xi.len() as f64;
    let (mut kxx, mut kyy, mut kxy) = (0.0, 0.0, 0.0);
    for (a, &i) in xi.iter().enumerate() {
        for &j in &xi[a + 1..] {
            kxx += polynomial_kernel(row(x, dim, i), row(x, dim, j));
        }
    }
    for (a, &i) in yi.iter().enumerate() {
        for &j in &yi[a + 1..] {
            kyy += polynomial_kernel(row(y, dim, i), row(y, dim, j));
        }
    }
    for &i in xi {
        for &j in yi {
            kxy += polynomial_kernel(row(x, dim, i), row(y, dim, j));
        }
    }
    // Each off-diagonal pair was summed once: twice that over m(m - 1).
    2.0 * (kxx + kyy) / (m * (m - 1.0)) - 2.0 * kxy / (m * m)
}

/// `m` distinct indices below `n`, uniformly (a partial Fisher-Yates shuffle).
fn draw(rng: &mut Rng, n: usize, m: usize) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..n).collect();
    for k in 0..m {
        let j = k + (rng.next_u64() % (n - k) as u64) as usize;
        idx.swap(k, j);
    }
    idx.truncate(m);
    idx
}

/// Checks a feature set: whole rows of `dim` finite values; returns its row count.
fn rows(name: &'static str, f: &[f32], dim: usize) -> Result<usize> {
    if dim == 0 || !f.len().is_multiple_of(dim) {
        return Err(MetricsError::Features {
            set: name,
            problem: format!("{} values are not whole rows of {dim} features", f.len()),
        });
    }
    if let Some(k) = f.iter().position(|v| !v.is_finite()) {
        return Err(MetricsError::Features {
            set: name,
            problem: format!("value {k} (row {}) is not finite: {}", k / dim, f[k]),
        });
    }
    Ok(f.len() / dim)
}

/// KID between the feature sets `real` and `fake` (row-major, `dim` features per row), over
/// `cfg.subsets` subsets of `cfg.subset_size` rows of each. Refuses sets with fewer rows than
/// the subset size, subsets of fewer than two rows, and non-finite features.
pub fn kid(real: &[f32], fake: &[f32], dim: usize, cfg: &KidConfig) -> Result<Kid> {
    let nr = rows("real", real, dim)?;
    let nf = rows("fake", fake, dim)?;
    let m = cfg.subset_size;
    if m < 2 || cfg.subsets == 0 {
        return Err(MetricsError::Features {
            set: "both",
            problem: format!(
                "KID needs at least one subset of at least 2 rows ({} subsets of {m} asked)",
                cfg.subsets
            ),
        });
    }
    for (set, n) in [("real", nr), ("fake", nf)] {
        if n < m {
            return Err(MetricsError::Features {
                set,
                problem: format!("{n} rows, fewer than the subset size {m}"),
            });
        }
    }
    let mut rng = Rng::new(cfg.seed);
    let est: Vec<f64> = (0..cfg.subsets)
        .map(|_| {
            let xi = draw(&mut rng, nr, m);
            let yi = draw(&mut rng, nf, m);
            mmd2_unbiased(real, fake, dim, &xi, &yi)
        })
        .collect();
    let n = est.len() as f64;
    let mean = est.iter().sum::<f64>() / n;
    let var = if est.len() > 1 {
        est.iter().map(|e| (e - mean) * (e - mean)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    Ok(Kid {
        mean,
        std: var.sqrt(),
        subsets: cfg.subsets,
        subset_size: m,
    })
}

/// Pixels of the mask inside the `s x s` crop at (x, y), in O(1) per crop after an O(w h)
/// summed-area table.
fn coverage(mask: &[bool], w: usize, h: usize, s: usize) -> impl Fn(usize, usize) -> u32 {
    let mut sat = vec![0u32; (w + 1) * (h + 1)];
    for y in 0..h {
        for x in 0..w {
            sat[(y + 1) * (w + 1) + x + 1] =
                u32::from(mask[y * w + x]) + sat[y * (w + 1) + x + 1] + sat[(y + 1) * (w + 1) + x]
                    - sat[y * (w + 1) + x];
        }
    }
    move |x: usize, y: usize| {
        sat[(y + s) * (w + 1) + x + s] + sat[y * (w + 1) + x]
            - sat[y * (w + 1) + x + s]
            - sat[(y + s) * (w + 1) + x]
    }
}

/// The largest share of a `size` x `size` crop's pixels that the mask covers, over every crop
/// position of the `width` x `height` image (0 when the crop does not fit or sizes disagree):
/// what `min_fraction` [`masked_crops`] can ask of this mask.
pub fn max_coverage(mask: &[bool], width: u32, height: u32, size: u32) -> f64 {
    let (w, h, s) = (width as usize, height as usize, size as usize);
    if mask.len() != w * h || s == 0 || s > w || s > h {
        return 0.0;
    }
    let covered = coverage(mask, w, h, s);
    let best = (0..=h - s)
        .flat_map(|y| (0..=w - s).map(move |x| (x, y)))
        .map(|(x, y)| covered(x, y))
        .max()
        .unwrap_or(0);
    f64::from(best) / (s * s) as f64
}

/// Top-left corners of `count` square `size` x `size` crops of a `width` x `height` image,
/// each covering at least `min_fraction` of its pixels with the mask (`mask[y * width + x]`
/// true: the region the crops study, such as what no training camera saw), drawn uniformly
/// among all such positions with a fixed seed, so the same crops can be taken from a render and
/// its ground truth (patch KID). Crops may repeat. Refuses a mask that no crop covers enough,
/// and sizes that do not fit the image.
pub fn masked_crops(
    mask: &[bool],
    width: u32,
    height: u32,
    size: u32,
    count: usize,
    min_fraction: f64,
    seed: u64,
) -> Result<Vec<(u32, u32)>> {
    let (w, h, s) = (width as usize, height as usize, size as usize);
    if mask.len() != w * h {
        return Err(MetricsError::SizeMismatch {
            len: mask.len(),
            width,
            height,
        });
    }
    if s == 0 || s > w || s > h {
        return Err(MetricsError::TooSmall {
            width,
            height,
            min: size.max(1),
            metric: "patch crops",
        });
    }
    let covered = coverage(mask, w, h, s);
    let need = (min_fraction * (s * s) as f64).ceil() as u32;
    let valid: Vec<(u32, u32)> = (0..=h - s)
        .flat_map(|y| (0..=w - s).map(move |x| (x, y)))
        .filter(|&(x, y)| covered(x, y) >= need)
        .map(|(x, y)| (x as u32, y as u32))
        .collect();
    if valid.is_empty() {
        return Err(MetricsError::Features {
            set: "both",
            problem: format!(
                "no {size}x{size} crop of the {width}x{height} mask covers {:.0}% of its pixels ({} mask pixels in all)",
                100.0 * min_fraction,
                mask.iter().filter(|m| **m).count()
            ),
        });
    }
    let mut rng = Rng::new(seed);
    Ok((0..count)
        .map(|_| valid[(rng.next_u64() % valid.len() as u64) as usize])
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn features(rng: &mut Rng, n: usize, dim: usize, shift: f32) -> Vec<f32> {
        (0..n * dim)
            .map(|_| rng.uniform(-1.0, 1.0) + shift)
            .collect()
    }

    /// The estimate against the definition computed the long way: full kernel matrices in
    /// f64, their diagonals removed, with every row in the subset (subset size = set size, so
    /// the draw only permutes).
    #[test]
    fn matches_the_kernel_matrix_definition() {
        let mut rng = Rng::new(3);
        let (n, dim) = (9, 5);
        let x = features(&mut rng, n, dim, 0.0);
        let y = features(&mut rng, n, dim, 0.3);
        let k = |a: &[f32], i: usize, b: &[f32], j: usize| {
            let d: f64 = (0..dim)
                .map(|c| a[i * dim + c] as f64 * b[j * dim + c] as f64)
                .sum();
            (d / dim as f64 + 1.0).powi(3)
        };
        let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
        for i in 0..n {
            for j in 0..n {
                if i != j {
                    sxx += k(&x, i, &x, j);
                    syy += k(&y, i, &y, j);
                }
                sxy += k(&x, i, &y, j);
            }
        }
        let nf = n as f64;
        let want = (sxx + syy) / (nf * (nf - 1.0)) - 2.0 * sxy / (nf * nf);
        let cfg = KidConfig {
            subsets: 3,
            subset_size: n,
            seed: 1,
        };
        let got = kid(&x, &y, dim, &cfg).unwrap();
        assert!(
            (got.mean - want).abs() < 1e-12 * want.abs().max(1.0),
            "{got:?} vs {want}"
        );
        assert!(got.std < 1e-12, "permutations only: {got:?}");
        assert!(want > 0.0);
    }

    /// Unbiased: over many subsets of two samples of one distribution the mean estimate is
    /// within 4 standard errors of 0, where the biased (V-statistic) estimate, which keeps the
    /// diagonal, sits far above; a shifted distribution gives a clearly positive estimate.
    #[test]
    fn is_unbiased_and_sees_a_shift() {
        let mut rng = Rng::new(11);
        let dim = 8;
        let x = features(&mut rng, 400, dim, 0.0);
        let y = features(&mut rng, 400, dim, 0.0);
        let cfg = KidConfig {
            subsets: 400,
            subset_size: 10,
            seed: 5,
        };
        let same = kid(&x, &y, dim, &cfg).unwrap();
        let se = same.std / (same.subsets as f64).sqrt();
        assert!(same.mean.abs() < 4.0 * se, "{same:?}");
        // The V-statistic adds (mean k(x, x) + mean k(y, y)) / m minus the same off the
        // diagonal, about 2 (E k(x, x) - E k(x, x')) / m: far outside the band.
        let diag: f64 = (0..400)
            .map(|i| polynomial_kernel(row(&x, dim, i), row(&x, dim, i)))
            .sum::<f64>()
            / 400.0;
        let bias = 2.0 * (diag - 1.0) / cfg.subset_size as f64;
        assert!(bias > 20.0 * se, "bias {bias} vs standard error {se}");
        let z = features(&mut rng, 400, dim, 0.5);
        let shifted = kid(&x, &z, dim, &cfg).unwrap();
        assert!(shifted.mean > 10.0 * se, "{shifted:?}");
        // The same seed gives the same estimate.
        assert_eq!(kid(&x, &y, dim, &cfg).unwrap(), same);
    }

    #[test]
    fn bad_inputs_are_refused() {
        let x = vec![0.5f32; 6 * 4];
        let cfg = KidConfig {
            subsets: 2,
            subset_size: 8,
            seed: 0,
        };
        let msg = |r: Result<Kid>| r.unwrap_err().to_string();
        let e = msg(kid(&x, &x, 4, &cfg));
        assert!(e.contains("6 rows, fewer than the subset size 8"), "{e}");
        let e = msg(kid(
            &x,
            &x[..23],
            4,
            &KidConfig {
                subset_size: 2,
                ..cfg
            },
        ));
        assert!(e.contains("fake") && e.contains("23 values"), "{e}");
        let e = msg(kid(
            &x,
            &x,
            4,
            &KidConfig {
                subset_size: 1,
                ..cfg
            },
        ));
        assert!(e.contains("at least 2 rows"), "{e}");
        let mut bad = x.clone();
        bad[9] = f32::NAN;
        let e = msg(kid(
            &bad,
            &x,
            4,
            &KidConfig {
                subset_size: 2,
                ..cfg
            },
        ));
        assert!(
            e.contains("real") && e.contains("row 2") && e.contains("not finite"),
            "{e}"
        );
        let e = msg(kid(&x, &x, 0, &cfg));
        assert!(e.contains("0 features"), "{e}");
    }

    /// Every crop covers the mask by at least the fraction asked (counted directly), lies in
    /// the image, and the same seed gives the same crops; a mask with too little coverage, a
    /// crop larger than the image and a mask of the wrong size are refused.
    #[test]
    fn masked_crops_cover_the_mask() {
        let (w, h, s) = (40u32, 30u32, 8u32);
        // A disc of radius 5.5, narrower than a crop: crops must sit mostly inside it, and
        // none fits wholly inside.
        let mask: Vec<bool> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32 - 25.0, (i / w) as f32 - 12.0);
                x * x + y * y < 30.25
            })
            .collect();
        let crops = masked_crops(&mask, w, h, s, 300, 0.5, 7).unwrap();
        assert_eq!(crops.len(), 300);
        let mut distinct = std::collections::BTreeSet::new();
        for &(x, y) in &crops {
            assert!(x + s <= w && y + s <= h);
            let inside = (y..y + s)
                .flat_map(|yy| (x..x + s).map(move |xx| (xx, yy)))
                .filter(|&(xx, yy)| mask[(yy * w + xx) as usize])
                .count();
            assert!(
                inside * 2 >= (s * s) as usize,
                "crop ({x}, {y}): {inside} inside"
            );
            distinct.insert((x, y));
        }
        // Spread over the valid positions, not stuck on one.
        assert!(distinct.len() > 30, "{} distinct crops", distinct.len());
        assert_eq!(masked_crops(&mask, w, h, s, 300, 0.5, 7).unwrap(), crops);
        let e = masked_crops(&mask, w, h, s, 10, 0.99, 7)
            .unwrap_err()
            .to_string();
        assert!(e.contains("covers 99%"), "{e}");
        assert!(masked_crops(&mask, w, h, 41, 10, 0.5, 7).is_err());
        assert!(masked_crops(&mask[1..], w, h, s, 10, 0.5, 7).is_err());
        // The best coverage, against a direct count over every position; crops can ask for
        // exactly that much and no more.
        let direct = (0..=h - s)
            .flat_map(|y| (0..=w - s).map(move |x| (x, y)))
            .map(|(x, y)| {
                (y..y + s)
                    .flat_map(|yy| (x..x + s).map(move |xx| (xx, yy)))
                    .filter(|&(xx, yy)| mask[(yy * w + xx) as usize])
                    .count()
            })
            .max()
            .unwrap();
        let best = max_coverage(&mask, w, h, s);
        assert_eq!(best, direct as f64 / (s * s) as f64);
        assert!(best < 1.0);
        assert!(masked_crops(&mask, w, h, s, 1, best, 7).is_ok());
        assert!(masked_crops(&mask, w, h, s, 1, best + 1e-6, 7).is_err());
        assert_eq!(max_coverage(&mask, w, h, 41), 0.0);
    }
}
