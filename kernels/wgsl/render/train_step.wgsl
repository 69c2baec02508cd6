// Fused training step: one thread per ray does the whole forward and backward pass between a
// batch pixel and the parameter gradients, except the MLP weight-gradient reduction.
//
//   pass 1 (forward): ray (NDC or world), jittered stratified samples (over the occupied part
//     of the ray when an occupancy grid is given, as render/sample.wgsl), per sample the
//     contraction, every hash-grid level, the density MLP, trunc-exp, SH4 and the colour MLP in
//     registers; compositing, and the O(N) distortion sums.
//   losses: RGB (L2 or Huber) and depth against the batch targets, as render/loss.wgsl; the
//     distortion loss as render/distortion.wgsl (its lambda already divided by the batch).
//   pass 2 (backward): the ray, strata, contraction, grid cells, weights and transmittance
//     again (recomputed, not stored), then the compositing gradient (render/composite.wgsl's,
//     with its suffix sums as the pass-1 totals minus a running prefix; the distortion part of
//     the total is 2 L, the loss being a quadratic form in the weights), gradient scaling,
//     sigmoid and trunc-exp, both MLPs' data gradients, and the hash-grid scatter with f32
//     atomics into d_table.
//
// The MLP weight gradient is a reduction over all samples, so each sample's layer inputs and
// pre-activation gradients go to memory (common/mlp_wgrad.wgsl's record layout) and
// field/mlp.wgsl's mlp_wgrad sums them, as after the standalone mlp_bwd_data. Pass 1 writes
// those records as it runs the MLPs, and pass 2 reads the MLPs' outputs back from them rather
// than running the MLPs again (re-running them was measured slower on lavapipe).
//
// The samples of a ray go through the MLPs MLP_GROUP at a time (common/mlp_block.wgsl's
// register blocking), then through compositing one by one in order. Slots past the last
// sample repeat it and are ignored: they write no record, no colour and no gradient.
//
// Layouts: common/hash_grid.wgsl (levels, table, split tables), common/mlp.wgsl (weights per
// layer W then b), the uniform block of common/mlp_block.wgsl with the density MLP at 0 and the
// colour MLP at params.color_base. The standalone chain computes the same quantities:
// render/{batch,rays,sample}.wgsl, field/*, render/{field_heads,composite,loss,distortion}.wgsl.
//!include common/dispatch.wgsl
//!include common/heads.wgsl
//!include common/camera.wgsl
//!include common/contract.wgsl
//!include common/hash_grid.wgsl
//!include common/mlp.wgsl
//!include common/mlp_block.wgsl
//!include common/occupancy.wgsl
//!include common/rng.wgsl
//!include common/strata.wgsl
//!include common/sh.wgsl
//!include common/volume.wgsl
//!include common/field_eval.wgsl
//!include common/ray_loss.wgsl

struct Params {
    // Rays in the batch.
    n: u32,
    // Samples per ray.
    samples: u32,
    // 0: linear in t, 1: linear in disparity.
    spacing: u32,
    near: f32,
    far: f32,
    // NDC's near plane (with flag bit 2).
    ndc_near: f32,
    // Contraction mode (common/contract.wgsl) and 1 / scene radius.
    contraction: u32,
    inv_radius: f32,
    // Hash-grid levels and features per level.
    levels: u32,
    features: u32,
    // Seed of the strata's jitter (render/sample.wgsl's) and of random backgrounds.
    seed: u32,
    // Bit 0: jitter the strata (else samples sit at midpoints); bit 1: each ray's background
    // is random (common/rng.wgsl's ray_background from `seed`), not `background.xyz`; bit 2:
    // march in NDC; bit 3: Huber photometric loss (else L2); bit 4: Floaters No More gradient
    // scaling, min(1, t^2) per sample.
    flags: u32,
    n_cameras: u32,
    // Float offset of the colour MLP in the uniform weight block.
    color_base: u32,
    // Distortion-loss weight over the batch size (0: off).
    dist_lambda: f32,
    // Floats per sample of the density and colour MLP records.
    density_stride: u32,
    // Scene centre (xyz); w: the Huber threshold.
    center: vec4<f32>,
    // Background colour (xyz); w: the depth-loss weight.
    background: vec4<f32>,
    color_stride: u32,
    // The occupancy grid (occ_cascades 0: none) and the probe intervals per ray: with a grid
    // the strata cover only the intervals whose centres lie in occupied cells, as
    // render/sample.wgsl's stratified_occupied places them (common/strata.wgsl).
    probes: u32,
    occ_res: u32,
    occ_cascades: u32,
    // (0, 1, 2, 3): the identity table of common/mlp_block.wgsl's mlp_uni.
    lut: vec4<u32>,
}
var<immediate> params: Params;

