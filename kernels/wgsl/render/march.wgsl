// Fused march: one thread per ray does everything between a pixel and its colour. It builds the
// ray from the camera (NDC for forward-facing scenes), places the samples (stratum midpoints,
// linear in t or in disparity), skips samples in cells the occupancy grid marks empty (points
// outside the grid are evaluated), and evaluates the
// field per sample in registers: contraction, every hash-grid level, the density MLP,
// trunc-exp, SH4 of the world direction, and the colour MLP, four samples at a time sharing
// each weight load (common/mlp_block.wgsl's MLP_GROUP). Groups are compacted in registers: each
// takes the next four samples in occupied cells. It composites front to back, sample by sample,
// and writes only (rgb, opacity) and the expected depth. Nothing per sample touches memory.
//
// Two cuts trade accuracy for speed. Each is exact at 0 and bounded otherwise:
//   min_weight: the colour MLP is skipped for a sample whose weight is <= min_weight, which
//     drops at most min_weight of colour per skipped sample;
//   min_transmittance: the march stops once the transmittance falls below it, which drops at
//     most that much of colour and opacity (the background term keeps the true tail).
//
// `march_occupancy` is the fused occupancy update. Per cell of a window it evaluates the
// density at a jittered point, then folds it into the cell's EMA:
// grid = max(decay * grid, density).
//
// The layouts match the standalone kernels: common/hash_grid.wgsl (levels, table),
// common/mlp.wgsl (weights row-major, then the bias, per layer), common/occupancy.wgsl. The
// MLPs' inputs and hidden widths must be multiples of 4 and both MLPs fit 16384 floats. The
// standalone pipeline (render/sample.wgsl, field/*, render/field_heads.wgsl,
// render/composite.wgsl) computes the same quantities sample by sample.
//!include common/dispatch.wgsl
//!include common/heads.wgsl
//!include common/camera.wgsl
//!include common/contract.wgsl
//!include common/hash_grid.wgsl
//!include common/mlp.wgsl
//!include common/mlp_block.wgsl
//!include common/occupancy.wgsl
//!include common/rng.wgsl
//!include common/sh.wgsl
//!include common/volume.wgsl
//!include common/field_eval.wgsl

