//! The depth-aware harmonic fill. Each hole (a 4-connected component of the mask) is filled
//! with the solution of Laplace's equation, in colour and depth, whose boundary values come
//! only from the far side of the hole's boundary: a disoccluded region shows what lies behind
//! the occluder, so the occluder's colour must not bleed into it.
//!
//! The far side: the hole's boundary depths are split in two by Otsu's threshold; when the two
//! classes' means differ by more than `edge_ratio` of the far mean, only the far class seeds
//! the fill and the near pixels act as insulating walls (no flux through them); otherwise the
//! whole boundary seeds it. The solve starts from each pixel's nearest seed and runs
//! successive over-relaxation until the largest update falls below `tol`.

use std::collections::VecDeque;

use super::api::{
    check, is_hole, Fill, InpaintError, Inpainter, InpainterKind, Result, Source, Target,
};

/// Settings of the depth-aware harmonic fill.
#[derive(Clone, Debug, PartialEq)]
pub struct Harmonic {
    /// Most over-relaxation sweeps.
    pub max_sweeps: usize,
    /// Stop when no value (colour, or depth over the boundary's depth scale) moves more than
    /// this in a sweep.
    pub tol: f32,
    /// Depth gap between the boundary's near and far classes, as a fraction of the far depth,
    /// from which on only the far side seeds the fill.
    pub edge_ratio: f32,
}

impl Default for Harmonic {
    fn default() -> Self {
        Harmonic {
            max_sweeps: 5000,
            tol: 1e-5,
            edge_ratio: 0.1,
        }
    }
}

/// The 4-neighbours of pixel `i` in a `w x h` image.
pub(crate) fn neighbours(i: usize, w: usize, h: usize) -> impl Iterator<Item = usize> {
    let (x, y) = (i % w, i / w);
    [
        (x > 0).then(|| i - 1),
        (x + 1 < w).then(|| i + 1),
        (y > 0).then(|| i - w),
        (y + 1 < h).then(|| i + w),
    ]
    .into_iter()
    .flatten()
}

/// Otsu's threshold of `v` (sorted ascending, at least two values): the split index k (class
/// 0 is `v[..k]`) that maximises the between-class variance.
fn otsu(v: &[f64]) -> usize {
    let n = v.len();
    let total: f64 = v.iter().sum();
    let mut best = (f64::NEG_INFINITY, 1);
    let mut left = 0.0;
    for k in 1..n {
        left += v[k - 1];
        let (n0, n1) = (k as f64, (n - k) as f64);
        let (m0, m1) = (left / n0, (total - left) / n1);
        let between = n0 * n1 * (m0 - m1) * (m0 - m1);
        if between > best.0 {
            best = (between, k);
        }
    }
    best.1
}

/// Which known pixels may seed the fill: false for the near side of a hole whose boundary
/// spans a depth edge (see the module notes). Also returns the hole components' count.
pub fn far_side_seeds(target: &Target<'_>, edge_ratio: f32) -> (Vec<bool>, usize) {
    let (w, h) = (target.width, target.height);
    let n = w * h;
    let mut seed = vec![true; n];
    let mut label = vec![usize::MAX; n];
    let mut stamp = vec![usize::MAX; n];
    let mut components = 0;
    for start in 0..n {
        if !is_hole(target.mask, start) || label[start] != usize::MAX {
            continue;
        }
        let c = components;
        components += 1;
        label[start] = c;
        let mut queue = VecDeque::from([start]);
        let mut boundary = Vec::new();
        while let Some(i) = queue.pop_front() {
            for j in neighbours(i, w, h) {
                if is_hole(target.mask, j) {
                    if label[j] == usize::MAX {
                        label[j] = c;
                        queue.push_back(j);
                    }
                } else if stamp[j] != c {
                    stamp[j] = c;
                    boundary.push(j);
                }
            }
        }
        if boundary.len() < 2 {
            continue;
        }
        let mut d: Vec<f64> = boundary.iter().map(|&j| target.depth[j] as f64).collect();
        d.sort_by(f64::total_cmp);
        let k = otsu(&d);
        let near = d[..k].iter().sum::<f64>() / k as f64;
        let far = d[k..].iter().sum::<f64>() / (d.len() - k) as f64;
        if far - near > edge_ratio as f64 * far.abs().max(1e-9) {
            let threshold = d[k];
            for &j in &boundary {
                if (target.depth[j] as f64) < threshold {
                    seed[j] = false;
                }
            }
        }
    }
    (seed, components)
}