// Bits of params.flags (render/train_step.rs has the host twins).
const STEP_JITTER: u32 = 1u;
const STEP_RANDOM_BG: u32 = 2u;
const STEP_NDC: u32 = 4u;
const STEP_HUBER: u32 = 8u;
const STEP_GRAD_SCALING: u32 = 16u;

@group(0) @binding(0) var<storage, read> cameras: array<GpuCamera>;
// (camera, pixel = y * width + x) per ray.
@group(0) @binding(1) var<storage, read> pixels: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> level_info: array<HashLevel>;
@group(0) @binding(3) var<storage, read> table: array<f32>;
@group(0) @binding(4) var<storage, read> density_shape: array<MlpShape>;
@group(0) @binding(5) var<storage, read> color_shape: array<MlpShape>;
// Targets per ray: colour (rgb, unused) and depth with its confidence (0: none).
@group(0) @binding(6) var<storage, read> target_rgb: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> target_depth: array<vec2<f32>>;
@group(0) @binding(8) var<storage, read> occ_bits: array<u32>;
// Per ray: (rgb, opacity), expected depth, photometric + depth loss (over the batch), squared
// colour error (mean of the channels) and distortion loss.
@group(0) @binding(9) var<storage, read_write> out_rgba: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(11) var<storage, read_write> loss: array<f32>;
@group(0) @binding(12) var<uniform> mlp: array<vec4<f32>, 4096>;
@group(0) @binding(13) var<storage, read> table_hi: array<f32>;
@group(0) @binding(14) var<storage, read_write> mse: array<f32>;
@group(0) @binding(15) var<storage, read_write> dist_loss: array<f32>;
// The hash table's gradient (both parts of a split table), added to with atomics.
@group(0) @binding(16) var<storage, read_write> d_table: array<atomic<f32>>;
@group(0) @binding(17) var<storage, read_write> d_table_hi: array<atomic<f32>>;
// Per sample s = ray * samples + j: the density MLP's record at float s * density_stride and
// the colour MLP's at s * color_stride. Both strides and every segment of a record are
// multiples of 4 floats, so the records are read and written as vec4s: on lavapipe each access
// at a varying address is a loop over the lanes, and a vec4 costs about what one float does.
@group(0) @binding(18) var<storage, read_write> saved_density: array<vec4<f32>>;
@group(0) @binding(19) var<storage, read_write> saved_color: array<vec4<f32>>;

// The vec4 at float e (a multiple of 4) of the colour (or density) MLP's records; a branch, so
// each binding is only indexed within its own range.
fn rec_set(color: bool, e: u32, v: vec4<f32>) {
    if color {
        saved_color[e >> 2u] = v;
    } else {
        saved_density[e >> 2u] = v;
    }
}

fn rec_get(color: bool, e: u32) -> vec4<f32> {
    if color {
        return saved_color[e >> 2u];
    }
    return saved_density[e >> 2u];
}

// v with the entries at 4 j4 + c >= n zeroed (the padding of a record segment n wide).
fn below(v: vec4<f32>, j4: u32, n: u32) -> vec4<f32> {
    return select(vec4<f32>(0.0), v, vec4<u32>(4u * j4) + vec4<u32>(0u, 1u, 2u, 3u) < vec4<u32>(n));
}

// The forward pass of MLP `s` (weights at float `base` of the block) on the group a, writing
// each valid slot's layer inputs and its output layer's pre-activations into its record at at[k]
// (mlp_bwd_data's layout; the hidden layers' pre-activation segments are left for the backward
// pass to fill with their gradients).
fn forward_recorded(color: bool, s: MlpShape, base: u32, at_in: vec4<u32>, valid: vec4<bool>,
                    a: ptr<function, ActGroup>) {
    var z: ActGroup;
    var at = at_in;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        for (var k = 0u; k < MLP_GROUP; k += 1u) {
            if valid[k] {
                for (var j4 = 0u; 4u * j4 < ni; j4 += 1u) {
                    rec_set(color, at[k] + 4u * j4, below((*a)[k][j4], j4, ni));
                }
            }
        }
        at += vec4<u32>(pad4(ni));
        mlp_layer_group(base + mlp_offset(s, l), ni, no, a, &z);
        // Only the output layer's pre-activations are stored: a hidden layer's are read back
        // as the next layer's input, their ReLU, which is positive exactly where they are.
        if l + 1u == s.layers {
            for (var k = 0u; k < MLP_GROUP; k += 1u) {
                if valid[k] {
                    for (var o4 = 0u; 4u * o4 < no; o4 += 1u) {
                        rec_set(color, at[k] + 4u * o4, below(z[k][o4], o4, no));
                    }
                }
            }
        }
        at += vec4<u32>(pad4(no));
        mlp_activate_group(&z, a, l + 1u < s.layers);
    }
}

