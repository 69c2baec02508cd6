// A training batch drawn on the device: ray r picks an image from a hash of (seed, r) with the
// images' sampling probabilities, then a pixel of it uniformly, and copies that pixel's colour
// (with its signed colour weight, common/ray_loss.wgsl) and depth target, so a training step
// needs no upload. Image i's pixels sit at image_info[i].x .. + width * height in the packed
// arrays.
//
// Probabilities come as a cumulative table of 24-bit fixed-point bounds: image i is drawn when
// u = (hash >> 8) lies in [image_cdf[i - 1], image_cdf[i]) (image_cdf[-1] = 0, the last bound
// is 2^24), so an image whose bound equals its predecessor's is never drawn.
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
// Per pixel of all images: (r, g, b, signed colour weight) and (depth, confidence).
@group(0) @binding(1) var<storage, read> image_rgb: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> image_depth: array<vec2<f32>>;
// Per ray: (camera index, y * width + x), target colour, target (depth, confidence).
@group(0) @binding(3) var<storage, read_write> pixels: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read_write> target_rgb: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> target_depth: array<vec2<f32>>;
// Per image: the upper bound of its share of [0, 2^24) (cumulative).
@group(0) @binding(6) var<storage, read> image_cdf: array<u32>;

// The image whose share of [0, 2^24) holds u: the first i with u < image_cdf[i] (binary search).
fn pick_image(u: u32) -> u32 {
    var lo = 0u;
    var hi = params.n_images - 1u;
    while lo < hi {
        let mid = (lo + hi) / 2u;
        if u < image_cdf[mid] {
            hi = mid;
        } else {
            lo = mid + 1u;
        }
    }
    return lo;
}

@compute @workgroup_size(64)
fn sample_batch(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let h1 = pcg_hash(params.seed ^ pcg_hash(r));
    let h2 = pcg_hash(h1 ^ 0x9e3779b9u);
    let info = image_info[pick_image(h1 >> 8u)];
    let pix = h2 % (info.y * info.z);
    pixels[r] = vec2<u32>(info.w, pix);
    target_rgb[r] = image_rgb[info.x + pix];
    target_depth[r] = image_depth[info.x + pix];
}
