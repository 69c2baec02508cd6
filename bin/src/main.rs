//! `extranerf`: the command line of the engine.

use std::path::PathBuf;

use anyhow::Context as _;
use clap::{Parser, Subcommand};
use extranerf_gpu::{Context, ContextDesc, Validation};

mod args;
mod bench;
mod diffusion;
mod extrapolate;
mod mvs;
mod nerf;
mod report;
mod tradeoff;
mod visibility;

/// extranerf: a Vulkan-native ExtraNeRF engine (neural radiance fields viewed from outside the
/// cameras that took them). This build trains the BaseNeRF field (hash grid + tiny MLPs) on
/// posed photos, renders and evaluates it, runs a self-contained demo, and benchmarks the
/// kernels and the training step, generates virtual cameras and computes multi-view visibility,
/// runs the inpainting and enhancement diffusion models (diffusers layout) on the same Vulkan
/// device, and runs ExtraNeRF (`extrapolate`: stage 2, inpainted virtual views supervising the
/// field, then stage 3, the same views enhanced), with `eval RUN` for its ablation table.
#[derive(Parser, Debug)]
#[command(name = "extranerf", version, propagate_version = true)]
struct Cli {
    /// Vulkan device: an index from `extranerf info --list` or part of its name
    /// (default: $EXTRANERF_DEVICE, else discrete > integrated > virtual > CPU).
    #[arg(long, global = true, value_name = "DEV")]
    device: Option<String>,
    /// Load the Khronos validation layer (slow; for debugging). Also EXTRANERF_VALIDATION=1.
    #[arg(long, global = true)]
    validation: bool,
    /// Treat the device as having only this many MiB for the engine's buffers: allocations past
    /// it fail as out-of-memory does on a smaller device (default: the device's own memory).
    #[arg(long, global = true, value_name = "MIB")]
    max_memory: Option<u64>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Show the device, driver, Vulkan version, heaps, subgroup size and the features the
    /// engine uses.
    Info {
        /// List every Vulkan device instead (index, name, kind, version).
        #[arg(long)]
        list: bool,
        /// Also write the information as JSON to FILE.
        #[arg(long, value_name = "FILE")]
        json: Option<PathBuf>,
    },
    /// Train a BaseNeRF field on a scene; writes config.json, checkpoint.safetensors and
    /// progress.jsonl into --out, checkpointing atomically every --checkpoint-every steps.
    Train(nerf::TrainArgs),
    /// Render a trained run's views: PNG colour and EXR depth (NDC t for forward-facing scenes).
    Render(nerf::RenderArgs),
    /// Evaluate a trained run: PSNR, SSIM, LPIPS (AlexNet, VGG) on the held-out views and PSNR
    /// on the training views, written as JSON.
    Eval(nerf::EvalArgs),
    /// ExtraNeRF end to end on a procedural scene generated in code: a BaseNeRF on its
    /// 6-camera rig, then visibility, stage 2 and stage 3, scored on 8 views outside the rig.
    ///
    /// The scene (textured spheres at several depths before a wall, above a floor) is ray
    /// traced with its exact visibility; a BaseNeRF is trained on the rig; the pipeline runs
    /// as `extrapolate` does without diffusion weights (harmonic inpainting, an unsharp-mask
    /// enhancer); the table scores the BaseNeRF and each stage over the whole image, the
    /// estimated not-visible mask and the exact visible and not-visible pixels, and writes
    /// report.html with the BaseNeRF beside the final field on every view outside the rig.
    /// About 3 minutes on two CPU cores with lavapipe (167 s measured, `tools/demo.sh`).
    ///
    /// Example: `extranerf demo --out runs/demo`, then open runs/demo/extranerf/report.html.
    Demo(nerf::DemoArgs),
    /// Write the generated 360-degree scene: an object on a turntable rig, ray traced exactly
    /// into RGBA images with a transparent background, in NeRF-synthetic's layout
    /// (transforms_train.json, transforms_test.json), for tests and benchmarks at any size.
    Turntable(nerf::TurntableArgs),
    /// Virtual cameras beyond the input rig (outward translation, a widened spiral, or rotation
    /// past the captured yaw), written as transforms.json for rendering and visibility.
    Cameras(nerf::CamerasArgs),
    /// Write a scene (LLFF, transforms.json or COLMAP, as `train` reads it) as a COLMAP
    /// capture: a sparse model (PINHOLE cameras, poses and the scene's sparse points in the
    /// source's world) under OUT/sparse/0 and the images it loaded under OUT/images, which
    /// `train --scene OUT --factor 1` reads back as the same scene.
    ///
    /// Example: `extranerf export --scene ../shared/data/llff/fern --out runs/fern_colmap`.
    Export(nerf::ExportArgs),
    /// ExtraNeRF: train (or reuse, --base) a BaseNeRF, find what no two training cameras saw
    /// in virtual views beyond the rig, train the field further on those views inpainted
    /// (stage 2; one variant per --inpainter), then on them enhanced by a model trained on the
    /// scene's own corrupted renders (stage 3). Resumable at every stage (--resume); `eval RUN`
    /// then writes the ablation table with KID and RUN/report.html.
    Extrapolate(extrapolate::ExtrapolateArgs),
    /// Multi-view transmittance visibility (ExtraNeRF): for each pixel of a view, what the
    /// training cameras saw of the surface it shows (a point counts as seen when --rank of
    /// them saw it). Writes visibility PNG + EXR, an inpainting mask and visibility.json per
    /// view, and with --training-masks the pseudo-disocclusion masks of the training views.
    Visibility(visibility::VisibilityArgs),
    /// Plane-sweep multi-view stereo for the training views (NCC, winner-take-all, multi-view
    /// consistency, a confidence per pixel): depth maps for `train --depth-dir`, and their
    /// agreement with the COLMAP sparse points.
    Mvs(mvs::MvsArgs),
    /// Inpainting diffusion models (diffusers UNet2DConditionModel / AutoencoderKL layout)
    /// through burn on the engine's Vulkan device: train a scene prior from scratch, LoRA
    /// fine-tuning, inpainting, and model folders.
    Diffusion {
        #[command(subcommand)]
        what: diffusion::DiffusionCommand,
    },
    /// Benchmarks.
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
}

