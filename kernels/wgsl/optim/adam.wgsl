// Adam over one flat parameter buffer (Kingma & Ba), one thread per vec4, ITEMS vec4s per
// thread. The host passes the step's learning rate and the bias corrections 1 - beta^t, so a
// schedule costs nothing here. Gradients are multiplied by grad_scale (undo loss scaling);
// non-finite gradient components are treated as zero, so one bad sample cannot poison the
// moments. Optional L2 weight decay is added to the gradient.
//
// Hash decay (Zip-NeRF, L = lambda sum_l mean(V_l^2)) is folded in: for the decay_floats floats
// from decay_start (the hash table), 2 lambda V / (size_l F) is added to the gradient, with the
// level bounds from a uniform block (`decay_block[l] = (first float of level l relative to the
// table, size_l * F, _, _)`, `decay_levels` entries). That saves the separate gradient pass over
// the table, which reads and writes as many bytes as this kernel.
//
// Buffers larger than one storage binding are updated in ranges: `offset` is the first float of
// the bound range in the whole buffer (decay_start counts in the whole buffer too).
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
    decay_lambda: f32,
    decay_start: u32,
    // 0: no hash decay.
    decay_floats: u32,
    decay_levels: u32,
    offset: u32,
    _pad1: u32,
    _pad2: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read_write> param: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> grad: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> m1: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> m2: array<vec4<f32>>;
@group(0) @binding(4) var<uniform> decay_block: array<vec4<u32>, 65>;

const WG: u32 = 64u;
const ITEMS: u32 = 4u;

fn finite(v: vec4<f32>) -> vec4<bool> {
    // NaN fails v == v; +-inf has |v| above the largest finite f32.
    return (v == v) & (abs(v) <= vec4<f32>(3.4028235e38));
}

// The level holding table float t: binary search over the level block (6 halvings cover 64
// levels; a fixed trip count so the loop unrolls).
fn decay_level(t: u32) -> u32 {
    var lo = 0u;
    var hi = params.decay_levels;
    for (var it = 0u; it < 6u; it += 1u) {
        if hi - lo > 1u {
            let mid = (lo + hi) / 2u;
            if t >= decay_block[mid].x {
                lo = mid;
            } else {
                hi = mid;
            }
        }
    }
    return lo;
}

// The hash-decay coefficient 2 lambda / (size_l F) of parameter idx (0 outside the table).
fn decay_coef(idx: u32) -> f32 {
    if idx < params.decay_start || idx - params.decay_start >= params.decay_floats {
        return 0.0;
    }
    return 2.0 * params.decay_lambda / f32(decay_block[decay_level(idx - params.decay_start)].y);
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
        // The vec4's first float in the whole buffer.
        let gb = base + params.offset;
        if params.decay_floats != 0u && gb + 3u >= params.decay_start
            && gb < params.decay_start + params.decay_floats {
            var c: vec4<f32>;
            let inside = gb >= params.decay_start;
            let l = decay_level(select(0u, gb - params.decay_start, inside));
            // decay_block[l + 1].x is the next level's first float (or the table's end).
            if inside && gb + 3u - params.decay_start < decay_block[l + 1u].x {
                // The whole vec4 lies in level l.
                c = vec4<f32>(2.0 * params.decay_lambda / f32(decay_block[l].y));
            } else {
                c = vec4<f32>(decay_coef(gb), decay_coef(gb + 1u), decay_coef(gb + 2u), decay_coef(gb + 3u));
            }
            g += c * p;
        }
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
