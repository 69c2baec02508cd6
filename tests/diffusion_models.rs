//! The diffusion models on burn's CPU backend (issue 5): diffusers compatibility (configs,
//! parameter names, counts, outputs against diffusers' own, save/load), LoRA, schedulers,
//! sampling, training and the simple fills. The Vulkan-device runs live in diffusion.rs.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::tensor::{Device, Tensor};
use extranerf_diffusion::blocks::{timestep_embedding, Attention};
use extranerf_diffusion::clip::{load_text_encoder, ClipTokenizer};
use extranerf_diffusion::config::{UNetConfig, VaeConfig};
use extranerf_diffusion::fill;
use extranerf_diffusion::inpaint::{seeded_noise, Codec, InpaintModel, PixelCodec, SampleSettings};
use extranerf_diffusion::layers::{Conv2d, Linear};
use extranerf_diffusion::lora::{self, LoraConfig};
use extranerf_diffusion::pipeline::Pipeline;
use extranerf_diffusion::scheduler::{
    ddim_timesteps, BetaSchedule, Prediction, Schedule, SchedulerConfig,
};
use extranerf_diffusion::text::LearnedTokens;
use extranerf_diffusion::train::{self, Augment, TrainImage, TrainSettings, Trainable};
use extranerf_diffusion::unet::UNet2DConditionModel;
use extranerf_diffusion::vae::AutoencoderKL;
use extranerf_diffusion::weights;
use extranerf_nerf::safetensors::SafeTensors;
use extranerf_tests::{
    burn_values, diffusers_fixtures, diffusers_golden, golden_tensor, max_rel_err, scratch_dir,
    tiny_pixel_unet_config,
};

fn fixtures() -> PathBuf {
    diffusers_fixtures()
}

fn cpu() -> Device {
    Device::flex()
}

fn golden() -> SafeTensors {
    diffusers_golden()
}

fn tensor<const D: usize>(st: &SafeTensors, name: &str, dev: &Device) -> Tensor<D> {
    golden_tensor(st, name, dev)
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    burn_values(t)
}

fn rel_err(a: &[f32], b: &[f32]) -> f64 {
    max_rel_err(a, b)
}

fn file_shapes(path: &Path) -> Vec<(String, Vec<usize>)> {
    let st = SafeTensors::read(path).unwrap();
    let mut v: Vec<_> = st
        .tensors
        .iter()
        .map(|(k, t)| (k.clone(), t.shape.clone()))
        .collect();
    v.sort();
    v
}

#[test]
fn parameter_counts_and_names_match_diffusers() {
    let dev = cpu();
    // Counts from diffusers 0.31 (UNet2DConditionModel / AutoencoderKL built with these
    // configs, summed over parameters); our models are lazy, so nothing is allocated here.
    let sd15 = UNet2DConditionModel::new(&UNetConfig::sd15_inpainting(), &dev).unwrap();
    assert_eq!(sd15.num_params(), 859_535_364);
    let sd2 = UNet2DConditionModel::new(&UNetConfig::sd2_inpainting(), &dev).unwrap();
    assert_eq!(sd2.num_params(), 865_925_124);
    let vae = AutoencoderKL::new(&VaeConfig::sd(), &dev).unwrap();
    assert_eq!(vae.num_params(), 83_653_863);
    assert_eq!(vae.factor(), 8);
    let names = weights::parameter_names(&sd15);
    for (name, shape) in [
        ("conv_in.weight", vec![320, 9, 3, 3]),
        ("time_embedding.linear_1.weight", vec![1280, 320]),
        (
            "down_blocks.0.attentions.0.proj_in.weight",
            vec![320, 320, 1, 1],
        ),
        (
            "down_blocks.0.attentions.0.transformer_blocks.0.attn2.to_k.weight",
            vec![320, 768],
        ),
        (
            "down_blocks.0.attentions.0.transformer_blocks.0.attn1.to_out.0.bias",
            vec![320],
        ),
        (
            "mid_block.attentions.0.transformer_blocks.0.ff.net.0.proj.weight",
            vec![10240, 1280],
        ),
        (
            "mid_block.attentions.0.transformer_blocks.0.ff.net.2.weight",
            vec![1280, 5120],
        ),
        (
            "down_blocks.2.downsamplers.0.conv.weight",
            vec![1280, 1280, 3, 3],
        ),
        (
            "up_blocks.3.resnets.2.conv_shortcut.weight",
            vec![320, 640, 1, 1],
        ),
        (
            "up_blocks.0.upsamplers.0.conv.weight",
            vec![1280, 1280, 3, 3],
        ),
        ("up_blocks.1.attentions.2.norm.weight", vec![1280]),
        ("conv_norm_out.bias", vec![320]),
        ("conv_out.weight", vec![4, 320, 3, 3]),
    ] {
        assert!(
            names.iter().any(|(n, s)| n == name && *s == shape),
            "{name} {shape:?} missing; near: {:?}",
            names
                .iter()
                .filter(|(n, _)| n.starts_with(&name[..name.len().min(12)]))
                .take(5)
                .collect::<Vec<_>>()
        );
    }
    let sd2_names = weights::parameter_names(&sd2);
    assert!(sd2_names
        .iter()
        .any(|(n, s)| n == "down_blocks.0.attentions.0.proj_in.weight" && *s == vec![320, 320]));
    let vae_names = weights::parameter_names(&vae);
    for (name, shape) in [
        ("encoder.mid_block.attentions.0.to_q.weight", vec![512, 512]),
        (
            "encoder.mid_block.attentions.0.group_norm.weight",
            vec![512],
        ),
        (
            "encoder.down_blocks.0.downsamplers.0.conv.weight",
            vec![128, 128, 3, 3],
        ),
        ("encoder.conv_out.weight", vec![8, 512, 3, 3]),
        ("quant_conv.weight", vec![8, 8, 1, 1]),
        (
            "decoder.up_blocks.3.resnets.0.conv_shortcut.weight",
            vec![128, 256, 1, 1],
        ),
    ] {
        assert!(
            vae_names.iter().any(|(n, s)| n == name && *s == shape),
            "{name} {shape:?} missing"
        );
    }
    // The tiny models have exactly the tensors diffusers saved for the same configs.
    for sub in ["unet_conv", "unet_linear", "unet_odd"] {
        let dir = fixtures().join(sub);
        let c = UNetConfig::from_file(&dir.join("config.json")).unwrap();
        let m = UNet2DConditionModel::new(&c, &dev).unwrap();
        let mut ours = weights::parameter_names(&m);
        ours.sort();
        assert_eq!(
            ours,
            file_shapes(&dir.join(weights::DIFFUSERS_WEIGHTS)),
            "{sub}"
        );
    }
    let dir = fixtures().join("vae");
    let m = AutoencoderKL::new(
        &VaeConfig::from_file(&dir.join("config.json")).unwrap(),
        &dev,
    )
    .unwrap();
    let mut ours = weights::parameter_names(&m);
    ours.sort();
    assert_eq!(ours, file_shapes(&dir.join(weights::DIFFUSERS_WEIGHTS)));
}

