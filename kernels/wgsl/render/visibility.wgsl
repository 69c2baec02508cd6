// Multi-view transmittance visibility (ExtraNeRF): one thread per pixel of a view.
//
// The thread marches the pixel's ray as render/march.wgsl does (same samples, same weights
// w_j): uniform strata, or (flag VIS_GIVEN) the samples given per pixel, `(t, dt)` sorted along
// the ray, as the proposal sampler draws them for the march. For every sample with w_j > min_weight it marches again, from the sample toward the
// centre of each selected training camera, and takes the transmittance T_jk of that segment.
// A camera for which the sample is behind it or outside its image has T_jk = 0. The sample's
// visibility v_j is the rank-th largest T_jk over the selected cameras (rank 2: a point counts
// as seen only when two views saw it; 0 when fewer cameras are selected). The pixel's
// visibility is sum_j w_j v_j, volume-rendered with the ray's own weights, so it lies in
// [0, opacity].
//
// Relative measure (flag VIS_RELATIVE): each T_jk is divided by the pixel ray's own
// transmittance T_j in front of sample j and clamped to 1, so v_j asks whether camera k sees
// the sample at least as well as the pixel's camera does. On a sharp surface T_j = 1 where the
// weight is and nothing changes; on a surface the field renders as a semi-transparent shell
// (opaque in sum, but spread in depth) the absolute measure gives sum_j w_j T_j, about half the
// opacity, even from a camera identical to the pixel's, while the relative one gives the
// opacity; an occluder that only camera k looks through still drives T_jk, and v_j, to 0.
// The cut `min_transmittance` then applies to the ratio, so its bound stays the same.
//
// The segment toward a camera starts at the previous sample's position (the near end of the
// sampled range for the first sample), for every camera, and ends at the camera centre, or where it crosses the plane
// where the sampled range starts (NDC t = near; for near 0 the NDC near plane z = -ndc_near,
// beyond which an NDC field is not defined) for forward-facing scenes, or `near` before the
// camera centre for world-space scenes. Starting there, a surface
// that begins between two samples (which the ray's quadrature puts into the second sample's
// alpha, not into its transmittance) does not hide the sample from the cameras: a camera
// identical to the pixel's sees what the ray stops at. The frustum test uses the sample itself.
// The segment is marched in the field's space with `vis_samples` stratum midpoints. Its
// optical depth uses the same unit as a camera ray along the optical axis: world length in
// world space, half the NDC length in NDC (a camera ray's t grows by 1 per 2 NDC
// units of depth). Empty occupancy cells are skipped. The march stops as soon as the
// transmittance can no longer be among the `rank` largest (exact); `min_transmittance` cuts
// it earlier (bounded: a value below the cut counts as 0).
//
// The density comes from the trained field (source 0, common/field_eval.wgsl) or from analytic
// shapes (source 1: spheres and boxes of constant density with a soft edge), in the field's
// space. The analytic source lets tests compare against the f64 reference on scenes whose
// visibility is known in closed form (a sphere before a plane, a wall with a hole).
//
// Two ways to get T_jk:
//   march (volume = 0): the segment march above, exact up to its quadrature;
//   volume (volume = 1): a lookup in camera k's transmittance volume (a deep shadow map), built
//     once per field by `transmittance_volume`: for a grid of vol_w x vol_h rays of camera k
//     (pixel-cell centres) it marches vol_depth strata over the camera's own sampling range
//     and stores T at the vol_depth + 1 stratum boundaries. For a sample inside camera k's
//     frustum, a query projects the point the march would start from (the previous sample)
//     into camera k, finds its sampling
//     parameter s along k's ray (NDC: t = 1 + ndc_near / z for world depth z, the same for
//     every camera; world space: depth along k's axis, then disparity), interpolates
//     bilinearly across rays and takes T at the near boundary of the stratum holding s. Like
//     a camera ray's T_j it leaves out that stratum's own density, so a surface does not
//     shadow itself (the shadow-map bias): at most one stratum in front of the point is
//     ignored. The cost no longer grows with
//     the segment length; the
//     volume's resolution sets the error (measured by `extranerf bench visibility`).
//
// Output per pixel: (visibility, opacity, depth, density evaluations or volume lookups of the
// cameras' transmittances).
//!include common/dispatch.wgsl
//!include common/heads.wgsl
//!include common/camera.wgsl
//!include common/contract.wgsl
//!include common/hash_grid.wgsl
//!include common/mlp.wgsl
//!include common/mlp_block.wgsl
//!include common/occupancy.wgsl
//!include common/volume.wgsl
//!include common/field_eval.wgsl

