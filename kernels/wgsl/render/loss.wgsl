// Per-ray photometric and depth losses and their gradients with respect to the rendered
// colour and depth (fed to composite_bwd). Losses are means over the batch: each ray's loss
// and gradient carry 1 / n_rays.
//   rgb: L2  l = |c - c*|^2 / 3            or Huber with threshold delta per channel
//   depth: lambda_d * confidence * (d - d*)^2 for rays with confidence > 0 (sparse points,
//   MVS, completed depth); rays without a target have confidence 0.
//!include common/dispatch.wgsl

struct Params {
    n_rays: u32,
    // 0: L2, 1: Huber.
    kind: u32,
    huber_delta: f32,
    depth_lambda: f32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> rendered_rgba: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> rendered_depth: array<f32>;
// Target colour (rgb, unused) and target depth with its confidence.
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
    let e = rendered_rgba[r].xyz - target_rgb[r].xyz;
    var l = 0.0;
    var g = vec3<f32>(0.0);
    if params.kind == 0u {
        l = dot(e, e) / 3.0;
        g = 2.0 * e / 3.0;
    } else {
        let a = abs(e);
        let delta = params.huber_delta;
        let quad = a <= vec3<f32>(delta);
        let lv = select(delta * (a - 0.5 * delta), 0.5 * e * e, quad);
        l = (lv.x + lv.y + lv.z) / 3.0;
        g = select(delta * sign(e), e, quad) / 3.0;
    }
    let td = target_depth[r];
    var gd = 0.0;
    if td.y > 0.0 {
        let de = rendered_depth[r] - td.x;
        l += params.depth_lambda * td.y * de * de;
        gd = 2.0 * params.depth_lambda * td.y * de;
    }
    loss[r] = l * inv_n;
    d_rgba[r] = vec4<f32>(g * inv_n, 0.0);
    d_depth[r] = gd * inv_n;
}