#[test]
fn unet_and_vae_match_diffusers_outputs() {
    let dev = cpu();
    let g = golden();
    let sample: Tensor<4> = tensor(&g, "unet.sample", &dev);
    let context: Tensor<3> = tensor(&g, "unet.context", &dev);
    let ts = g.tensors["unet.timesteps"].data.clone();
    for sub in ["unet_conv", "unet_linear", "unet_odd"] {
        let (_, unet) = weights::load_unet(&fixtures().join(sub), &dev).unwrap();
        let out = values(unet.forward(sample.clone(), &ts, &context));
        let err = rel_err(&out, &g.tensors[&format!("{sub}.out")].data);
        eprintln!("{sub}: max error {err:.2e} of the largest output");
        assert!(err < 1e-4, "{sub}: {err}");
    }
    let (_, vae) = weights::load_vae(&fixtures().join("vae"), &dev).unwrap();
    let image: Tensor<4> = tensor(&g, "vae.image", &dev);
    let (mean, logvar) = vae.encode_moments(image);
    let mean_v = values(mean.clone());
    assert!(rel_err(&mean_v, &g.tensors["vae.mean"].data) < 1e-4);
    assert!(rel_err(&values(logvar), &g.tensors["vae.logvar"].data) < 1e-4);
    let decoded = values(vae.decode(mean * vae.scaling_factor));
    let err = rel_err(&decoded, &g.tensors["vae.decoded"].data);
    eprintln!("vae: decode max error {err:.2e}");
    assert!(err < 1e-4, "{err}");
    // The same VAE saved as an older checkpoint (fp16, deprecated attention names) loads to
    // the same network within fp16 rounding.
    let (_, old) = weights::load_vae(&fixtures().join("vae_old_fp16"), &dev).unwrap();
    let image: Tensor<4> = tensor(&g, "vae.image", &dev);
    let err = rel_err(&values(old.encode_moments(image).0), &mean_v);
    eprintln!("vae fp16 with deprecated names: max error {err:.2e}");
    assert!(err < 2e-2, "{err}");
}

#[test]
fn saved_models_reload_to_identical_outputs() {
    let dev = cpu();
    let g = golden();
    let sample: Tensor<4> = tensor(&g, "unet.sample", &dev);
    let context: Tensor<3> = tensor(&g, "unet.context", &dev);
    let ts = g.tensors["unet.timesteps"].data.clone();
    let dir = scratch_dir("diffusion-save");
    // A freshly initialised model (its random weights) saved and loaded back.
    let c = UNetConfig::from_file(&fixtures().join("unet_linear/config.json")).unwrap();
    let fresh = UNet2DConditionModel::new(&c, &dev).unwrap();
    let before = values(fresh.forward(sample.clone(), &ts, &context));
    weights::save_unet(&dir.join("unet"), &c, &fresh).unwrap();
    let (c2, back) = weights::load_unet(&dir.join("unet"), &dev).unwrap();
    assert_eq!(c2, c);
    let after = values(back.forward(sample, &ts, &context));
    assert_eq!(before, after, "reloaded U-Net differs");
    // The saved file has diffusers' names and layouts: the same keys and shapes as the file
    // diffusers wrote for this config.
    assert_eq!(
        file_shapes(&dir.join("unet").join(weights::DIFFUSERS_WEIGHTS)),
        file_shapes(
            &fixtures()
                .join("unet_linear")
                .join(weights::DIFFUSERS_WEIGHTS)
        )
    );
    let vc = VaeConfig::tiny();
    let vae = AutoencoderKL::new(&vc, &dev).unwrap();
    let img = Tensor::<4>::ones([1, 3, 16, 16], &dev) * 0.3;
    let z1 = values(vae.encode(img.clone(), false));
    weights::save_vae(&dir.join("vae"), &vc, &vae).unwrap();
    let (_, vae2) = weights::load_vae(&dir.join("vae"), &dev).unwrap();
    assert_eq!(z1, values(vae2.encode(img, false)));
}

fn copy_fixture(name: &str, sub: &str) -> PathBuf {
    let dir = scratch_dir(name);
    let src = fixtures().join(sub);
    for f in ["config.json", weights::DIFFUSERS_WEIGHTS] {
        std::fs::copy(src.join(f), dir.join(f)).unwrap();
    }
    dir
}

