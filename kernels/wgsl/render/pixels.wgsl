// Small per-ray helpers of rendering and training:
//   pixel_range: pixels[r] = (camera, first + r), the rays of a band of one image (no upload);
//   ray_mse: mse[r] = mean over r, g, b of (rendered - target)^2, for the PSNR on progress lines.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
    camera: u32,
    first: u32,
    _pad: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read_write> pixels: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read> rendered: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> target_rgb: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> mse: array<f32>;

@compute @workgroup_size(64)
fn pixel_range(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n {
        return;
    }
    pixels[r] = vec2<u32>(params.camera, params.first + r);
}

@compute @workgroup_size(64)
fn ray_mse(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n {
        return;
    }
    let d = rendered[r].xyz - target_rgb[r].xyz;
    mse[r] = dot(d, d) / 3.0;
}
