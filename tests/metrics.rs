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
