//! Frames of several fields side by side, each under a label (the fly-through video's frames):
//! a grid of tiles of one size, a label band above each tile, text drawn in the public-domain
//! 8x8 bitmap font of the `font8x8` crate.

use font8x8::{UnicodeFonts, BASIC_FONTS};

use crate::error::{ExtrapolateError, Result};

/// The most tiles in one row; more wrap onto further rows of as even a length as they allow.
pub const MAX_COLUMNS: u32 = 4;

/// Pixels between neighbouring tiles (black).
pub const GAP: u32 = 2;

/// The most pixels a montage may have on a side (what the video encoder takes).
pub const MAX_SIDE: u32 = 4096;

/// Where the tiles of a montage go: `columns` x `rows` tiles of `tile` pixels, each under a
/// label band of `band` pixels holding text at `scale` pixels per font pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Layout {
    /// One tile's width and height.
    pub tile: (u32, u32),
    /// Tiles per row, and rows.
    pub columns: u32,
    pub rows: u32,
    /// Font pixels are `scale` x `scale` image pixels.
    pub scale: u32,
    /// Height of the label band above each tile.
    pub band: u32,
}

impl Layout {
    /// The layout of `n` tiles of `width` x `height`: one row of up to [`MAX_COLUMNS`], else
    /// rows of equal length where they divide (`n` = 5: 3 + 2); text at one font pixel per
    /// image pixel up to tiles 320 wide, two up to 640, and so on.
    pub fn new(n: usize, width: u32, height: u32) -> Result<Layout> {
        if n == 0 || width == 0 || height == 0 {
            return Err(ExtrapolateError::usage(format!(
                "a montage of {n} tiles of {width}x{height}: it needs at least one tile of at least one pixel"
            )));
        }
        let n = n as u32;
        let rows = n.div_ceil(MAX_COLUMNS);
        let columns = n.div_ceil(rows);
        let scale = 1 + (width - 1) / 320;
        let l = Layout {
            tile: (width, height),
            columns,
            rows,
            scale,
            band: 10 * scale,
        };
        let (w, h) = l.size();
        if w > MAX_SIDE || h > MAX_SIDE {
            return Err(ExtrapolateError::usage(format!(
                "{n} frames of {width}x{height} side by side make {w}x{h}; a video takes at most \
                 {MAX_SIDE} pixels a side: choose a smaller fly-through size"
            )));
        }
        Ok(l)
    }

    /// The montage's width and height.
    pub fn size(&self) -> (u32, u32) {
        (
            self.columns * self.tile.0 + (self.columns - 1) * GAP,
            self.rows * (self.band + self.tile.1) + (self.rows - 1) * GAP,
        )
    }

    /// The top-left pixel of tile `i`'s label band (its image starts `band` rows below).
    pub fn origin(&self, i: usize) -> (u32, u32) {
        let (c, r) = (i as u32 % self.columns, i as u32 / self.columns);
        (c * (self.tile.0 + GAP), r * (self.band + self.tile.1 + GAP))
    }

    /// The montage of `tiles` (label, row-major RGB of the tile size in [0, 1]): black
    /// around them, each label in white, centred in its band and cut to the characters
    /// that fit; characters outside ASCII are drawn as `?`.
    pub fn compose(&self, tiles: &[(&str, &[f32])]) -> Result<Vec<f32>> {
        let (tw, th) = (self.tile.0 as usize, self.tile.1 as usize);
        if tiles.len() > (self.columns * self.rows) as usize {
            return Err(ExtrapolateError::usage(format!(
                "{} tiles for a montage of {} x {}",
                tiles.len(),
                self.columns,
                self.rows
            )));
        }
        let (w, h) = self.size();
        let w = w as usize;
        let mut out = vec![0.0f32; w * h as usize * 3];
        for (i, (label, rgb)) in tiles.iter().enumerate() {
            if rgb.len() != tw * th * 3 {
                return Err(ExtrapolateError::usage(format!(
                    "tile {i} ({label}) holds {} values; {tw}x{th} RGB needs {}",
                    rgb.len(),
                    tw * th * 3
                )));
            }
            let (x0, y0) = self.origin(i);
            let (x0, y0) = (x0 as usize, y0 as usize);
            let top = y0 + self.band as usize;
            for y in 0..th {
                let o = ((top + y) * w + x0) * 3;
                out[o..o + tw * 3].copy_from_slice(&rgb[y * tw * 3..(y + 1) * tw * 3]);
            }
            self.label(&mut out, w, (x0, y0), label);
        }
        Ok(out)
    }

