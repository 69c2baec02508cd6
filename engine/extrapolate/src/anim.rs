//! Animated images a browser plays: frames of linear RGB in [0, 1] written as a looping GIF.

use std::path::Path;

use crate::error::{ExtrapolateError, Result};
use extranerf_nerf::data::unorm8;
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbaImage};

/// Writes `frames` (each `width * height * 3` floats, row-major RGB in [0, 1]; values outside
/// are clamped, NaN is black) as a GIF that loops forever, `delay_ms` per frame. The file is
/// written to a temporary name and renamed, so a crash leaves no half-written animation.
pub fn write_gif(
    path: &Path,
    width: u32,
    height: u32,
    frames: &[Vec<f32>],
    delay_ms: u32,
) -> Result<()> {
    if frames.is_empty() {
        return Err(ExtrapolateError::usage(format!(
            "{}: an animation needs at least one frame",
            path.display()
        )));
    }
    if width == 0 || height == 0 || width > u16::MAX as u32 || height > u16::MAX as u32 {
        return Err(ExtrapolateError::usage(format!(
            "{}: {width}x{height} frames; a GIF holds 1 to 65535 pixels per side",
            path.display()
        )));
    }
    let n = (width * height * 3) as usize;
    let tmp = path.with_extension("gif.tmp");
    {
        let file =
            std::fs::File::create(&tmp).map_err(|e| ExtrapolateError::io("creating", &tmp, e))?;
        let mut enc = GifEncoder::new_with_speed(std::io::BufWriter::new(file), 10);
        let encoding =
            |e: image::ImageError| ExtrapolateError::io("writing", &tmp, std::io::Error::other(e));
        enc.set_repeat(Repeat::Infinite).map_err(encoding)?;
        for (i, f) in frames.iter().enumerate() {
            if f.len() != n {
                return Err(ExtrapolateError::usage(format!(
                    "{}: frame {i} holds {} values, {width}x{height} RGB needs {n}",
                    path.display(),
                    f.len()
                )));
            }
            let px: Vec<u8> = f
                .chunks_exact(3)
                .flat_map(|c| [unorm8(c[0]), unorm8(c[1]), unorm8(c[2]), 255])
                .collect();
            let Some(img) = RgbaImage::from_raw(width, height, px) else {
                return Err(ExtrapolateError::usage(format!(
                    "{}: frame {i} does not fit {width}x{height}",
                    path.display()
                )));
            };
            enc.encode_frame(Frame::from_parts(
                img,
                0,
                0,
                Delay::from_numer_denom_ms(delay_ms, 1),
            ))
            .map_err(encoding)?;
        }
    }
    std::fs::rename(&tmp, path).map_err(|e| ExtrapolateError::io("writing", path, e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_round_trip_through_the_decoder() {
        use image::AnimationDecoder;
        let dir = std::env::temp_dir().join(format!("extranerf-anim-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.gif");
        let (w, h) = (5u32, 3u32);
        // Two flat frames (exact in any palette) and one with out-of-range values and a NaN.
        let red = [1.0f32, 0.0, 0.0].repeat((w * h) as usize);
        let grey = [0.5f32, 0.5, 0.5].repeat((w * h) as usize);
        let mut wild = [2.0f32, -1.0, f32::NAN].repeat((w * h) as usize);
        wild[0] = 0.0;
        write_gif(&path, w, h, &[red, grey, wild], 80).unwrap();
        let dec = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(
            std::fs::File::open(&path).unwrap(),
        ))
        .unwrap();
        let frames = dec.into_frames().collect_frames().unwrap();
        assert_eq!(frames.len(), 3);
        let px = |f: usize, i: usize| frames[f].buffer().pixels().nth(i).unwrap().0;
        assert_eq!(frames[0].buffer().dimensions(), (w, h));
        assert_eq!(px(0, 7), [255, 0, 0, 255]);
        let g = px(1, 4);
        assert!(g[..3].iter().all(|&c| (c as i32 - 128).abs() <= 2), "{g:?}");
        // Clamped: 2 -> 255, -1 -> 0, NaN -> 0.
        assert_eq!(px(2, 3), [255, 0, 0, 255]);
        assert_eq!(frames[0].delay().numer_denom_ms(), (80, 1));
        // Mis-sized frames and no frames are errors naming the file.
        let e = write_gif(&path, w, h, &[vec![0.0; 3]], 80).unwrap_err();
        assert!(e.to_string().contains("a.gif"), "{e}");
        assert!(write_gif(&path, w, h, &[], 80).is_err());
        assert!(write_gif(&path, 0, h, &[vec![]], 80).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
