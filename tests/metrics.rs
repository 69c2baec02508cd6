//! Image-quality metrics on real images: the LPIPS goldens of the authors' example images (both
//! backbones), identity and symmetry, PSNR / SSIM sanity on fern, and the weights-file errors.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::path::PathBuf;

use extranerf_nerf::data::{load_image, Image};
use extranerf_nerf::metrics::{psnr, ssim, Lpips, LpipsNet, MetricsError};
use extranerf_tests::shared_data;

fn weights(net: LpipsNet) -> PathBuf {
    let name = match net {
        LpipsNet::Alex => "lpips_alex_v0.1.safetensors",
        LpipsNet::Vgg => "lpips_vgg_v0.1.safetensors",
    };
    shared_data().join("../models/lpips").join(name)
}

fn example(name: &str) -> Image {
    load_image(&shared_data().join("lpips_examples").join(name)).unwrap()
}

fn fern(i: usize) -> Image {
    load_image(
        &shared_data()
            .join("llff/fern/images_8")
            .join(format!("image{i:03}.png")),
    )
    .unwrap()
}

fn check_goldens(net: LpipsNet, p0: f64, p1: f64) {
    let m = Lpips::load(&weights(net), net).unwrap();
    let [r, a, b] = ["ex_ref.png", "ex_p0.png", "ex_p1.png"].map(example);
    assert_eq!((r.width, r.height), (64, 64));
    let d = |x: &Image, y: &Image| m.distance(&x.rgb, &y.rgb, x.width, x.height).unwrap();
    let (d0, d1, dr) = (d(&r, &a), d(&r, &b), d(&r, &r));
    eprintln!("{net:?}: d(ref, p0) = {d0:.7}, d(ref, p1) = {d1:.7}, d(ref, ref) = {dr}");
    assert!(
        (d0 - p0).abs() < 1e-4,
        "{net:?} d(ref, p0) = {d0}, golden {p0}"
    );
    assert!(
        (d1 - p1).abs() < 1e-4,
        "{net:?} d(ref, p1) = {d1}, golden {p1}"
    );
    assert!(dr.abs() < 1e-6, "{net:?} d(ref, ref) = {dr}");
    for (x, y) in [(&r, &a), (&r, &b), (&a, &b)] {
        assert!((d(x, y) - d(y, x)).abs() < 1e-6, "{net:?} not symmetric");
    }
}

#[test]
fn lpips_alex_matches_goldens() {
    check_goldens(LpipsNet::Alex, 0.721881, 0.137566);
}

#[test]
fn lpips_vgg_matches_goldens() {
    check_goldens(LpipsNet::Vgg, 0.568613, 0.421664);
}

#[test]
fn missing_weights_file_names_the_path() {
    let p = shared_data().join("../models/lpips/no_such_weights.safetensors");
    let e = Lpips::load(&p, LpipsNet::Vgg).unwrap_err();
    assert!(matches!(e, MetricsError::Io { .. }), "{e}");
    assert!(e.to_string().contains("no_such_weights.safetensors"), "{e}");
}

#[test]
fn wrong_weights_file_is_an_error() {
    // AlexNet's first conv is 11x11, VGG's 3x3.
    let e = Lpips::load(&weights(LpipsNet::Alex), LpipsNet::Vgg).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("lpips_alex_v0.1.safetensors")
            && msg.ends_with(
                "tensor `features.0.weight` has shape [64, 3, 11, 11], expected [64, 3, 3, 3]"
            ),
        "{msg}"
    );
}

#[test]
fn psnr_and_ssim_on_fern() {
    let (a, b) = (fern(0), fern(1));
    let p = psnr(&a.rgb, &b.rgb).unwrap();
    let s = ssim(&a.rgb, &b.rgb, a.width, a.height).unwrap();
    eprintln!("fern 0 vs 1: PSNR {p:.3} dB, SSIM {s:.4}");
    // PSNR against its definition, in f64 here.
    let mse = a
        .rgb
        .iter()
        .zip(&b.rgb)
        .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
        .sum::<f64>()
        / a.rgb.len() as f64;
    let want = -10.0 * mse.log10();
    assert!((p - want).abs() < 1e-6, "PSNR {p} against {want}");
    // Two neighbouring photos of one scene: alike, far from identical.
    assert!(p > 10.0 && p < 30.0, "{p}");
    // SSIM is symmetric, and ranks a lightly perturbed copy above the neighbouring view.
    let s_ba = ssim(&b.rgb, &a.rgb, a.width, a.height).unwrap();
    assert!((s - s_ba).abs() < 1e-12, "{s} vs {s_ba}");
    let near: Vec<f32> = a
        .rgb
        .iter()
        .enumerate()
        .map(|(i, v)| (v + if i % 2 == 0 { 0.01 } else { -0.01 }).clamp(0.0, 1.0))
        .collect();
    let s_near = ssim(&a.rgb, &near, a.width, a.height).unwrap();
    assert!(
        s > 0.1 && s < 0.9 && s_near > s && s_near < 1.0,
        "{s} {s_near}"
    );
    assert_eq!(psnr(&a.rgb, &a.rgb).unwrap(), f64::INFINITY);
    assert!((ssim(&a.rgb, &a.rgb, a.width, a.height).unwrap() - 1.0).abs() < 1e-12);
}