// Largest supported rank.
const MAX_RANK: u32 = 8u;

struct Params {
    // Pixels in this dispatch.
    n: u32,
    // Samples per camera ray and per segment toward a training camera.
    samples: u32,
    vis_samples: u32,
    // 0: linear in t, 1: linear in disparity.
    spacing: u32,
    // Bit 0: the field lives in NDC (near plane at `ndc_near`); bit 1: the density is
    // `n_shapes` analytic shapes, not the trained field; bit 2: look transmittances up in the
    // volume (its size per camera below); bit 3: the relative measure; bit 4: the samples of
    // each pixel's ray are given (`given_t_dt`).
    flags: u32,
    near: f32,
    far: f32,
    ndc_near: f32,
    contraction: u32,
    inv_radius: f32,
    occ_res: u32,
    occ_cascades: u32,
    levels: u32,
    features: u32,
    min_weight: f32,
    min_transmittance: f32,
    // Scene centre (xyz).
    center: vec4<f32>,
    // Cameras of the pixels, training cameras, and the bitmask of training cameras used.
    n_cameras: u32,
    n_train: u32,
    train_mask: u32,
    rank: u32,
    n_shapes: u32,
    vol_w: u32,
    vol_h: u32,
    vol_depth: u32,
    // (0, 1, 2, 3): the identity table of common/mlp_block.wgsl's mlp_uni.
    lut: vec4<u32>,
}
var<immediate> params: Params;

// The strata's spacing, for common/field_eval.wgsl's t_of.
fn sample_spacing() -> u32 {
    return params.spacing;
}

// Bits of params.flags (render/visibility.rs has the host twins).
const VIS_NDC: u32 = 1u;
const VIS_ANALYTIC: u32 = 2u;
const VIS_VOLUME: u32 = 4u;
const VIS_RELATIVE: u32 = 8u;
const VIS_GIVEN: u32 = 16u;

// Whether the field lives in NDC.
fn in_ndc() -> bool {
    return (params.flags & VIS_NDC) != 0u;
}

@group(0) @binding(0) var<storage, read> cameras: array<GpuCamera>;
// (camera, pixel = y * width + x) per thread.
@group(0) @binding(1) var<storage, read> pixels: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> train_cams: array<GpuCamera>;
@group(0) @binding(3) var<storage, read> level_info: array<HashLevel>;
@group(0) @binding(4) var<storage, read> table: array<f32>;
@group(0) @binding(5) var<storage, read> density_shape: array<MlpShape>;
@group(0) @binding(6) var<storage, read> occ_bits: array<u32>;
// Per shape three vec4s: (kind, sigma, soft edge width, unused), a, b. Kind 0: sphere with
// centre a.xyz and radius b.x; kind 1: box from a.xyz to b.xyz.
@group(0) @binding(7) var<storage, read> shapes: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> out_vis: array<vec4<f32>>;
@group(0) @binding(9) var<uniform> mlp: array<vec4<f32>, 4096>;
// Transmittance volumes, camera-major, then row, column, stratum boundary (vol_depth + 1).
@group(0) @binding(10) var<storage, read_write> tvol: array<f32>;
// The second part of a split hash table (common/hash_grid.wgsl).
@group(0) @binding(11) var<storage, read> table_hi: array<f32>;
// With VIS_GIVEN: (t, dt) of sample j of pixel i at i * samples + j, sorted along the ray.
@group(0) @binding(12) var<storage, read> given_t_dt: array<vec2<f32>>;

