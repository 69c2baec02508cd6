// Tiny MLPs evaluated per thread with the weights in a uniform block. The including file
// declares `mlp: array<vec4<f32>, 4096>` (64 KiB) as a `var<uniform>` binding, holding
// common/mlp.wgsl's layout: per layer W (row-major) then b. Every lane reads the same entry. On
// lavapipe a dynamically indexed uniform load is a branchless 8-lane gather. A storage load at
// an offset that is not a constant is a per-lane loop with branches: measured about 3x slower
// for a 64-wide MLP on Mesa 25.0.
//
// Requirements, which the host checks: every layer's input width and weight offset is a
// multiple of 4 (W rows are read as vec4s), and every width is at most 64. The inner loops have
// a constant trip count (16 vec4s), so lavapipe unrolls them (it unrolls up to 32 iterations).
// The activations, 16 vec4s, are then read at constant indices and stay in registers.
//!include common/mlp.wgsl

// Activations of one point: a[j / 4][j % 4] is activation j (at most 64).
alias Act = array<vec4<f32>, 16>;

fn act_set(a: ptr<function, Act>, j: u32, v: f32) {
    (*a)[j >> 2u][j & 3u] = v;
}

fn act_get(a: ptr<function, Act>, j: u32) -> f32 {
    return (*a)[j >> 2u][j & 3u];
}

// Pre-activations of one layer: z[0 .. no] = W a + b, with W at float offset w of the block.
fn mlp_layer(w: u32, ni: u32, no: u32, a: ptr<function, Act>, z: ptr<function, Act>) {
    let n4 = ni >> 2u;
    let no4 = (no + 3u) >> 2u;
    for (var o4 = 0u; o4 < no4; o4 += 1u) {
        var r = vec4<f32>(0.0);
        for (var q = 0u; q < 4u; q += 1u) {
            // Rows past the last output repeat it (their results are never read).
            let o = min(o4 * 4u + q, no - 1u);
            let row = (w + o * ni) >> 2u;
            var acc = 0.0;
            for (var j = 0u; j < 16u; j += 1u) {
                if j < n4 {
                    acc += dot(mlp[row + j], (*a)[j]);
                }
            }
            let bi = w + no * ni + o;
            r[q] = acc + mlp[bi >> 2u][bi & 3u];
        }
        (*z)[o4] = r;
    }
}

// a <- z, with ReLU when `relu`.
fn mlp_activate(z: ptr<function, Act>, a: ptr<function, Act>, relu: bool) {
    for (var j = 0u; j < 16u; j += 1u) {
        (*a)[j] = select((*z)[j], max((*z)[j], vec4<f32>(0.0)), relu);
    }
}

// The whole MLP (shape s, weights at float offset base of the block) in place on a.
fn mlp_forward(s: MlpShape, base: u32, a: ptr<function, Act>) {
    var z: Act;
    for (var l = 0u; l < s.layers; l += 1u) {
        mlp_layer(base + mlp_offset(s, l), mlp_dim(s, l), mlp_dim(s, l + 1u), a, &z);
        mlp_activate(&z, a, l + 1u < s.layers);
    }
}

// gi[0 .. ni] = W^T d for the layer at float offset w (d: gradient of its pre-activations).
fn mlp_layer_back(w: u32, ni: u32, no: u32, d: ptr<function, Act>, gi: ptr<function, Act>) {
    let n4 = ni >> 2u;
    for (var j = 0u; j < 16u; j += 1u) {
        (*gi)[j] = vec4<f32>(0.0);
    }
    for (var o = 0u; o < no; o += 1u) {
        let dv = act_get(d, o);
        let row = (w + o * ni) >> 2u;
        for (var j = 0u; j < 16u; j += 1u) {
            if j < n4 {
                (*gi)[j] += mlp[row + j] * dv;
            }
        }
    }
}
