// The fused training step with both MLPs through cooperative matrices
// (VK_KHR_cooperative_matrix), tiny-cuda-nn style: the step of render/train_step.wgsl, with a
// workgroup of COOP_POINTS threads, one ray each, walking its rays' samples in step. Sample j
// of every ray forms a block of COOP_POINTS points whose activations stay in workgroup memory
// in f16 between layers (common/coop_tiles.wgsl); the subgroups multiply them with tiles of the
// MLPs' f16 weights with f32 accumulation, and each thread adds the f32 biases (the uniform
// block's) for its own point. Every ray has params.samples samples, so the sample loop runs the
// same number of times in every thread, and the cooperative operations and barriers stay in
// uniform control flow; threads past the batch or with an invalid pixel feed zero rows.
//
// The records are the scalar step's (common/step.wgsl's layout): each layer's input, as the
// f16 value the tiles read, and the output layer's pre-activations in pass 1; the
// pre-activation gradients in pass 2, which multiplies them, scaled by a power of two per block
// and layer, with the weights' tiles to get the inputs' gradients. The weight gradient then
// sums the records as after the scalar step.
//
// The including file includes common/coop8.wgsl or common/coop16.wgsl first (the tile).
//!include common/step.wgsl
//!include common/coop_tiles.wgsl
//!include common/coop_fused.wgsl


// The forward pass of the density or colour MLP (shape s, f16 weights at element wbase of w16,
// f32 biases at float base of the uniform block) on the block's rows, staged in coop_x with
// stride round_tile(inputs). A `live` thread records its layer inputs and output
// pre-activations at float `at_in` of its record, as forward_recorded does. On return coop_acc
// holds the output pre-activations, row lid at lid * round_tile(outputs).
fn coop_forward_recorded(color: bool, s: MlpShape, wbase: u32, base: u32, at_in: u32, live: bool,
                         lid: u32, sg: u32, n_sg: u32) {
    var at = at_in;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nip = round_tile(ni);
        let nop = round_tile(no);
        if live {
            for (var j = 0u; j < pad4(ni); j += 4u) {
                let x = lid * nip + j;
                rec_set(color, at + j, vec4<f32>(f32(coop_x[x]), f32(coop_x[x + 1u]),
                                                 f32(coop_x[x + 2u]), f32(coop_x[x + 3u])));
            }
        }
        at += pad4(ni);
        coop_layer_forward(wbase + coop_w_offset(s, l), nip, nop, sg, n_sg);
        let last = l + 1u == s.layers;
        coop_bias_relu(lid, no, nop, base + mlp_offset(s, l) + no * ni, last);
        if last && live {
            for (var o = 0u; o < pad4(no); o += 4u) {
                let z = lid * nop + o;
                rec_set(color, at + o, vec4<f32>(coop_acc[z], coop_acc[z + 1u], coop_acc[z + 2u],
                                                 coop_acc[z + 3u]));
            }
        }
        at += pad4(no);
    }
}

// Back-propagates g (dL/d output) through the MLP after coop_forward_recorded at at_in: g
// becomes dL/d input, and a live thread's record holds the pre-activation gradients (ReLU' on
// hidden layers), as backward_recorded does. A thread that is not live must come in with
// g = 0.
fn coop_backward_recorded(color: bool, s: MlpShape, wbase: u32, at_in: u32, live: bool, lid: u32,
                          sg: u32, n_sg: u32, g: ptr<function, Act>) {
    var at = at_in;
    for (var l = 0u; l < s.layers; l += 1u) {
        at += pad4(mlp_dim(s, l)) + pad4(mlp_dim(s, l + 1u));
    }
    for (var li = 0u; li < s.layers; li += 1u) {
        let l = s.layers - 1u - li;
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nip = round_tile(ni);
        let nop = round_tile(no);
        at -= pad4(no);
        let last = l + 1u == s.layers;
        var dz: Act;
        for (var q = 0u; q < 16u; q += 1u) {
            dz[q] = vec4<f32>(0.0);
        }
        var md = 0.0;
        if live {
            for (var o4 = 0u; 4u * o4 < no; o4 += 1u) {
                let go = (*g)[o4];
                // ReLU' of a hidden layer from the next layer's input (its ReLU); the output
                // layer passes go through.
                let act = rec_get(color, select(at + pad4(no), at, last) + 4u * o4);
                let d = below(select(select(vec4<f32>(0.0), go, act > vec4<f32>(0.0)), go, last),
                              o4, no);
                rec_set(color, at + 4u * o4, d);
                dz[o4] = d;
                let m = abs(d);
                md = max(md, max(max(m.x, m.y), max(m.z, m.w)));
            }
        }
        let ed = coop_block_exponent(lid, md);
        let sd = exp2(ed);
        for (var o = 0u; o < nop; o += 1u) {
            coop_d[lid * nop + o] = coop_f16(act_get(&dz, o) * sd);
        }
        at -= pad4(ni);
        coop_layer_backward(wbase + coop_w_offset(s, l), nip, nop, sg, n_sg);
        let inv = exp2(-ed);
        for (var q = 0u; q < 16u; q += 1u) {
            (*g)[q] = vec4<f32>(0.0);
        }
        for (var j = 0u; j < ni; j += 1u) {
            act_set(g, j, coop_acc[lid * nip + j] * inv);
        }
    }
}

