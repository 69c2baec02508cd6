//! Videos (extranerf_nerf::video): H.264 in MP4, written frame by frame and decoded back.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_nerf::video::{read_video, VideoWriter};
use extranerf_tests::scratch_dir;

/// Frame `k` of a test pattern: a gradient across, another down, a level per frame.
fn pattern(w: u32, h: u32, k: u32) -> Vec<f32> {
    (0..h)
        .flat_map(|y| {
            (0..w).flat_map(move |x| {
                [
                    x as f32 / w as f32,
                    y as f32 / h as f32,
                    (k % 8) as f32 / 8.0,
                ]
            })
        })
        .collect()
}

#[test]
fn a_video_decodes_to_its_frames_size_and_rate() {
    let dir = scratch_dir("video");
    // An odd size: H.264 needs even ones, so the last column and row are repeated.
    let (w, h, n, fps) = (45u32, 31u32, 12u32, 12.5);
    let path = dir.join("path.mp4");
    let mut v = VideoWriter::create(&path, w, h, fps).unwrap();
    for k in 0..n {
        v.push(&pattern(w, h, k)).unwrap();
    }
    assert!(!path.exists(), "the video is there only once finished");
    assert_eq!(v.finish().unwrap(), n as u64);
    assert!(!dir.join("path.mp4.partial").exists());
    let d = read_video(&path).unwrap();
    assert_eq!((d.width, d.height), (46, 32));
    assert!((d.fps - fps).abs() < 1e-6, "{} fps", d.fps);
    assert_eq!(d.frames.len(), n as usize);
    // Each decoded frame is its own pattern (not another frame's), within the codec's loss.
    for (k, f) in d.frames.iter().enumerate() {
        assert_eq!(f.len(), 46 * 32 * 3);
        let want = pattern(w, h, k as u32);
        let mut err = 0.0;
        for y in 0..h as usize {
            for x in 0..w as usize {
                for c in 0..3 {
                    let a = f[(y * 46 + x) * 3 + c] as f64 / 255.0;
                    err += (a - want[(y * w as usize + x) * 3 + c] as f64).abs();
                }
            }
        }
        let mean = err / (w * h * 3) as f64;
        assert!(mean < 0.03, "frame {k}: mean error {mean}");
        // The repeated row is the last row.
        let (last, pad) = (31 * 46 * 3, 30 * 46 * 3);
        let diff: i32 = (0..46 * 3)
            .map(|i| (f[last + i] as i32 - f[pad + i] as i32).abs())
            .max()
            .unwrap();
        assert!(diff <= 12, "frame {k}: padding row differs by {diff}");
    }
    // Refused: a frame of another size, no frame at all, a size or rate that cannot be.
    let mut v = VideoWriter::create(&dir.join("bad.mp4"), 8, 8, 30.0).unwrap();
    let e = v.push(&[0.5; 10]).unwrap_err().to_string();
    assert!(e.contains("bad.mp4") && e.contains("8x8"), "{e}");
    let e = v.finish().unwrap_err().to_string();
    assert!(e.contains("no frame"), "{e}");
    assert!(!dir.join("bad.mp4").exists());
    for (w, h, fps) in [(0, 8, 30.0), (8, 5000, 30.0), (8, 8, 0.0), (8, 8, f64::NAN)] {
        assert!(VideoWriter::create(&dir.join("x.mp4"), w, h, fps).is_err());
    }
    // A file cut short is an error naming it.
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.join("cut.mp4");
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    let e = read_video(&cut).unwrap_err().to_string();
    assert!(e.contains("cut.mp4"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
