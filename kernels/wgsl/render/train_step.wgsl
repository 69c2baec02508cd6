// Fused training step: one thread per ray does the whole forward and backward pass between a
// batch pixel and the parameter gradients, except the MLP weight-gradient reduction.
//
//   pass 1 (forward): ray (NDC or world), jittered stratified samples (over the occupied part
//     of the ray when an occupancy grid is given, as render/sample.wgsl; or the samples given,
//     the proposal sampler's, with STEP_GIVEN, whose densities it then writes), per sample the
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
// common/step.wgsl holds the parameters, bindings and per-ray pieces this kernel shares with
// the cooperative-matrix step (common/step_coop.wgsl, built as render/train_step_coop8.wgsl and
// render/train_step_coop16.wgsl), which runs the MLPs on blocks of 32 rays' samples.
//
// Layouts: common/hash_grid.wgsl (levels, table, split tables), common/mlp.wgsl (weights per
// layer W then b), the uniform block of common/mlp_block.wgsl with the density MLP at 0 and the
// colour MLP at params.color_base. The standalone chain computes the same quantities:
// render/{batch,rays,sample}.wgsl, field/*, render/{field_heads,composite,loss,distortion}.wgsl.
//!include common/step.wgsl

@compute @workgroup_size(64)
fn train_step(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let k = params.samples;
    var mask: ProbeMask;
    let r = step_ray(i, &mask);
    if !r.valid {
        // (Here, not in step_ray: the cooperative-matrix step binds no given samples.)
        if (params.flags & STEP_GIVEN) != 0u {
            for (var j = 0u; j < k; j += 1u) {
                given_sigma[i * k + j] = 0.0;
            }
        }
        return;
    }
    let dshape = density_shape[0];
    let cshape = color_shape[0];

    // Pass 1: forward, MLP_GROUP samples at a time through the MLPs.
    var f: Composite;
    var a: ActGroup;
    let groups = (k + MLP_GROUP - 1u) / MLP_GROUP;
    for (var gi = 0u; gi < groups; gi += 1u) {
        let sl = group_slots(i, gi, r.ray, &mask, r.ds);
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
            if sl.valid[q] && (params.flags & STEP_GIVEN) != 0u {
                given_sigma[i * k + gi * MLP_GROUP + q] = sigma[q];
            }
        }
        color_input_group(&a, r.sh);
        forward_recorded(true, cshape, params.color_base, sl.rc, sl.valid, &a);
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            if sl.valid[q] {
                composite_sample(&f, sl.st[q], sigma[q], sigmoid3(a[q][0]), sl.ds[q]);
            }
        }
    }
    var sg = step_losses(i, f, r.ds);

    // Pass 2: per sample its forward values again (the MLPs' outputs from the records), the
    // compositing gradient in order, then the group's backward through both MLPs.
    let d_out = output_at(dshape);
    let c_out = output_at(cshape);
    var g: ActGroup;
    for (var gi = 0u; gi < groups; gi += 1u) {
        let sl = group_slots(i, gi, r.ray, &mask, r.ds);
        var sigma = vec4<f32>(0.0);
        var d_sigma = vec4<f32>(0.0);
        for (var q = 0u; q < MLP_GROUP; q += 1u) {
            for (var c = 0u; c < 16u; c += 1u) {
                g[q][c] = vec4<f32>(0.0);
            }
            if !sl.valid[q] {
                continue;
            }
            sigma[q] = trunc_exp(rec_get(false, sl.rd[q] + d_out).x);
            let col = sigmoid3(rec_get(true, sl.rc[q] + c_out));
            let dg = composite_grad(&sg, sl.st[q], sigma[q], col, sl.ds[q]);
            d_sigma[q] = dg.w;
            g[q][0] = vec4<f32>(dg.xyz, 0.0);
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
