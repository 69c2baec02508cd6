//! Image operations on `[h, w, c]` f32 images in row-major order, shared by every caller:
//! luminance, resizing (integer box downscale, area resize, nearest-neighbour masks), the tent
//! blur, the unsharp mask, detail energy, bounding boxes and crops.

use extranerf_gpu::{GpuError, Result};

use crate::data::Image;

/// Luminance (Rec. 601) of RGB pixels.
pub fn grey(rgb: &[f32]) -> Vec<f32> {
    rgb.chunks_exact(3)
        .map(|p| 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2])
        .collect()
}

/// A `width` x `height` RGB image shrunk by an integer `factor` (box filter over whole
/// blocks; the last partial row and column are dropped). Returns (rgb, width, height).
///
/// # Errors
/// When `rgb` does not hold `width * height * 3` values.
pub fn downscale_rgb(
    rgb: &[f32],
    width: u32,
    height: u32,
    factor: u32,
) -> Result<(Vec<f32>, u32, u32)> {
    if rgb.len() as u64 != width as u64 * height as u64 * 3 {
        return Err(GpuError::Usage(format!(
            "{} values for a {width}x{height} RGB image",
            rgb.len()
        )));
    }
    let f = factor.max(1);
    let (w, h) = ((width / f).max(1), (height / f).max(1));
    let mut out = vec![0.0f32; w as usize * h as usize * 3];
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let mut s = 0.0;
                let mut n = 0.0;
                for dy in 0..f {
                    for dx in 0..f {
                        let (sx, sy) = (x * f + dx, y * f + dy);
                        if sx < width && sy < height {
                            s += rgb[(sy as usize * width as usize + sx as usize) * 3 + c as usize];
                            n += 1.0;
                        }
                    }
                }
                out[(y as usize * w as usize + x as usize) * 3 + c as usize] = s / n;
            }
        }
    }
    Ok((out, w, h))
}

/// A one-channel image as grey RGB (each value three times).
pub fn grey_to_rgb(v: &[f32]) -> Vec<f32> {
    v.iter().flat_map(|&x| [x, x, x]).collect()
}

/// `img` resized to `w x h` by area averaging (box filter over the covered source pixels), its
/// alpha too when it has one.
pub fn downscale_image(img: &Image, w: u32, h: u32) -> Image {
    let (sw, sh) = (img.width as usize, img.height as usize);
    let box_filter = |src: &[f32], ch: usize| {
        let (w, h) = (w as usize, h as usize);
        let mut out = vec![0f32; w * h * ch];
        for y in 0..h {
            let (y0, y1) = (y * sh / h, ((y + 1) * sh / h).max(y * sh / h + 1));
            for x in 0..w {
                let (x0, x1) = (x * sw / w, ((x + 1) * sw / w).max(x * sw / w + 1));
                let n = ((y1.min(sh) - y0) * (x1.min(sw) - x0)).max(1) as f32;
                for c in 0..ch {
                    let mut acc = 0f32;
                    for yy in y0..y1.min(sh) {
                        for xx in x0..x1.min(sw) {
                            acc += src[ch * (yy * sw + xx) + c];
                        }
                    }
                    out[ch * (y * w + x) + c] = acc / n;
                }
            }
        }
        out
    };
    Image {
        width: w,
        height: h,
        rgb: box_filter(&img.rgb, 3),
        alpha: img.alpha.as_ref().map(|a| box_filter(a, 1)),
    }
}

/// A separable box blur of radius `r` (applied twice: a tent) over an `[h, w, c]` image.
pub fn blur(img: &[f32], w: usize, h: usize, c: usize, r: usize) -> Vec<f32> {
    let pass = |src: &[f32], horizontal: bool| -> Vec<f32> {
        let mut out = vec![0f32; src.len()];
        for y in 0..h {
            for x in 0..w {
                let (lo, hi) = if horizontal {
                    (x.saturating_sub(r), (x + r).min(w - 1))
                } else {
                    (y.saturating_sub(r), (y + r).min(h - 1))
                };
                for ch in 0..c {
                    let mut s = 0f32;
                    for k in lo..=hi {
                        let j = if horizontal { y * w + k } else { k * w + x };
                        s += src[j * c + ch];
                    }
                    out[(y * w + x) * c + ch] = s / (hi - lo + 1) as f32;
                }
            }
        }
        out
    };
    let mut v = img.to_vec();
    for _ in 0..2 {
        v = pass(&v, true);
        v = pass(&v, false);
    }
    v
}