// Back-propagates g[k] (dL/d output) through MLP `s` after forward_recorded at at_in: g[k]
// becomes dL/d input, and each valid record's pre-activation segments hold their gradients
// (ReLU' on hidden layers). Invalid slots must come in with g[k] = 0.
fn backward_recorded(color: bool, s: MlpShape, base: u32, at_in: vec4<u32>, valid: vec4<bool>,
                     g: ptr<function, ActGroup>) {
    var z: ActGroup;
    var at = at_in;
    for (var l = 0u; l < s.layers; l += 1u) {
        at += vec4<u32>(pad4(mlp_dim(s, l)) + pad4(mlp_dim(s, l + 1u)));
    }
    for (var li = 0u; li < s.layers; li += 1u) {
        let l = s.layers - 1u - li;
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        at -= vec4<u32>(pad4(no));
        let last = l + 1u == s.layers;
        for (var k = 0u; k < MLP_GROUP; k += 1u) {
            for (var q = 0u; q < 16u; q += 1u) {
                z[k][q] = vec4<f32>(0.0);
            }
            if valid[k] {
                for (var o4 = 0u; 4u * o4 < no; o4 += 1u) {
                    let go = (*g)[k][o4];
                    // ReLU' of a hidden layer from the next layer's input (its ReLU); the
                    // output layer passes go through (its own pre-activations are read).
                    let act = rec_get(color, select(at[k] + pad4(no), at[k], last) + 4u * o4);
                    let d = below(select(select(vec4<f32>(0.0), go, act > vec4<f32>(0.0)), go, last),
                                  o4, no);
                    rec_set(color, at[k] + 4u * o4, d);
                    z[k][o4] = d;
                }
            }
        }
        at -= vec4<u32>(pad4(ni));
        mlp_layer_back_group(base + mlp_offset(s, l), ni, no, &z, g);
    }
}

// Float offset, within a record, of the last layer's pre-activations (the MLP's output).
fn output_at(s: MlpShape) -> u32 {
    var at = 0u;
    for (var l = 0u; l < s.layers; l += 1u) {
        at += pad4(mlp_dim(s, l));
        if l + 1u < s.layers {
            at += pad4(mlp_dim(s, l + 1u));
        }
    }
    return at;
}

// A record of zeros (words a multiple of 4), so the weight-gradient pass adds nothing for this
// sample.
fn zero_record(color: bool, at: u32, words: u32) {
    for (var k = 0u; k < words; k += 4u) {
        rec_set(color, at + k, vec4<f32>(0.0));
    }
}

fn scatter(hi: bool, e: u32, v: f32) {
    if v == 0.0 {
        return;
    }
    if hi {
        atomicAdd(&d_table_hi[e], v);
        return;
    }
    atomicAdd(&d_table[e], v);
}

// Adds d_enc (dL/d features, levels * features) of the contracted point x to d_table.
fn encode_backward(x: vec3<f32>, d_enc: ptr<function, Act>) {
    if !hg_valid(x) {
        return;
    }
    let F = params.features;
    for (var l = 0u; l < params.levels; l += 1u) {
        let lv = level_info[l];
        let cell = hg_cell(x, lv);
        let hi = hg_part(lv) != 0u;
        for (var k = 0u; k < 8u; k += 1u) {
            let wk = hg_weight(cell.frac, k);
            let e = lv.offset + hg_index(hg_corner(cell.corner, k), lv) * F;
            for (var f = 0u; f < F; f += 1u) {
                scatter(hi, e + f, wk * act_get(d_enc, l * F + f));
            }
        }
    }
}

