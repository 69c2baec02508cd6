// Output activations of the field and their backward passes, elementwise:
//   trunc_exp (Instant-NGP's density): y = exp(min(x, 15)), dy/dx = exp(min(x, 15)) — the
//   gradient is clamped with the value, so huge logits neither overflow nor explode;
//   sigmoid (colour): y = 1 / (1 + exp(-x)), dy/dx = y (1 - y) = e / (1 + e)^2, e = exp(-|x|).
//!include common/dispatch.wgsl
//!include common/heads.wgsl

struct Params {
    n: u32,
    // 0: trunc_exp, 1: sigmoid.
    kind: u32,
    // Elements are taken every `stride` floats starting at `offset` (e.g. the density column
    // of an MLP output); the result and gradient arrays are dense.
    stride: u32,
    offset: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read_write> y: array<f32>;
@group(0) @binding(2) var<storage, read> dy: array<f32>;
@group(0) @binding(3) var<storage, read_write> dx: array<f32>;

fn act(v: f32) -> f32 {
    if params.kind == 0u {
        return trunc_exp(v);
    }
    return sigmoid(v);
}

@compute @workgroup_size(64)
fn activation_fwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    y[i] = act(x[i * params.stride + params.offset]);
}

// dx[i * stride + offset] = dy[i] * act'(x); other entries of dx are left alone.
@compute @workgroup_size(64)
fn activation_bwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let j = i * params.stride + params.offset;
    var g = act(x[j]);
    if params.kind == 1u {
        // y (1 - y) = e / (1 + e)^2 with e = exp(-|x|): no cancellation when y is near 1.
        let e = exp(-abs(x[j]));
        g = e / ((1.0 + e) * (1.0 + e));
    }
    dx[j] = dy[i] * g;
}
