// The fused training step's parameters, bindings and per-ray pieces, shared by its scalar
// kernel (render/train_step.wgsl, which describes the step) and its cooperative-matrix kernel
// (common/step_coop.wgsl): the ray and its strata, forward compositing, the losses and the
// compositing gradient per sample, the MLP records, and the hash-grid scatter.
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
//!include common/pixel_ray.wgsl
//!include common/ray_loss.wgsl

struct Params {
    // Rays in the batch.
    n: u32,
    // Samples per ray.
    samples: u32,
    // The core of the virtual views' smooth L1 (0: plain L1; common/ray_loss.wgsl). The
    // strata are linear in t in NDC and linear in disparity otherwise (sample_spacing).
    l1_core: f32,
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
    // Bit 0: jitter the strata (else samples sit at midpoints; never on virtual views' rays,
    // those with a negative colour weight); bit 1: each ray's background
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
// Set the bit of every vec4 of the table the step adds a gradient to in `touched` (for the
// sparse Adam, optim/adam_sparse.wgsl; unsplit tables only: the host refuses split ones).
const STEP_TOUCHED: u32 = 32u;
// The samples are given (the proposal sampler's, render/proposal.wgsl's resample): sample j of
// ray i is (t, dt) = given_t_dt[i * samples + j] and (s, ds) = given_s_ds[...], in place of
// the strata; the step writes each sample's density to given_sigma for the interlevel loss.
// The scalar kernel only (group_slots); the host refuses it with cooperative matrices.
const STEP_GIVEN: u32 = 64u;

// The strata's spacing (render/sample.wgsl; common/field_eval.wgsl's t_of asks for it): 0
// (linear in t) in NDC, else 1 (linear in disparity).
fn sample_spacing() -> u32 {
    return select(1u, 0u, (params.flags & STEP_NDC) != 0u);
}

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
// With STEP_TOUCHED: bit i of word w marks the table's vec4 32 w + i as holding a gradient.
@group(0) @binding(20) var<storage, read_write> touched: array<atomic<u32>>;
// With STEP_GIVEN: the samples, and their densities out (bindings 21 and 22 are the
// cooperative-matrix step's, common/coop_fused.wgsl).
@group(0) @binding(23) var<storage, read> given_t_dt: array<vec2<f32>>;
@group(0) @binding(24) var<storage, read> given_s_ds: array<vec2<f32>>;
@group(0) @binding(25) var<storage, read_write> given_sigma: array<f32>;

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

// Marks the vec4s holding table floats e .. e + count - 1 (an unsplit table's) in `touched`.
fn mark_touched(e: u32, count: u32) {
    for (var q = e / 4u; q <= (e + count - 1u) / 4u; q += 1u) {
        atomicOr(&touched[q / 32u], 1u << (q % 32u));
    }
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
            var nz = false;
            for (var f = 0u; f < F; f += 1u) {
                let v = wk * act_get(d_enc, l * F + f);
                scatter(hi, e + f, v);
                nz = nz || v != 0.0;
            }
            if nz && (params.flags & STEP_TOUCHED) != 0u {
                mark_touched(e, F);
            }
        }
    }
}

// The stratum of sample j: (t, dt, s) with s the jittered normalised position; with an
// occupancy grid, spread over the ray's occupied probe intervals `mask`. A ray with a negative
// colour weight (a virtual view's, whose target the renderer made with centred samples) is not
// jittered, as render/sample.wgsl's jitter 2.
fn stratum(ray: u32, j: u32, mask: ptr<function, ProbeMask>) -> vec3<f32> {
    var jit = 0.5;
    if (params.flags & STEP_JITTER) != 0u && target_rgb[ray].w >= 0.0 {
        jit = strata_jitter(params.seed, ray, j);
    }
    let nf = vec2<f32>(params.near, params.far);
    if params.occ_cascades != 0u {
        return occupied_stratum(mask, j, params.samples, jit, params.probes, nf, sample_spacing());
    }
    return ray_stratum(j, params.samples, jit, nf, sample_spacing());
}

