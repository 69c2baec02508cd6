// Tiny MLPs evaluated per thread with the weights in a uniform block. The including file
// declares `mlp: array<vec4<f32>, 4096>` (64 KiB) as a `var<uniform>` binding, holding
// common/mlp.wgsl's layout: per layer W (row-major) then b. Every lane reads the same entry. On
// lavapipe a dynamically indexed uniform load is a branchless 8-lane gather. A storage load at
// an offset that is not a constant is a per-lane loop with branches: measured about 3x slower
// for a 64-wide MLP on Mesa 25.0.
//
// Weight addresses are passed through `mlp_uni(x, bits)` (below), which rebuilds x from an
// identity table that the including file's push constants hold as `params.lut` = (0, 1, 2, 3).
// Mesa's gallivm (25.0) treats a value as uniform across the lanes only when it derives from
// constants and push constants alone, and loads a uniform block entry at a uniform offset once,
// as a scalar, instead of lane by lane; a loop counter or a value read from a storage buffer is
// treated as varying even when every lane holds the same. The weight offsets here derive from
// both, so the table lookup (one lane-by-lane push-constant load per 2 bits) turns each row's
// 4 x (inputs / 4) lane-by-lane loads into scalar ones.
//
// Requirements, which the host checks: every layer's input width and weight offset is a
// multiple of 4 (W rows are read as vec4s), and every width is at most 64. The inner loops have
// a constant trip count (16 vec4s), so lavapipe unrolls them (it unrolls up to 32 iterations).
// The activations, 16 vec4s, are then read at constant indices and stay in registers.
//!include common/mlp.wgsl

// x (< 2^bits, bits even) rebuilt two bits at a time from push-constant loads of `params.lut`.
// A push-constant load counts as uniform whatever its index (nir_src_is_always_uniform), so the
// result, equal to x, lets a uniform-block load at an offset built from it run once as a
// scalar. x must be the same in every active lane (true of every offset here).
fn mlp_uni(x: u32, bits: u32) -> u32 {
    var r = 0u;
    for (var b = 0u; b < bits; b += 2u) {
        r |= params.lut[(x >> b) & 3u] << b;
    }
    return r;
}

// Float e of the block.
fn mlp_block_at(e: u32) -> f32 {
    return mlp[e >> 2u][e & 3u];
}

// Activations of one point: a[j / 4][j % 4] is activation j (at most 64).
alias Act = array<vec4<f32>, 16>;

fn act_set(a: ptr<function, Act>, j: u32, v: f32) {
    (*a)[j >> 2u][j & 3u] = v;
}

fn act_get(a: ptr<function, Act>, j: u32) -> f32 {
    return (*a)[j >> 2u][j & 3u];
}

