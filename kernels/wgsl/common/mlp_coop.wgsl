// The tiny MLPs through cooperative matrices (VK_KHR_cooperative_matrix): forward, backward to
// the inputs, and the weight gradient.
//
// Forward and backward (mlp_fwd_coop, mlp_bwd_data_coop), tiny-cuda-nn style: a workgroup owns
// a block of COOP_POINTS points whose activations stay in workgroup memory, in f16, between
// layers; each subgroup multiplies TILE x TILE tiles of them with tiles of the f16 weights
// (mlp_weights_to_f16 writes them per layer as [outputs][inputs], both padded to TILE) with f32
// accumulation; the threads then add the f32 biases and apply ReLU, one point each. The
// backward pass recomputes the forward pass, writing the f32 records that the weight gradient
// reads (each layer's input as the f16 value the tiles used, and its pre-activation gradient),
// and multiplies the pre-activation gradients, scaled per block and layer as below, with the
// weights' tiles. Master weights and biases stay f32.
//
// The weight gradient, from
// the f32 records that field/mlp.wgsl's mlp_bwd_data and the fused training step write (per
// point and layer: the layer's input, then the gradient of its pre-activation, each padded to
// 4 floats; common/mlp_wgrad.wgsl describes the layout).
//
// dW_l = sum over points of delta (x) input is a matrix product D^T X with the points as the
// inner dimension. A workgroup owns a chunk of points and walks it in blocks of COOP_POINTS:
// the block's deltas and inputs are converted to f16 in workgroup memory, each scaled by a
// power of two that puts the block's largest magnitude just under 2^14 (f16 keeps 11 bits of
// mantissa but only 5 of exponent, and the gradients of a NeRF step lie near 1e-6); every
// subgroup then multiplies TILE x TILE tiles, f16 inputs with f32 accumulation, and adds the
// unscaled tile to the workgroup's f32 sum of the layer. The bias is one more column of ones.
// At the end of the chunk one f32 atomic per parameter adds the sums to d_weights.
//
// The including file includes common/coop8.wgsl or common/coop16.wgsl first (the tile).
//!include common/dispatch.wgsl
//!include common/coop_tiles.wgsl

// Widest padded layer input plus the bias tile.
const COOP_XW: u32 = MLP_MAX + TILE;
// Workgroup memory of common/coop_tiles.wgsl: the weight gradient's block inputs
// [point][column] (stride xw: the padded inputs, then the bias tile whose first column is 1)
// and its layer sums [output][column] (stride xw, f32).
const COOP_X: u32 = COOP_POINTS * COOP_XW;
const COOP_ACC: u32 = MLP_MAX * COOP_XW;