#[derive(Subcommand, Debug)]
enum BenchCommand {
    /// Microbenchmarks of the primitive kernels: median GPU time (timestamp queries) per kernel
    /// and size, GB/s and elements/s, and the ratio to vkCmdCopyBuffer bandwidth measured in
    /// the same run at the same size.
    Kernels(bench::KernelsArgs),
    /// The BaseNeRF training step: samples/s over whole steps and the GPU time of every stage
    /// (rays, sampling, hash grid, MLPs, compositing, losses, backward passes, Adam).
    Train(nerf::BenchTrainArgs),
    /// Rendering a trained run: the standalone training kernels against the fused march
    /// (exact, early termination, colour cut, occupancy grids), with time per view, rays/s,
    /// samples/s, PSNR and the difference from the exact render for each.
    Render(nerf::BenchRenderArgs),
    /// Visibility cost per pixel against the number of training cameras (0 = the camera ray
    /// alone, the reference), for the exact segment march and the transmittance volumes, with
    /// field evaluations (march) or lookups (volume) per pixel and the volume's difference
    /// from the march.
    Visibility(visibility::BenchVisibilityArgs),
    /// Quality against time: trains a model per sweep point (table size, levels, features,
    /// finest resolution, samples per ray, batch, steps, and the auto-config's choice), scores
    /// the held-out views (PSNR, SSIM, LPIPS), and writes CSV, JSON and an SVG plot with the
    /// Pareto frontier.
    Tradeoff(tradeoff::TradeoffArgs),
    /// The diffusion U-Net: forward and forward+backward it/s at a tiny and a medium config,
    /// the LoRA fine-tuning step, on burn's CPU backend and on the engine's Vulkan device
    /// (warm-up with shader compilation reported apart), and the FLOPs of SD-1.5 inpainting
    /// at 64x64 latents for scale.
    Diffusion(diffusion::BenchDiffusionArgs),
}

fn context(cli: &Cli) -> anyhow::Result<Context> {
    context_with(cli, false)
}

