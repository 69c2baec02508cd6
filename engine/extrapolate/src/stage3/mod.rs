//! ExtraNeRF's stage 3: an enhancer trained on the scene's own corrupted renders sharpens the
//! renders of the virtual views, and the field is supervised by the result.
//!
//! - [`EnhancerDataStage`] (`RUN/stage3-data`): (corrupted render, mask, photo) triplets of
//!   the training views. A field whose supervision inside each training view's
//!   pseudo-disocclusion mask (the view against the other training cameras) comes from the
//!   stage-2 inpainter instead of the photo is optimised from the BaseNeRF, and the training
//!   views are rendered after each of its rounds; renders of an under-fitted field (a fresh
//!   field trained with the BaseNeRF's settings, at a few step counts) and of the BaseNeRF
//!   itself are added.
//! - [`EnhancerStage`] (`RUN/stage3-enhancer`): the enhancer trained on them
//!   ([`extranerf_diffusion::enhancer`]).
//! - [`EnhanceStage`] (`RUN/stage3-NAME`, one per stage-2 variant): rounds of rendering the
//!   virtual views, enhancing them from a moderate noise level in a few DDIM steps, and
//!   training on them (w(t)-weighted L1 of the colours, the depth loss on the rendered depth)
//!   mixed with the captured views.
//!
//! Files: [`spec`] (the settings and the target of a virtual view), [`triplets`] (the
//! enhancer's training data on disk), [`data`], [`enhancer`] and [`enhance`] (the three
//! stages), [`gate`] (the check that the enhancer helps).

pub mod data;
pub mod enhance;
pub mod enhancer;
pub mod gate;
pub mod spec;
pub mod triplets;

pub use data::{collector_views, DataSpec, EnhancerDataStage};
pub use enhance::EnhanceStage;
pub use enhancer::{EnhancerStage, EnhancerStageSpec};
pub use gate::{check_enhancer, check_triplets, EnhancerCheck, CHECK_FILE};
pub use spec::{
    stage3_target, virtual_weights, Stage3Enhancer, Stage3Gate, Stage3Spec, MAX_RADIUS,
};
pub use triplets::{TripletEntry, Triplets, TRIPLETS_FILE, TRIPLETS_INDEX};

#[cfg(test)]
mod tests {
    use super::{
        check_triplets, stage3_target, virtual_weights, EnhancerCheck, Stage3Enhancer, Stage3Spec,
        TripletEntry, Triplets,
    };
    use extranerf_nerf::image_ops::{detail_energy, unsharp};

    #[test]
    fn the_unsharp_mask_overshoots_an_edge_by_the_tent_blur() {
        // A vertical step 0.2 | 0.8 between columns 3 and 4 of an 8x3 image. The tent of
        // radius 1 is [1, 2, 3, 2, 1] / 9: beside the edge the blur is 0.4 (dark side) and 0.6
        // (bright side), so amount 0.5 gives 0.1 and 0.9; two columns away it is 2.4 / 9 and
        // 6.6 / 9, giving 1 / 6 and 5 / 6; three columns away nothing changes.
        let (w, h) = (8, 3);
        let img: Vec<f32> = (0..w * h * 3)
            .map(|i| if (i / 3) % w < 4 { 0.2 } else { 0.8 })
            .collect();
        let out = unsharp(&img, w, h, 0.5, 1);
        let want = [0.2, 0.2, 1.0 / 6.0, 0.1, 0.9, 5.0 / 6.0, 0.8, 0.8];
        for (i, v) in out.iter().enumerate() {
            let x = (i / 3) % w;
            assert!((v - want[x]).abs() < 1e-6, "column {x}: {v}");
        }
        // Clamped to [0, 1]; a constant image is left as it is.
        let strong = unsharp(&img, w, h, 4.0, 1);
        assert!(strong.iter().all(|v| (0.0..=1.0).contains(v)));
        assert_eq!((strong[3 * 3], strong[4 * 3]), (0.0, 1.0));
        let flat = vec![0.37f32; w * h * 3];
        assert!(unsharp(&flat, w, h, 2.0, 2)
            .iter()
            .all(|v| (v - 0.37).abs() < 1e-6));
        // Its settings are checked only when it is chosen.
        let spec = |amount, radius| Stage3Spec {
            enhance: Stage3Enhancer::Unsharp,
            unsharp_amount: amount,
            unsharp_radius: radius,
            ..Stage3Spec::default()
        };
        assert!(spec(0.5, 1).validate().is_ok());
        for (a, r) in [(0.0, 1), (4.5, 1), (f32::NAN, 1), (0.5, 0), (0.5, 65)] {
            let e = spec(a, r).validate().unwrap_err().to_string();
            assert!(e.contains("--stage3-unsharp-amount"), "{e}");
        }
        let diffusion = Stage3Spec {
            unsharp_amount: 0.0,
            ..Stage3Spec::default()
        };
        assert!(diffusion.validate().is_ok());
    }

