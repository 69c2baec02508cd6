// Per-ray photometric and depth losses and their gradients with respect to the rendered
// colour and depth (fed to composite_bwd). Losses are means over the batch: each ray's loss
// and gradient carry 1 / n_rays.
//   rgb: L2  l = |c - c*|^2 / 3            or Huber with threshold delta per channel, scaled by
//        the target's colour weight (or L1 where that weight is negative: common/ray_loss.wgsl)
//   depth: lambda_d * confidence * (d - d*)^2 for rays with confidence > 0 (sparse points,
//   MVS, completed depth); rays without a target have confidence 0.
//!include common/dispatch.wgsl
//!include common/ray_loss.wgsl

struct Params {
    n_rays: u32,
    // 0: L2, 1: Huber.
    kind: u32,
    huber_delta: f32,
    depth_lambda: f32,
    // The core of the virtual views' smooth L1 (0: plain L1; common/ray_loss.wgsl).
    l1_core: f32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> rendered_rgba: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> rendered_depth: array<f32>;
// Target colour (rgb, signed colour weight) and target depth with its confidence.
@group(0) @binding(2) var<storage, read> target_rgb: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> target_depth: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read_write> loss: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_rgba: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> d_depth: array<f32>;

@compute @workgroup_size(64)
fn ray_loss(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let inv_n = 1.0 / f32(params.n_rays);
    let rl = photo_depth_loss(rendered_rgba[r].xyz, rendered_depth[r], target_rgb[r], target_depth[r],
                              params.kind, params.huber_delta, params.depth_lambda, params.l1_core);
    loss[r] = rl.loss * inv_n;
    d_rgba[r] = vec4<f32>(rl.d_rgb * inv_n, 0.0);
    d_depth[r] = rl.d_depth * inv_n;
}
