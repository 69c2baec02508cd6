// Fused march: one thread per ray does everything between a pixel and its colour. It builds the
// ray from the camera (NDC for forward-facing scenes), places the samples (stratum midpoints,
// linear in t or in disparity, or takes the samples given: the proposal sampler's, sorted along
// the ray, when params.center.w is non-zero), skips samples in cells the occupancy grid marks empty (points
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
// common/march_body.wgsl holds the parameters, bindings and the ray of a pixel, shared with the
// cooperative-matrix march (common/march_coop.wgsl, built as render/march_coop8.wgsl and
// render/march_coop16.wgsl), which runs the MLPs on blocks of 32 rays' samples.
//
// The layouts match the standalone kernels: common/hash_grid.wgsl (levels, table),
// common/mlp.wgsl (weights row-major, then the bias, per layer), common/occupancy.wgsl. The
// MLPs' inputs and hidden widths must be multiples of 4 and both MLPs fit 16384 floats. The
// standalone pipeline (render/sample.wgsl, field/*, render/field_heads.wgsl,
// render/composite.wgsl) computes the same quantities sample by sample.
//!include common/march_body.wgsl

@compute @workgroup_size(64)
fn march_render(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let r = march_ray(i);
    if !r.valid {
        return;
    }
    let ray = r.ray;
    let sh = r.sh;
    let k = params.samples;
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
    let given = params.center.w != 0.0;
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
            var td: vec2<f32>;
            if given {
                td = given_t_dt[i * k + j];
            } else {
                td = march_stratum(j, k);
            }
            let u = scene_point(ray, td.x);
            if !occupied(u) {
                continue;
            }
            var e: Act;
            encode(contract_unit(u, params.contraction), &e);
            // Slot n, written through constant indices.
            for (var q = 0u; q < MLP_GROUP; q += 1u) {
                if q == n {
                    a[q] = e;
                    t[q] = td.x;
                    dt[q] = td.y;
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