// The samples of group gi of ray i: validity, record offsets (density, colour), strata
// (t, dt, s), each one's share ds of s, and scene-normalised points. Slots past the last
// sample repeat it.
struct Slots {
    valid: vec4<bool>,
    rd: vec4<u32>,
    rc: vec4<u32>,
    st: array<vec3<f32>, 4>,
    ds: vec4<f32>,
    u: array<vec3<f32>, 4>,
}

// ds: the strata's share of s (StepRay.ds), used unless the samples are given.
fn group_slots(i: u32, gi: u32, ray: array<vec3<f32>, 2>, mask: ptr<function, ProbeMask>,
               ds: f32) -> Slots {
    let k = params.samples;
    var sl: Slots;
    for (var q = 0u; q < MLP_GROUP; q += 1u) {
        let j = gi * MLP_GROUP + q;
        sl.valid[q] = j < k;
        let jj = min(j, k - 1u);
        sl.rd[q] = (i * k + jj) * params.density_stride;
        sl.rc[q] = (i * k + jj) * params.color_stride;
        if (params.flags & STEP_GIVEN) != 0u {
            let tdt = given_t_dt[i * k + jj];
            let sds = given_s_ds[i * k + jj];
            sl.st[q] = vec3<f32>(tdt, sds.x);
            sl.ds[q] = sds.y;
        } else {
            sl.st[q] = stratum(i, jj, mask);
            sl.ds[q] = ds;
        }
        sl.u[q] = scene_point(ray, sl.st[q].x);
    }
    return sl;
}


// A ray of the batch: the ray it marches (NDC or world), SH4 of its world direction, and each
// stratum's share of s; `valid` false for an out-of-range camera or pixel index.
struct StepRay {
    valid: bool,
    ray: array<vec3<f32>, 2>,
    sh: array<f32, 16>,
    ds: f32,
}

// Ray i (< params.n) of the batch, with its occupied probe intervals in mask (with a grid).
// An out-of-range camera or pixel index gives a zero pixel, no loss and no gradient: its
// outputs and records are zeroed here.
fn step_ray(i: u32, mask: ptr<function, ProbeMask>) -> StepRay {
    let k = params.samples;
    var r: StepRay;
    let p = pixel_ray(pixels[i], params.n_cameras, (params.flags & STEP_NDC) != 0u,
                      params.ndc_near);
    r.valid = p.valid;
    if !r.valid {
        out_rgba[i] = vec4<f32>(0.0);
        out_depth[i] = 0.0;
        loss[i] = 0.0;
        mse[i] = 0.0;
        dist_loss[i] = 0.0;
        for (var j = 0u; j < k; j += 1u) {
            zero_record(false, (i * k + j) * params.density_stride, params.density_stride);
            zero_record(true, (i * k + j) * params.color_stride, params.color_stride);
        }
        return r;
    }
    r.ray = p.ray;
    r.sh = p.sh;
    r.ds = 1.0 / f32(k);
    if params.occ_cascades != 0u {
        *mask = probe_mask(r.ray[0], r.ray[1], vec2<f32>(params.near, params.far), sample_spacing(),
                           params.probes, vec4<f32>(params.center.xyz, params.inv_radius),
                           OccGrid(params.occ_res, params.occ_cascades));
        r.ds = strata_ds(mask, k, params.probes);
    }
    return r;
}

// The forward pass's running sums over a ray's samples: optical depth, colour, depth,
// opacity, the weights' sum of s (wm_tot) and the distortion loss.
struct Composite {
    tau: f32,
    c: vec3<f32>,
    depth: f32,
    opacity: f32,
    wm_tot: f32,
    dist: f32,
}

// Adds the next sample (stratum st = (t, dt, s), density sigma, colour rgb) to f.
fn composite_sample(f: ptr<function, Composite>, st: vec3<f32>, sigma: f32, rgb: vec3<f32>,
                    ds: f32) {
    let x = optical_depth(sigma, st.y);
    let w = exp(-(*f).tau) * alpha_of(x);
    (*f).tau += x;
    (*f).c += w * rgb;
    (*f).depth += w * st.x;
    // Distortion: opacity and wm_tot are the running W_<j and WM_<j here.
    let below = st.z * (*f).opacity - (*f).wm_tot;
    (*f).dist += 2.0 * w * below + w * w * ds / 3.0;
    (*f).opacity += w;
    (*f).wm_tot += w * st.z;
}