struct Params {
    // Points.
    n: u32,
    // Points per workgroup (a multiple of COOP_POINTS).
    chunk: u32,
    // Floats per point of the records.
    saved_stride: u32,
    _pad: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> shape_buf: array<MlpShape>;
@group(0) @binding(1) var<storage, read> saved4: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> d_weights: array<atomic<f32>>;
// The weights in f16, per layer [round_tile(outputs)][round_tile(inputs)], zero padded.
@group(0) @binding(3) var<storage, read> w16: array<f16>;
// The f32 weights (common/mlp.wgsl's layout; the biases are read from here).
@group(0) @binding(4) var<storage, read> weights: array<f32>;
@group(0) @binding(5) var<storage, read> inputs: array<f32>;
@group(0) @binding(6) var<storage, read_write> outputs: array<f32>;
@group(0) @binding(7) var<storage, read> d_outputs: array<f32>;
@group(0) @binding(8) var<storage, read_write> d_inputs: array<f32>;
// The records again, written by mlp_bwd_data_coop.
@group(0) @binding(9) var<storage, read_write> saved: array<f32>;
// w16, written by mlp_weights_to_f16.
@group(0) @binding(10) var<storage, read_write> w16_out: array<f16>;

fn coop_bias(e: u32) -> f32 {
    return weights[e];
}

@compute @workgroup_size(32)
fn mlp_wgrad_coop(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32,
                  @builtin(subgroup_id) sg: u32, @builtin(num_subgroups) n_sg: u32) {
    let s = shape_buf[0];
    let p0 = linear_group(wid, nwg) * params.chunk;
    let p1 = min(p0 + params.chunk, params.n);
    let stride4 = params.saved_stride / 4u;
    var at = 0u;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nip = round_tile(ni);
        let nop = round_tile(no);
        let xw = nip + TILE;
        let x_at = at / 4u;
        let d_at = (at + pad4(ni)) / 4u;
        for (var i = lid; i < nop * xw; i += COOP_POINTS) {
            coop_acc[i] = 0.0;
        }
        // The block loop runs the same number of times in every invocation (p0 < p1 or not).
        for (var b0 = p0; b0 < p1; b0 += COOP_POINTS) {
            if lid == 0u {
                atomicStore(&coop_max[0], 0u);
                atomicStore(&coop_max[1], 0u);
            }
            workgroupBarrier();
            let p = b0 + lid;
            let live = p < p1;
            var mx = 0.0;
            var md = 0.0;
            if live {
                for (var v = 0u; v < pad4(ni) / 4u; v += 1u) {
                    let x = abs(below(saved4[p * stride4 + x_at + v], v, ni));
                    mx = max(mx, max(max(x.x, x.y), max(x.z, x.w)));
                }
                for (var v = 0u; v < pad4(no) / 4u; v += 1u) {
                    let d = abs(below(saved4[p * stride4 + d_at + v], v, no));
                    md = max(md, max(max(d.x, d.y), max(d.z, d.w)));
                }
            }
            atomicMax(&coop_max[0], bitcast<u32>(coop_finite(mx)));
            atomicMax(&coop_max[1], bitcast<u32>(coop_finite(md)));
            workgroupBarrier();
            let ex = coop_exponent(bitcast<f32>(atomicLoad(&coop_max[0])));
            let ed = coop_exponent(bitcast<f32>(atomicLoad(&coop_max[1])));
            let sx = exp2(ex);
            let sd = exp2(ed);
            // Stage this thread's point (zeros past the end and in the padding).
            for (var j = 0u; j < xw; j += 4u) {
                var x = vec4<f32>(0.0);
                if live && j < pad4(ni) {
                    x = below(saved4[p * stride4 + x_at + j / 4u], j / 4u, ni) * sx;
                } else if live && j == nip {
                    x = vec4<f32>(1.0, 0.0, 0.0, 0.0);
                }
                let o = lid * xw + j;
                coop_x[o] = coop_f16(x.x);
                coop_x[o + 1u] = coop_f16(x.y);
                coop_x[o + 2u] = coop_f16(x.z);
                coop_x[o + 3u] = coop_f16(x.w);
            }
            for (var j = 0u; j < nop; j += 4u) {
                var d = vec4<f32>(0.0);
                if live && j < pad4(no) {
                    d = below(saved4[p * stride4 + d_at + j / 4u], j / 4u, no) * sd;
                }
                let o = lid * nop + j;
                coop_d[o] = coop_f16(d.x);
                coop_d[o + 1u] = coop_f16(d.y);
                coop_d[o + 2u] = coop_f16(d.z);
                coop_d[o + 3u] = coop_f16(d.w);
            }
            workgroupBarrier();
            // Tiles of [outputs] x [columns], round-robin over the subgroups (uniform within
            // each subgroup, as cooperative operations require).
            let cols = xw / TILE;
            for (var t = sg; t < (nop / TILE) * cols; t += n_sg) {
                let ot = t / cols;
                let jt = t % cols;
                var c = CoopC();
                for (var k = 0u; k < COOP_POINTS; k += TILE) {
                    // A(o, p) = delta of point p, output o: column-major with stride nop.
                    let a = coopLoad<CoopA>(&coop_d[k * nop + ot * TILE], nop);
                    // B(p, j) = input j of point p: row-major with stride xw.
                    let bm = coopLoadT<CoopB>(&coop_x[k * xw + jt * TILE], xw);
                    c = coopMultiplyAdd(a, bm, c);
                }
                // The bias tile carries unscaled ones.
                let e = select(ed + ex, ed, jt * TILE == nip);
                let at_acc = ot * TILE * xw + jt * TILE;
                let sum = coopLoadT<CoopC>(&coop_acc[at_acc], xw);
                coopStoreT(sum + c * exp2(-e), &coop_acc[at_acc], xw);
            }
            workgroupBarrier();
        }
        // One atomic per parameter: W (row-major, outputs x inputs) then b.
        let off = mlp_offset(s, l);
        for (var i = lid; i < no * (ni + 1u); i += COOP_POINTS) {
            let o = i / (ni + 1u);
            let j = i % (ni + 1u);
            if p0 < p1 {
                if j == ni {
                    atomicAdd(&d_weights[off + no * ni + o], coop_acc[o * xw + nip]);
                } else {
                    atomicAdd(&d_weights[off + o * ni + j], coop_acc[o * xw + j]);
                }
            }
        }
        workgroupBarrier();
        at += pad4(ni) + pad4(no);
    }
}

// Float offset of layer l's segment in a point's record (its input, then its pre-activation
// gradient, each padded to 4).
fn coop_record_offset(s: MlpShape, l: u32) -> u32 {
    var at = 0u;
    for (var k = 0u; k < l; k += 1u) {
        at += pad4(mlp_dim(s, k)) + pad4(mlp_dim(s, k + 1u));
    }
    return at;
}

// One thread per element of w16.
@compute @workgroup_size(64)
fn mlp_weights_to_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                      @builtin(local_invocation_index) lid: u32) {
    let e = linear_group(wid, nwg) * 64u + lid;
    if e >= arrayLength(&w16_out) {
        return;
    }
    let src = coop_w16_source(shape_buf[0], e);
    var v = 0.0;
    if src != COOP_PAD {
        v = weights[src];
    }
    w16_out[e] = coop_f16(v);
}