// The stratum of sample j: (t, dt, s) with s the jittered normalised position; with an
// occupancy grid, spread over the ray's occupied probe intervals `mask`.
fn stratum(ray: u32, j: u32, mask: ptr<function, ProbeMask>) -> vec3<f32> {
    var jit = 0.5;
    if (params.flags & STEP_JITTER) != 0u {
        jit = strata_jitter(params.seed, ray, j);
    }
    let nf = vec2<f32>(params.near, params.far);
    if params.occ_cascades != 0u {
        return occupied_stratum(mask, j, params.samples, jit, params.probes, nf, params.spacing);
    }
    return ray_stratum(j, params.samples, jit, nf, params.spacing);
}

// The samples of group gi of ray i: validity, record offsets (density, colour), strata
// (t, dt, s) and scene-normalised points. Slots past the last sample repeat it.
struct Slots {
    valid: vec4<bool>,
    rd: vec4<u32>,
    rc: vec4<u32>,
    st: array<vec3<f32>, 4>,
    u: array<vec3<f32>, 4>,
}

fn group_slots(i: u32, gi: u32, ray: array<vec3<f32>, 2>, mask: ptr<function, ProbeMask>) -> Slots {
    let k = params.samples;
    var sl: Slots;
    for (var q = 0u; q < MLP_GROUP; q += 1u) {
        let j = gi * MLP_GROUP + q;
        sl.valid[q] = j < k;
        let jj = min(j, k - 1u);
        sl.rd[q] = (i * k + jj) * params.density_stride;
        sl.rc[q] = (i * k + jj) * params.color_stride;
        sl.st[q] = stratum(i, jj, mask);
        sl.u[q] = scene_point(ray, sl.st[q].x);
    }
    return sl;
}

