// Stratified samples along rays (NeRF's coarse sampling): ray r gets `per_ray` samples between
// its near and far distance, spaced linearly in t or in disparity (1/t, for unbounded depth),
// jittered within their strata by a hash of (seed, ray, sample) unless jitter is off (or, in
// training, the ray is a virtual view's: see Params.jitter). Writes
// the sample positions, (t, dt) for compositing and (s, ds) in [0, 1] for the distortion loss,
// and each ray's (first sample, count).
//
// `stratified_occupied` skips empty space: it probes `probes` equal intervals of s along the
// ray against the occupancy grid (one test at each interval's centre) and spreads the same
// per-ray count of strata over the occupied intervals only, as if the empty ones were cut out
// of [0, 1]. A ray with no occupied interval samples all of it. With every interval occupied it
// gives `stratified`'s samples. dt is the length in t of a stratum's occupied part; ds is its
// share of s (the strata of one ray then tile the occupied part of s). The strata are
// common/strata.wgsl's, which the fused training step shares.
//!include common/dispatch.wgsl
//!include common/rng.wgsl
//!include common/occupancy.wgsl
//!include common/strata.wgsl

struct Params {
    n_rays: u32,
    per_ray: u32,
    // 0: linear in t, 1: linear in disparity.
    spacing: u32,
    // 0: samples at stratum centres; 1: jittered; 2: jittered except on rays whose target colour
    // weight (target_rgb.w) is negative, the virtual views, whose targets are renders made with
    // centred samples: trained with jittered ones, such a target is off by the jitter's noise
    // and the loss rewards a smoother field.
    jitter: u32,
    seed: u32,
    // stratified_occupied: the grid, the probe intervals per ray (at most MAX_PROBES), and the
    // scene box (u = (p - centre.xyz) * centre.w).
    occ_res: u32,
    occ_cascades: u32,
    probes: u32,
    centre: vec4<f32>,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> origins: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> directions: array<vec4<f32>>;
// Per ray (near, far).
@group(0) @binding(2) var<storage, read> near_far: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read_write> positions: array<f32>;
@group(0) @binding(4) var<storage, read_write> t_dt: array<vec2<f32>>;
@group(0) @binding(5) var<storage, read_write> s_ds: array<vec2<f32>>;
@group(0) @binding(6) var<storage, read_write> rays: array<vec2<u32>>;
@group(0) @binding(7) var<storage, read> occ_bits: array<u32>;
// A training batch's target colours (jitter 2; any vec4 buffer of n_rays elements otherwise,
// unread).
@group(0) @binding(8) var<storage, read> target_rgb: array<vec4<f32>>;

@compute @workgroup_size(64)
fn stratified(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let k = params.per_ray;
    let nf = near_far[r];
    let o = origins[r].xyz;
    let d = directions[r].xyz;
    let first = r * k;
    rays[r] = vec2<u32>(first, k);
    let inv_k = 1.0 / f32(k);
    for (var i = 0u; i < k; i += 1u) {
        let st = ray_stratum(i, k, jitter(r, i), nf, params.spacing);
        write_sample(first + i, o, d, st.x, st.y, st.z, inv_k);
    }
}

// The position of sample i of ray r inside its stratum, in [0, 1).
fn jitter(r: u32, i: u32) -> f32 {
    if params.jitter == 1u || (params.jitter == 2u && target_rgb[r].w >= 0.0) {
        return strata_jitter(params.seed, r, i);
    }
    return 0.5;
}

fn write_sample(idx: u32, o: vec3<f32>, d: vec3<f32>, t: f32, dt: f32, s: f32, ds: f32) {
    let p = o + t * d;
    positions[3u * idx] = p.x;
    positions[3u * idx + 1u] = p.y;
    positions[3u * idx + 2u] = p.z;
    t_dt[idx] = vec2<f32>(t, dt);
    s_ds[idx] = vec2<f32>(s, ds);
}

@compute @workgroup_size(64)
fn stratified_occupied(@builtin(workgroup_id) wid: vec3<u32>,
                       @builtin(num_workgroups) nwg: vec3<u32>,
                       @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let k = params.per_ray;
    let nf = near_far[r];
    let o = origins[r].xyz;
    let d = directions[r].xyz;
    let first = r * k;
    rays[r] = vec2<u32>(first, k);
    var mask = probe_mask(o, d, nf, params.spacing, params.probes, params.centre,
                          OccGrid(params.occ_res, params.occ_cascades));
    let ds = strata_ds(&mask, k, params.probes);
    for (var i = 0u; i < k; i += 1u) {
        let st = occupied_stratum(&mask, i, k, jitter(r, i), params.probes, nf, params.spacing);
        write_sample(first + i, o, d, st.x, st.y, st.z, ds);
    }
}