    #[test]
    fn the_check_judges_by_lpips_and_by_psnr_without_it() {
        let c = EnhancerCheck {
            t: 0.3,
            ddim_steps: 10,
            seed: 0,
            anchor_radius: 0,
            smooth_radius: 0,
            triplets: vec!["t000".into()],
            psnr_render: 25.0,
            psnr_enhanced: 26.0,
            lpips_render: Some(0.20),
            lpips_enhanced: Some(0.25),
            seconds: 1.0,
        };
        // LPIPS rules where measured, even against a better PSNR; an equal LPIPS fails.
        assert!(!c.helps());
        let better = EnhancerCheck {
            lpips_enhanced: Some(0.15),
            psnr_enhanced: 20.0,
            ..c.clone()
        };
        assert!(better.helps());
        assert!(!EnhancerCheck {
            lpips_enhanced: Some(0.20),
            ..c.clone()
        }
        .helps());
        let psnr_only = EnhancerCheck {
            lpips_render: None,
            lpips_enhanced: None,
            ..c.clone()
        };
        assert!(psnr_only.helps());
        assert!(!EnhancerCheck {
            psnr_enhanced: 25.0,
            ..psnr_only.clone()
        }
        .helps());
        assert!(c.describe().contains("LPIPS-alex 0.200 -> 0.250"));
        assert!(!psnr_only.describe().contains("LPIPS"));
    }

    #[test]
    fn the_check_takes_one_triplet_per_view_with_the_sources_in_turn() {
        let entry = |k: usize, slot: usize, source: &str| TripletEntry {
            key: format!("t{k:03}"),
            slot,
            source: source.into(),
        };
        // Three views: view 0 with two triplets, view 1 with none, view 2 with three.
        let entries = vec![
            entry(0, 0, "base"),
            entry(1, 2, "base"),
            entry(2, 0, "inpainted@0"),
            entry(3, 2, "inpainted@0"),
            entry(4, 2, "inpainted@1"),
        ];
        let tr = Triplets {
            width: 1,
            height: 1,
            photos: vec![vec![0.0; 3]; 3],
            masks: vec![vec![0.0]; 3],
            renders: vec![(vec![0.0; 3], vec![0.0]); entries.len()],
            entries,
        };
        // View 0: its 0th (t000); view 1: none; view 2: its 2 mod 3 = 2nd (t004).
        assert_eq!(check_triplets(&tr), [0, 4]);
    }

    /// An `[h, w, 3]` image from a per-pixel function of (x, y), the same in every channel.
    fn image(w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> Vec<f32> {
        (0..w * h).flat_map(|i| [f(i % w, i / w); 3]).collect()
    }

    #[test]
    fn detail_energy_is_the_mean_squared_laplacian() {
        assert_eq!(detail_energy(&image(6, 5, |_, _| 0.3), 6, 5), 0.0);
        // A linear ramp has no Laplacian.
        let ramp = image(7, 6, |x, y| 0.1 * x as f32 + 0.05 * y as f32);
        assert!(detail_energy(&ramp, 7, 6) < 1e-12);
        // A checkerboard of +-a around 0.5: every interior Laplacian is +-8a.
        let a = 0.1f32;
        let board = image(
            8,
            7,
            |x, y| if (x + y) % 2 == 0 { 0.5 + a } else { 0.5 - a },
        );
        let want = 64.0 * f64::from(a) * f64::from(a);
        assert!((detail_energy(&board, 8, 7) - want).abs() < 1e-6 * want);
        // Too small for an interior: 0, not a division by zero.
        assert_eq!(detail_energy(&image(2, 9, |x, _| x as f32), 2, 9), 0.0);
    }

    #[test]
    fn smoothing_keeps_the_enhancements_colour_change_and_drops_its_pixel_noise() {
        let (w, h) = (40, 30);
        // The render: a smooth shading with a sharp edge (detail the targets must keep).
        let render = image(w, h, |x, y| {
            0.3 + 0.004 * x as f32 + 0.003 * y as f32 + if x >= 20 { 0.2 } else { 0.0 }
        });
        // The enhancer: the render brightened by 0.05, plus a +-0.05 checkerboard of noise.
        let noise = |x: usize, y: usize| {
            if (x + y).is_multiple_of(2) {
                0.05
            } else {
                -0.05
            }
        };
        let enhanced: Vec<f32> = render
            .iter()
            .enumerate()
            .map(|(i, &r)| r + 0.05 + noise((i / 3) % w, (i / 3) / w))
            .collect();
        assert_eq!(stage3_target(&render, &enhanced, w, h, 0, 0), enhanced);
        let t = stage3_target(&render, &enhanced, w, h, 0, 2);
        // Away from the borders (where the box blur's window is cut) the target is the render
        // plus the change of colour: the noise is gone, the edge is kept.
        for y in 5..h - 5 {
            for x in 5..w - 5 {
                let i = (y * w + x) * 3;
                let d = t[i] - render[i] - 0.05;
                assert!(d.abs() < 2e-3, "({x}, {y}): {d}");
            }
        }
        assert!(detail_energy(&t, w, h) < 1.2 * detail_energy(&render, w, h));
        assert!(detail_energy(&enhanced, w, h) > 10.0 * detail_energy(&render, w, h));
        // Colour anchoring alone does the opposite: it keeps the noise and drops the colour
        // change; the two together keep neither.
        let a = stage3_target(&render, &enhanced, w, h, 2, 0);
        let both = stage3_target(&render, &enhanced, w, h, 2, 2);
        let i = (15 * w + 10) * 3;
        assert!((a[i] - render[i] - noise(10, 15)).abs() < 2e-3);
        assert!((both[i] - render[i]).abs() < 2e-3);
    }

    #[test]
    fn seen_pixels_of_a_virtual_view_carry_the_visible_weight() {
        let mask = [0.0, 0.49, 0.5, 1.0];
        assert_eq!(virtual_weights(&mask, 0.9, 1.0), [0.9; 4]);
        assert_eq!(virtual_weights(&mask, 0.9, 0.0), [0.0, 0.0, 0.9, 0.9]);
        assert_eq!(virtual_weights(&mask, 0.8, 0.5), [0.4, 0.4, 0.8, 0.8]);
    }
}
