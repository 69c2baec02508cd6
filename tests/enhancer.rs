//! The stage-3 enhancer on a task with a known answer (issue 18), alone in a process of its own
//! (rusty-fork runs it in a child of the test binary): burn's random state is process-global, so
//! a test sharing the process would change the enhancer's initialisation from run to run. Alone,
//! the run is the same every time.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use burn::tensor::Device;
use extranerf_diffusion::inpaint::SampleSettings;
use extranerf_diffusion::pipeline::Pipeline;
use extranerf_diffusion::scheduler::SchedulerConfig;
use extranerf_diffusion::train::TrainImage;
use extranerf_tests::{scratch_dir, tiny_pixel_unet_config};
use rusty_fork::rusty_fork_test;

fn cpu() -> Device {
    Device::flex()
}

/// A checkerboard of random cell size, phase and colours, `s x s`.
fn checkers(s: usize, seed: u64) -> Vec<f32> {
    let mut rng = extranerf_diffusion::inpaint::SplitMix(seed);
    let cell = 4 + rng.below(5);
    let (ox, oy) = (rng.below(cell), rng.below(cell));
    let a: [f32; 3] = std::array::from_fn(|_| rng.unit() as f32);
    let b: [f32; 3] = std::array::from_fn(|_| rng.unit() as f32);
    let mut v = Vec::with_capacity(s * s * 3);
    for y in 0..s {
        for x in 0..s {
            let on = ((x + ox) / cell + (y + oy) / cell).is_multiple_of(2);
            v.extend_from_slice(if on { &a } else { &b });
        }
    }
    v
}

/// `img` (`s x s x 3`) box-blurred with a `(2r + 1)^2` window, clamped at the borders.
fn box_blur(img: &[f32], s: usize, r: usize) -> Vec<f32> {
    let mut out = vec![0f32; img.len()];
    for y in 0..s {
        for x in 0..s {
            let (y0, y1) = (y.saturating_sub(r), (y + r).min(s - 1));
            let (x0, x1) = (x.saturating_sub(r), (x + r).min(s - 1));
            let n = ((y1 - y0 + 1) * (x1 - x0 + 1)) as f32;
            for c in 0..3 {
                let mut acc = 0f32;
                for yy in y0..=y1 {
                    for xx in x0..=x1 {
                        acc += img[3 * (yy * s + xx) + c];
                    }
                }
                out[3 * (y * s + x) + c] = acc / n;
            }
        }
    }
    out
}

/// The enhancer on a task with a known answer: blurred checkerboards back to sharp ones. After a
/// short training on 12 (blurred, sharp) pairs it must bring held-out blurred boards closer to
/// their sharp originals in LPIPS than the blurred input is, by at least 15%, with either
/// output (v, and the residual on the render); the folder
/// it writes reloads as an enhancer, and an inpainting model is refused as one.
fn an_enhancer_learns_to_sharpen_blurred_textures_in_this_process() {
    use extranerf_diffusion::enhancer::{self, EnhancerOutput, EnhancerSpec};
    use extranerf_diffusion::train::Guide;
    let s = 48;
    let images: Vec<TrainImage> = (0..12)
        .map(|i| {
            let sharp = checkers(s, 100 + i);
            let mut im = TrainImage::new(s, s, sharp.clone());
            im.guides = vec![Guide {
                rgb: box_blur(&sharp, s, 2),
                mask: vec![0.0; s * s],
            }];
            im
        })
        .collect();
    let lp = extranerf_nerf::metrics::Lpips::load(
        &extranerf_tests::shared_data().join("../models/lpips/lpips_alex_v0.1.safetensors"),
        extranerf_nerf::metrics::LpipsNet::Alex,
    )
    .unwrap();
    // Both outputs: v (the scene prior's) and the residual on the render (the default).
    let mut dirs = Vec::new();
    for output in [EnhancerOutput::V, EnhancerOutput::Residual] {
        let out = scratch_dir(&format!("enhancer_checkers_{output:?}"));
        let spec = EnhancerSpec {
            channels: vec![16, 32],
            steps: 250,
            batch: 8,
            crop: 24,
            lr: 5e-3,
            jitter: 0.0,
            max_strength: 0.3,
            output,
            ..EnhancerSpec::default()
        };
        let t = std::time::Instant::now();
        let rec = enhancer::train_enhancer(&images, &spec, &out, &cpu(), &mut |_| {}).unwrap();
        eprintln!(
            "enhancer ({output:?}): {} parameters, loss {:.4} -> {:.4} in {:.1} s",
            rec.params,
            rec.curve[0].1,
            rec.curve.last().unwrap().1,
            t.elapsed().as_secs_f64()
        );
        let pipe = enhancer::load(&out, &cpu()).unwrap();
        let (mut before, mut after) = (0.0, 0.0);
        let held_out = 6;
        for i in 0..held_out {
            let sharp = checkers(s, 900 + i);
            let blurred = box_blur(&sharp, s, 2);
            let e = pipe
                .model
                .enhance_image(
                    &blurred,
                    None,
                    s,
                    s,
                    i,
                    &SampleSettings {
                        strength: 0.3,
                        steps: 6,
                        guidance: 1.0,
                        keep_known: true,
                    },
                    &cpu(),
                )
                .unwrap();
            before += lp.distance(&blurred, &sharp, s as u32, s as u32).unwrap();
            after += lp.distance(&e.rgb, &sharp, s as u32, s as u32).unwrap();
        }
        let (before, after) = (before / held_out as f64, after / held_out as f64);
        eprintln!(
            "held-out boards ({output:?}): LPIPS-alex blurred {before:.4}, enhanced {after:.4}"
        );
        // Alone in its process the run repeats exactly. v: 0.1197 -> 0.0841 twice (loss
        // 0.8773 -> 0.2198); sharing a process with other tests it measured 0.084-0.115
        // (burn's random state is global): at least 15% less. Residual: 0.1197 -> 0.0458
        // (loss 0.0474 -> 0.0035): at least 40% less.
        let bound = match output {
            EnhancerOutput::V => 0.85,
            EnhancerOutput::Residual => 0.6,
        };
        assert!(
            after < bound * before,
            "the enhancer ({output:?}) did not sharpen: LPIPS {before:.4} -> {after:.4}"
        );
        dirs.push(out);
    }
    // An inpainting model is not an enhancer.
    let inpainter = scratch_dir("enhancer_not");
    Pipeline::new(
        tiny_pixel_unet_config(),
        None,
        SchedulerConfig::default(),
        2,
        &cpu(),
    )
    .unwrap()
    .save(&inpainter)
    .unwrap();
    let e = enhancer::load_any(&inpainter, None, &cpu()).unwrap_err();
    assert!(e.to_string().contains("not an enhancer"), "{e}");
    let p = Pipeline::load(&inpainter, &cpu(), "").unwrap();
    let e = p
        .model
        .enhance_image(
            &vec![0.5; 16 * 16 * 3],
            None,
            16,
            16,
            0,
            &SampleSettings::default(),
            &cpu(),
        )
        .unwrap_err();
    assert!(e.to_string().contains("trained to inpaint"), "{e}");
    for out in dirs {
        let _ = std::fs::remove_dir_all(&out);
    }
    let _ = std::fs::remove_dir_all(&inpainter);
}

rusty_fork_test! {
    /// In a process of its own (rusty-fork): burn's random generator is process-global, so a test
    /// drawing from it at the same time would change the enhancer's initialisation.
    #[test]
    fn an_enhancer_learns_to_sharpen_blurred_textures() {
        an_enhancer_learns_to_sharpen_blurred_textures_in_this_process();
    }
}
