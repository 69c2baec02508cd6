// The glue between the field's stages, per sample (samples of ray r are r * per_ray ..
// r * per_ray + per_ray - 1):
//   density_head_fwd: sigma = trunc_exp(dens[0]) from the density MLP's output row `dens`
//     (geo_dims floats), and the colour MLP's input row = (dens[0 .. geo_dims], SH4(ray dir));
//   color_head_fwd: rgb = sigmoid(colour MLP output), written as (r, g, b, 0);
//   color_head_bwd / density_head_bwd: the matching gradients (the density row's gradient is
//     the colour input's gradient plus, in column 0, dL/dsigma * trunc_exp').
// trunc_exp(x) = exp(min(x, 15)) with the gradient clamped alike; sigmoid is evaluated without
// overflow on both sides.
//!include common/dispatch.wgsl
//!include common/heads.wgsl
//!include common/sh.wgsl

struct Params {
    // Samples.
    n: u32,
    // Samples per ray.
    per_ray: u32,
    // Floats per density-MLP output row (its first is the density logit).
    geo_dims: u32,
    _pad: u32,
}
var<immediate> params: Params;

// Per ray: world direction (xyz, unused); only its direction matters.
@group(0) @binding(0) var<storage, read> dirs: array<vec4<f32>>;
// [n, geo_dims] density MLP output / its gradient.
@group(0) @binding(1) var<storage, read> dens: array<f32>;
@group(0) @binding(2) var<storage, read_write> d_dens: array<f32>;
// [n] density / its gradient.
@group(0) @binding(3) var<storage, read_write> sigma: array<f32>;
@group(0) @binding(4) var<storage, read> d_sigma: array<f32>;
// [n, geo_dims + 16] colour MLP input / its gradient.
@group(0) @binding(5) var<storage, read_write> color_in: array<f32>;
@group(0) @binding(6) var<storage, read> d_color_in: array<f32>;
// [n, 3] colour MLP output / its gradient.
@group(0) @binding(7) var<storage, read> color_out: array<f32>;
@group(0) @binding(8) var<storage, read_write> d_color_out: array<f32>;
// [n] (r, g, b, 0) / its gradient.
@group(0) @binding(9) var<storage, read_write> rgb: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read> d_rgb: array<vec4<f32>>;

fn sample_index(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return linear_group(wid, nwg) * 64u + lid;
}

@compute @workgroup_size(64)
fn density_head_fwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                    @builtin(local_invocation_index) lid: u32) {
    let i = sample_index(wid, nwg, lid);
    if i >= params.n {
        return;
    }
    let g = params.geo_dims;
    let cin = g + 16u;
    sigma[i] = trunc_exp(dens[i * g]);
    for (var j = 0u; j < g; j += 1u) {
        color_in[i * cin + j] = dens[i * g + j];
    }
    let sh = sh4(unit_dir(dirs[i / params.per_ray].xyz));
    for (var k = 0u; k < 16u; k += 1u) {
        color_in[i * cin + g + k] = sh[k];
    }
}

@compute @workgroup_size(64)
fn color_head_fwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32) {
    let i = sample_index(wid, nwg, lid);
    if i >= params.n {
        return;
    }
    rgb[i] = vec4<f32>(sigmoid(color_out[3u * i]), sigmoid(color_out[3u * i + 1u]),
                       sigmoid(color_out[3u * i + 2u]), 0.0);
}

@compute @workgroup_size(64)
fn color_head_bwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32) {
    let i = sample_index(wid, nwg, lid);
    if i >= params.n {
        return;
    }
    let d = d_rgb[i];
    for (var c = 0u; c < 3u; c += 1u) {
        let s = sigmoid(color_out[3u * i + c]);
        d_color_out[3u * i + c] = d[c] * s * (1.0 - s);
    }
}

@compute @workgroup_size(64)
fn density_head_bwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                    @builtin(local_invocation_index) lid: u32) {
    let i = sample_index(wid, nwg, lid);
    if i >= params.n {
        return;
    }
    let g = params.geo_dims;
    let cin = g + 16u;
    for (var j = 0u; j < g; j += 1u) {
        d_dens[i * g + j] = d_color_in[i * cin + j];
    }
    d_dens[i * g] += d_sigma[i] * trunc_exp(dens[i * g]);
}
