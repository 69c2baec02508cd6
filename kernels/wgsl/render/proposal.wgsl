// The proposal sampler (Mip-NeRF 360; nerfacto): a small density-only field is evaluated at
// cheap samples along each ray, and its weights decide where the main field's few samples go.
// One thread per ray in both kernels; positions along a ray are its normalised distance s in
// [0, 1] (common/spacing.wgsl's strata_t maps s to t). A ray's source bins are given by their
// src_count + 1 sorted edges in s: src_edges at r * src_stride (src_stride 0: one set of edges
// shared by every ray, as the uniform strata of render/sample.wgsl's `stratified` have), with
// one sample per bin whose density and (t, dt) are src_sigma and src_t_dt at r * src_count.
//
// resample: the source weights w_i (volume rendering of src_sigma over the bins' dt), padded
//   by `pad` per bin, are a piecewise-constant density in s; count + 1 new edges sit at its
//   inverse CDF of u_j = (j + jitter_j) / (count + 1) (jittered as render/sample.wgsl jitters:
//   not on rays with a negative target colour weight) or u_j = j / count (no jitter). The main
//   field's sample j lies at the middle (in s) of the bin between edges j and j + 1, with dt
//   and ds that bin's length in t and s; the kernel writes the edges and the samples as
//   `stratified` writes its own (positions, (t, dt), (s, ds), ray spans). The Rust reference
//   is reference::proposal_resample.
//
// interlevel: Mip-NeRF 360's loss that makes the source weights bound the main field's. For the
//   main bin j, [a, b] with weight w_j (volume rendering of `sigma` over t_dt, held constant),
//   the bound is the summed source weight from the source bin holding a (the count of interior
//   source edges <= a) to the one holding b (the count of interior edges < b), at least one
//   bin; the ray's loss is lambda sum_j max(0, w_j - bound_j)^2 / (w_j + INTERLEVEL_EPS).
//   A source weight's gradient is the sum over the main bins whose bound holds it of
//   -2 lambda max(0, w_j - bound_j) / (w_j + eps), written to d_weight per source sample for
//   composite_bwd's d_weight (which turns it into dL/dsigma of the proposal field), built as a
//   difference array and prefix-summed in place. The Rust reference is reference::interlevel.
//!include common/dispatch.wgsl
//!include common/rng.wgsl
//!include common/spacing.wgsl
//!include common/volume.wgsl

const INTERLEVEL_EPS: f32 = 1e-7;
// Salt of the resampling's jitter seed, so it does not repeat the source strata's jitter.
const RESAMPLE_SALT: u32 = 0x3c6ef372u;