// The forward pass of the workgroup's block of points (this thread's point p, `live` when it
// exists). On return coop_acc holds the last layer's outputs, row lid at lid * round_tile(n_out).
// With `record`, each layer's input (the f16 values the tiles read) and pre-activation go to
// the point's record in `saved`.
fn coop_forward(s: MlpShape, p: u32, live: bool, lid: u32, sg: u32, n_sg: u32, record: bool) {
    let n_in = mlp_dim(s, 0u);
    let nip0 = round_tile(n_in);
    for (var j = 0u; j < nip0; j += 1u) {
        var v = 0.0;
        if live && j < n_in {
            v = inputs[p * n_in + j];
        }
        coop_x[lid * nip0 + j] = coop_f16(v);
    }
    var at = p * params.saved_stride;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nip = round_tile(ni);
        let nop = round_tile(no);
        let woff = coop_w_offset(s, l);
        if record && live {
            for (var j = 0u; j < pad4(ni); j += 1u) {
                saved[at + j] = select(0.0, f32(coop_x[lid * nip + j]), j < ni);
            }
        }
        coop_layer_forward(woff, nip, nop, sg, n_sg);
        coop_bias_relu(lid, no, nop, mlp_offset(s, l) + no * ni, l + 1u == s.layers);
        if record && live {
            for (var o = 0u; o < pad4(no); o += 1u) {
                saved[at + pad4(ni) + o] = coop_acc[lid * nop + o];
            }
        }
        at += pad4(ni) + pad4(no);
    }
}

// outputs[n, out] = mlp(inputs[n, in]), one point per thread.
@compute @workgroup_size(32)
fn mlp_fwd_coop(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32,
                @builtin(subgroup_id) sg: u32, @builtin(num_subgroups) n_sg: u32) {
    let s = shape_buf[0];
    let p = linear_group(wid, nwg) * COOP_POINTS + lid;
    let live = p < params.n;
    coop_forward(s, p, live, lid, sg, n_sg, false);
    let n_out = mlp_dim(s, s.layers);
    let nop = round_tile(n_out);
    if live {
        for (var o = 0u; o < n_out; o += 1u) {
            outputs[p * n_out + o] = coop_acc[lid * nop + o];
        }
    }
}

// The forward pass again, then d_outputs back to d_inputs, writing every layer's input and
// pre-activation gradient into the point's record (field/mlp.wgsl's layout) for the weight
// gradient.
@compute @workgroup_size(32)
fn mlp_bwd_data_coop(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                     @builtin(local_invocation_index) lid: u32,
                     @builtin(subgroup_id) sg: u32, @builtin(num_subgroups) n_sg: u32) {
    let s = shape_buf[0];
    let p = linear_group(wid, nwg) * COOP_POINTS + lid;
    let live = p < params.n;
    coop_forward(s, p, live, lid, sg, n_sg, true);
    // g: the gradient of this point's layer output, f32.
    var g: array<f32, 64>;
    let n_out = mlp_dim(s, s.layers);
    for (var o = 0u; o < n_out; o += 1u) {
        g[o] = select(0.0, d_outputs[p * n_out + o], live);
    }
    for (var li = 0u; li < s.layers; li += 1u) {
        let l = s.layers - 1u - li;
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nip = round_tile(ni);
        let nop = round_tile(no);
        let woff = coop_w_offset(s, l);
        let d_at = p * params.saved_stride + coop_record_offset(s, l) + pad4(ni);
        // The pre-activation gradient: ReLU'(pre) on hidden layers, identity on the last.
        var md = 0.0;
        for (var o = 0u; o < no; o += 1u) {
            var d = 0.0;
            if live {
                let pre = saved[d_at + o];
                d = select(select(0.0, g[o], pre > 0.0), g[o], l + 1u == s.layers);
                saved[d_at + o] = d;
            }
            g[o] = d;
            md = max(md, abs(d));
        }
        let ed = coop_block_exponent(lid, md);
        let sd = exp2(ed);
        for (var o = 0u; o < nop; o += 1u) {
            coop_d[lid * nop + o] = coop_f16(select(0.0, g[o] * sd, o < no));
        }
        // g_in (points x inputs) = delta (points x outputs) W (outputs x inputs).
        coop_layer_backward(woff, nip, nop, sg, n_sg);
        let inv = exp2(-ed);
        for (var j = 0u; j < ni; j += 1u) {
            g[j] = coop_acc[lid * nip + j] * inv;
        }
    }
    let n_in = mlp_dim(s, 0u);
    if live {
        for (var j = 0u; j < n_in; j += 1u) {
            d_inputs[p * n_in + j] = g[j];
        }
    }
}