@compute @workgroup_size(64)
fn train_step(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let k = params.samples;
    let pc = pixels[i];
    var valid = pc.x < params.n_cameras;
    var cam: GpuCamera;
    if valid {
        cam = cameras[pc.x];
        valid = pc.y < cam.size.x * cam.size.y;
    }
    // Out-of-range camera or pixel indices: a zero pixel, no loss and no gradient.
    if !valid {
        out_rgba[i] = vec4<f32>(0.0);
        out_depth[i] = 0.0;
        loss[i] = 0.0;
        mse[i] = 0.0;
        dist_loss[i] = 0.0;
        for (var j = 0u; j < k; j += 1u) {
            zero_record(false, (i * k + j) * params.density_stride, params.density_stride);
            zero_record(true, (i * k + j) * params.color_stride, params.color_stride);
        }
        return;
    }
    let world = camera_ray(cam, pixel_centre(cam, pc.y));
    var ray = world;
    if (params.flags & STEP_NDC) != 0u {
        ray = ndc_ray(cam, world[0], world[1], params.ndc_near);
    }
    let sh = sh4(unit_dir(world[1]));
    // The occupied probe intervals (with a grid) and each stratum's share of s.
    var mask: ProbeMask;
    var ds = 1.0 / f32(k);
    if params.occ_cascades != 0u {
        mask = probe_mask(ray[0], ray[1], vec2<f32>(params.near, params.far), params.spacing,
                          params.probes, vec4<f32>(params.center.xyz, params.inv_radius),
                          OccGrid(params.occ_res, params.occ_cascades));
        ds = strata_ds(&mask, k, params.probes);
    }
    let dshape = density_shape[0];
    let cshape = color_shape[0];

    // Pass 1: forward, MLP_GROUP samples at a time through the MLPs.
    var tau = 0.0;
    var c = vec3<f32>(0.0);
    var depth = 0.0;
    var opacity = 0.0;
    var wm_tot = 0.0;
    var dist = 0.0;
    var a: ActGroup;
    let groups = (k + MLP_GROUP - 1u) / MLP_GROUP;
    for (var gi = 0u; gi < groups; gi += 1u) {
        let sl = group_slots(i, gi, ray, &mask);
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            // (A pointer to a[q] cannot be a call argument in SPIR-V: copy through t.)
            var t: Act;
            encode(contract_unit(sl.u[q], params.contraction), &t);
            a[q] = t;
        }
        forward_recorded(false, dshape, 0u, sl.rd, sl.valid, &a);
        var sigma = vec4<f32>(0.0);
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            sigma[q] = trunc_exp(a[q][0].x);
        }
        color_input_group(&a, sh);
        forward_recorded(true, cshape, params.color_base, sl.rc, sl.valid, &a);
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            if !sl.valid[q] {
                continue;
            }
            let st = sl.st[q];
            let w = next_weight(sigma[q], st.y, &tau);
            c += w * sigmoid3(a[q][0]);
            depth += w * st.x;
            // Distortion: opacity and wm_tot are the running W_<j and WM_<j here.
            let below = st.z * opacity - wm_tot;
            dist += 2.0 * w * below + w * w * ds / 3.0;
            opacity += w;
            wm_tot += w * st.z;
        }
    }
    let t_end = exp(-tau);
    let bgc = ray_background(params.background.xyz, params.flags & STEP_RANDOM_BG, params.seed, i);
    let rgb_out = c + t_end * bgc;
    out_rgba[i] = vec4<f32>(rgb_out, opacity);
    out_depth[i] = depth;

    // Losses and their gradients with respect to the rendered colour and depth.
    let inv_n = 1.0 / f32(params.n);
    let e = rgb_out - target_rgb[i].xyz;
    mse[i] = dot(e, e) / 3.0;
    let rl = photo_depth_loss(rgb_out, depth, target_rgb[i], target_depth[i],
                              u32((params.flags & STEP_HUBER) != 0u),
                              params.center.w, params.background.w);
    loss[i] = rl.loss * inv_n;
    let gc = rl.d_rgb * inv_n;
    let gd = rl.d_depth * inv_n;
    let lam = params.dist_lambda;
    dist_loss[i] = lam * dist;
    let w_tot = opacity;
    // sum_j w_j dL/dw_j: colour, depth and (the distortion loss being quadratic in w) 2 L.
    let total = dot(c, gc) + depth * gd + 2.0 * lam * dist;
    let bg = t_end * dot(bgc, gc);

    // Pass 2: per sample its forward values again (the MLPs' outputs from the records), the
    // compositing gradient in order, then the group's backward through both MLPs.
    let d_out = output_at(dshape);
    let c_out = output_at(cshape);
    tau = 0.0;
    var prefix = 0.0;
    var w_lt = 0.0;
    var wm_lt = 0.0;
    var g: ActGroup;
    for (var gi = 0u; gi < groups; gi += 1u) {
        let sl = group_slots(i, gi, ray, &mask);
        var sigma = vec4<f32>(0.0);
        var d_sigma = vec4<f32>(0.0);
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            for (var r = 0u; r < 16u; r += 1u) {
                g[q][r] = vec4<f32>(0.0);
            }
            if !sl.valid[q] {
                continue;
            }
            let st = sl.st[q];
            let rd = sl.rd[q];
            let rc = sl.rc[q];
            sigma[q] = trunc_exp(rec_get(false, rd + d_out).x);
            let dt = st.y;
            let w = next_weight(sigma[q], dt, &tau);
            let col = sigmoid3(rec_get(true, rc + c_out));
            // dL/dw_j: colour, depth and distortion.
            let m = st.z;
            let w_gt = w_tot - w_lt - w;
            let wm_gt = wm_tot - wm_lt - w * m;
            let below = m * w_lt - wm_lt;
            let dw = lam * (2.0 * below + 2.0 * (wm_gt - m * w_gt) + 2.0 / 3.0 * w * ds);
            w_lt += w;
            wm_lt += w * m;
            let uj = dot(col, gc) + st.x * gd + dw;
            prefix += w * uj;
            let dx = exp(-tau) * uj - (total - prefix) - bg;
            var scale = 1.0;
            if (params.flags & STEP_GRAD_SCALING) != 0u {
                scale = min(1.0, st.x * st.x);
            }
            d_sigma[q] = select(0.0, scale * dt * dx, dt > 0.0 && sigma[q] >= 0.0);
            // Through the sigmoid into the colour MLP's output.
            let d_rgb = scale * w * gc;
            g[q][0] = vec4<f32>(d_rgb * col * (vec3<f32>(1.0) - col), 0.0);
        }
        backward_recorded(true, cshape, params.color_base, sl.rc, sl.valid, &g);
        // The density row's gradient: the colour input's first geo_dims entries, plus the
        // density through trunc-exp (its gradient clamped like the value). The SH part of the
        // colour input's gradient is not read (the density MLP's output is geo_dims wide).
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            g[q][0].x += d_sigma[q] * sigma[q];
        }
        backward_recorded(false, dshape, 0u, sl.rd, sl.valid, &g);
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            if sl.valid[q] {
                var t = g[q];
                encode_backward(contract_unit(sl.u[q], params.contraction), &t);
            }
        }
    }
}