// Fraction of a soft edge at signed distance `inside` (positive inside) for edge width `soft`.
fn edge(inside: f32, soft: f32) -> f32 {
    if soft <= 0.0 {
        return select(0.0, 1.0, inside >= 0.0);
    }
    return clamp(inside / soft + 0.5, 0.0, 1.0);
}

fn analytic_density(x: vec3<f32>) -> f32 {
    var sigma = 0.0;
    for (var s = 0u; s < params.n_shapes; s += 1u) {
        let h = shapes[3u * s];
        let a = shapes[3u * s + 1u].xyz;
        let b = shapes[3u * s + 2u].xyz;
        var f = 0.0;
        if h.x == 0.0 {
            f = edge(b.x - length(x - a), h.z);
        } else {
            let lo = x - a;
            let hi = b - x;
            f = edge(lo.x, h.z) * edge(lo.y, h.z) * edge(lo.z, h.z) * edge(hi.x, h.z) * edge(hi.y, h.z) * edge(hi.z, h.z);
        }
        sigma += h.y * f;
    }
    return sigma;
}

// Density at a point of the field's space (NDC or world), skipping empty occupancy cells.
fn density(x: vec3<f32>, a: ptr<function, Act>) -> f32 {
    let u = (x - params.center.xyz) * params.inv_radius;
    if !occupied(u) {
        return 0.0;
    }
    if (params.flags & VIS_ANALYTIC) != 0u {
        return analytic_density(x);
    }
    return density_at(u, a);
}

// World position of a point of the field's space, using the NDC frame of camera `cam`.
fn to_world(x: vec3<f32>, cam: GpuCamera) -> vec3<f32> {
    if !in_ndc() {
        return x;
    }
    let a = ndc_scale(cam);
    let z = 2.0 * params.ndc_near / (x.z - 1.0);
    return vec3<f32>(x.x * z / a.x, x.y * z / a.y, z);
}

fn to_field(p: vec3<f32>, cam: GpuCamera) -> vec3<f32> {
    if !in_ndc() {
        return p;
    }
    let a = ndc_scale(cam);
    return vec3<f32>(a.x * p.x / p.z, a.y * p.y / p.z, 1.0 + 2.0 * params.ndc_near / p.z);
}

// True when world point p is in front of camera c and projects inside its image.
fn in_frustum(p: vec3<f32>, c: GpuCamera) -> bool {
    return in_image(project_point(p, c), c);
}

// Sampling parameter s in [0, 1] of camera rays (inverse of t_of) for distance t.
fn s_of(t: f32) -> f32 {
    if params.spacing == 1u {
        return (1.0 / t - 1.0 / params.near) / (1.0 / params.far - 1.0 / params.near);
    }
    return (t - params.near) / (params.far - params.near);
}

// Camera k's transmittance to world point p from its volume; 0 when the sample `at` is
// outside its frustum (p, the previous sample, may project just outside: it is clamped).
fn volume_lookup(k: u32, p: vec3<f32>, at: vec3<f32>) -> f32 {
    let c = train_cams[k];
    if !in_frustum(at, c) {
        return 0.0;
    }
    let q = project_point(p, c);
    if !(q.z > 0.0) {
        return 1.0;
    }
    var t = q.z;
    if in_ndc() {
        t = 1.0 + params.ndc_near / p.z;
    }
    let s = clamp(s_of(t), 0.0, 1.0);
    let w = params.vol_w;
    let h = params.vol_h;
    let d = params.vol_depth;
    let fx = clamp(q.x / f32(c.size.x) * f32(w) - 0.5, 0.0, f32(w - 1u));
    let fy = clamp(q.y / f32(c.size.y) * f32(h) - 0.5, 0.0, f32(h - 1u));
    // The stratum holding s; its near boundary's T (exclusive of its own density).
    let z0 = min(u32(s * f32(d)), d - 1u);
    let x0 = min(u32(fx), w - 1u);
    let y0 = min(u32(fy), h - 1u);
    let x1 = min(x0 + 1u, w - 1u);
    let y1 = min(y0 + 1u, h - 1u);
    let ax = fx - f32(x0);
    let ay = fy - f32(y0);
    let base = k * w * h;
    let v00 = tvol[((base + y0 * w + x0) * (d + 1u)) + z0];
    let v01 = tvol[((base + y0 * w + x1) * (d + 1u)) + z0];
    let v10 = tvol[((base + y1 * w + x0) * (d + 1u)) + z0];
    let v11 = tvol[((base + y1 * w + x1) * (d + 1u)) + z0];
    return mix(mix(v00, v01, ax), mix(v10, v11, ax), ay);
}

