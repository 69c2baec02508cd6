// Microbenchmarks of the fused training step's arithmetic (issue 61; extranerf_prims::micro):
// FMA throughput with every operand in registers, and one 64-wide dense layer (the MLPs'
// hidden shape, 64 x 64 weights and 64 biases) per lane through common/mlp_block.wgsl's own
// functions, its weights read from the uniform block as the step reads them: one point per
// lane (mlp_layer), four (mlp_layer_group, the step's register blocking) and four backward
// (mlp_layer_back_group). A CPU core's 16 vector registers cannot hold 64 x 64 weights, so
// "weights in registers" is what micro_fma measures; the dense layers add the weights' loads.
//!include common/dispatch.wgsl
//!include common/micro.wgsl
//!include common/mlp_block.wgsl

@group(0) @binding(0) var<uniform> mlp: array<vec4<f32>, 4096>;
// Per lane: 4 points x 16 vec4s of activations (micro_dense1 uses the first point).
@group(0) @binding(1) var<storage, read> inputs: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;

// 8 independent vec4 chains a = fma(a, m, c): 32 FMAs per lane and iteration, enough
// independent work to hide the FMA latency.
@compute @workgroup_size(64)
fn micro_fma(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    let m = vec4<f32>(params.m);
    let c = vec4<f32>(params.c);
    let x = f32(i & 63u) / 64.0;
    var a0 = vec4<f32>(x, x + 1.0, x + 2.0, x + 3.0);
    var a1 = a0 + 4.0;
    var a2 = a0 + 8.0;
    var a3 = a0 + 12.0;
    var a4 = a0 + 16.0;
    var a5 = a0 + 20.0;
    var a6 = a0 + 24.0;
    var a7 = a0 + 28.0;
    for (var n = 0u; n < params.ops; n += 32u) {
        a0 = fma(a0, m, c);
        a1 = fma(a1, m, c);
        a2 = fma(a2, m, c);
        a3 = fma(a3, m, c);
        a4 = fma(a4, m, c);
        a5 = fma(a5, m, c);
        a6 = fma(a6, m, c);
        a7 = fma(a7, m, c);
    }
    let s = a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7;
    out[i] = dot(s, vec4<f32>(1.0));
}

// The layer W a + b then ReLU, params.ops times, on one point per lane; the weights sit at
// float 0 of the block (W row-major, then b).
@compute @workgroup_size(64)
fn micro_dense1(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var a: Act;
    var z: Act;
    for (var j = 0u; j < 16u; j += 1u) {
        a[j] = inputs[i * 64u + j];
    }
    for (var n = 0u; n < params.ops; n += 1u) {
        mlp_layer(0u, 64u, 64u, &a, &z);
        mlp_activate(&z, &a, true);
    }
    var acc = 0.0;
    for (var j = 0u; j < 16u; j += 1u) {
        acc += dot(a[j], vec4<f32>(1.0));
    }
    out[i] = acc;
}

// The same on four points per lane sharing each weight load (out: the sum over the four).
@compute @workgroup_size(64)
fn micro_dense4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var a: ActGroup;
    var z: ActGroup;
    for (var q = 0u; q < 4u; q += 1u) {
        for (var j = 0u; j < 16u; j += 1u) {
            a[q][j] = inputs[i * 64u + q * 16u + j];
        }
    }
    for (var n = 0u; n < params.ops; n += 1u) {
        mlp_layer_group(0u, 64u, 64u, &a, &z);
        mlp_activate_group(&z, &a, true);
    }
    var acc = 0.0;
    for (var q = 0u; q < 4u; q += 1u) {
        for (var j = 0u; j < 16u; j += 1u) {
            acc += dot(a[q][j], vec4<f32>(1.0));
        }
    }
    out[i] = acc;
}

// The backward data pass of that layer on four points per lane: d <- W^T d, params.ops times
// (no activation: the step applies ReLU' from its records, a select per vec4).
@compute @workgroup_size(64)
fn micro_dense4_back(@builtin(workgroup_id) wid: vec3<u32>,
                     @builtin(num_workgroups) nwg: vec3<u32>,
                     @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var d: ActGroup;
    var g: ActGroup;
    for (var q = 0u; q < 4u; q += 1u) {
        for (var j = 0u; j < 16u; j += 1u) {
            d[q][j] = inputs[i * 64u + q * 16u + j];
        }
    }
    for (var n = 0u; n < params.ops; n += 1u) {
        mlp_layer_back_group(0u, 64u, 64u, &d, &g);
        d = g;
    }
    var acc = 0.0;
    for (var q = 0u; q < 4u; q += 1u) {
        for (var j = 0u; j < 16u; j += 1u) {
            acc += dot(d[q][j], vec4<f32>(1.0));
        }
    }
    out[i] = acc;
}
