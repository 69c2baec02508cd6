//! burn on the engine's Vulkan device (issue 5): the engine creates the device, burn's wgpu
//! runtime adopts it, engine kernels read and write burn's tensors in place, and the diffusion
//! models run there and match burn's CPU backend and diffusers.
//!
//! One context shared by this module's tests (its own, shared with wgpu; the other modules use
//! `extranerf_tests::engine`) and fixed shapes: the test process pays burn's shader compilation
//! once per shape set. The tests take a lock: burn and the engine submit to the same queue and
//! must take turns.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::sync::{Mutex, MutexGuard, OnceLock};

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};
use extranerf_diffusion::device::{burn_device, TensorBuffer};
use extranerf_diffusion::inpaint::{seeded_noise, Codec, InpaintModel, SampleSettings, SplitMix};
use extranerf_diffusion::lora::{self, LoraConfig};
use extranerf_diffusion::scheduler::{Schedule, SchedulerConfig};
use extranerf_diffusion::text::LearnedTokens;
use extranerf_diffusion::train::{self, Augment, TrainImage, Trainable};
use extranerf_diffusion::weights;
use extranerf_gpu::{Buffer, Context, ContextDesc};
use extranerf_prims::{Prims, ReducePlan};
use extranerf_tests::{
    assert_no_validation_messages, burn_values, desc, diffusers_fixtures, diffusers_golden,
    golden_tensor, max_rel_err,
};

struct Shared {
    ctx: Context,
    dev: Device,
    prims: Prims,
}

fn shared() -> (&'static Shared, MutexGuard<'static, ()>) {
    static SHARED: OnceLock<Shared> = OnceLock::new();
    static TURN: Mutex<()> = Mutex::new(());
    let guard = TURN.lock().unwrap_or_else(|p| p.into_inner());
    let s = SHARED.get_or_init(|| {
        let ctx = Context::new(&ContextDesc {
            share_with_wgpu: true,
            ..desc()
        })
        .unwrap();
        let dev = burn_device(&ctx).unwrap();
        let prims = Prims::new(&ctx).unwrap();
        Shared { ctx, dev, prims }
    });
    (s, guard)
}

#[test]
fn burn_runs_on_the_engine_device_and_shares_tensors_in_place() {
    let (s, _turn) = shared();
    let (ctx, dev) = (&s.ctx, &s.dev);
    let h = ctx.wgpu().expect("shared context has wgpu handles");
    // One VkDevice: wgpu's raw device is the engine's.
    assert_eq!(h.raw_device(), Some(ctx.raw_device()));
    let n = 1024usize;
    let a: Vec<f32> = (0..n).map(|i| i as f32 * 0.25 - 7.0).collect();
    let ta = Tensor::<1>::from_floats(a.as_slice(), dev);
    let tb = ta * 3.0 + 1.0;
    dev.sync().unwrap();
    // The engine reads burn's result in place: y = 2 b + y.
    let y = Buffer::from_slice(ctx, "y", &vec![1.0f32; n]).unwrap();
    let view = TensorBuffer::new(ctx, &tb).unwrap();
    let mut rec = ctx.recorder("read burn tensor").unwrap();
    s.prims
        .saxpy(&mut rec, 2.0, view.binding(), y.binding(), n as u64)
        .unwrap();
    ctx.run(rec).unwrap();
    let got = y.read().unwrap();
    for (i, (&g, &x)) in got.iter().zip(&a).enumerate() {
        let want = 2.0 * (3.0 * x + 1.0) + 1.0;
        assert!(
            (g - want).abs() <= 1e-5 * want.abs().max(1.0),
            "{i}: {g} vs {want}"
        );
    }
    // The engine writes burn's tensor in place; burn reads what the engine wrote.
    let mut rec = ctx.recorder("write burn tensor").unwrap();
    s.prims
        .fill(&mut rec, view.binding(), n as u64, 5.5f32.to_bits())
        .unwrap();
    ctx.run(rec).unwrap();
    drop(view);
    let back: Vec<f32> = (tb * 2.0).into_data().try_to_vec::<f32>().unwrap();
    assert!(back.iter().all(|&v| v == 11.0), "{:?}", &back[..4]);
    assert_no_validation_messages(ctx);
}

#[test]
fn diffusers_models_on_the_engine_device_match_diffusers_and_the_cpu_backend() {
    let (s, _turn) = shared();
    let g = diffusers_golden();
    let cpu = Device::flex();
    for (dev, label) in [(&s.dev, "device"), (&cpu, "cpu")] {
        let sample: Tensor<4> = golden_tensor(&g, "unet.sample", dev);
        let context: Tensor<3> = golden_tensor(&g, "unet.context", dev);
        let ts = g.tensors["unet.timesteps"].data.clone();
        for sub in ["unet_conv", "unet_linear"] {
            let (_, unet) = weights::load_unet(&diffusers_fixtures().join(sub), dev).unwrap();
            let out = burn_values(unet.forward(sample.clone(), &ts, &context));
            let err = max_rel_err(&out, &g.tensors[&format!("{sub}.out")].data);
            eprintln!("{label} {sub}: max error {err:.2e} against diffusers");
            assert!(err < 1e-4, "{label} {sub}: {err}");
        }
        let (_, vae) = weights::load_vae(&diffusers_fixtures().join("vae"), dev).unwrap();
        let image: Tensor<4> = golden_tensor(&g, "vae.image", dev);
        let (mean, _) = vae.encode_moments(image);
        let err = max_rel_err(&burn_values(mean.clone()), &g.tensors["vae.mean"].data);
        assert!(err < 1e-4, "{label} vae encode: {err}");
        let dec = burn_values(vae.decode(mean * vae.scaling_factor));
        let err = max_rel_err(&dec, &g.tensors["vae.decoded"].data);
        eprintln!("{label} vae: decode max error {err:.2e}");
        assert!(err < 1e-4, "{label} vae decode: {err}");
    }
    assert_no_validation_messages(&s.ctx);
}

