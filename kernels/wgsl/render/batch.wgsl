// A training batch drawn on the device: ray r picks an image from a hash of (seed, r) with the
// images' sampling probabilities, then a pixel of it uniformly, and copies that pixel's colour
// (with its signed colour weight, common/ray_loss.wgsl) composited over the ray's background,
// and its depth target, so a training step needs no upload.
//
// The pixel store (views.rs `TrainData`) is compact and spread over up to STORE_BINDINGS
// bindings, so that it can exceed one binding's limit (maxStorageBufferRange: 128 MiB on
// lavapipe): per pixel two words, the colour as rgba8 (pack4x8unorm: r, g, b and alpha) and the
// signed colour weight as f32 bits; views with depth targets also hold per pixel the
// (depth, confidence) f32 pair's bits. `places[i]` says which binding and element hold image
// i's colour and depth blocks (depth binding NO_DEPTH: no targets, (0, 0)).
//
// A pixel's target colour is rgb * alpha + background * (1 - alpha), with the background the
// training step adds to its render of the same ray (common/rng.wgsl's ray_background with the
// same seed), so transparent pixels teach empty space.
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
    // 1: each ray's background is random (ray_background), else `background.xyz`.
    random_bg: u32,
    background: vec4<f32>,
}
var<immediate> params: Params;

struct Place {
    rgb_binding: u32,
    rgb_at: u32,
    depth_binding: u32,
    depth_at: u32,
    width: u32,
    height: u32,
    view: u32,
    _pad: u32,
}

const NO_DEPTH: u32 = 0xffffffffu;

@group(0) @binding(0) var<storage, read> places: array<Place>;
// The pixel store's bindings (unused ones repeat store0 and are never read).
@group(0) @binding(1) var<storage, read> store0: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> store1: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> store2: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read> store3: array<vec2<u32>>;
@group(0) @binding(5) var<storage, read> store4: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read> store5: array<vec2<u32>>;
@group(0) @binding(7) var<storage, read> store6: array<vec2<u32>>;
@group(0) @binding(8) var<storage, read> store7: array<vec2<u32>>;
// Per ray: (view index, y * width + x), target colour, target (depth, confidence).
@group(0) @binding(9) var<storage, read_write> pixels: array<vec2<u32>>;
@group(0) @binding(10) var<storage, read_write> target_rgb: array<vec4<f32>>;
@group(0) @binding(11) var<storage, read_write> target_depth: array<vec2<f32>>;
// Per image: the upper bound of its share of [0, 2^24) (cumulative).
@group(0) @binding(12) var<storage, read> image_cdf: array<u32>;

// Element i of store binding b (a branch: only the chosen binding is read).
fn store_at(b: u32, i: u32) -> vec2<u32> {
    switch b {
        case 0u: { return store0[i]; }
        case 1u: { return store1[i]; }
        case 2u: { return store2[i]; }
        case 3u: { return store3[i]; }
        case 4u: { return store4[i]; }
        case 5u: { return store5[i]; }
        case 6u: { return store6[i]; }
        default: { return store7[i]; }
    }
}

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
    let place = places[pick_image(h1 >> 8u)];
    let pix = h2 % (place.width * place.height);
    pixels[r] = vec2<u32>(place.view, pix);
    let px = store_at(place.rgb_binding, place.rgb_at + pix);
    let c = unpack4x8unorm(px.x);
    let bg = ray_background(params.background.xyz, params.random_bg, params.seed, r);
    target_rgb[r] = vec4<f32>(c.xyz * c.w + bg * (1.0 - c.w), bitcast<f32>(px.y));
    if place.depth_binding == NO_DEPTH {
        target_depth[r] = vec2<f32>(0.0);
    } else {
        target_depth[r] = bitcast<vec2<f32>>(store_at(place.depth_binding, place.depth_at + pix));
    }
}