// Transmittance from field point x (world position p) to the centre of training camera c;
// stops (returning 0) once it is at most `floor`. `frame` is the camera whose NDC frame the
// field point is in.
fn transmittance(x: vec3<f32>, p: vec3<f32>, c: GpuCamera, frame: GpuCamera, floor: f32,
                 a: ptr<function, Act>, evals: ptr<function, f32>) -> f32 {
    let centre = camera_centre(c);
    var end = centre;
    var scale = 1.0;
    if in_ndc() {
        // Clip where the sampled range starts, the plane of NDC t = near: world z =
        // -ndc_near / (1 - near), the NDC near plane itself for near 0 (the camera centres
        // lie behind it). Nearer than that no training ray has a sample, so the field there
        // is untrained.
        let zn = -params.ndc_near / (1.0 - params.near);
        if centre.z > zn {
            let s = (zn - p.z) / (centre.z - p.z);
            end = p + s * (centre - p);
            end.z = zn;
        }
        end = to_field(end, frame);
        scale = 0.5;
    } else {
        let len = length(centre - p);
        if len <= params.near {
            return 1.0;
        }
        end = p + (centre - p) * ((len - params.near) / len);
    }
    let seg = end - x;
    let len = length(seg);
    if !(len > 0.0) {
        return 1.0;
    }
    let dir = seg / len;
    let step = len / f32(params.vis_samples);
    let dt = step * scale;
    var tau = 0.0;
    let stop = -log(max(floor, 1e-30));
    for (var m = 0u; m < params.vis_samples; m += 1u) {
        let y = x + dir * ((f32(m) + 0.5) * step);
        tau += optical_depth(density(y, a), dt);
        *evals += 1.0;
        if tau >= stop {
            return 0.0;
        }
    }
    return exp(-tau);
}