@compute @workgroup_size(32)
fn train_step_coop(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32,
                   @builtin(subgroup_id) sg: u32, @builtin(num_subgroups) n_sg: u32) {
    let i = linear_group(wid, nwg) * COOP_POINTS + lid;
    let k = params.samples;
    var mask: ProbeMask;
    var r: StepRay;
    if i < params.n {
        r = step_ray(i, &mask);
    }
    let live = r.valid;
    let dshape = density_shape[0];
    let cshape = color_shape[0];
    let nop_d = round_tile(mlp_dim(dshape, dshape.layers));
    let nop_c = round_tile(mlp_dim(cshape, cshape.layers));
    let cw = coop_w_offset(dshape, dshape.layers);

    // Pass 1: forward, sample j of every ray of the workgroup at a time.
    var f: Composite;
    for (var j = 0u; j < k; j += 1u) {
        let rd = (i * k + j) * params.density_stride;
        let rc = (i * k + j) * params.color_stride;
        var st = vec3<f32>(0.0);
        var e: Act;
        for (var q = 0u; q < 16u; q += 1u) {
            e[q] = vec4<f32>(0.0);
        }
        if live {
            st = stratum(i, j, &mask);
            encode(contract_unit(scene_point(r.ray, st.x), params.contraction), &e);
        }
        coop_stage_encoding(lid, &e);
        coop_forward_recorded(false, dshape, 0u, 0u, rd, live, lid, sg, n_sg);
        let sigma = trunc_exp(coop_acc[lid * nop_d]);
        coop_stage_color(lid, live, r.sh);
        coop_forward_recorded(true, cshape, cw, params.color_base, rc, live, lid, sg, n_sg);
        if live {
            let o = lid * nop_c;
            let rgb = sigmoid3(vec4<f32>(coop_acc[o], coop_acc[o + 1u], coop_acc[o + 2u], 0.0));
            composite_sample(&f, st, sigma, rgb, r.ds);
        }
    }
    var sgrad: StepGrad;
    if live {
        sgrad = step_losses(i, f, r.ds);
    }

    // Pass 2: per sample the compositing gradient in order (the MLPs' outputs from the
    // records), then the block's backward through both MLPs.
    let d_out = output_at(dshape);
    let c_out = output_at(cshape);
    for (var j = 0u; j < k; j += 1u) {
        let rd = (i * k + j) * params.density_stride;
        let rc = (i * k + j) * params.color_stride;
        var g: Act;
        for (var q = 0u; q < 16u; q += 1u) {
            g[q] = vec4<f32>(0.0);
        }
        var u = vec3<f32>(0.0);
        var sigma = 0.0;
        var d_sigma = 0.0;
        if live {
            let st = stratum(i, j, &mask);
            u = scene_point(r.ray, st.x);
            sigma = trunc_exp(rec_get(false, rd + d_out).x);
            let col = sigmoid3(rec_get(true, rc + c_out));
            let dg = composite_grad(&sgrad, st, sigma, col, sgrad.ds);
            d_sigma = dg.w;
            g[0] = vec4<f32>(dg.xyz, 0.0);
        }
        coop_backward_recorded(true, cshape, cw, rc, live, lid, sg, n_sg, &g);
        // The density row's gradient: the colour input's first geo_dims entries, plus the
        // density through trunc-exp.
        g[0].x += d_sigma * sigma;
        coop_backward_recorded(false, dshape, 0u, rd, live, lid, sg, n_sg, &g);
        if live {
            encode_backward(contract_unit(u, params.contraction), &g);
        }
    }
}

// One thread per element of w16: both MLPs' weights from the uniform block in f16.
@compute @workgroup_size(64)
fn step_weights_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
      @builtin(local_invocation_index) lid: u32) {
    coop_fused_weights(linear_group(wid, nwg) * 64u + lid);
}