struct Params {
    n_rays: u32,
    // Source bins per ray and main bins (samples) per ray.
    src_count: u32,
    count: u32,
    // Floats between two rays' source edges (0: shared).
    src_stride: u32,
    // resample: 0 linear in t, 1 linear in disparity (render/sample.wgsl's spacing).
    spacing: u32,
    // resample: 0 no jitter; 1 jittered; 2 jittered except on rays with a negative target
    // colour weight.
    jitter: u32,
    seed: u32,
    // resample: the padding added to each source weight; interlevel: lambda (over the batch).
    pad_or_lambda: f32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> src_edges: array<f32>;
@group(0) @binding(1) var<storage, read> src_sigma: array<f32>;
@group(0) @binding(2) var<storage, read> src_t_dt: array<vec2<f32>>;
// resample: the ray origins, directions and (near, far) as render/sample.wgsl reads them, and
// a training batch's target colours (jitter 2; any vec4 buffer of n_rays otherwise, unread).
@group(0) @binding(3) var<storage, read> origins: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> directions: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> near_far: array<vec2<f32>>;
@group(0) @binding(6) var<storage, read> target_rgb: array<vec4<f32>>;
// Per ray count + 1 edges (resample writes them, interlevel reads them).
@group(0) @binding(7) var<storage, read_write> edges: array<f32>;
@group(0) @binding(8) var<storage, read_write> positions: array<f32>;
@group(0) @binding(9) var<storage, read_write> t_dt: array<vec2<f32>>;
@group(0) @binding(10) var<storage, read_write> s_ds: array<vec2<f32>>;
@group(0) @binding(11) var<storage, read_write> rays: array<vec2<u32>>;
// interlevel: the main field's densities per sample, the loss per ray and dL/dw per source
// sample.
@group(0) @binding(12) var<storage, read> sigma: array<f32>;
@group(0) @binding(13) var<storage, read_write> loss: array<f32>;
@group(0) @binding(14) var<storage, read_write> d_weight: array<f32>;

fn src_edge(r: u32, i: u32) -> f32 {
    return src_edges[r * params.src_stride + i];
}

// Optical depth of source bin i of the ray whose first sample is `first`.
fn src_depth(first: u32, i: u32) -> f32 {
    return optical_depth(src_sigma[first + i], src_t_dt[first + i].y);
}

@compute @workgroup_size(64)
fn resample(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let n = params.src_count;
    let k = params.count;
    let pad = params.pad_or_lambda;
    let first = r * n;
    // The histogram's mass: the source weights plus the padding.
    var tau = 0.0;
    var total = 0.0;
    for (var i = 0u; i < n; i += 1u) {
        total += next_weight(src_sigma[first + i], src_t_dt[first + i].y, &tau) + pad;
    }
    let jittered = params.jitter == 1u || (params.jitter == 2u && target_rgb[r].w >= 0.0);
    let seed = params.seed ^ RESAMPLE_SALT;
    let nf = near_far[r];
    let o = origins[r].xyz;
    let d = directions[r].xyz;
    rays[r] = vec2<u32>(r * k, k);
    // Walk the bins once: bin i covers the CDF from c to c + m.
    tau = 0.0;
    var i = 0u;
    var c = 0.0;
    var m = (next_weight(src_sigma[first], src_t_dt[first].y, &tau) + pad) / total;
    var prev = 0.0;
    for (var j = 0u; j <= k; j += 1u) {
        var u = f32(j) / f32(k);
        if jittered {
            u = (f32(j) + strata_jitter(seed, r, j)) / f32(k + 1u);
        }
        while i + 1u < n && c + m <= u {
            c += m;
            i += 1u;
            m = (next_weight(src_sigma[first + i], src_t_dt[first + i].y, &tau) + pad) / total;
        }
        let f = clamp((u - c) / m, 0.0, 1.0);
        let e0 = src_edge(r, i);
        let e = e0 + f * (src_edge(r, i + 1u) - e0);
        edges[r * (k + 1u) + j] = e;
        if j > 0u {
            let idx = r * k + j - 1u;
            let s = 0.5 * (prev + e);
            let t = strata_t(s, nf, params.spacing);
            let p = o + t * d;
            positions[3u * idx] = p.x;
            positions[3u * idx + 1u] = p.y;
            positions[3u * idx + 2u] = p.z;
            t_dt[idx] = vec2<f32>(t, strata_t(e, nf, params.spacing) - strata_t(prev, nf, params.spacing));
            s_ds[idx] = vec2<f32>(s, e - prev);
        }
        prev = e;
    }
}

@compute @workgroup_size(64)
fn interlevel(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let n = params.src_count;
    let k = params.count;
    let lambda = params.pad_or_lambda;
    let first = r * n;
    for (var i = 0u; i < n; i += 1u) {
        d_weight[first + i] = 0.0;
    }
    // lo: the source bin holding a, tau_lo the optical depth before it (it only moves
    // forward). The bound sums the weights from lo on, bin by bin: over a ray the main bins
    // visit about src_count + count source bins in all.
    var lo = 0u;
    var tau_lo = 0.0;
    var tau = 0.0;
    var l = 0.0;
    for (var j = 0u; j < k; j += 1u) {
        let a = edges[r * (k + 1u) + j];
        let b = edges[r * (k + 1u) + j + 1u];
        let w = next_weight(sigma[r * k + j], t_dt[r * k + j].y, &tau);
        while lo + 1u < n && src_edge(r, lo + 1u) <= a {
            tau_lo += src_depth(first, lo);
            lo += 1u;
        }
        // h: one past the last source bin whose interior start edge lies below b.
        var bound = 0.0;
        var tau_h = tau_lo;
        var h = lo;
        loop {
            bound += next_weight(src_sigma[first + h], src_t_dt[first + h].y, &tau_h);
            h += 1u;
            if h >= n || src_edge(r, h) >= b {
                break;
            }
        }
        let excess = max(w - bound, 0.0);
        l += excess * excess / (w + INTERLEVEL_EPS);
        let g = -2.0 * lambda * excess / (w + INTERLEVEL_EPS);
        if g != 0.0 {
            d_weight[first + lo] += g;
            if h < n {
                d_weight[first + h] -= g;
            }
        }
    }
    var acc = 0.0;
    for (var i = 0u; i < n; i += 1u) {
        acc += d_weight[first + i];
        d_weight[first + i] = acc;
    }
    loss[r] = lambda * l;
}