@compute @workgroup_size(64)
fn visibility_map(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let pc = pixels[i];
    if pc.x >= params.n_cameras {
        out_vis[i] = vec4<f32>(0.0);
        return;
    }
    let cam = cameras[pc.x];
    if pc.y >= cam.size.x * cam.size.y {
        out_vis[i] = vec4<f32>(0.0);
        return;
    }
    let world = camera_ray(cam, pixel_centre(cam, pc.y));
    var ray = world;
    if in_ndc() {
        ray = ndc_ray(cam, world[0], world[1], params.ndc_near);
    }
    let inv_k = 1.0 / f32(params.samples);
    let rank = min(params.rank, MAX_RANK);
    let n_train = min(params.n_train, 32u);
    var tau = 0.0;
    var vis = 0.0;
    var depth = 0.0;
    var opacity = 0.0;
    var evals = 0.0;
    var a: Act;
    let given = (params.flags & VIS_GIVEN) != 0u;
    for (var j = 0u; j < params.samples; j += 1u) {
        var t: f32;
        var dt: f32;
        // Where the previous sample was (the near end for the first).
        var t_prev = t_of(0.0);
        if given {
            let td = given_t_dt[i * params.samples + j];
            t = td.x;
            dt = td.y;
            if j > 0u {
                t_prev = given_t_dt[i * params.samples + j - 1u].x;
            }
        } else {
            let s0 = f32(j) * inv_k;
            let s1 = f32(j + 1u) * inv_k;
            t = t_of(mix(s0, s1, 0.5));
            dt = t_of(s1) - t_of(s0);
            if j > 0u {
                t_prev = t_of(s0 - 0.5 * inv_k);
            }
        }
        let x = ray[0] + t * ray[1];
        // The relative measure's unit: the ray's own transmittance in front of the sample.
        var t_own = 1.0;
        if (params.flags & VIS_RELATIVE) != 0u {
            t_own = exp(-tau);
        }
        let w = next_weight(density(x, &a), dt, &tau);
        depth += w * t;
        opacity += w;
        if !(w > params.min_weight) || rank == 0u {
            continue;
        }
        let p = to_world(x, cam);
        let x_prev = ray[0] + t_prev * ray[1];
        let p_prev = to_world(x_prev, cam);
        // A sample at the far end of an NDC ray (z' = 1) has no finite world position.
        if !all(abs(p) < vec3<f32>(3.0e38)) || !all(abs(p_prev) < vec3<f32>(3.0e38)) {
            continue;
        }
        // The `rank` largest transmittances so far, in decreasing order.
        var top: array<f32, 8>;
        for (var r = 0u; r < MAX_RANK; r += 1u) {
            top[r] = 0.0;
        }
        for (var k = 0u; k < n_train; k += 1u) {
            if ((params.train_mask >> k) & 1u) == 0u {
                continue;
            }
            var tr = 0.0;
            if (params.flags & VIS_VOLUME) != 0u {
                tr = volume_lookup(k, p_prev, p);
                evals += 1.0;
                if tr < params.min_transmittance * t_own {
                    tr = 0.0;
                }
                tr = min(tr / t_own, 1.0);
            } else {
                let c = train_cams[k];
                if !in_frustum(p, c) {
                    continue;
                }
                // A transmittance at or below the current rank-th value cannot change the
                // result.
                let floor = max(top[rank - 1u], params.min_transmittance) * t_own;
                tr = min(transmittance(x_prev, p_prev, c, cam, floor, &a, &evals) / t_own, 1.0);
            }
            if tr <= top[rank - 1u] {
                continue;
            }
            // Insert, keeping the order.
            var v = tr;
            for (var r = 0u; r < rank; r += 1u) {
                if v > top[r] {
                    let o = top[r];
                    top[r] = v;
                    v = o;
                }
            }
        }
        vis += w * top[rank - 1u];
    }
    out_vis[i] = vec4<f32>(vis, opacity, depth, evals);
}

// Builds the transmittance volumes: one thread per (camera, row, column) ray of the vol_w x
// vol_h grid over each training camera's image (cell centres). The ray is camera k's own (in
// its NDC frame for forward-facing scenes), marched over vol_depth strata of its sampling
// range with the density at each stratum's midpoint; T at every boundary is stored.
@compute @workgroup_size(64)
fn transmittance_volume(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                        @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let w = params.vol_w;
    let h = params.vol_h;
    let d = params.vol_depth;
    let k = i / (w * h);
    let cell = i % (w * h);
    let c = train_cams[k];
    let px = vec2<f32>((f32(cell % w) + 0.5) / f32(w) * f32(c.size.x), (f32(cell / w) + 0.5) / f32(h) * f32(c.size.y));
    let world = camera_ray(c, px);
    var ray = world;
    if in_ndc() {
        ray = ndc_ray(c, world[0], world[1], params.ndc_near);
    }
    let inv_d = 1.0 / f32(d);
    let base = i * (d + 1u);
    var tau = 0.0;
    var a: Act;
    tvol[base] = 1.0;
    for (var m = 0u; m < d; m += 1u) {
        let s0 = f32(m) * inv_d;
        let s1 = f32(m + 1u) * inv_d;
        let t = t_of(mix(s0, s1, 0.5));
        let dt = t_of(s1) - t_of(s0);
        tau += optical_depth(density(ray[0] + t * ray[1], &a), dt);
        tvol[base + m + 1u] = exp(-tau);
    }
}