fn load_err(dir: &Path) -> String {
    match weights::load_unet(dir, &cpu()) {
        Ok(_) => panic!("loading {} should fail", dir.display()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn malformed_configs_and_weights_are_clear_errors() {
    let wfile = weights::DIFFUSERS_WEIGHTS;
    // Truncated weights.
    let dir = copy_fixture("diff-trunc", "unet_conv");
    let bytes = std::fs::read(dir.join(wfile)).unwrap();
    std::fs::write(dir.join(wfile), &bytes[..bytes.len() / 2]).unwrap();
    let e = load_err(&dir);
    assert!(e.contains(wfile) && e.contains("truncated"), "{e}");
    // Garbage.
    std::fs::write(dir.join(wfile), b"not a safetensors file at all").unwrap();
    let e = load_err(&dir);
    assert!(e.contains(wfile), "{e}");
    // A missing tensor, a mis-shaped tensor, an extra tensor.
    let src = fixtures().join("unet_conv").join(wfile);
    let edit = |name: &str, f: &dyn Fn(&mut SafeTensors)| -> String {
        let dir = copy_fixture(name, "unet_conv");
        let mut st = SafeTensors::read(&src).unwrap();
        f(&mut st);
        st.write(&dir.join(wfile)).unwrap();
        load_err(&dir)
    };
    let e = edit("diff-missing", &|st| {
        st.tensors.remove("conv_out.weight");
    });
    assert!(e.contains(wfile) && e.contains("conv_out.weight"), "{e}");
    let e = edit("diff-shape", &|st| {
        let t = st.tensors.get_mut("conv_in.bias").unwrap();
        t.shape = vec![4, 2];
    });
    assert!(e.contains(wfile) && e.contains("conv_in.bias"), "{e}");
    let e = edit("diff-extra", &|st| {
        let t = st.tensors["conv_in.bias"].clone();
        st.tensors.insert("extra_head.bias".into(), t);
    });
    assert!(
        e.contains("extra_head.bias") && e.contains("not part of this model"),
        "{e}"
    );
    // Only pickle weights.
    let dir = copy_fixture("diff-bin", "unet_conv");
    std::fs::rename(dir.join(wfile), dir.join("diffusion_pytorch_model.bin")).unwrap();
    let e = load_err(&dir);
    assert!(
        e.contains("diffusion_pytorch_model.bin") && e.contains("safetensors"),
        "{e}"
    );
    // Configs: unsupported values and unknown keys name the key and the file.
    let dir = copy_fixture("diff-config", "unet_conv");
    let cfg = dir.join("config.json");
    let text = std::fs::read_to_string(&cfg).unwrap();
    for (from, to, want) in [
        (
            "\"dual_cross_attention\": false",
            "\"dual_cross_attention\": true",
            "dual_cross_attention",
        ),
        ("\"act_fn\": \"silu\"", "\"act_fn\": \"gelu\"", "act_fn"),
        (
            "\"dropout\": 0.0",
            "\"dropout\": 0.0, \"fancy_new_key\": 1",
            "fancy_new_key",
        ),
        (
            "\"norm_num_groups\": 4",
            "\"norm_num_groups\": 3",
            "norm_num_groups",
        ),
        (
            "\"in_channels\": 9",
            "\"in_channels\": \"nine\"",
            "\"nine\"",
        ),
        (
            "\"UpBlock2D\",\n    \"CrossAttnUpBlock2D\"",
            "\"CrossAttnUpBlock2D\",\n    \"UpBlock2D\"",
            "mirror",
        ),
    ] {
        assert!(text.contains(from), "fixture lacks {from}");
        std::fs::write(&cfg, text.replace(from, to)).unwrap();
        let e = load_err(&dir);
        assert!(e.contains("config.json") && e.contains(want), "{want}: {e}");
    }
    std::fs::remove_file(&cfg).unwrap();
    let e = load_err(&dir);
    assert!(e.contains("config.json"), "{e}");
    // A VAE config with an unsupported value.
    let vdir = scratch_dir("diff-vae-config");
    let vtext = std::fs::read_to_string(fixtures().join("vae/config.json")).unwrap();
    std::fs::write(
        vdir.join("config.json"),
        vtext.replace("\"use_quant_conv\": true", "\"use_quant_conv\": false"),
    )
    .unwrap();
    let e = VaeConfig::from_file(&vdir.join("config.json"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("use_quant_conv"), "{e}");
}

fn f64_linear(x: &[f32], w: &[f32], b: Option<&[f32]>, d_in: usize, d_out: usize) -> Vec<f64> {
    // w is burn-layout [in, out].
    let rows = x.len() / d_in;
    let mut y = vec![0f64; rows * d_out];
    for r in 0..rows {
        for o in 0..d_out {
            let mut s = b.map_or(0.0, |b| b[o] as f64);
            for i in 0..d_in {
                s += x[r * d_in + i] as f64 * w[i * d_out + o] as f64;
            }
            y[r * d_out + o] = s;
        }
    }
    y
}

fn close(a: &[f32], b: &[f64], tol: f64, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}");
    let scale = b.iter().fold(0f64, |m, v| m.max(v.abs())).max(1e-9);
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!(
            (*x as f64 - y).abs() <= tol * scale,
            "{what}[{i}]: {x} vs {y}"
        );
    }
}

fn rand_vec(n: usize, seed: u64) -> Vec<f32> {
    let mut r = extranerf_diffusion::inpaint::SplitMix(seed);
    (0..n).map(|_| (r.unit() * 2.0 - 1.0) as f32).collect()
}

fn set_param<const D: usize>(p: &mut burn::module::Param<Tensor<D>>, v: &[f32], dev: &Device) {
    let shape: [usize; D] = p.lazy_shape().to_vec().try_into().unwrap();
    *p = burn::module::Param::from_tensor(Tensor::<1>::from_floats(v, dev).reshape(shape));
}

#[test]
fn layers_with_lora_match_an_f64_reference() {
    let dev = cpu();
    // Linear with LoRA: y = x W + b + s (x A^T) B^T.
    let (di, dout, r, rows) = (5, 3, 2, 4);
    let mut lin = Linear::new(di, dout, true, &dev);
    lin.add_lora(r, 3.0, &dev);
    let (w, b, a, bb) = (
        rand_vec(di * dout, 1),
        rand_vec(dout, 2),
        rand_vec(r * di, 3),
        rand_vec(dout * r, 4),
    );
    set_param(&mut lin.weight, &w, &dev);
    set_param(lin.bias.as_mut().unwrap(), &b, &dev);
    set_param(lin.lora_a.as_mut().unwrap(), &a, &dev);
    set_param(lin.lora_b.as_mut().unwrap(), &bb, &dev);
    let x = rand_vec(rows * di, 5);
    let got = values(lin.forward(Tensor::<1>::from_floats(x.as_slice(), &dev).reshape([rows, di])));
    let mut want = f64_linear(&x, &w, Some(&b), di, dout);
    for row in 0..rows {
        for o in 0..dout {
            let mut s = 0f64;
            for k in 0..r {
                let xa: f64 = (0..di)
                    .map(|i| x[row * di + i] as f64 * a[k * di + i] as f64)
                    .sum();
                s += xa * bb[o * r + k] as f64;
            }
            want[row * dout + o] += 1.5 * s;
        }
    }
    close(&got, &want, 1e-5, "linear+lora");

    // Conv2d 3x3, stride 2, asymmetric (0, 0, 1, 1) padding, with a LoRA pair.
    let (ci, co, h, w_) = (2, 3, 5, 6);
    let mut conv = Conv2d::new(ci, co, 3, 2, 0, &dev).with_padding([0, 0, 1, 1]);
    conv.add_lora(1, 2.0, &dev);
    let (cw, cb, ca, cbb) = (
        rand_vec(co * ci * 9, 6),
        rand_vec(co, 7),
        rand_vec(ci * 9, 8),
        rand_vec(co, 9),
    );
    set_param(&mut conv.weight, &cw, &dev);
    set_param(conv.bias.as_mut().unwrap(), &cb, &dev);
    set_param(conv.lora_a.as_mut().unwrap(), &ca, &dev);
    set_param(conv.lora_b.as_mut().unwrap(), &cbb, &dev);
    let x = rand_vec(ci * h * w_, 10);
    let got =
        values(conv.forward(Tensor::<1>::from_floats(x.as_slice(), &dev).reshape([1, ci, h, w_])));
    let (oh, ow) = conv.out_size(h, w_);
    // diffusers pads (0, 1, 0, 1) then convolves with stride 2: 5 -> 2, 6 -> 3.
    assert_eq!((oh, ow), (2, 3));
    let px = |c: usize, y: isize, xx: isize| -> f64 {
        if y < 0 || xx < 0 || y >= h as isize || xx >= w_ as isize {
            0.0
        } else {
            x[c * h * w_ + y as usize * w_ + xx as usize] as f64
        }
    };
    let mut want = vec![0f64; co * oh * ow];
    for o in 0..co {
        for y in 0..oh {
            for xx in 0..ow {
                let mut base = cb[o] as f64;
                let mut down = 0f64;
                for c in 0..ci {
                    for ky in 0..3 {
                        for kx in 0..3 {
                            let v = px(c, (2 * y + ky) as isize, (2 * xx + kx) as isize);
                            base += v * cw[((o * ci + c) * 3 + ky) * 3 + kx] as f64;
                            down += v * ca[(c * 3 + ky) * 3 + kx] as f64;
                        }
                    }
                }
                want[(o * oh + y) * ow + xx] = base + 2.0 * down * cbb[o] as f64;
            }
        }
    }
    close(&got, &want, 1e-5, "conv+lora");

    // Multi-head cross-attention against a naive f64 softmax attention.
    let (qd, cd, heads, dh, l, s) = (4, 3, 2, 2, 3, 5);
    let mut att = Attention::new(qd, Some(cd), heads, dh, &dev);
    let wq = rand_vec(qd * 4, 11);
    let wk = rand_vec(cd * 4, 12);
    let wv = rand_vec(cd * 4, 13);
    let wo = rand_vec(4 * qd, 14);
    let bo = rand_vec(qd, 15);
    set_param(&mut att.to_q.weight, &wq, &dev);
    set_param(&mut att.to_k.weight, &wk, &dev);
    set_param(&mut att.to_v.weight, &wv, &dev);
    set_param(&mut att.to_out[0].weight, &wo, &dev);
    set_param(att.to_out[0].bias.as_mut().unwrap(), &bo, &dev);
    let x = rand_vec(l * qd, 16);
    let ctx = rand_vec(s * cd, 17);
    let got = values(att.forward(
        Tensor::<1>::from_floats(x.as_slice(), &dev).reshape([1, l, qd]),
        Some(&Tensor::<1>::from_floats(ctx.as_slice(), &dev).reshape([1, s, cd])),
    ));
    let q = f64_linear(&x, &wq, None, qd, 4);
    let k = f64_linear(&ctx, &wk, None, cd, 4);
    let v = f64_linear(&ctx, &wv, None, cd, 4);
    let mut o = vec![0f64; l * 4];
    for hh in 0..heads {
        for i in 0..l {
            let scores: Vec<f64> = (0..s)
                .map(|j| {
                    (0..dh)
                        .map(|d| q[i * 4 + hh * dh + d] * k[j * 4 + hh * dh + d])
                        .sum::<f64>()
                        / (dh as f64).sqrt()
                })
                .collect();
            let m = scores.iter().cloned().fold(f64::MIN, f64::max);
            let e: Vec<f64> = scores.iter().map(|v| (v - m).exp()).collect();
            let z: f64 = e.iter().sum();
            for d in 0..dh {
                o[i * 4 + hh * dh + d] = (0..s)
                    .map(|j| e[j] / z * v[j * 4 + hh * dh + d])
                    .sum::<f64>();
            }
        }
    }
    let o32: Vec<f32> = o.iter().map(|v| *v as f32).collect();
    let want = f64_linear(&o32, &wo, Some(&bo), 4, qd);
    close(&got, &want, 1e-5, "attention");

    // The timestep embedding is diffusers' formula: [cos, sin] of t * 10000^(-i / half).
    let emb = values(timestep_embedding(&[0.0, 37.0], 6, true, 0, &dev));
    for (row, t) in [0.0f64, 37.0].iter().enumerate() {
        for i in 0..3 {
            let f = (-(10000f64.ln()) * i as f64 / 3.0).exp();
            assert!((emb[row * 6 + i] as f64 - (t * f).cos()).abs() < 1e-6);
            assert!((emb[row * 6 + 3 + i] as f64 - (t * f).sin()).abs() < 1e-5);
        }
    }
}

fn schedule(kind: BetaSchedule, pred: Prediction) -> Schedule {
    Schedule::new(&SchedulerConfig {
        beta_schedule: kind,
        prediction_type: pred,
        ..SchedulerConfig::default()
    })
    .unwrap()
}

#[test]
fn schedules_and_ddim_match_references() {
    // alphas_cumprod at t = 0, 1, 499, 998, 999 from diffusers' DDPMScheduler (f32).
    for (kind, want) in [
        (
            BetaSchedule::ScaledLinear,
            [
                0.9991499781608582,
                0.9982960224151611,
                0.27766942977905273,
                0.004716695751994848,
                0.00466009508818388,
            ],
        ),
        (
            BetaSchedule::Linear,
            [
                0.9991499781608582,
                0.9982895255088806,
                0.1618121713399887,
                0.0015981405740603805,
                0.0015789627796038985,
            ],
        ),
        (
            BetaSchedule::SquaredCosCapV2,
            [
                0.9999586939811707,
                0.9999125599861145,
                0.4938434660434723,
                2.428766265438753e-06,
                2.4287349909002387e-09,
            ],
        ),
    ] {
        let s = schedule(kind, Prediction::Epsilon);
        for (t, w) in [0usize, 1, 499, 998, 999].iter().zip(want) {
            let a = s.alpha_bar(Some(*t));
            assert!(((a - w) / w).abs() < 2e-4, "{kind:?} t={t}: {a} vs {w}");
        }
    }
    let bad = Schedule::new(&SchedulerConfig {
        beta_end: 1.5,
        beta_schedule: BetaSchedule::Linear,
        ..SchedulerConfig::default()
    });
    assert!(bad.unwrap_err().contains("betas"));
    let dev = cpu();
    let x0 = seeded_noise([2, 3, 4, 4], 1, &dev) * 0.5;
    let eps = seeded_noise([2, 3, 4, 4], 2, &dev);
    let x0v = values(x0.clone());
    for pred in [Prediction::Epsilon, Prediction::V, Prediction::Sample] {
        let s = schedule(BetaSchedule::ScaledLinear, pred);
        // The target splits back into the noise and the image.
        let t = [700usize, 700];
        let xt = s.add_noise(x0.clone(), eps.clone(), &t);
        let target = s.target(x0.clone(), eps.clone(), &t);
        let (e2, x2) = s.split(target, xt.clone(), 700);
        assert!(rel_err(&values(x2), &x0v) < 1e-4, "{pred:?}");
        assert!(
            rel_err(&values(e2), &values(eps.clone())) < 1e-4,
            "{pred:?}"
        );
        // A model that predicts the exact target: DDIM from strength 0.8 lands on x0 in 10
        // deterministic steps (each step keeps x_t on the line between x0 and the noise).
        let steps = ddim_timesteps(&s, 0.8, 10);
        assert_eq!(steps.len(), 10);
        assert_eq!(steps[0], s.timestep_for_strength(0.8));
        assert!(steps.windows(2).all(|w| w[0] > w[1]));
        let mut x = s.add_noise(x0.clone(), eps.clone(), &[steps[0]; 2]);
        for (i, &t) in steps.iter().enumerate() {
            let out = s.target(x0.clone(), eps.clone(), &[t; 2]);
            let next = steps.get(i + 1).copied();
            x = s.ddim_step(out, x, t, next);
            // Each step lands exactly on the noised image of the next timestep.
            let want = match next {
                Some(tn) => values(s.add_noise(x0.clone(), eps.clone(), &[tn; 2])),
                None => x0v.clone(),
            };
            assert!(
                rel_err(&values(x.clone()), &want) < 1e-4,
                "{pred:?} step {i}"
            );
        }
    }
    // Small strengths: distinct descending timesteps, every one once when steps exceed them.
    let s = schedule(BetaSchedule::ScaledLinear, Prediction::Epsilon);
    let few = ddim_timesteps(&s, 0.02, 50);
    assert_eq!(
        few,
        (0..=s.timestep_for_strength(0.02))
            .rev()
            .collect::<Vec<_>>()
    );
    for (strength, k) in [(0.02, 5), (0.3, 299), (1.0, 10), (0.001, 3)] {
        let t = ddim_timesteps(&s, strength, k);
        assert!(t.windows(2).all(|w| w[0] > w[1]), "{strength} {k}: {t:?}");
        assert_eq!(t[0], s.timestep_for_strength(strength));
    }
    // w(t) basis: the noise level grows with t.
    let s = schedule(BetaSchedule::ScaledLinear, Prediction::Epsilon);
    assert!(s.noise_level(0) < 0.03 && s.noise_level(999) > 0.99);
}

fn tiny_pixel_unet(dev: &Device) -> UNet2DConditionModel {
    UNet2DConditionModel::new(&tiny_pixel_unet_config(), dev).unwrap()
}

fn pixel_model(dev: &Device) -> InpaintModel {
    InpaintModel {
        unet: tiny_pixel_unet(dev),
        codec: Codec::Pixels(PixelCodec),
        tokens: LearnedTokens::new(2, 8, dev),
        schedule: schedule(BetaSchedule::ScaledLinear, Prediction::Epsilon),
        task: extranerf_diffusion::inpaint::Task::Inpaint,
    }
}

#[test]
fn seeded_sampling_is_deterministic_and_keeps_known_pixels() {
    let dev = cpu();
    dev.seed(7);
    let m = pixel_model(&dev);
    let img = seeded_noise([1, 3, 8, 8], 3, &dev).clamp(-1.0, 1.0) * 0.5 + 0.5;
    let mut mask = vec![0f32; 64];
    for y in 2..6 {
        for x in 3..7 {
            mask[y * 8 + x] = 1.0;
        }
    }
    let mask_t = Tensor::<1>::from_floats(mask.as_slice(), &dev).reshape([1, 1, 8, 8]);
    let s = SampleSettings {
        strength: 1.0,
        steps: 4,
        guidance: 2.0,
        keep_known: true,
    };
    let run = |seed: u64| {
        let out = m
            .inpaint(
                img.clone(),
                mask_t.clone(),
                seeded_noise([1, 3, 8, 8], seed, &dev),
                &s,
            )
            .unwrap();
        assert!(out.noise_level > 0.99);
        values(out.image)
    };
    let a = run(11);
    assert_eq!(a, run(11), "same seed, different samples");
    let b = run(12);
    assert_ne!(a, b, "different seeds, same samples");
    let src = values(img);
    for (i, m) in mask.iter().enumerate() {
        for c in 0..3 {
            let k = c * 64 + i;
            if *m == 0.0 {
                assert_eq!(a[k], src[k], "known pixel {i} changed");
            }
            assert!((0.0..=1.0).contains(&a[k]));
        }
    }
    // Bad settings are errors, not panics.
    let bad = SampleSettings {
        strength: 0.0,
        ..s.clone()
    };
    assert!(m
        .inpaint(
            img_of(&dev),
            mask_t.clone(),
            seeded_noise([1, 3, 8, 8], 1, &dev),
            &bad
        )
        .is_err());
    assert!(m
        .inpaint(
            Tensor::zeros([1, 3, 7, 8], &dev),
            mask_t,
            seeded_noise([1, 3, 7, 8], 1, &dev),
            &s
        )
        .is_err());
}

/// A residual enhancer (`Task::EnhanceResidual`, the `sample` prediction) whose last
/// convolution is zero, as `train_enhancer` starts it, is the identity: it returns the render
/// it is shown from any noise level and seed, and its training loss is 0 when the render is
/// already the photo. A v-predicting enhancer with the same zero output is not (it returns
/// a noisy image); a residual task with another prediction is refused.
#[test]
fn a_residual_enhancer_starts_as_the_identity() {
    use extranerf_diffusion::inpaint::Task;
    let dev = cpu();
    dev.seed(5);
    let model = |pred: Prediction, task: Task| {
        let mut unet = tiny_pixel_unet(&dev);
        unet.conv_out.zero(&dev);
        InpaintModel {
            unet,
            codec: Codec::Pixels(PixelCodec),
            tokens: LearnedTokens::new(2, 8, &dev),
            schedule: schedule(BetaSchedule::ScaledLinear, pred),
            task,
        }
    };
    // 13 x 10: not a multiple of the model's size step, so the padding is crossed too.
    let (w, h) = (13, 10);
    let rgb: Vec<f32> = rand_vec(w * h * 3, 4)
        .iter()
        .map(|v| 0.5 + 0.45 * v.clamp(-1.0, 1.0))
        .collect();
    let mask: Vec<f32> = (0..w * h).map(|i| (i % 7 == 0) as u8 as f32).collect();
    let residual = model(Prediction::Sample, Task::EnhanceResidual);
    let v = model(Prediction::V, Task::Enhance);
    let mut v_change = 0f32;
    for (seed, strength, steps) in [(1, 0.3, 10), (2, 0.3, 1), (3, 1.0, 4)] {
        let set = SampleSettings {
            strength,
            steps,
            guidance: 1.0,
            keep_known: false,
        };
        let out = residual
            .enhance_image(&rgb, Some(&mask), w, h, seed, &set, &dev)
            .unwrap();
        let err = out
            .rgb
            .iter()
            .zip(&rgb)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(
            err < 1e-5,
            "strength {strength}, {steps} steps: the identity moved a pixel by {err}"
        );
        let out = v
            .enhance_image(&rgb, Some(&mask), w, h, seed, &set, &dev)
            .unwrap();
        v_change = v_change.max(
            out.rgb
                .iter()
                .zip(&rgb)
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max),
        );
    }
    assert!(
        v_change > 0.05,
        "a zero v-prediction returned the render ({v_change})"
    );
    // The residual prediction needs the `sample` prediction.
    let bad = model(Prediction::V, Task::EnhanceResidual);
    let e = bad
        .enhance_image(&rgb, None, w, h, 0, &SampleSettings::default(), &dev)
        .unwrap_err();
    assert!(e.to_string().contains("\"sample\""), "{e}");
    // Training: with the photo as its own guide, the residual loss starts at 0; v's does not.
    let ad = dev.clone().autodiff();
    let mut im = TrainImage::new(16, 16, stripes(16, 16));
    im.guides = vec![train::Guide {
        rgb: im.rgb.clone(),
        mask: vec![0.0; 256],
    }];
    let aug = Augment {
        crop: 16,
        jitter: 0.0,
        ..Augment::default()
    };
    let mut unet = tiny_pixel_unet(&ad);
    unet.conv_out.zero(&ad);
    let trainable = Trainable {
        unet,
        tokens: LearnedTokens::new(2, 8, &ad),
    };
    let loss = |pred: Prediction, residual: bool| {
        let mut rng = extranerf_diffusion::inpaint::SplitMix(3);
        let batch = train::draw_batch(std::slice::from_ref(&im), &aug, 4, &mut rng).unwrap();
        assert!(batch.guide.is_some());
        let s = schedule(BetaSchedule::ScaledLinear, pred);
        train::batch_loss_upto(
            &trainable,
            &Codec::Pixels(PixelCodec),
            &s,
            &batch,
            0.0,
            0.6,
            residual,
            &mut rng,
            &ad,
        )
        .into_scalar::<f32>()
    };
    let (r, plain) = (
        loss(Prediction::Sample, true),
        loss(Prediction::Sample, false),
    );
    assert!(r < 1e-10, "residual loss of an exact guide: {r}");
    assert!(plain > 0.1, "x0 loss of a zero output: {plain}");
}

fn img_of(dev: &Device) -> Tensor<4> {
    Tensor::ones([1, 3, 8, 8], dev) * 0.5
}

fn stripes(w: usize, h: usize) -> Vec<f32> {
    let mut v = vec![0f32; w * h * 3];
    for y in 0..h {
        for x in 0..w {
            let on = ((x / 4) + (y / 4)) % 2 == 0;
            v[3 * (y * w + x)] = if on { 0.9 } else { 0.1 };
            v[3 * (y * w + x) + 1] = 0.5;
            v[3 * (y * w + x) + 2] = if on { 0.2 } else { 0.7 };
        }
    }
    v
}

#[test]
fn lora_trains_only_the_adapters_and_round_trips() {
    let dev = cpu().autodiff();
    dev.seed(3);
    let base = tiny_pixel_unet(&dev);
    let cfg = LoraConfig {
        target_modules: ["to_q", "to_k", "to_v", "to_out.0", "conv1"]
            .iter()
            .map(|s| s.to_string())
            .collect(),
        ..LoraConfig::attention(2, 2.0)
    };
    let x = seeded_noise([1, 7, 8, 8], 5, &dev);
    let ctx: Tensor<3> = seeded_noise([1, 2, 8, 1], 6, &dev).reshape([1, 2, 8]);
    let before = values(base.forward(x.clone(), &[500.0], &ctx));
    let dir = scratch_dir("lora");
    weights::save_unet(&dir.join("unet"), &tiny_pixel_unet_config(), &base).unwrap();
    let unet = lora::apply(base, &cfg, &dev).unwrap();
    let (lora_params, base_params) = lora::params_by_kind(&unet);
    assert!(!lora_params.is_empty() && !base_params.is_empty());
    // A fresh adapter (B = 0) changes nothing.
    let fresh = values(unet.forward(x.clone(), &[500.0], &ctx));
    assert_eq!(fresh, before);
    // Gradients reach the adapters and nothing else.
    let tokens = LearnedTokens::new(2, 8, &dev).no_grad();
    let model = Trainable { unet, tokens };
    let images = vec![TrainImage::new(16, 16, stripes(16, 16))];
    let aug = Augment {
        crop: 8,
        ..Augment::default()
    };
    let mut rng = extranerf_diffusion::inpaint::SplitMix(1);
    let batch = train::draw_batch(&images, &aug, 2, &mut rng).unwrap();
    let s = schedule(BetaSchedule::ScaledLinear, Prediction::Epsilon);
    let loss = train::batch_loss(
        &model,
        &Codec::Pixels(PixelCodec),
        &s,
        &batch,
        0.0,
        &mut rng,
        &dev,
    );
    let grads = loss.backward();
    let reached = lora::gradients_reached(&model, &grads);
    assert!(reached.len() > 20);
    for (path, is_lora, has) in &reached {
        assert_eq!(is_lora, has, "{path}: lora {is_lora}, gradient {has}");
    }
    // Training moves the output; the saved adapters reproduce it on a fresh base.
    let settings = TrainSettings {
        steps: 3,
        batch: 2,
        lr: 1e-2,
        token_lr: 0.0,
        warmup: 0,
        log_every: 1,
        ..TrainSettings::default()
    };
    let (model, curve) = train::train(
        model,
        &Codec::Pixels(PixelCodec),
        &s,
        &images,
        &aug,
        &settings,
        &dev,
        None,
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(curve.len(), 3);
    let tuned = values(model.unet.forward(x.clone(), &[500.0], &ctx));
    assert_ne!(tuned, before, "LoRA training changed nothing");
    lora::save(&dir.join("lora"), &model.unet, &cfg).unwrap();
    let keys = file_shapes(&dir.join("lora").join(lora::LORA_WEIGHTS));
    assert!(
        keys.iter().any(|(k, s)| k
            == "unet.down_blocks.0.attentions.0.transformer_blocks.0.attn1.to_q.lora_A.weight"
            && *s == vec![2, 16]),
        "{:?}",
        &keys[..4]
    );
    assert!(keys.iter().any(
        |(k, s)| k == "unet.up_blocks.1.resnets.0.conv1.lora_B.weight" && *s == vec![16, 2, 1, 1]
    ));
    let (_, fresh_base) = weights::load_unet(&dir.join("unet"), &dev).unwrap();
    let (back_cfg, reloaded) = lora::load(&dir.join("lora"), fresh_base, &dev).unwrap();
    assert_eq!(back_cfg, cfg);
    assert_eq!(values(reloaded.forward(x, &[500.0], &ctx)), tuned);
    // Adapter configs are validated.
    assert!(LoraConfig::attention(0, 1.0).validate().is_err());
    let mut bad = LoraConfig::attention(2, 1.0);
    bad.target_modules.push("time_embedding".into());
    assert!(bad.validate().unwrap_err().contains("time_embedding"));
}

#[test]
fn a_tiny_model_overfits_one_image() {
    let dev = cpu().autodiff();
    dev.seed(5);
    let model = Trainable {
        unet: tiny_pixel_unet(&dev),
        tokens: LearnedTokens::new(2, 8, &dev),
    };
    let images = vec![TrainImage::new(16, 16, stripes(16, 16))];
    let aug = Augment {
        crop: 16,
        flip: false,
        jitter: 0.0,
        ..Augment::default()
    };
    let s = schedule(BetaSchedule::ScaledLinear, Prediction::Epsilon);
    let settings = TrainSettings {
        steps: 200,
        batch: 8,
        lr: 3e-3,
        token_lr: 3e-3,
        warmup: 10,
        log_every: 20,
        seed: 9,
        clip: 1.0,
        cond_dropout: 0.1,
        max_strength: 1.0,
        residual: false,
    };
    let mut reports = 0;
    let (_, curve) = train::train(
        model,
        &Codec::Pixels(PixelCodec),
        &s,
        &images,
        &aug,
        &settings,
        &dev,
        None,
        &mut |_| reports += 1,
    )
    .unwrap();
    assert_eq!(reports, 10);
    let first = curve[0].1;
    let last = curve.last().unwrap().1;
    eprintln!(
        "overfit: loss {first:.4} -> {last:.4} ({:.1}x)",
        first / last
    );
    assert!(last < first / 3.0, "loss {first} -> {last}");
}

#[test]
fn fills_reproduce_simple_images() {
    let (w, h) = (24, 16);
    let mut mask = vec![0f32; w * h];
    for y in 4..12 {
        for x in 6..18 {
            mask[y * w + x] = 1.0;
        }
    }
    // A linear ramp is harmonic: the diffusion fill restores it.
    let ramp: Vec<f32> = (0..w * h)
        .flat_map(|i| {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            [x / w as f32, y / h as f32, 0.25 + 0.01 * (x + y)]
        })
        .collect();
    let mut holed = ramp.clone();
    for i in 0..w * h {
        if mask[i] > 0.5 {
            holed[3 * i..3 * i + 3].copy_from_slice(&[0.0; 3]);
        }
    }
    // The reflecting borders make the ramp harmonic only away from them; the hole is inside.
    let f = fill::harmonic_fill(&holed, &mask, w, h, 5000, 1e-7).unwrap();
    let err = f
        .iter()
        .zip(&ramp)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(err < 1e-3, "harmonic fill of a ramp: {err}");
    let m = fill::mean_fill(&holed, &mask, w, h).unwrap();
    for i in 0..w * h {
        if mask[i] < 0.5 {
            assert_eq!(&m[3 * i..3 * i + 3], &holed[3 * i..3 * i + 3]);
        }
    }
    // A vertical step edge through the hole: the edge-aware fill keeps it sharper.
    let step: Vec<f32> = (0..w * h)
        .flat_map(|i| {
            let v = if i % w < 12 { 0.1 } else { 0.9 };
            [v, v, v]
        })
        .collect();
    let mut holed = step.clone();
    for i in 0..w * h {
        if mask[i] > 0.5 {
            holed[3 * i..3 * i + 3].copy_from_slice(&[0.5; 3]);
        }
    }
    let mse = |a: &[f32]| -> f64 {
        a.iter()
            .zip(&step)
            .map(|(x, y)| ((x - y) as f64).powi(2))
            .sum::<f64>()
    };
    let harm = fill::harmonic_fill(&holed, &mask, w, h, 5000, 1e-7).unwrap();
    let edge = fill::edge_aware_fill(&holed, &mask, w, h, 200, 0.05).unwrap();
    assert!(
        mse(&edge) < mse(&harm) * 0.8,
        "edge-aware {} vs harmonic {}",
        mse(&edge),
        mse(&harm)
    );
    assert!(fill::mean_fill(&holed, &mask[1..], w, h).is_err());
}

#[test]
fn clip_tokenizer_and_text_encoder_match_transformers() {
    let dev = cpu();
    let g = golden();
    let tok = ClipTokenizer::load(&fixtures().join("tokenizer")).unwrap();
    let want: Vec<Vec<u32>> = g.tensors["clip.ids"]
        .data
        .chunks(12)
        .map(|r| r.iter().map(|v| *v as u32).collect())
        .collect();
    let prompts = ["a photo of sks scene", "The  fern's leaves, 2024!"];
    let ids: Vec<Vec<u32>> = prompts.iter().map(|p| tok.encode(p, 12).unwrap()).collect();
    assert_eq!(
        ids, want,
        "token ids differ from transformers' CLIPTokenizer"
    );
    for sub in ["clip_quick", "clip_gelu"] {
        let (_, clip) = load_text_encoder(&fixtures().join(sub), &dev).unwrap();
        let out = values(clip.forward(&ids, &dev).unwrap());
        let err = rel_err(&out, &g.tensors[&format!("{sub}.hidden")].data);
        eprintln!("{sub}: max error {err:.2e} against transformers");
        assert!(err < 1e-4, "{sub}: {err}");
    }
    // Bad input is an error.
    let (_, clip) = load_text_encoder(&fixtures().join("clip_quick"), &dev).unwrap();
    assert!(clip.forward(&[vec![1; 13]], &dev).is_err());
    assert!(clip.forward(&[vec![9999; 4]], &dev).is_err());
}

/// A Stable-Diffusion-style inpainting folder of the tiny fixture models (U-Net, VAE, CLIP).
fn sd_folder(name: &str) -> std::path::PathBuf {
    let dir = scratch_dir(name);
    let f = fixtures();
    for (from, to) in [
        ("unet_conv", "unet"),
        ("vae", "vae"),
        ("clip_quick", "text_encoder"),
        ("tokenizer", "tokenizer"),
    ] {
        std::fs::create_dir_all(dir.join(to)).unwrap();
        for e in std::fs::read_dir(f.join(from)).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), dir.join(to).join(e.file_name())).unwrap();
        }
    }
    SchedulerConfig::default()
        .save(&dir.join("scheduler/scheduler_config.json"))
        .unwrap();
    std::fs::write(
        dir.join("model_index.json"),
        r#"{"_class_name": "StableDiffusionInpaintPipeline", "_diffusers_version": "0.31.0"}"#,
    )
    .unwrap();
    dir
}