/// A context whose VkDevice burn's wgpu runtime can adopt (diffusion commands).
fn context_with(cli: &Cli, share_with_wgpu: bool) -> anyhow::Result<Context> {
    let validation = if cli.validation {
        Validation::Required
    } else {
        Validation::from_env(Validation::Off)
    };
    Context::new(&ContextDesc {
        validation,
        device: cli.device.clone(),
        max_binding_bytes: None,
        max_memory_bytes: cli.max_memory.map(|m| m.saturating_mul(1 << 20)),
        share_with_wgpu,
        no_coop_matrix: false,
    })
    .context("creating the Vulkan device")
}

fn main() {
    // burn-optim 0.22.1 restores an optimiser's moments (resuming `diffusion prior`,
    // `diffusion finetune` or the enhancer) on burn's `Device::default()`, which is a new wgpu
    // device of its own, not the engine's, unless BURN_DEVICE names another. On the CPU the
    // moments move to the parameters' device at the next step, so nothing else changes. Set
    // here, before any thread exists.
    if std::env::var_os("BURN_DEVICE").is_none() {
        std::env::set_var("BURN_DEVICE", "flex");
    }
    let cli = Cli::parse();
    if let Err(e) = run(&cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: &Cli) -> anyhow::Result<()> {
    match &cli.command {
        Command::Info { list: true, .. } => {
            for d in extranerf_gpu::list_devices()? {
                println!(
                    "{}: {} ({}, Vulkan {})",
                    d.index, d.name, d.device_type, d.api_version
                );
            }
            Ok(())
        }
        Command::Info { list: false, json } => {
            let ctx = context(cli)?;
            let info = ctx.info();
            print!("{}", info_text(info));
            if let Some(path) = json {
                bench::write_json(path, &info_json(info))?;
                println!("wrote {}", path.display());
            }
            Ok(())
        }
        Command::Train(a) => nerf::train(&context(cli)?, a),
        Command::Render(a) => nerf::render(&context(cli)?, a),
        Command::Eval(a) => nerf::eval(&context_with(cli, a.needs_wgpu())?, a),
        Command::Extrapolate(a) => extrapolate::extrapolate(&context_with(cli, a.needs_wgpu())?, a),
        Command::Demo(a) => nerf::demo(&context(cli)?, a),
        Command::Cameras(a) => nerf::cameras(a),
        Command::Export(a) => nerf::export(a),
        Command::Turntable(a) => nerf::turntable(a),
        Command::Visibility(a) => visibility::visibility(&context(cli)?, a),
        Command::Mvs(a) => mvs::mvs(&context(cli)?, a),
        Command::Diffusion { what } => diffusion::run(&context_with(cli, true)?, what),
        Command::Bench {
            what: BenchCommand::Diffusion(args),
        } => diffusion::bench(&context_with(cli, true)?, args),
        Command::Bench {
            what: BenchCommand::Visibility(args),
        } => visibility::bench_visibility(&context(cli)?, args),
        Command::Bench {
            what: BenchCommand::Tradeoff(args),
        } => tradeoff::tradeoff(&context(cli)?, args),
        Command::Bench {
            what: BenchCommand::Train(args),
        } => nerf::bench_train(&context(cli)?, args),
        Command::Bench {
            what: BenchCommand::Render(args),
        } => nerf::bench_render(&context(cli)?, args),
        Command::Bench {
            what: BenchCommand::Kernels(args),
        } => {
            let ctx = context(cli)?;
            bench::kernels(&ctx, args)
        }
    }
}

fn gib(b: u64) -> String {
    format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64)
}

fn yes(b: bool) -> &'static str {
    if b {
        "yes"
    } else {
        "no"
    }
}

