// Adam's update of one vec4 of a flat parameter buffer, shared by the dense kernel
// (`optim/adam.wgsl`) and the sparse one (`optim/adam_sparse.wgsl`); each declares its `grad`
// binding and entry point. See `optim/adam.wgsl` for the arithmetic (loss scaling, non-finite
// gradients, weight decay, hash decay folded in, ranged buffers).
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

// The update of vec4 i (its first float `base` in the bound range) with the raw gradient
// `g_raw`: scaled, non-finite components zeroed, weight and hash decay added, then Adam. A
// partial last vec4 writes only its floats below n.
fn adam_update(i: u32, base: u32, g_raw: vec4<f32>) {
    let p = param[i];
    var g = g_raw * params.grad_scale;
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