#[test]
fn the_diffusion_inpainter_fills_only_the_mask_at_any_size() {
    use extranerf_extrapolate::inpaint::diffusion::DiffusionInpainter;
    use extranerf_extrapolate::inpaint::{rect_mask, Inpainter, Target};
    let dir = sd_folder("sd-inpainter");
    let mut inp = DiffusionInpainter::load(&dir, None, cpu(), 2).unwrap();
    // Without adapters it is the un-fine-tuned model (the `diffusion-base` row).
    assert_eq!(
        inp.kind(),
        extranerf_extrapolate::inpaint::InpainterKind::DiffusionBase
    );
    // 13x10: not a multiple of the latent factor, so the view is padded and cropped back.
    let (w, h) = (13usize, 10usize);
    let rgb: Vec<f32> = (0..w * h * 3).map(|i| (i % 11) as f32 / 11.0).collect();
    let depth: Vec<f32> = (0..w * h)
        .map(|i| if i % w < 6 { 0.3 } else { 0.9 })
        .collect();
    let mask: Vec<f32> = rect_mask(w, h, 4..9, 3..7);
    let t = Target::new(w, h, &rgb, &depth, &mask, 0.6);
    let f = inp.inpaint(&t, &[], 3).unwrap();
    for i in 0..w * h {
        if mask[i] < 0.5 {
            assert_eq!(
                &f.rgb[3 * i..3 * i + 3],
                &rgb[3 * i..3 * i + 3],
                "pixel {i}"
            );
            assert_eq!(f.depth[i], depth[i]);
        } else {
            assert!(f.rgb[3 * i..3 * i + 3]
                .iter()
                .all(|v| (0.0..=1.0).contains(v)));
            // Depth from the far side of the hole's edge only.
            assert!(
                (f.depth[i] - 0.9).abs() < 1e-3,
                "pixel {i}: depth {}",
                f.depth[i]
            );
        }
    }
    // Repeatable with the seed; a mask over the whole view is refused.
    assert_eq!(inp.inpaint(&t, &[], 3).unwrap(), f);
    let full = vec![1.0f32; w * h];
    let e = inp
        .inpaint(&Target { mask: &full, ..t }, &[], 3)
        .unwrap_err();
    assert!(e.0.contains("whole view"), "{e}");
}