// The backward pass's state of a ray: the loss gradients with respect to its colour (gc) and
// depth (gd), the distortion weight, the forward totals, and the running sums of the walk.
struct StepGrad {
    gc: vec3<f32>,
    gd: f32,
    lam: f32,
    // sum_j w_j dL/dw_j (colour, depth and, the distortion loss being quadratic in w, 2 L).
    total: f32,
    // The background's share: T_end dL/d(background term).
    bg: f32,
    w_tot: f32,
    wm_tot: f32,
    ds: f32,
    tau: f32,
    prefix: f32,
    w_lt: f32,
    wm_lt: f32,
}

// Ray i's outputs and losses from its forward sums, and the state its backward walk starts
// from.
fn step_losses(i: u32, f: Composite, ds: f32) -> StepGrad {
    let t_end = exp(-f.tau);
    let bgc = ray_background(params.background.xyz, params.flags & STEP_RANDOM_BG, params.seed, i);
    let rgb_out = f.c + t_end * bgc;
    out_rgba[i] = vec4<f32>(rgb_out, f.opacity);
    out_depth[i] = f.depth;
    let inv_n = 1.0 / f32(params.n);
    let e = rgb_out - target_rgb[i].xyz;
    mse[i] = dot(e, e) / 3.0;
    let rl = photo_depth_loss(rgb_out, f.depth, target_rgb[i], target_depth[i],
                              u32((params.flags & STEP_HUBER) != 0u),
                              params.center.w, params.background.w, params.l1_core);
    loss[i] = rl.loss * inv_n;
    var g: StepGrad;
    g.gc = rl.d_rgb * inv_n;
    g.gd = rl.d_depth * inv_n;
    g.lam = params.dist_lambda;
    dist_loss[i] = g.lam * f.dist;
    g.w_tot = f.opacity;
    g.wm_tot = f.wm_tot;
    g.ds = ds;
    g.total = dot(f.c, g.gc) + f.depth * g.gd + 2.0 * g.lam * f.dist;
    g.bg = t_end * dot(bgc, g.gc);
    return g;
}

// The compositing gradient of the next sample in order (stratum st, density sigma, colour
// col): (dL/d colour MLP output rgb, through the sigmoid; dL/d sigma), both scaled by Floaters
// No More's min(1, t^2) when on.
fn composite_grad(g: ptr<function, StepGrad>, st: vec3<f32>, sigma: f32, col: vec3<f32>,
                  ds: f32) -> vec4<f32> {
    let dt = st.y;
    let x = optical_depth(sigma, dt);
    let w = exp(-(*g).tau) * alpha_of(x);
    (*g).tau += x;
    // dL/dw_j: colour, depth and distortion.
    let m = st.z;
    let w_gt = (*g).w_tot - (*g).w_lt - w;
    let wm_gt = (*g).wm_tot - (*g).wm_lt - w * m;
    let below = m * (*g).w_lt - (*g).wm_lt;
    let dw = (*g).lam * (2.0 * below + 2.0 * (wm_gt - m * w_gt) + 2.0 / 3.0 * w * ds);
    (*g).w_lt += w;
    (*g).wm_lt += w * m;
    let uj = dot(col, (*g).gc) + st.x * (*g).gd + dw;
    (*g).prefix += w * uj;
    let dx = exp(-(*g).tau) * uj - ((*g).total - (*g).prefix) - (*g).bg;
    var scale = 1.0;
    if (params.flags & STEP_GRAD_SCALING) != 0u {
        scale = min(1.0, st.x * st.x);
    }
    let d_sigma = select(0.0, scale * dt * dx, dt > 0.0 && sigma >= 0.0);
    // Through the sigmoid into the colour MLP's output.
    let d_rgb = scale * w * (*g).gc;
    return vec4<f32>(d_rgb * col * (vec3<f32>(1.0) - col), d_sigma);
}
