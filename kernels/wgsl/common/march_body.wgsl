// The fused march's parameters and bindings, and the ray of a pixel, shared by its scalar
// kernels (render/march.wgsl, which describes the march) and its cooperative-matrix kernel
// (common/march_coop.wgsl).
//!include common/dispatch.wgsl
//!include common/heads.wgsl
//!include common/camera.wgsl
//!include common/contract.wgsl
//!include common/hash_grid.wgsl
//!include common/mlp.wgsl
//!include common/mlp_block.wgsl
//!include common/occupancy.wgsl
//!include common/rng.wgsl
//!include common/sh.wgsl
//!include common/volume.wgsl
//!include common/field_eval.wgsl
//!include common/pixel_ray.wgsl

struct Params {
    // Rays (march_render) or cells in the window (march_occupancy).
    n: u32,
    // Samples per ray.
    samples: u32,
    // 0: linear in t, 1: linear in disparity.
    spacing: u32,
    // Non-zero: march in NDC (near plane at `ndc_near`).
    ndc: u32,
    // Sampling range along the ray.
    near: f32,
    far: f32,
    ndc_near: f32,
    // Contraction mode (common/contract.wgsl) and 1 / scene radius.
    contraction: u32,
    inv_radius: f32,
    // Occupancy grid resolution and cascades; cascades = 0 disables skipping in the march.
    occ_res: u32,
    occ_cascades: u32,
    // Hash-grid levels and features per level.
    levels: u32,
    features: u32,
    // Float offset of the colour MLP in the uniform weight block (the density MLP is at 0).
    color_base: u32,
    min_weight: f32,
    min_transmittance: f32,
    // Scene centre (xyz); w: non-zero when march_render takes the samples given (the proposal
    // sampler's, render/proposal.wgsl's resample: sample j of ray i is
    // given_t_dt[i * samples + j]) in place of the strata.
    center: vec4<f32>,
    // Background colour (xyz).
    background: vec4<f32>,
    // Occupancy update: first cell of the window, jitter seed, EMA decay.
    first: u32,
    seed: u32,
    decay: f32,
    n_cameras: u32,
    // (0, 1, 2, 3): the identity table of common/mlp_block.wgsl's mlp_uni.
    lut: vec4<u32>,
}
var<immediate> params: Params;

// The strata's spacing, for common/field_eval.wgsl's t_of.
fn sample_spacing() -> u32 {
    return params.spacing;
}

@group(0) @binding(0) var<storage, read> cameras: array<GpuCamera>;
// (camera, pixel = y * width + x) per ray.
@group(0) @binding(1) var<storage, read> pixels: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> level_info: array<HashLevel>;
@group(0) @binding(3) var<storage, read> table: array<f32>;
@group(0) @binding(4) var<storage, read> density_shape: array<MlpShape>;
@group(0) @binding(6) var<storage, read> color_shape: array<MlpShape>;
@group(0) @binding(8) var<storage, read> occ_bits: array<u32>;
@group(0) @binding(9) var<storage, read_write> out_rgba: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(11) var<storage, read_write> occ_grid: array<f32>;
// Both MLPs' weights (common/mlp.wgsl layout; density at 0, colour at params.color_base),
// copied here from the parameter buffer before each pass. Every lane reads the same entry; a
// uniform block lets lavapipe load it without the per-lane branches of a storage buffer.
@group(0) @binding(12) var<uniform> mlp: array<vec4<f32>, 4096>;
// The second part of a split hash table (common/hash_grid.wgsl).
@group(0) @binding(13) var<storage, read> table_hi: array<f32>;
// The samples given, (t, dt) per sample (params.center.w non-zero; the scalar march only).
@group(0) @binding(14) var<storage, read> given_t_dt: array<vec2<f32>>;


// Ray i (< params.n). Out-of-range camera or pixel indices give a zero pixel (written here)
// rather than reading out of bounds.
fn march_ray(i: u32) -> PixelRay {
    let r = pixel_ray(pixels[i], params.n_cameras, params.ndc != 0u, params.ndc_near);
    if !r.valid {
        out_rgba[i] = vec4<f32>(0.0);
        out_depth[i] = 0.0;
    }
    return r;
}

// Sample j of the march's k: its distance (the stratum's midpoint) and length.
fn march_stratum(j: u32, k: u32) -> vec2<f32> {
    let inv_k = 1.0 / f32(k);
    let s0 = f32(j) * inv_k;
    let s1 = f32(j + 1u) * inv_k;
    return vec2<f32>(t_of(mix(s0, s1, 0.5)), t_of(s1) - t_of(s0));
}