#[test]
fn images_in_inpainted_images_out() {
    use extranerf_diffusion::inpaint::SampleSettings;
    let dev = cpu();
    let p = Pipeline::load(&sd_folder("sd-images"), &dev, "").unwrap();
    let (w, h) = (13usize, 10usize);
    let a: Vec<f32> = (0..w * h * 3).map(|i| (i % 7) as f32 / 7.0).collect();
    let b: Vec<f32> = (0..w * h * 3).map(|i| (i % 5) as f32 / 5.0).collect();
    let hole = extranerf_extrapolate::inpaint::rect_mask(w, h, 2..7, 1..5);
    let none = vec![0f32; w * h];
    let s = SampleSettings {
        strength: 0.7,
        steps: 2,
        guidance: 1.0,
        keep_known: true,
    };
    let out = p
        .model
        .inpaint_images(&[(&a[..], &hole[..]), (&b, &none)], w, h, 5, &s, &dev)
        .unwrap();
    assert_eq!(out.len(), 2);
    // Known pixels come back as given; filled ones are colours in [0, 1]; with nothing to fill
    // the image comes back unchanged.
    for i in 0..w * h {
        let px = &out[0].rgb[3 * i..3 * i + 3];
        if hole[i] > 0.5 {
            assert!(
                px.iter().all(|v| (0.0..=1.0).contains(v)),
                "pixel {i}: {px:?}"
            );
        } else {
            assert_eq!(px, &a[3 * i..3 * i + 3], "pixel {i}");
        }
    }
    assert_eq!(out[1].rgb, b);
    assert!(out[0].noise_level > 0.0 && out[0].noise_level <= 1.0);
    // One image alone is the batch of one, repeatable with the seed.
    let one = p.model.inpaint_image(&a, &hole, w, h, 5, &s, &dev).unwrap();
    assert_eq!(
        one,
        p.model.inpaint_image(&a, &hole, w, h, 5, &s, &dev).unwrap()
    );
    // Sizes that do not match the stated image are refused, naming what was expected.
    let e = p
        .model
        .inpaint_images(&[(&a[..], &hole[..]), (&b[1..], &none)], w, h, 5, &s, &dev)
        .unwrap_err()
        .to_string();
    assert!(e.contains("image 1") && e.contains("390"), "{e}");
    assert!(p.model.inpaint_images(&[], w, h, 5, &s, &dev).is_err());
}