// Pre-activations of one layer: z[0 .. no] = W a + b, with W at float offset w of the block.
fn mlp_layer(w_in: u32, ni_in: u32, no_in: u32, a: ptr<function, Act>, z: ptr<function, Act>) {
    let w = mlp_uni(w_in, 16u);
    let ni = mlp_uni(ni_in, 8u);
    let no = mlp_uni(no_in, 8u);
    let n4 = ni >> 2u;
    let no4 = (no + 3u) >> 2u;
    for (var o4 = 0u; o4 < no4; o4 += 1u) {
        var r = vec4<f32>(0.0);
        for (var q = 0u; q < 4u; q += 1u) {
            // Rows past the last output repeat it (their results are never read).
            let o = mlp_uni(min(o4 * 4u + q, no - 1u), 8u);
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
fn mlp_layer_back(w_in: u32, ni_in: u32, no: u32, d: ptr<function, Act>, gi: ptr<function, Act>) {
    let w = mlp_uni(w_in, 16u);
    let ni = mlp_uni(ni_in, 8u);
    let n4 = ni >> 2u;
    for (var j = 0u; j < 16u; j += 1u) {
        (*gi)[j] = vec4<f32>(0.0);
    }
    for (var o = 0u; o < no; o += 1u) {
        let dv = act_get(d, o);
        let row = (w + mlp_uni(o, 8u) * ni) >> 2u;
        for (var j = 0u; j < 16u; j += 1u) {
            if j < n4 {
                (*gi)[j] += mlp[row + j] * dv;
            }
        }
    }
}


// Register blocking: MLP_GROUP points per thread share each weight load. On lavapipe a weight
// vec4 read from the block costs far more than its four multiply-adds (the load is assembled
// lane by lane), so four points per load ran the 32-64-64-3 forward 2.6x faster than one
// (bench kernels, one run).
const MLP_GROUP: u32 = 4u;
alias ActGroup = array<Act, 4>;

// mlp_layer for the group: z[k][0 .. no] = W a[k] + b.
fn mlp_layer_group(w_in: u32, ni_in: u32, no_in: u32, a: ptr<function, ActGroup>,
                   z: ptr<function, ActGroup>) {
    let w = mlp_uni(w_in, 16u);
    let ni = mlp_uni(ni_in, 8u);
    let no = mlp_uni(no_in, 8u);
    let n4 = ni >> 2u;
    let no4 = (no + 3u) >> 2u;
    for (var o4 = 0u; o4 < no4; o4 += 1u) {
        var r0 = vec4<f32>(0.0);
        var r1 = vec4<f32>(0.0);
        var r2 = vec4<f32>(0.0);
        var r3 = vec4<f32>(0.0);
        for (var q = 0u; q < 4u; q += 1u) {
            // Rows past the last output repeat it (their results are never read).
            let o = mlp_uni(min(o4 * 4u + q, no - 1u), 8u);
            let row = (w + o * ni) >> 2u;
            var acc = vec4<f32>(0.0);
            for (var j = 0u; j < 16u; j += 1u) {
                if j < n4 {
                    let wv = mlp[row + j];
                    acc += vec4<f32>(dot(wv, (*a)[0][j]), dot(wv, (*a)[1][j]), dot(wv, (*a)[2][j]),
                                     dot(wv, (*a)[3][j]));
                }
            }
            let bi = w + no * ni + o;
            let r = acc + vec4<f32>(mlp[bi >> 2u][bi & 3u]);
            r0[q] = r.x;
            r1[q] = r.y;
            r2[q] = r.z;
            r3[q] = r.w;
        }
        (*z)[0][o4] = r0;
        (*z)[1][o4] = r1;
        (*z)[2][o4] = r2;
        (*z)[3][o4] = r3;
    }
}

// mlp_layer_back for the group: gi[k][0 .. ni] = W^T d[k].
fn mlp_layer_back_group(w_in: u32, ni_in: u32, no: u32, d: ptr<function, ActGroup>,
                        gi: ptr<function, ActGroup>) {
    let w = mlp_uni(w_in, 16u);
    let ni = mlp_uni(ni_in, 8u);
    let n4 = ni >> 2u;
    for (var j = 0u; j < 16u; j += 1u) {
        (*gi)[0][j] = vec4<f32>(0.0);
        (*gi)[1][j] = vec4<f32>(0.0);
        (*gi)[2][j] = vec4<f32>(0.0);
        (*gi)[3][j] = vec4<f32>(0.0);
    }
    for (var o = 0u; o < no; o += 1u) {
        let o4 = o >> 2u;
        let oc = o & 3u;
        let d0 = (*d)[0][o4][oc];
        let d1 = (*d)[1][o4][oc];
        let d2 = (*d)[2][o4][oc];
        let d3 = (*d)[3][o4][oc];
        let row = (w + mlp_uni(o, 8u) * ni) >> 2u;
        for (var j = 0u; j < 16u; j += 1u) {
            if j < n4 {
                let wv = mlp[row + j];
                (*gi)[0][j] += wv * d0;
                (*gi)[1][j] += wv * d1;
                (*gi)[2][j] += wv * d2;
                (*gi)[3][j] += wv * d3;
            }
        }
    }
}

// mlp_activate for the group: a[k] <- z[k], with ReLU when `relu`.
fn mlp_activate_group(z: ptr<function, ActGroup>, a: ptr<function, ActGroup>, relu: bool) {
    for (var k = 0u; k < MLP_GROUP; k += 1u) {
        for (var j = 0u; j < 16u; j += 1u) {
            (*a)[k][j] = select((*z)[k][j], max((*z)[k][j], vec4<f32>(0.0)), relu);
        }
    }
}

// mlp_forward for the group, in place on a.
fn mlp_forward_group(s: MlpShape, base: u32, a: ptr<function, ActGroup>) {
    var z: ActGroup;
    for (var l = 0u; l < s.layers; l += 1u) {
        mlp_layer_group(base + mlp_offset(s, l), mlp_dim(s, l), mlp_dim(s, l + 1u), a, &z);
        mlp_activate_group(&z, a, l + 1u < s.layers);
    }
}
