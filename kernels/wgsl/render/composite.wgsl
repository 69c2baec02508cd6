// Standalone compositing of per-sample density and colour into per-ray colour, expected depth
// and opacity, and its backward pass; one thread per ray. The fused march kernels use the same
// functions (common/volume.wgsl). rays[r] = (first sample, sample count).
//!include common/dispatch.wgsl
//!include common/volume.wgsl
//!include common/rng.wgsl

struct Params {
    n_rays: u32,
    // Floaters No More (Philip & Deschaintre 2023): 1 scales each sample's gradients by
    // min(1, t^2), damping the near-camera floaters that few views constrain.
    grad_scaling: u32,
    // Non-zero: each ray's background is random (common/rng.wgsl's ray_background from
    // `bg_seed`), not `background`.
    random_bg: u32,
    bg_seed: u32,
    // Background colour (rgb, w unused), added with the ray's final transmittance.
    background: vec4<f32>,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> rays: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read> sigma: array<f32>;
@group(0) @binding(2) var<storage, read> rgb: array<vec4<f32>>;
// Per sample: (t, dt) = distance of the sample along the ray and its interval length.
@group(0) @binding(3) var<storage, read> t_dt: array<vec2<f32>>;
// Per ray: (r, g, b, opacity) and expected depth.
@group(0) @binding(4) var<storage, read_write> out_rgba: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> out_depth: array<f32>;
// Backward inputs: dL/d(rgb, opacity), dL/ddepth per ray, and an extra dL/dw per sample
// (e.g. the distortion loss; zeros when unused).
@group(0) @binding(6) var<storage, read> d_rgba: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> d_depth: array<f32>;
@group(0) @binding(8) var<storage, read> d_weight: array<f32>;
// Backward outputs per sample.
@group(0) @binding(9) var<storage, read_write> d_sigma: array<f32>;
@group(0) @binding(10) var<storage, read_write> d_rgb: array<vec4<f32>>;

@compute @workgroup_size(64)
fn composite_fwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let span = rays[r];
    var tau = 0.0;
    var c = vec3<f32>(0.0);
    var depth = 0.0;
    var opacity = 0.0;
    for (var s = span.x; s < span.x + span.y; s += 1u) {
        let w = next_weight(sigma[s], t_dt[s].y, &tau);
        c += w * rgb[s].xyz;
        depth += w * t_dt[s].x;
        opacity += w;
    }
    let t_end = exp(-tau);
    let bgc = ray_background(params.background.xyz, params.random_bg, params.bg_seed, r);
    out_rgba[r] = vec4<f32>(c + t_end * bgc, opacity);
    out_depth[r] = depth;
}

// dL/dx_i = T_{i+1} u_i - sum_{j>i} w_j u_j - T_N (background . g_c), with
// u_j = dL/dw_j = c_j . g_c + t_j g_d + g_o + d_weight_j; dL/dsigma_i = dt_i dL/dx_i.
@compute @workgroup_size(64)
fn composite_bwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let span = rays[r];
    let g = d_rgba[r];
    let gd = d_depth[r];
    // First pass: total of w_j u_j and the final optical depth.
    var tau = 0.0;
    var total = 0.0;
    for (var s = span.x; s < span.x + span.y; s += 1u) {
        let w = next_weight(sigma[s], t_dt[s].y, &tau);
        let u = dot(rgb[s].xyz, g.xyz) + t_dt[s].x * gd + g.w + d_weight[s];
        total += w * u;
    }
    let bgc = ray_background(params.background.xyz, params.random_bg, params.bg_seed, r);
    let bg = exp(-tau) * dot(bgc, g.xyz);
    // Second pass: suffix sums as total minus the running prefix.
    tau = 0.0;
    var prefix = 0.0;
    for (var s = span.x; s < span.x + span.y; s += 1u) {
        let dt = t_dt[s].y;
        let w = next_weight(sigma[s], dt, &tau);
        let u = dot(rgb[s].xyz, g.xyz) + t_dt[s].x * gd + g.w + d_weight[s];
        prefix += w * u;
        let dx = exp(-tau) * u - (total - prefix) - bg;
        // sigma <= 0 or dt <= 0 contribute x = 0 with zero slope in sigma below 0; the
        // gradient still flows for sigma = 0 (the density can grow).
        var scale = 1.0;
        if params.grad_scaling != 0u {
            scale = min(1.0, t_dt[s].x * t_dt[s].x);
        }
        d_sigma[s] = select(0.0, scale * dt * dx, dt > 0.0 && sigma[s] >= 0.0);
        d_rgb[s] = vec4<f32>(scale * w * g.xyz, 0.0);
    }
}