/// An unsharp mask of an `[h, w, 3]` image: `img + amount * (img - blur(img))` with the tent
/// blur of radius `radius` ([`blur`]), clamped to [0, 1].
pub fn unsharp(img: &[f32], w: usize, h: usize, amount: f32, radius: usize) -> Vec<f32> {
    let b = blur(img, w, h, 3, radius);
    img.iter()
        .zip(&b)
        .map(|(&x, &y)| (x + amount * (x - y)).clamp(0.0, 1.0))
        .collect()
}

/// Mean squared discrete Laplacian (4 x centre minus the 4 neighbours) of an `[h, w, 3]` image
/// over its interior pixels and channels: the energy of its finest detail (and of its pixel
/// noise). 0 for an image narrower or shorter than 3 pixels.
pub fn detail_energy(rgb: &[f32], w: usize, h: usize) -> f64 {
    if w < 3 || h < 3 {
        return 0.0;
    }
    let at = |x: usize, y: usize, c: usize| f64::from(rgb[(y * w + x) * 3 + c]);
    let mut sum = 0.0;
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            for c in 0..3 {
                let l = 4.0 * at(x, y, c)
                    - at(x - 1, y, c)
                    - at(x + 1, y, c)
                    - at(x, y - 1, c)
                    - at(x, y + 1, c);
                sum += l * l;
            }
        }
    }
    sum / ((w - 2) * (h - 2) * 3) as f64
}

/// A `sw x sh` mask resized to `w x h` by nearest neighbour (>= 0.5: 1).
pub fn resize_mask(mask: &[f32], sw: usize, sh: usize, w: usize, h: usize) -> Vec<f32> {
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let (sx, sy) = ((x * sw / w).min(sw - 1), (y * sh / h).min(sh - 1));
            f32::from(mask[sy * sw + sx] >= 0.5)
        })
        .collect()
}

/// The mask's bounding box grown to at least `min` pixels a side (within the image).
pub fn bbox(mask: &[bool], w: usize, h: usize, min: usize) -> Option<(usize, usize, usize, usize)> {
    let (mut x0, mut x1, mut y0, mut y1) = (w, 0, h, 0);
    for (i, &m) in mask.iter().enumerate() {
        if m {
            let (x, y) = (i % w, i / w);
            (x0, x1, y0, y1) = (x0.min(x), x1.max(x + 1), y0.min(y), y1.max(y + 1));
        }
    }
    if x1 == 0 {
        return None;
    }
    let grow = |lo: usize, hi: usize, size: usize| {
        let want = min.min(size);
        if hi - lo >= want {
            return (lo, hi);
        }
        let lo = lo.saturating_sub((want - (hi - lo)).div_ceil(2));
        let lo = lo.min(size - want);
        (lo, lo + want)
    };
    let (x0, x1) = grow(x0, x1, w);
    let (y0, y1) = grow(y0, y1, h);
    Some((x0, x1, y0, y1))
}

/// The RGB pixels of `img` (`w` wide) inside the box `(x0, x1, y0, y1)` (ends exclusive), row
/// by row.
pub fn crop(img: &[f32], w: usize, b: (usize, usize, usize, usize)) -> Vec<f32> {
    let mut v = Vec::new();
    for y in b.2..b.3 {
        v.extend_from_slice(&img[3 * (y * w + b.0)..3 * (y * w + b.1)]);
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn boxes_grow_to_the_smallest_input_inside_the_image() {
        let (w, h) = (40, 30);
        let mut mask = vec![false; w * h];
        assert_eq!(bbox(&mask, w, h, 16), None);
        mask[2 * w + 1] = true;
        let b = bbox(&mask, w, h, 16).unwrap();
        assert_eq!((b.1 - b.0, b.3 - b.2), (16, 16));
        assert!(b.0 <= 1 && b.1 > 1 && b.2 <= 2 && b.3 > 2);
        mask[29 * w + 39] = true;
        assert_eq!(bbox(&mask, w, h, 16), Some((1, 40, 2, 30)));
        // Larger than the image: the whole image.
        assert_eq!(bbox(&mask, w, h, 100), Some((0, 40, 0, 30)));
    }

    #[test]
    fn masks_resize_by_nearest_neighbour() {
        let up = resize_mask(&[1.0, 0.0], 2, 1, 4, 2);
        assert_eq!(up, [1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0]);
        assert_eq!(resize_mask(&[0.2, 0.7, 0.5, 0.0], 2, 2, 1, 1), [0.0]);
    }
}