struct Params {
    // Rays (march_render) or cells in the window (march_occupancy).
    n: u32,
    // Samples per ray.
    samples: u32,
    // 0: linear in t, 1: linear in disparity.
    spacing: u32,
    // Non-zero: march in NDC (near plane at `ndc_near`).
    ndc: u32,
    // Sampling range along the ray.
    near: f32,
    far: f32,
    ndc_near: f32,
    // Contraction mode (common/contract.wgsl) and 1 / scene radius.
    contraction: u32,
    inv_radius: f32,
    // Occupancy grid resolution and cascades; cascades = 0 disables skipping in the march.
    occ_res: u32,
    occ_cascades: u32,
    // Hash-grid levels and features per level.
    levels: u32,
    features: u32,
    // Float offset of the colour MLP in the uniform weight block (the density MLP is at 0).
    color_base: u32,
    min_weight: f32,
    min_transmittance: f32,
    // Scene centre (xyz).
    center: vec4<f32>,
    // Background colour (xyz).
    background: vec4<f32>,
    // Occupancy update: first cell of the window, jitter seed, EMA decay.
    first: u32,
    seed: u32,
    decay: f32,
    n_cameras: u32,
    // (0, 1, 2, 3): the identity table of common/mlp_block.wgsl's mlp_uni.
    lut: vec4<u32>,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> cameras: array<GpuCamera>;
// (camera, pixel = y * width + x) per ray.
@group(0) @binding(1) var<storage, read> pixels: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> level_info: array<HashLevel>;
@group(0) @binding(3) var<storage, read> table: array<f32>;
@group(0) @binding(4) var<storage, read> density_shape: array<MlpShape>;
@group(0) @binding(6) var<storage, read> color_shape: array<MlpShape>;
@group(0) @binding(8) var<storage, read> occ_bits: array<u32>;
@group(0) @binding(9) var<storage, read_write> out_rgba: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(11) var<storage, read_write> occ_grid: array<f32>;
// Both MLPs' weights (common/mlp.wgsl layout; density at 0, colour at params.color_base),
// copied here from the parameter buffer before each pass. Every lane reads the same entry; a
// uniform block lets lavapipe load it without the per-lane branches of a storage buffer.
@group(0) @binding(12) var<uniform> mlp: array<vec4<f32>, 4096>;
// The second part of a split hash table (common/hash_grid.wgsl).
@group(0) @binding(13) var<storage, read> table_hi: array<f32>;

@compute @workgroup_size(64)
fn march_render(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let pc = pixels[i];
    // Out-of-range camera or pixel indices give a zero pixel rather than reading out of bounds.
    if pc.x >= params.n_cameras {
        out_rgba[i] = vec4<f32>(0.0);
        out_depth[i] = 0.0;
        return;
    }
    let cam = cameras[pc.x];
    if pc.y >= cam.size.x * cam.size.y {
        out_rgba[i] = vec4<f32>(0.0);
        out_depth[i] = 0.0;
        return;
    }
    let world = camera_ray(cam, pixel_centre(cam, pc.y));
    var ray = world;
    if params.ndc != 0u {
        ray = ndc_ray(cam, world[0], world[1], params.ndc_near);
    }
    let sh = sh4(unit_dir(world[1]));
    let k = params.samples;
    let inv_k = 1.0 / f32(k);
    var tau = 0.0;
    var c = vec3<f32>(0.0);
    var depth = 0.0;
    var opacity = 0.0;
    var a: ActGroup;
    let dshape = density_shape[0];
    let cshape = color_shape[0];
    // MLP_GROUP samples at a time through the MLPs (common/mlp_block.wgsl's register
    // blocking), then compositing one by one in order, so the cuts act exactly as per sample.
    // Compaction in registers: a group takes the next MLP_GROUP samples in occupied cells, so
    // samples in empty space cost no MLP work.
    var done = false;
    var next = 0u;
    loop {
        if done || next >= k {
            break;
        }
        var live = vec4<bool>(false);
        var t = vec4<f32>(0.0);
        var dt = vec4<f32>(0.0);
        var n = 0u;
        loop {
            if n >= MLP_GROUP || next >= k {
                break;
            }
            let j = next;
            next += 1u;
            let s0 = f32(j) * inv_k;
            let s1 = f32(j + 1u) * inv_k;
            let tj = t_of(mix(s0, s1, 0.5));
            let u = scene_point(ray, tj);
            if !occupied(u) {
                continue;
            }
            var e: Act;
            encode(contract_unit(u, params.contraction), &e);
            // Slot n, written through constant indices.
            for (var q = 0u; q < MLP_GROUP; q += 1u) {
                if q == n {
                    a[q] = e;
                    t[q] = tj;
                    dt[q] = t_of(s1) - t_of(s0);
                    live[q] = true;
                }
            }
            n += 1u;
        }
        if n == 0u {
            break;
        }
        mlp_forward_group(dshape, 0u, &a);
        // Weights in order; the march stops after the sample that drops the transmittance
        // below the cut.
        var w = vec4<f32>(0.0);
        var colour = false;
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            if !live[q] || done {
                live[q] = false;
                continue;
            }
            w[q] = next_weight(trunc_exp(a[q][0].x), dt[q], &tau);
            colour = colour || w[q] > params.min_weight;
            if exp(-tau) < params.min_transmittance {
                done = true;
            }
        }
        if colour {
            color_input_group(&a, sh);
            mlp_forward_group(cshape, params.color_base, &a);
        }
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            if !live[q] {
                continue;
            }
            if w[q] > params.min_weight {
                c += w[q] * sigmoid3(a[q][0]);
            }
            depth += w[q] * t[q];
            opacity += w[q];
        }
    }
    out_rgba[i] = vec4<f32>(c + exp(-tau) * params.background.xyz, opacity);
    out_depth[i] = depth;
}

@compute @workgroup_size(64)
fn march_occupancy(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    let k = linear_group(wid, nwg) * 64u + lid;
    if k >= params.n {
        return;
    }
    let grid = OccGrid(params.occ_res, params.occ_cascades);
    let total = params.occ_res * params.occ_res * params.occ_res * params.occ_cascades;
    let cell = (params.first + k) % total;
    // The jitter of render/occupancy.wgsl's occ_sample.
    let h = params.seed * 3u * total + 3u * cell;
    let u = occ_cell_point(cell, vec3<f32>(rand01(h), rand01(h + 1u), rand01(h + 2u)), grid);
    var a: Act;
    var d = density_at(u, &a);
    // A non-finite density must not freeze a cell as occupied forever.
    if !(d == d) || d < 0.0 {
        d = 0.0;
    }
    occ_grid[cell] = max(occ_grid[cell] * params.decay, min(d, 3.0e38));
}
