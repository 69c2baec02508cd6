// Plane-sweep multi-view stereo for the input views (a depth prior without SPARF).
//
// `mvs_sweep`: one thread per pixel of the reference view. For each of `planes` fronto-parallel
// planes of the reference camera (uniform in inverse depth between near and far) it warps the
// (2 radius + 1)^2 window around the pixel into every selected source view through that plane
// (the neighbour pixel's ray at the same depth, projected into the source; bilinear samples of
// the source's grey image), and scores it by zero-mean normalised cross-correlation with the
// reference window: cost = 1 - NCC in [0, 2]. A source that sees any warped sample outside its
// image, or behind it, does not vote on that plane. The plane's cost is the mean of the
// `best_k` lowest source costs (robust to occlusion; 2 when fewer sources vote). The cost
// volume is swept in registers: winner-take-all keeps the lowest cost and its two neighbours,
// and a parabola through them refines the inverse depth within half a plane. Output: depth
// along the viewing axis (0: no match), confidence = the winning NCC clamped to [0, 1] (0 for
// a textureless window, whose NCC is undefined).
//
// `mvs_consistency`: one thread per reference pixel. Its 3-D point is projected into each
// selected source, which reads its own depth at the nearest pixel, lifts that back to 3-D and
// projects it into the reference; the source agrees when that lands within `px_tol` pixels and
// `rel_tol` relative depth. Pixels with fewer than `min_agree` agreeing sources get depth and
// confidence 0.
//
// Views are stored view-major, row-major, all width x height.
//!include common/dispatch.wgsl
//!include common/camera.wgsl

// Largest window radius (7 x 7).
const MAX_RADIUS: u32 = 3u;