fn info_text(i: &extranerf_gpu::DeviceInfo) -> String {
    let mut s = String::new();
    let lavapipe = i.driver_name.to_lowercase().contains("llvmpipe")
        || i.name.to_lowercase().contains("llvmpipe");
    s += &format!(
        "device          {} [{}] (index {})\n",
        i.name, i.device_type, i.index
    );
    s += &format!(
        "driver          {} {}{}\n",
        i.driver_name,
        i.driver_info,
        if lavapipe {
            "  (Mesa lavapipe: Vulkan on the CPU)"
        } else {
            ""
        }
    );
    s += &format!(
        "vulkan          device {}, engine uses {}\n",
        i.api_version, i.used_api_version
    );
    for (k, h) in i.heaps.iter().enumerate() {
        s += &format!(
            "heap {k}          {}{}\n",
            gib(h.size),
            if h.device_local { " device-local" } else { "" }
        );
    }
    s += &format!(
        "subgroup size   {} (arithmetic+ballot in compute: {})\n",
        i.subgroup_size,
        yes(i.subgroup_arithmetic)
    );
    s += &format!(
        "storage binding max {} bytes ({} MiB)\n",
        i.max_storage_buffer_range,
        i.max_storage_buffer_range >> 20
    );
    s += &format!(
        "workgroups      max {} x {}, shared memory {} KiB\n",
        i.max_workgroup_count_x,
        i.max_workgroup_count_y,
        i.max_shared_memory / 1024
    );
    s += &format!(
        "timestamps      {} ({} ns/tick)\n",
        yes(i.timestamps),
        i.timestamp_period_ns
    );
    s += &format!(
        "f32 atomic add  {} (scatter-add kernels)\n",
        yes(i.float32_atomic_add)
    );
    s += &format!(
        "shaderFloat16   {}, storageBuffer16BitAccess {}\n",
        yes(i.shader_float16),
        yes(i.storage_buffer_16bit)
    );
    if i.coop_matrix.is_empty() {
        s += "coop matrix     none (VK_KHR_cooperative_matrix absent): --mlp auto runs scalar\n";
    } else {
        for (k, shape) in i.coop_matrix.iter().enumerate() {
            s += &format!(
                "{}{shape}\n",
                if k == 0 {
                    "coop matrix     "
                } else {
                    "                "
                }
            );
        }
        s += &format!(
            "                --mlp auto runs {}\n",
            match i.coop_tile() {
                Some(t) if i.is_cpu() => format!(
                    "scalar on this CPU device (its {t}x{t}x{t} tiles are emulated, measured slower; --mlp coop uses them)"
                ),
                Some(t) => format!("coop ({t}x{t}x{t} f16*f16+f32 tiles)"),
                None => "scalar (no f16*f16+f32 subgroup tile of 8 or 16)".into(),
            }
        );
    }
    s += &format!(
        "validation      {}\n",
        if i.validation {
            "Khronos layer loaded"
        } else {
            "off"
        }
    );
    s
}

fn info_json(i: &extranerf_gpu::DeviceInfo) -> serde_json::Value {
    serde_json::json!({
        "index": i.index,
        "name": i.name,
        "device_type": i.device_type,
        "driver_name": i.driver_name,
        "driver_info": i.driver_info,
        "api_version": i.api_version,
        "used_api_version": i.used_api_version,
        "vendor_id": i.vendor_id,
        "heaps": i.heaps.iter().map(|h| serde_json::json!({"bytes": h.size, "device_local": h.device_local})).collect::<Vec<_>>(),
        "subgroup_size": i.subgroup_size,
        "subgroup_arithmetic": i.subgroup_arithmetic,
        "max_storage_buffer_range": i.max_storage_buffer_range,
        "max_workgroup_count": [i.max_workgroup_count_x, i.max_workgroup_count_y],
        "max_shared_memory": i.max_shared_memory,
        "timestamps": i.timestamps,
        "timestamp_period_ns": i.timestamp_period_ns,
        "float32_atomic_add": i.float32_atomic_add,
        "shader_float16": i.shader_float16,
        "storage_buffer_16bit": i.storage_buffer_16bit,
        "coop_matrix": i.coop_matrix.iter().map(|c| serde_json::json!({"m": c.m, "n": c.n, "k": c.k, "a": c.types[0], "b": c.types[1], "c": c.types[2], "result": c.types[3], "scope": c.scope})).collect::<Vec<_>>(),
        "coop_tile": i.coop_tile(),
        "validation": i.validation,
    })
}
