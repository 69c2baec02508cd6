// Stratified samples along rays (NeRF's coarse sampling): ray r gets `per_ray` samples between
// its near and far distance, spaced linearly in t or in disparity (1/t, for unbounded depth),
// jittered within their strata by a hash of (seed, ray, sample) unless jitter is off. Writes
// the sample positions, (t, dt) for compositing and (s, ds) in [0, 1] for the distortion loss,
// and each ray's (first sample, count).
//!include common/dispatch.wgsl
//!include common/rng.wgsl

struct Params {
    n_rays: u32,
    per_ray: u32,
    // 0: linear in t, 1: linear in disparity.
    spacing: u32,
    jitter: u32,
    seed: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
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

// Distance at normalised position s in [0, 1].
fn t_of(s: f32, near: f32, far: f32) -> f32 {
    if params.spacing == 1u {
        return 1.0 / mix(1.0 / near, 1.0 / far, s);
    }
    return mix(near, far, s);
}

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
        var u = 0.5;
        if params.jitter != 0u {
            u = rand01(pcg_hash(params.seed ^ pcg_hash(r)) + i);
        }
        // Stratum edges and the jittered point inside it.
        let s0 = f32(i) * inv_k;
        let s1 = f32(i + 1u) * inv_k;
        let s = mix(s0, s1, u);
        let t = t_of(s, nf.x, nf.y);
        let dt = t_of(s1, nf.x, nf.y) - t_of(s0, nf.x, nf.y);
        let p = o + t * d;
        let idx = first + i;
        positions[3u * idx] = p.x;
        positions[3u * idx + 1u] = p.y;
        positions[3u * idx + 2u] = p.z;
        t_dt[idx] = vec2<f32>(t, dt);
        s_ds[idx] = vec2<f32>(s, inv_k);
    }
}