#[test]
fn stable_diffusion_style_folders_load_with_clip_conditioning() {
    let dev = cpu();
    let dir = sd_folder("sd-folder");
    let p = Pipeline::load(&dir, &dev, "a photo of sks scene").unwrap();
    assert!(p.notes.iter().any(|n| n.contains("CLIP")), "{:?}", p.notes);
    assert_eq!(p.model.tokens.dims(), [12, 12]);
    assert!(p.model.tokens.null_tokens.is_some());
    let img = Tensor::<4>::ones([1, 3, 8, 8], &dev) * 0.4;
    let mut mask = vec![0f32; 64];
    mask[27] = 1.0;
    let mask = Tensor::<1>::from_floats(mask.as_slice(), &dev).reshape([1, 1, 8, 8]);
    let out = p
        .model
        .inpaint(
            img,
            mask,
            seeded_noise([1, 4, 4, 4], 1, &dev),
            &SampleSettings {
                strength: 0.5,
                steps: 2,
                guidance: 3.0,
                keep_known: true,
            },
        )
        .unwrap();
    assert!(values(out.image).iter().all(|v| v.is_finite()));
    // This project's folder round-trips through save and load (tokens saved, configs kept).
    let own = scratch_dir("own-folder");
    p.save(&own).unwrap();
    let back = Pipeline::load(&own, &dev, "ignored").unwrap();
    assert_eq!(back.unet_config, p.unet_config);
    assert_eq!(
        values(back.model.tokens.tokens.val()),
        values(p.model.tokens.tokens.val())
    );
    // The guidance baseline (CLIP's empty prompt) survives the round trip.
    let null_of = |t: &LearnedTokens| values(t.null(1, &dev));
    assert_eq!(null_of(&back.model.tokens), null_of(&p.model.tokens));
    assert!(null_of(&back.model.tokens).iter().any(|v| *v != 0.0));
    // A pipeline of another kind is refused by name.
    std::fs::write(
        dir.join("model_index.json"),
        r#"{"_class_name": "StableDiffusionXLPipeline"}"#,
    )
    .unwrap();
    let e = Pipeline::load(&dir, &dev, "").unwrap_err().to_string();
    assert!(
        e.contains("StableDiffusionXLPipeline") && e.contains("model_index.json"),
        "{e}"
    );
}

