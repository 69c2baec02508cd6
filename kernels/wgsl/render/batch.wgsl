// A training batch drawn on the device: ray r picks an image and a pixel uniformly from a hash
// of (seed, r), and copies that pixel's colour and depth target, so a training step needs no
// upload. Image i's pixels sit at image_info[i].x .. + width * height in the packed arrays.
//!include common/dispatch.wgsl
//!include common/rng.wgsl

struct Params {
    n_rays: u32,
    n_images: u32,
    seed: u32,
    _pad: u32,
}
var<immediate> params: Params;

// Per image: (first pixel, width, height, camera index).
@group(0) @binding(0) var<storage, read> image_info: array<vec4<u32>>;
// Per pixel of all images: (r, g, b, unused) and (depth, confidence).
@group(0) @binding(1) var<storage, read> image_rgb: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> image_depth: array<vec2<f32>>;
// Per ray: (camera index, y * width + x), target colour, target (depth, confidence).
@group(0) @binding(3) var<storage, read_write> pixels: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read_write> target_rgb: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> target_depth: array<vec2<f32>>;

@compute @workgroup_size(64)
fn sample_batch(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let h1 = pcg_hash(params.seed ^ pcg_hash(r));
    let h2 = pcg_hash(h1 ^ 0x9e3779b9u);
    let info = image_info[h1 % params.n_images];
    let pix = h2 % (info.y * info.z);
    pixels[r] = vec2<u32>(info.w, pix);
    target_rgb[r] = image_rgb[info.x + pix];
    target_depth[r] = image_depth[info.x + pix];
}