struct Params {
    n: u32,
    width: u32,
    height: u32,
    ref_view: u32,
    src_mask: u32,
    n_views: u32,
    planes: u32,
    radius: u32,
    near: f32,
    far: f32,
    best_k: u32,
    min_agree: u32,
    px_tol: f32,
    rel_tol: f32,
    _pad0: u32,
    _pad1: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> cams: array<GpuCamera>;
@group(0) @binding(1) var<storage, read> grey: array<f32>;
// Per view: winner-take-all depth and confidence (written by the sweep for the reference view).
@group(0) @binding(2) var<storage, read_write> depths: array<f32>;
@group(0) @binding(3) var<storage, read_write> confs: array<f32>;
// Per view: the depth and confidence the consistency check keeps.
@group(0) @binding(4) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(5) var<storage, read_write> out_conf: array<f32>;

fn ray_dir(c: GpuCamera, px: vec2<f32>) -> vec3<f32> {
    return camera_ray(c, px)[1];
}

// Bilinear sample of view v's grey image at pixel coordinates q (centres at +0.5), clamped
// to the edge.
fn sample(v: u32, q: vec2<f32>) -> f32 {
    let w = params.width;
    let h = params.height;
    let f = clamp(q - 0.5, vec2<f32>(0.0), vec2<f32>(f32(w - 1u), f32(h - 1u)));
    let x0 = min(u32(f.x), w - 1u);
    let y0 = min(u32(f.y), h - 1u);
    let x1 = min(x0 + 1u, w - 1u);
    let y1 = min(y0 + 1u, h - 1u);
    let a = f - vec2<f32>(f32(x0), f32(y0));
    let base = v * w * h;
    let top = mix(grey[base + y0 * w + x0], grey[base + y0 * w + x1], a.x);
    let bottom = mix(grey[base + y1 * w + x0], grey[base + y1 * w + x1], a.x);
    return mix(top, bottom, a.y);
}

fn plane_depth(m: f32) -> f32 {
    let s = m / max(f32(params.planes) - 1.0, 1.0);
    return 1.0 / mix(1.0 / params.near, 1.0 / params.far, s);
}

@compute @workgroup_size(64)
fn mvs_sweep(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let w = params.width;
    let h = params.height;
    let r = i32(min(params.radius, MAX_RADIUS));
    let side = 2 * r + 1;
    let count = f32(side * side);
    let x = i32(i % w);
    let y = i32(i / w);
    let ref_cam = cams[params.ref_view];
    let o = camera_centre(ref_cam);
    let out = params.ref_view * w * h + i;
    // The reference window (clamped at the border), its mean and spread.
    var win: array<f32, 49>;
    var dirs: array<vec3<f32>, 49>;
    var sa = 0.0;
    var saa = 0.0;
    for (var k = 0; k < side * side; k += 1) {
        let qx = clamp(x + k % side - r, 0, i32(w) - 1);
        let qy = clamp(y + k / side - r, 0, i32(h) - 1);
        let g = grey[params.ref_view * w * h + u32(qy) * w + u32(qx)];
        win[k] = g;
        sa += g;
        saa += g * g;
        dirs[k] = ray_dir(ref_cam, vec2<f32>(f32(qx) + 0.5, f32(qy) + 0.5));
    }
    let var_a = saa - sa * sa / count;
    if !(var_a > 1e-6 * count) {
        depths[out] = 0.0;
        confs[out] = 0.0;
        return;
    }
    var best = 3.0;
    var best_m = 0u;
    var c_before = 3.0;
    var c_after = 3.0;
    var c_prev = 3.0;
    let k_best = max(params.best_k, 1u);
    for (var m = 0u; m < params.planes; m += 1u) {
        let d = plane_depth(f32(m));
        // The k_best lowest source costs, in increasing order (at most 8 kept).
        var low: array<f32, 8>;
        for (var j = 0u; j < 8u; j += 1u) {
            low[j] = 3.0;
        }
        var voters = 0u;
        for (var s = 0u; s < params.n_views; s += 1u) {
            if ((params.src_mask >> s) & 1u) == 0u || s == params.ref_view {
                continue;
            }
            let sc = cams[s];
            var sb = 0.0;
            var sbb = 0.0;
            var sab = 0.0;
            var ok = true;
            for (var k = 0; k < side * side; k += 1) {
                let q = project_point(o + d * dirs[k], sc);
                if !in_image(q, sc) {
                    ok = false;
                    break;
                }
                let b = sample(s, q.xy);
                sb += b;
                sbb += b * b;
                sab += win[k] * b;
            }
            if !ok {
                continue;
            }
            let var_b = sbb - sb * sb / count;
            let cov = sab - sa * sb / count;
            var ncc = -1.0;
            if var_b > 1e-6 * count {
                ncc = clamp(cov / sqrt(var_a * var_b), -1.0, 1.0);
            }
            var v = 1.0 - ncc;
            voters += 1u;
            for (var j = 0u; j < min(k_best, 8u); j += 1u) {
                if v < low[j] {
                    let t = low[j];
                    low[j] = v;
                    v = t;
                }
            }
        }
        var cost = 2.0;
        if voters >= k_best {
            var sum = 0.0;
            for (var j = 0u; j < min(k_best, 8u); j += 1u) {
                sum += low[j];
            }
            cost = sum / f32(min(k_best, 8u));
        }
        if m == best_m + 1u {
            c_after = cost;
        }
        if cost < best {
            best = cost;
            best_m = m;
            c_before = c_prev;
            c_after = 3.0;
        }
        c_prev = cost;
    }
    if best >= 2.0 {
        depths[out] = 0.0;
        confs[out] = 0.0;
        return;
    }
    // Parabola through the winner and its neighbours, in plane index (inverse depth).
    var delta = 0.0;
    if c_before < 3.0 && c_after < 3.0 {
        let den = c_before - 2.0 * best + c_after;
        if den > 1e-12 {
            delta = clamp(0.5 * (c_before - c_after) / den, -0.5, 0.5);
        }
    }
    depths[out] = plane_depth(f32(best_m) + delta);
    confs[out] = clamp(1.0 - best, 0.0, 1.0);
}

@compute @workgroup_size(64)
fn mvs_consistency(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let w = params.width;
    let h = params.height;
    let at = params.ref_view * w * h + i;
    let d = depths[at];
    out_depth[at] = 0.0;
    out_conf[at] = 0.0;
    if !(d > 0.0) {
        return;
    }
    let ref_cam = cams[params.ref_view];
    let px = vec2<f32>(f32(i % w) + 0.5, f32(i / w) + 0.5);
    let p = camera_centre(ref_cam) + d * ray_dir(ref_cam, px);
    var agree = 0u;
    for (var s = 0u; s < params.n_views; s += 1u) {
        if ((params.src_mask >> s) & 1u) == 0u || s == params.ref_view {
            continue;
        }
        let sc = cams[s];
        let q = project_point(p, sc);
        if !(q.z > 0.0 && q.x >= 0.0 && q.y >= 0.0 && q.x < f32(w) && q.y < f32(h)) {
            continue;
        }
        let sx = min(u32(q.x), w - 1u);
        let sy = min(u32(q.y), h - 1u);
        let ds = depths[s * w * h + sy * w + sx];
        if !(ds > 0.0) {
            continue;
        }
        let ps = camera_centre(sc) + ds * ray_dir(sc, vec2<f32>(f32(sx) + 0.5, f32(sy) + 0.5));
        let back = project_point(ps, ref_cam);
        if !(back.z > 0.0) {
            continue;
        }
        if length(back.xy - px) <= params.px_tol && abs(back.z - d) <= params.rel_tol * d {
            agree += 1u;
        }
    }
    if agree >= params.min_agree {
        out_depth[at] = d;
        out_conf[at] = confs[at];
    }
}