/// The fixture latent inpainting model (U-Net + VAE from diffusers) with fixed tokens.
fn fixture_model(dev: &Device) -> InpaintModel {
    let (_, unet) = weights::load_unet(&diffusers_fixtures().join("unet_conv"), dev).unwrap();
    let (_, vae) = weights::load_vae(&diffusers_fixtures().join("vae"), dev).unwrap();
    let mut rng = SplitMix(4);
    let toks: Vec<f32> = (0..36).map(|_| (rng.unit() * 2.0 - 1.0) as f32).collect();
    InpaintModel {
        unet,
        codec: Codec::Vae(vae),
        tokens: LearnedTokens {
            tokens: Param::from_tensor(
                Tensor::<1>::from_floats(toks.as_slice(), dev).reshape([3, 12]),
            ),
            null_tokens: None,
        },
        schedule: Schedule::new(&SchedulerConfig::default()).unwrap(),
        task: extranerf_diffusion::inpaint::Task::Inpaint,
    }
}

fn image_and_mask(dev: &Device) -> (Tensor<4>, Tensor<4>) {
    let (h, w) = (12usize, 16usize);
    let img: Vec<f32> = (0..3 * h * w)
        .map(|i| ((i * 37) % 101) as f32 / 100.0)
        .collect();
    let mut mask = vec![0f32; h * w];
    for y in 3..9 {
        for x in 4..12 {
            mask[y * w + x] = 1.0;
        }
    }
    (
        Tensor::<1>::from_floats(img.as_slice(), dev).reshape([1, 3, h, w]),
        Tensor::<1>::from_floats(mask.as_slice(), dev).reshape([1, 1, h, w]),
    )
}

#[test]
fn inpainting_runs_on_the_device_and_engine_kernels_read_the_result_in_place() {
    let (s, _turn) = shared();
    let cpu = Device::flex();
    let settings = SampleSettings {
        strength: 0.7,
        steps: 3,
        guidance: 2.0,
        keep_known: true,
    };
    let mut results = Vec::new();
    for dev in [&s.dev, &cpu] {
        let m = fixture_model(dev);
        let (img, mask) = image_and_mask(dev);
        let noise = seeded_noise([1, 4, 6, 8], 21, dev);
        let out = m.inpaint(img, mask, noise, &settings).unwrap();
        assert_eq!(out.t_start, m.schedule.timestep_for_strength(0.7));
        results.push(out.image);
    }
    let cpu_v = burn_values(results[1].clone());
    let err = max_rel_err(&burn_values(results[0].clone()), &cpu_v);
    eprintln!("inpainting, device against cpu: max error {err:.2e}");
    assert!(err < 1e-3, "{err}");
    // The engine reduces the device result where it lies: no bytes cross the host.
    let dev_img = results.remove(0);
    s.dev.sync().unwrap();
    let view = TensorBuffer::new(&s.ctx, &dev_img).unwrap();
    let out = Buffer::from_slice(&s.ctx, "sum", &[0f32]).unwrap();
    let plan = ReducePlan::new(&s.ctx).unwrap();
    let mut rec = s.ctx.recorder("sum inpainted").unwrap();
    s.prims
        .reduce_sum(
            &mut rec,
            &plan,
            view.binding(),
            cpu_v.len() as u64,
            out.binding(),
        )
        .unwrap();
    s.ctx.run(rec).unwrap();
    let sum = out.read().unwrap()[0] as f64;
    let want: f64 = cpu_v.iter().map(|v| *v as f64).sum();
    assert!((sum - want).abs() < 1e-3 * want.abs(), "{sum} vs {want}");
    drop(view);
    assert_no_validation_messages(&s.ctx);
}

#[test]
fn lora_fine_tuning_steps_on_the_device_train_only_the_adapters() {
    let (s, _turn) = shared();
    let cpu = Device::flex().autodiff();
    let images = vec![TrainImage::new(
        16,
        16,
        (0..768).map(|i| ((i * 13) % 29) as f32 / 28.0).collect(),
    )];
    let aug = Augment {
        crop: 16,
        ..Augment::default()
    };
    let sched = Schedule::new(&SchedulerConfig::default()).unwrap();
    let mut losses = Vec::new();
    for dev in [s.dev.clone().autodiff(), cpu] {
        let base = fixture_model(&dev);
        let unet = lora::apply(base.unet, &LoraConfig::attention(2, 2.0), &dev).unwrap();
        let model = Trainable {
            unet,
            tokens: base.tokens.no_grad(),
        };
        let codec = base.codec.no_grad();
        let mut rng = SplitMix(8);
        let batch = train::draw_batch(&images, &aug, 2, &mut rng).unwrap();
        let loss = train::batch_loss(&model, &codec, &sched, &batch, 0.0, &mut rng, &dev);
        let grads = loss.backward();
        for (path, is_lora, has) in lora::gradients_reached(&model, &grads) {
            assert_eq!(is_lora, has, "{path}");
        }
        // Fresh adapters (B = 0) leave the base loss; both backends see the same batch.
        losses.push(loss.into_scalar::<f32>());
    }
    eprintln!("LoRA loss device {} cpu {}", losses[0], losses[1]);
    assert!(
        (losses[0] - losses[1]).abs() <= 1e-4 * losses[1].abs().max(1e-3),
        "{losses:?}"
    );
    assert_no_validation_messages(&s.ctx);
}