#[test]
fn unknown_pixels_never_reach_the_model_or_the_loss() {
    let dev = cpu().autodiff();
    dev.seed(2);
    let mut im = TrainImage::new(16, 16, stripes(16, 16));
    for y in 4..9 {
        for x in 3..12 {
            im.known[y * 16 + x] = 0.0;
        }
    }
    // The same image with other content where it is unknown.
    let mut other = im.clone();
    for i in 0..256 {
        if other.known[i] == 0.0 {
            other.rgb[3 * i..3 * i + 3].copy_from_slice(&[1.0, 0.0, 1.0]);
        }
    }
    let model = Trainable {
        unet: tiny_pixel_unet(&dev),
        tokens: LearnedTokens::new(2, 8, &dev),
    };
    let aug = Augment {
        crop: 16,
        ..Augment::default()
    };
    let s = schedule(BetaSchedule::ScaledLinear, Prediction::Epsilon);
    let mut runs = Vec::new();
    for img in [&im, &other] {
        let mut rng = extranerf_diffusion::inpaint::SplitMix(3);
        let batch = train::draw_batch(std::slice::from_ref(img), &aug, 4, &mut rng).unwrap();
        // Every unknown pixel is a hole shown to the model.
        for (k, h) in batch.known.iter().zip(&batch.hole) {
            assert!(*k == 1.0 || *h == 1.0, "an unknown pixel is shown as known");
        }
        assert!(batch.known.contains(&0.0));
        let loss = train::batch_loss(
            &model,
            &Codec::Pixels(PixelCodec),
            &s,
            &batch,
            0.5,
            &mut rng,
            &dev,
        );
        runs.push((batch.image.clone(), loss.into_scalar::<f32>()));
    }
    assert_eq!(runs[0].0, runs[1].0, "unknown content reached the batch");
    assert_eq!(runs[0].1, runs[1].1, "unknown content changed the loss");
    // At latent resolution a cell is a hole when any of its pixels is.
    let vae = AutoencoderKL::new(&VaeConfig::tiny(), &cpu()).unwrap();
    let codec = Codec::Vae(vae);
    let mut m = vec![0f32; 64];
    m[9] = 1.0; // pixel (1, 1): one pixel of the 4x4 cell (0, 0)
    let mz =
        values(codec.mask(Tensor::<1>::from_floats(m.as_slice(), &cpu()).reshape([1, 1, 8, 8])));
    assert_eq!(mz, vec![1.0, 0.0, 0.0, 0.0]);
}

