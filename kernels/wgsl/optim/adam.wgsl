// Adam over one flat parameter buffer (Kingma & Ba), one thread per vec4, ITEMS vec4s per
// thread. The host passes the step's learning rate and the bias corrections 1 - beta^t, so a
// schedule costs nothing here. Gradients are multiplied by grad_scale (undo loss scaling);
// non-finite gradient components are treated as zero, so one bad sample cannot poison the
// moments. Optional L2 weight decay is added to the gradient.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
    lr: f32,
    beta1: f32,
    beta2: f32,
    eps: f32,
    // 1 - beta1^t and 1 - beta2^t for step t (1-based).
    bias1: f32,
    bias2: f32,
    grad_scale: f32,
    weight_decay: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read_write> param: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> grad: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> m1: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> m2: array<vec4<f32>>;

const WG: u32 = 64u;
const ITEMS: u32 = 4u;

fn finite(v: vec4<f32>) -> vec4<bool> {
    // NaN fails v == v; +-inf has |v| above the largest finite f32.
    return (v == v) & (abs(v) <= vec4<f32>(3.4028235e38));
}

@compute @workgroup_size(64)
fn adam(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let g0 = linear_group(wid, nwg);
    for (var k = 0u; k < ITEMS; k += 1u) {
        let i = (g0 * ITEMS + k) * WG + lid;
        let base = i * 4u;
        if base >= params.n {
            return;
        }
        let p = param[i];
        var g = grad[i] * params.grad_scale;
        g = select(vec4<f32>(0.0), g, finite(g)) + params.weight_decay * p;
        let m = params.beta1 * m1[i] + (1.0 - params.beta1) * g;
        let v = params.beta2 * m2[i] + (1.0 - params.beta2) * g * g;
        let step = params.lr * (m / params.bias1) / (sqrt(v / params.bias2) + params.eps);
        let np = p - step;
        if base + 3u < params.n {
            m1[i] = m;
            m2[i] = v;
            param[i] = np;
        } else {
            for (var c = 0u; base + c < params.n; c += 1u) {
                m1[i][c] = m[c];
                m2[i][c] = v[c];
                param[i][c] = np[c];
            }
        }
    }
}