    /// Draws `text` in the band whose top-left pixel is `at`.
    fn label(&self, out: &mut [f32], w: usize, at: (usize, usize), text: &str) {
        let s = self.scale as usize;
        let glyph = 8 * s;
        let fit = self.tile.0 as usize / glyph;
        let chars: Vec<char> = text.chars().take(fit).collect();
        let x0 = at.0 + (self.tile.0 as usize - chars.len() * glyph) / 2;
        let y0 = at.1 + s;
        for (k, &c) in chars.iter().enumerate() {
            let bits = glyph_of(c);
            for (row, byte) in bits.iter().enumerate() {
                for col in 0..8 {
                    if byte >> col & 1 == 0 {
                        continue;
                    }
                    for dy in 0..s {
                        for dx in 0..s {
                            let (x, y) = (x0 + k * glyph + col * s + dx, y0 + row * s + dy);
                            out[(y * w + x) * 3..(y * w + x) * 3 + 3].fill(1.0);
                        }
                    }
                }
            }
        }
    }
}

/// The 8x8 bitmap of `c` (rows top to bottom, bit `k` of a row: column `k` from the left);
/// `?`'s for characters the font does not hold.
pub fn glyph_of(c: char) -> [u8; 8] {
    BASIC_FONTS
        .get(c)
        .or_else(|| BASIC_FONTS.get('?'))
        .unwrap_or([0; 8])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_wrap_past_four_columns_and_refuse_what_a_video_cannot_hold() {
        let l = |n| {
            let l = Layout::new(n, 100, 50).unwrap();
            (l.columns, l.rows)
        };
        assert_eq!(l(1), (1, 1));
        assert_eq!(l(3), (3, 1));
        assert_eq!(l(4), (4, 1));
        assert_eq!(l(5), (3, 2));
        assert_eq!(l(9), (3, 3));
        let one = Layout::new(3, 100, 50).unwrap();
        assert_eq!(one.size(), (3 * 100 + 2 * GAP, 10 + 50));
        assert_eq!(one.origin(2), (2 * (100 + GAP), 0));
        let big = Layout::new(2, 640, 480).unwrap();
        assert_eq!((big.scale, big.band), (2, 20));
        assert_eq!(Layout::new(1, 320, 10).unwrap().scale, 1);
        assert!(Layout::new(0, 10, 10).is_err());
        assert!(Layout::new(1, 0, 10).is_err());
        let e = Layout::new(4, 1100, 800).unwrap_err().to_string();
        assert!(e.contains("4096") && e.contains("4406x840"), "{e}");
    }

    #[test]
    fn tiles_land_where_the_layout_says_under_their_labels() {
        let (tw, th) = (20u32, 6u32);
        let l = Layout::new(5, tw, th).unwrap();
        let tile = |k: usize| -> Vec<f32> {
            (0..tw * th)
                .flat_map(|p| [k as f32 / 10.0, p as f32 / 1000.0, 0.5])
                .collect()
        };
        let tiles: Vec<Vec<f32>> = (0..5).map(tile).collect();
        let labels = ["I", "", "IIIIIIII", "x", "\u{263a}"];
        let refs: Vec<(&str, &[f32])> = labels
            .iter()
            .zip(&tiles)
            .map(|(&s, t)| (s, t.as_slice()))
            .collect();
        let img = l.compose(&refs).unwrap();
        let (w, h) = l.size();
        assert_eq!(img.len(), (w * h * 3) as usize);
        let px = |x: u32, y: u32| {
            let o = ((y * w + x) * 3) as usize;
            [img[o], img[o + 1], img[o + 2]]
        };
        // Every tile's pixels, exactly, below its band.
        for (k, t) in tiles.iter().enumerate() {
            let (x0, y0) = l.origin(k);
            for y in 0..th {
                for x in 0..tw {
                    let o = ((y * tw + x) * 3) as usize;
                    assert_eq!(px(x0 + x, y0 + l.band + y), [t[o], t[o + 1], t[o + 2]]);
                }
            }
        }
        // The label: tile 0's "I" centred ((20 - 8) / 2 = 6 from the tile's edge), one row
        // down, white exactly where the font's bits are set and black elsewhere in the band.
        let bits = glyph_of('I');
        for y in 0..l.band {
            for x in 0..tw {
                let inside = (6..14).contains(&x) && (1..9).contains(&y);
                let set = inside && bits[(y - 1) as usize] >> (x - 6) & 1 == 1;
                assert_eq!(px(x, y), [f32::from(set); 3], "({x}, {y})");
            }
        }
        // An empty label leaves its band black; a long one is cut to the two characters that
        // fit; a character outside the font is drawn as `?`.
        let (x1, y1) = l.origin(1);
        assert!((0..l.band).all(|y| (0..tw).all(|x| px(x1 + x, y1 + y) == [0.0; 3])));
        let (x2, y2) = l.origin(2);
        let lit = |x0: u32, y0: u32, xs: std::ops::Range<u32>| {
            xs.filter(|&x| (0..l.band).any(|y| px(x0 + x, y0 + y)[0] == 1.0))
                .count()
        };
        assert!(lit(x2, y2, 0..2) == 0 && lit(x2, y2, 2..18) > 0 && lit(x2, y2, 18..20) == 0);
        let (x4, y4) = l.origin(4);
        let q = glyph_of('?');
        assert_ne!(q, [0; 8]);
        assert_eq!(glyph_of('\u{263a}'), q);
        for (row, byte) in q.iter().enumerate() {
            for col in 0..8u32 {
                let v = px(x4 + 6 + col, y4 + 1 + row as u32)[0];
                assert_eq!(v, f32::from(byte >> col & 1 == 1));
            }
        }
        // The gaps between tiles stay black.
        assert!((0..h).all(|y| px(tw, y) == [0.0; 3] && px(tw + 1, y) == [0.0; 3]));
        // Mis-sized tiles and too many of them are errors.
        let short = vec![0.0f32; 3];
        assert!(l.compose(&[("a", &short)]).is_err());
        let many: Vec<(&str, &[f32])> = (0..7).map(|_| ("a", tiles[0].as_slice())).collect();
        assert!(l.compose(&many).is_err());
    }

    #[test]
    fn a_montage_decodes_from_its_video_where_the_layout_put_it() {
        use extranerf_nerf::video::{read_video, VideoWriter};
        let (tw, th) = (24u32, 18u32);
        let l = Layout::new(2, tw, th).unwrap();
        // Smooth tiles (what H.264 keeps well), unlike each other.
        let tile = |k: u32| -> Vec<f32> {
            (0..tw * th)
                .flat_map(|p| {
                    let (x, y) = ((p % tw) as f32 / tw as f32, (p / tw) as f32 / th as f32);
                    [0.2 + 0.6 * x, 0.3 + 0.4 * y * k as f32, 0.8 - 0.5 * x * y]
                })
                .collect()
        };
        let (a, b) = (tile(0), tile(1));
        let img = l.compose(&[("BaseNeRF", &a), ("stage 2", &b)]).unwrap();
        let dir = std::env::temp_dir().join(format!("extranerf-montage-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("m.mp4");
        let (w, h) = l.size();
        let mut v = VideoWriter::create(&path, w, h, 10.0).unwrap();
        v.push(&img).unwrap();
        v.push(&img).unwrap();
        v.finish().unwrap();
        let d = read_video(&path).unwrap();
        assert_eq!((d.width, d.height, d.frames.len()), (w, h, 2));
        for (k, t) in [&a, &b].iter().enumerate() {
            let (x0, y0) = l.origin(k);
            // Mean error of the tile against the video shifted by (dx, dy).
            let err = |dx: i32, dy: i32| {
                let mut e = 0.0;
                let mut n = 0.0;
                for y in 1..th - 1 {
                    for x in 1..tw - 1 {
                        let (vx, vy) = ((x0 + x) as i32 + dx, (y0 + l.band + y) as i32 + dy);
                        let o = ((vy as u32 * w + vx as u32) * 3) as usize;
                        let q = ((y * tw + x) * 3) as usize;
                        for c in 0..3 {
                            e += (d.frames[1][o + c] as f64 - 255.0 * t[q + c] as f64).abs();
                            n += 1.0;
                        }
                    }
                }
                e / n
            };
            let here = err(0, 0);
            // The codec's own error (a fixed quantiser of 26, 4:2:0 chroma): 3.2 and 4.4
            // (`cargo test -p extranerf-extrapolate montage -- --nocapture`).
            eprintln!("tile {k}: {here:.2}/255 from the video");
            assert!(here < 6.0, "tile {k}: {here}/255");
            for (dx, dy) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
                assert!(
                    here < err(dx, dy),
                    "tile {k} fits better shifted by ({dx}, {dy})"
                );
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