impl Inpainter for Harmonic {
    fn kind(&self) -> InpainterKind {
        InpainterKind::Harmonic
    }

    fn inpaint(&mut self, target: &Target<'_>, sources: &[Source<'_>], _seed: u64) -> Result<Fill> {
        check(target, sources)?;
        let (seed, _) = far_side_seeds(target, self.edge_ratio);
        let (rgb, depth) = solve(target, &seed, self.max_sweeps, self.tol)?;
        Ok(Fill { rgb, depth })
    }
}

/// Solves Laplace's equation on the hole pixels with the `seed` pixels as boundary values and
/// the other known pixels as insulating walls. Returns colour and depth.
pub(crate) fn solve(
    target: &Target<'_>,
    seed: &[bool],
    max_sweeps: usize,
    tol: f32,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let (w, h) = (target.width, target.height);
    let n = w * h;
    let holes: Vec<usize> = (0..n).filter(|&i| is_hole(target.mask, i)).collect();
    let mut rgb = target.rgb.to_vec();
    let mut depth = target.depth.to_vec();
    if holes.is_empty() {
        return Ok((rgb, depth));
    }
    if holes.len() == n {
        return Err(InpaintError(
            "the mask covers the whole view: no seen pixel to start the fill from".into(),
        ));
    }
    // Depth is solved in units of the boundary's largest depth, so one tolerance serves both.
    let scale = (0..n)
        .filter(|&i| !is_hole(target.mask, i))
        .map(|i| target.depth[i].abs())
        .fold(0f32, f32::max)
        .max(1e-6);
    // Values: r, g, b, depth / scale.
    let mut u = vec![[0f32; 4]; n];
    let mut known = vec![false; n];
    let mut queue = VecDeque::new();
    for i in 0..n {
        if !is_hole(target.mask, i) {
            u[i] = [
                target.rgb[3 * i],
                target.rgb[3 * i + 1],
                target.rgb[3 * i + 2],
                target.depth[i] / scale,
            ];
            if seed[i] {
                known[i] = true;
                queue.push_back(i);
            }
        }
    }
    // Start from the nearest seed (a breadth-first sweep through the holes).
    let mut reached = known.clone();
    while let Some(i) = queue.pop_front() {
        for j in neighbours(i, w, h) {
            if is_hole(target.mask, j) && !reached[j] {
                reached[j] = true;
                u[j] = u[i];
                queue.push_back(j);
            }
        }
    }
    // Each hole pixel's neighbours that take part: holes and seeds.
    let links: Vec<([usize; 4], usize)> = holes
        .iter()
        .map(|&i| {
            let mut nb = [0usize; 4];
            let mut k = 0;
            for j in neighbours(i, w, h) {
                if is_hole(target.mask, j) || seed[j] {
                    nb[k] = j;
                    k += 1;
                }
            }
            if k == 0 {
                // Walled in by near pixels on every side: they are all it has.
                for j in neighbours(i, w, h) {
                    nb[k] = j;
                    k += 1;
                }
            }
            (nb, k)
        })
        .collect();
    // The optimal over-relaxation factor of a square of the holes' extent.
    let (mut x0, mut x1, mut y0, mut y1) = (w, 0, h, 0);
    for &i in &holes {
        let (x, y) = (i % w, i / w);
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    let extent = (x1 - x0).max(y1 - y0) as f64 + 2.0;
    let omega = (2.0 / (1.0 + (std::f64::consts::PI / extent).sin())) as f32;
    for _ in 0..max_sweeps {
        let mut largest = 0f32;
        for (&i, (nb, k)) in holes.iter().zip(&links) {
            let mut avg = [0f32; 4];
            for &j in &nb[..*k] {
                for c in 0..4 {
                    avg[c] += u[j][c];
                }
            }
            for c in 0..4 {
                let d = omega * (avg[c] / *k as f32 - u[i][c]);
                u[i][c] += d;
                largest = largest.max(d.abs());
            }
        }
        if largest < tol {
            break;
        }
    }
    for &i in &holes {
        for c in 0..3 {
            rgb[3 * i + c] = u[i][c].clamp(0.0, 1.0);
        }
        depth[i] = u[i][3] * scale;
    }
    Ok((rgb, depth))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inpaint::rect_mask;

    #[test]
    fn a_linear_ramp_is_filled_exactly() {
        // A linear function is harmonic: the fill must reproduce it (up to the tolerance).
        let (w, h) = (48, 36);
        let rgb: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                [0.1 + 0.015 * x, 0.9 - 0.02 * y, 0.2 + 0.01 * x + 0.005 * y]
            })
            .collect();
        let depth: Vec<f32> = (0..w * h).map(|i| 2.0 + 0.01 * (i % w) as f32).collect();
        let mask = rect_mask(w, h, 10..30, 8..28);
        let t = Target::new(w, h, &rgb, &depth, &mask, 0.5);
        let f = Harmonic {
            tol: 1e-7,
            ..Harmonic::default()
        }
        .inpaint(&t, &[], 0)
        .unwrap();
        let err = f
            .rgb
            .iter()
            .zip(&rgb)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        let derr = f
            .depth
            .iter()
            .zip(&depth)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(err < 1e-3, "colour error {err}");
        assert!(derr < 2e-3, "depth error {derr}");
        // Outside the mask nothing changes.
        for i in 0..w * h {
            if mask[i] < 0.5 {
                assert_eq!(&f.rgb[3 * i..3 * i + 3], &rgb[3 * i..3 * i + 3]);
                assert_eq!(f.depth[i], depth[i]);
            }
        }
    }

    #[test]
    fn only_the_far_side_of_a_depth_edge_seeds_the_fill() {
        // Left: a near red occluder (depth 0.3); right: a far blue wall (depth 0.9). The hole
        // straddles the edge, as a disocclusion beside the occluder does.
        let (w, h) = (40, 30);
        let near = |i: usize| i % w < 20;
        let rgb: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                if near(i) {
                    [0.9, 0.1, 0.1]
                } else {
                    [0.1, 0.2, 0.9]
                }
            })
            .collect();
        let depth: Vec<f32> = (0..w * h)
            .map(|i| if near(i) { 0.3 } else { 0.9 })
            .collect();
        let mask = rect_mask(w, h, 16..26, 8..22);
        let t = Target::new(w, h, &rgb, &depth, &mask, 0.5);
        let f = Harmonic::default().inpaint(&t, &[], 0).unwrap();
        for i in 0..w * h {
            if mask[i] > 0.5 {
                let c = &f.rgb[3 * i..3 * i + 3];
                assert!(
                    (c[0] - 0.1).abs() < 1e-3 && (c[2] - 0.9).abs() < 1e-3,
                    "pixel {i}: {c:?}"
                );
                assert!(
                    (f.depth[i] - 0.9).abs() < 1e-3,
                    "pixel {i}: depth {}",
                    f.depth[i]
                );
            }
        }
        // Without an edge (a gap under edge_ratio) both sides seed it.
        let flat: Vec<f32> = (0..w * h)
            .map(|i| if near(i) { 0.88 } else { 0.9 })
            .collect();
        let t = Target { depth: &flat, ..t };
        let f = Harmonic::default().inpaint(&t, &[], 0).unwrap();
        let reds = (0..w * h)
            .filter(|&i| mask[i] > 0.5 && f.rgb[3 * i] > 0.5)
            .count();
        assert!(
            reds > 0,
            "the near side should seed a fill without a depth edge"
        );
    }

    #[test]
    fn separate_holes_are_judged_separately() {
        // Two holes: one inside a flat far wall, one on an edge; the first must not lose its
        // seeds to the second's edge test.
        let (w, h) = (60, 20);
        let near = |i: usize| i % w >= 40;
        let rgb: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                if near(i) {
                    [1.0, 0.0, 0.0]
                } else {
                    [0.0, 0.0, 1.0]
                }
            })
            .collect();
        let depth: Vec<f32> = (0..w * h)
            .map(|i| if near(i) { 0.2 } else { 0.8 })
            .collect();
        let mask: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                f32::from((5..10).contains(&y) && ((5..15).contains(&x) || (36..44).contains(&x)))
            })
            .collect();
        let t = Target::new(w, h, &rgb, &depth, &mask, 0.5);
        let (seed, comps) = far_side_seeds(&t, 0.1);
        assert_eq!(comps, 2);
        assert!(
            seed[7 * w + 4] && seed[7 * w + 15],
            "the flat hole keeps its seeds"
        );
        assert!(
            !seed[7 * w + 44] && seed[7 * w + 35],
            "the edge hole loses its near side"
        );
    }
}
