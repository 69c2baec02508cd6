// Ray generation: one thread per ray, from (camera index, pixel index) pairs; optionally in
// NDC for forward-facing scenes. Outputs origin (xyz, 0) and direction (xyz, |d|).
//!include common/dispatch.wgsl
//!include common/camera.wgsl

struct Params {
    n: u32,
    ndc: u32,
    near: f32,
    n_cameras: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> cameras: array<GpuCamera>;
// (camera, pixel = y * width + x) per ray.
@group(0) @binding(1) var<storage, read> pixels: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read_write> origins: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> directions: array<vec4<f32>>;

@compute @workgroup_size(64)
fn generate_rays(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let pc = pixels[i];
    // Out-of-range camera or pixel indices give a zero ray rather than reading out of bounds.
    if pc.x >= params.n_cameras {
        origins[i] = vec4<f32>(0.0);
        directions[i] = vec4<f32>(0.0);
        return;
    }
    let cam = cameras[pc.x];
    if pc.y >= cam.size.x * cam.size.y {
        origins[i] = vec4<f32>(0.0);
        directions[i] = vec4<f32>(0.0);
        return;
    }
    var r = camera_ray(cam, pixel_centre(cam, pc.y));
    if params.ndc != 0u {
        r = ndc_ray(cam, r[0], r[1], params.near);
    }
    origins[i] = vec4<f32>(r[0], 0.0);
    directions[i] = vec4<f32>(r[1], length(r[1]));
}