/// Training killed after a checkpoint and resumed ends where an uninterrupted run ends: same
/// loss curve and same model, for a model trained whole (the scene prior) and for LoRA
/// adapters on a frozen base (fine-tuning, whose state holds only the adapters and tokens).
#[test]
fn training_resumes_where_it_stopped() {
    use extranerf_diffusion::train_state::{self, Checkpointing};
    let images = vec![TrainImage::new(16, 16, stripes(16, 16))];
    let aug = Augment {
        crop: 8,
        ..Augment::default()
    };
    let s = schedule(BetaSchedule::ScaledLinear, Prediction::V);
    let settings = |steps| TrainSettings {
        steps,
        batch: 2,
        lr: 3e-3,
        token_lr: 1e-3,
        warmup: 4,
        log_every: 3,
        seed: 4,
        ..TrainSettings::default()
    };
    let base_dir = scratch_dir("resume-base");
    let base_dev = cpu().autodiff();
    base_dev.seed(1);
    weights::save_unet(
        &base_dir,
        &tiny_pixel_unet_config(),
        &tiny_pixel_unet(&base_dev),
    )
    .unwrap();
    // A fresh model as the command builds it: whole or with fresh adapters.
    let build = |lora_rank: Option<usize>, dev: &Device| {
        let (_, unet) = weights::load_unet(&base_dir, dev).unwrap();
        let unet = match lora_rank {
            Some(r) => lora::apply(unet, &LoraConfig::attention(r, 2.0), dev).unwrap(),
            None => unet,
        };
        Trainable {
            unet,
            tokens: LearnedTokens::new(2, 8, dev),
        }
    };
    let x = seeded_noise([1, 7, 8, 8], 5, &cpu());
    let ctx: Tensor<3> = seeded_noise([1, 2, 8, 1], 6, &cpu()).reshape([1, 2, 8]);
    let output = |m: Trainable| {
        let m = m.valid();
        values(m.unet.forward(x.clone(), &[300.0], &ctx))
    };
    for lora_rank in [None, Some(2)] {
        let dev = cpu().autodiff();
        let train_on =
            |model, set: &TrainSettings, imgs: &[TrainImage], ck: Option<&Checkpointing>| {
                train::train(
                    model,
                    &Codec::Pixels(PixelCodec),
                    &s,
                    imgs,
                    &aug,
                    set,
                    &dev,
                    ck,
                    &mut |_| {},
                )
            };
        let run = |model, steps, ck: Option<&Checkpointing>| {
            train_on(model, &settings(steps), &images, ck)
        };
        // One starting model for both runs (the device's generator is shared with tests
        // running alongside, so two builds need not agree); the resume starts from another.
        let init = build(lora_rank, &dev);
        let (straight, curve) = run(init.clone(), 10, None).unwrap();
        let want = output(straight);
        let dir = scratch_dir(&format!("resume-{lora_rank:?}"));
        let ck = Checkpointing {
            dir: dir.clone(),
            every: 4,
            resume: false,
            identity: serde_json::json!({"rank": lora_rank}),
        };
        // Stopped after step 6 (saves at 4 and 6), then resumed to 10 from a fresh model.
        run(init, 6, Some(&ck)).unwrap();
        let st = train_state::peek(&dir).unwrap().unwrap();
        assert_eq!(st.step, 6);
        let files: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".bpk"))
            .collect();
        assert_eq!(files.len(), 3, "only the last step's files stay: {files:?}");
        // A second fresh start on the same folder is refused: it holds someone's work.
        let err = run(build(lora_rank, &dev), 10, Some(&ck))
            .err()
            .unwrap()
            .to_string();
        assert!(
            err.contains("holds an unfinished training (step 6)"),
            "{err}"
        );
        let resume = Checkpointing {
            resume: true,
            ..ck.clone()
        };
        let (resumed, resumed_curve) = run(build(lora_rank, &dev), 10, Some(&resume)).unwrap();
        assert_eq!(resumed_curve, curve, "{lora_rank:?}: loss curves differ");
        let got = output(resumed);
        let err = rel_err(&got, &want);
        eprintln!("{lora_rank:?}: resumed vs uninterrupted output, relative error {err:e}");
        assert!(err < 1e-6, "{lora_rank:?}: relative error {err}");
        assert_eq!(train_state::peek(&dir).unwrap().unwrap().step, 10);
        // Other settings, another identity or other images are refused by name.
        let mut other = settings(12);
        other.lr = 1e-2;
        let err = train_on(build(lora_rank, &dev), &other, &images, Some(&resume))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("lr: 0.003 when saved, 0.01 now"), "{err}");
        let moved = Checkpointing {
            identity: serde_json::json!({"rank": 9}),
            ..resume.clone()
        };
        let err = run(build(lora_rank, &dev), 12, Some(&moved))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("rank:") && err.contains("9 now"), "{err}");
        let flipped = vec![TrainImage::new(
            16,
            16,
            stripes(16, 16).into_iter().rev().collect(),
        )];
        let err = train_on(
            build(lora_rank, &dev),
            &settings(12),
            &flipped,
            Some(&resume),
        )
        .err()
        .unwrap()
        .to_string();
        assert!(err.contains("training images: hash"), "{err}");
        // Fewer steps than saved: refused, not silently returned.
        let err = run(build(lora_rank, &dev), 8, Some(&resume))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("past the 8 steps"), "{err}");
    }
}

/// A damaged training state is a clear error naming the file, never a panic or a silent
/// fresh start.
#[test]
fn damaged_training_states_are_refused() {
    use extranerf_diffusion::train_state::{self, Checkpointing, STATE_FILE};
    let dev = cpu().autodiff();
    dev.seed(2);
    let images = vec![TrainImage::new(16, 16, stripes(16, 16))];
    let aug = Augment {
        crop: 8,
        ..Augment::default()
    };
    let s = schedule(BetaSchedule::ScaledLinear, Prediction::V);
    let settings = TrainSettings {
        steps: 2,
        batch: 1,
        log_every: 1,
        ..TrainSettings::default()
    };
    let dir = scratch_dir("resume-damaged");
    let ck = Checkpointing {
        dir: dir.clone(),
        every: 1,
        resume: true,
        identity: serde_json::Value::Null,
    };
    let model = || Trainable {
        unet: tiny_pixel_unet(&dev),
        tokens: LearnedTokens::new(2, 8, &dev),
    };
    let run = |m| {
        train::train(
            m,
            &Codec::Pixels(PixelCodec),
            &s,
            &images,
            &aug,
            &settings,
            &dev,
            Some(&ck),
            &mut |_| {},
        )
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default()
    };
    let err = run(model());
    assert!(err.contains("no training state to resume"), "{err}");
    let fresh = Checkpointing {
        resume: false,
        ..ck.clone()
    };
    train::train(
        model(),
        &Codec::Pixels(PixelCodec),
        &s,
        &images,
        &aug,
        &settings,
        &dev,
        Some(&fresh),
        &mut |_| {},
    )
    .unwrap();
    let st = train_state::peek(&dir).unwrap().unwrap();
    let state = dir.join(STATE_FILE);
    let good = std::fs::read(&state).unwrap();
    // Truncated state.json.
    std::fs::write(&state, &good[..good.len() / 2]).unwrap();
    let err = run(model());
    assert!(err.contains("state.json: not a training state"), "{err}");
    // A state naming a file outside its folder.
    let text = String::from_utf8(good.clone())
        .unwrap()
        .replace(&st.model, "../../etc/passwd.bpk");
    std::fs::write(&state, text).unwrap();
    let err = run(model());
    assert!(err.contains("names an odd file"), "{err}");
    std::fs::write(&state, &good).unwrap();
    // Truncated weights and optimiser files.
    for name in [&st.model, &st.adamw_unet] {
        let p = dir.join(name);
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() / 3]).unwrap();
        let err = run(model());
        assert!(err.contains(name.as_str()), "{name}: {err}");
        std::fs::write(&p, &bytes).unwrap();
    }
    // Weights of another architecture.
    let wide = Trainable {
        unet: UNet2DConditionModel::new(
            &UNetConfig {
                block_out_channels: vec![16, 24],
                ..tiny_pixel_unet_config()
            },
            &dev,
        )
        .unwrap(),
        tokens: LearnedTokens::new(2, 8, &dev),
    };
    let err = run(wide);
    assert!(err.contains(&st.model), "{err}");
    // Intact again: it resumes (nothing left to train).
    assert_eq!(run(model()), "");
}