/// u8 value of channel `c` at pixel (x, y) of golden image `k` (tools/inception_golden.py).
fn golden_pattern(x: u32, y: u32, c: u32, k: u32) -> u32 {
    let mut v = x * (3 + k) + y * (5 + 2 * k) + c * 71 + ((x * y) % 37) * 3;
    if ((x / (8 + k)) + (y / 11)).is_multiple_of(2) {
        v += 40;
    }
    v % 256
}

fn golden_image(w: u32, h: u32, k: u32) -> Vec<f32> {
    let mut rgb = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                rgb.push(golden_pattern(x, y, c, k) as f32 / 255.0);
            }
        }
    }
    rgb
}

#[test]
fn inception_features_match_the_torchscript_module() {
    use extranerf_extrapolate::eval::inception::{preprocess, ImageRef, Inception, FEATURES};
    let golden: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/inception_golden.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let dev = burn::tensor::Device::flex();
    let net = Inception::load(&extranerf_tests::inception_weights(), &dev).unwrap();
    let cases = golden["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 3);
    let images: Vec<(usize, usize, Vec<f32>)> = cases
        .iter()
        .map(|c| {
            let (w, h, k) = (
                c["width"].as_u64().unwrap() as u32,
                c["height"].as_u64().unwrap() as u32,
                c["pattern"].as_u64().unwrap() as u32,
            );
            (w as usize, h as usize, golden_image(w, h, k))
        })
        .collect();
    let refs: Vec<ImageRef> = images
        .iter()
        .map(|(w, h, rgb)| ImageRef {
            rgb,
            width: *w,
            height: *h,
        })
        .collect();
    // The resize and range mapping, in f64 against torch's f32 grid sample.
    for (c, im) in cases.iter().zip(&refs) {
        let x = preprocess(im).unwrap();
        let sum: f64 = x.iter().map(|&v| f64::from(v)).sum();
        let sq: f64 = x.iter().map(|&v| f64::from(v).powi(2)).sum();
        let (gs, gq) = (
            c["input_sum"].as_f64().unwrap(),
            c["input_sum_sq"].as_f64().unwrap(),
        );
        eprintln!(
            "{}x{}: input sum {sum:.4} (golden {gs:.4}), sum of squares {sq:.4} ({gq:.4})",
            im.width, im.height
        );
        assert!((sum - gs).abs() < 1e-3 * gq, "input sum {sum} vs {gs}");
        assert!(
            (sq - gq).abs() < 1e-5 * gq,
            "input sum of squares {sq} vs {gq}"
        );
    }
    // All three in one batch (batch 2: a full batch and a partial one).
    let feats = net.features(&refs, 2).unwrap();
    assert_eq!(feats.len(), 3 * FEATURES);
    for (i, c) in cases.iter().enumerate() {
        let g: Vec<f32> = c["features"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap() as f32)
            .collect();
        let f = &feats[i * FEATURES..(i + 1) * FEATURES];
        let err = extranerf_tests::max_rel_err(f, &g);
        let dot: f64 = f
            .iter()
            .zip(&g)
            .map(|(a, b)| f64::from(*a) * f64::from(*b))
            .sum();
        let nf: f64 = f.iter().map(|a| f64::from(*a).powi(2)).sum::<f64>().sqrt();
        let ng: f64 = g.iter().map(|a| f64::from(*a).powi(2)).sum::<f64>().sqrt();
        eprintln!(
            "{}x{}: max |f - golden| / max |golden| = {err:.2e}, cosine {:.9}",
            refs[i].width,
            refs[i].height,
            dot / (nf * ng)
        );
        assert!(
            err < 1e-4,
            "image {i}: features differ from the golden by {err:.2e}"
        );
    }
    // A batch of one gives the same features as the batch.
    let one = net.features(&refs[1..2], 1).unwrap();
    let err = extranerf_tests::max_rel_err(&one, &feats[FEATURES..2 * FEATURES]);
    assert!(err < 1e-5, "batching changes the features by {err:.2e}");
}

#[test]
fn inception_weight_errors_name_the_file() {
    use extranerf_extrapolate::eval::inception::Inception;
    let dev = burn::tensor::Device::flex();
    let dir = extranerf_tests::scratch_dir("inception-weights");
    let missing = dir.join("none.safetensors");
    let e = Inception::load(&missing, &dev).unwrap_err().to_string();
    assert!(
        e.contains("none.safetensors") && e.contains("fetch_inception"),
        "{e}"
    );
    // A file with one convolution: the others are reported missing by name.
    let mut st = extranerf_nerf::safetensors::SafeTensors::default();
    let t = |shape: Vec<usize>| extranerf_nerf::safetensors::Tensor {
        data: vec![0.5; shape.iter().product()],
        shape,
    };
    st.tensors
        .insert("net.layers.conv.weight".into(), t(vec![32, 3, 3, 3]));
    for n in ["mean", "var", "beta"] {
        st.tensors
            .insert(format!("net.layers.conv.{n}"), t(vec![32]));
    }
    let part = dir.join("part.safetensors");
    st.write(&part).unwrap();
    let e = Inception::load(&part, &dev).unwrap_err().to_string();
    assert!(
        e.contains("part.safetensors") && e.contains("net.layers.conv_1.weight"),
        "{e}"
    );
    // A wrong shape is named too.
    st.tensors
        .insert("net.layers.conv.beta".into(), t(vec![31]));
    st.write(&part).unwrap();
    let e = Inception::load(&part, &dev).unwrap_err().to_string();
    assert!(
        e.contains("net.layers.conv.beta") && e.contains("[31]"),
        "{e}"
    );
}
