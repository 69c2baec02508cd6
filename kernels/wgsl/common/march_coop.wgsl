// The fused march with both MLPs through cooperative matrices (VK_KHR_cooperative_matrix):
// render/march.wgsl's march_render, with a workgroup of COOP_POINTS threads, one ray each.
// Each round, every ray still marching takes its next sample in an occupied cell (the
// compaction of the scalar march, per ray), and the workgroup's samples form one block of
// COOP_POINTS points through the density MLP (common/coop_tiles.wgsl: f16 activations in
// workgroup memory, f16 weight tiles, f32 accumulation and biases); the colour MLP runs on the
// block when any of its samples weighs more than min_weight. The rounds go on while any ray of
// the workgroup has a sample left, so the cooperative operations and barriers stay in uniform
// control flow; a ray that has ended, or has no valid pixel, feeds a zero row. Both cuts act
// per sample as in the scalar march.
//
// The including file includes common/coop8.wgsl or common/coop16.wgsl first (the tile).
//!include common/march_body.wgsl
//!include common/coop_tiles.wgsl
//!include common/coop_fused.wgsl


@compute @workgroup_size(32)
fn march_render_coop(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                     @builtin(local_invocation_index) lid: u32,
                     @builtin(subgroup_id) sg: u32, @builtin(num_subgroups) n_sg: u32) {
    let i = linear_group(wid, nwg) * COOP_POINTS + lid;
    var r: PixelRay;
    if i < params.n {
        r = march_ray(i);
    }
    // Whether this ray still marches.
    var marching = r.valid;
    let k = params.samples;
    var tau = 0.0;
    var c = vec3<f32>(0.0);
    var depth = 0.0;
    var opacity = 0.0;
    let dshape = density_shape[0];
    let cshape = color_shape[0];
    let nop_d = round_tile(mlp_dim(dshape, dshape.layers));
    let nop_c = round_tile(mlp_dim(cshape, cshape.layers));
    let cw = coop_w_offset(dshape, dshape.layers);
    var next = 0u;
    loop {
        // This ray's next sample in an occupied cell, if any.
        var have = false;
        var tj = 0.0;
        var dtj = 0.0;
        var e: Act;
        for (var q = 0u; q < 16u; q += 1u) {
            e[q] = vec4<f32>(0.0);
        }
        loop {
            if !marching || next >= k {
                break;
            }
            let j = next;
            next += 1u;
            let td = march_stratum(j, k);
            let u = scene_point(r.ray, td.x);
            if !occupied(u) {
                continue;
            }
            encode(contract_unit(u, params.contraction), &e);
            tj = td.x;
            dtj = td.y;
            have = true;
            break;
        }
        marching = have;
        if !coop_any(lid, have) {
            break;
        }
        coop_stage_encoding(lid, &e);
        coop_mlp_forward(dshape, 0u, 0u, lid, sg, n_sg);
        var w = 0.0;
        if have {
            w = next_weight(trunc_exp(coop_acc[lid * nop_d]), dtj, &tau);
            // The march stops after the sample that drops the transmittance below the cut.
            if exp(-tau) < params.min_transmittance {
                marching = false;
            }
        }
        let colour = have && w > params.min_weight;
        if coop_any(lid, colour) {
            coop_stage_color(lid, have, r.sh);
            coop_mlp_forward(cshape, cw, params.color_base, lid, sg, n_sg);
            if colour {
                let o = lid * nop_c;
                c += w * sigmoid3(vec4<f32>(coop_acc[o], coop_acc[o + 1u], coop_acc[o + 2u], 0.0));
            }
        }
        if have {
            depth += w * tj;
            opacity += w;
        }
    }
    if r.valid {
        out_rgba[i] = vec4<f32>(c + exp(-tau) * params.background.xyz, opacity);
        out_depth[i] = depth;
    }
}

// One thread per element of w16: both MLPs' weights from the uniform block in f16.
@compute @workgroup_size(64)
fn march_weights_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
      @builtin(local_invocation_index) lid: u32) {
    coop_fused_weights(linear_group(wid, nwg) * 64u + lid);
}
