// A workgroup's block of COOP_POINTS points through one MLP layer with cooperative matrices
// (VK_KHR_cooperative_matrix): the tiny-cuda-nn layout shared by the standalone MLP kernels
// (common/mlp_coop.wgsl) and the fused ones (common/step_coop.wgsl, common/march_coop.wgsl).
//
// The block's activations sit in workgroup memory in f16, one row per point (coop_x, row
// stride the layer's padded input width); every subgroup multiplies TILE x TILE tiles of them
// with tiles of the layer's f16 weights, accumulating in f32, and stores the products in
// coop_acc (row stride the padded output width). The threads then add the f32 biases and
// apply ReLU, one point each. Backward, the block's pre-activation gradients (coop_d, f16,
// scaled by a power of two per block and layer, coop_exponent) times the weights' tiles give
// the gradients of the layer's inputs in coop_acc.
//
// The f16 weights are laid out per layer as [outputs][inputs], both padded to TILE and zero in
// the padding, in the including file's binding `w16: array<f16>` (coop_w_offset gives a layer's
// first element after the MLP's own). The including file:
//   - includes common/coop8.wgsl or common/coop16.wgsl first (f16 and cooperative matrices
//     enabled, TILE, and the matrix types CoopA, CoopB and CoopC);
//   - declares COOP_X (halves of coop_x) and COOP_ACC (floats of coop_acc);
//   - defines `fn coop_bias(e: u32) -> f32`, the f32 parameter at float e of the MLPs'
//     weights (common/mlp.wgsl's layout).
// The functions with barriers or cooperative operations (coop_block_max and its users,
// coop_layer_forward, coop_layer_backward, coop_mlp_forward) must be called by the whole
// workgroup in uniform control flow.
//!include common/mlp.wgsl

// Points per block: the workgroup size, one point per thread. (64 would put the standalone
// weight gradient's workgroup memory past lavapipe's 32 KiB.)
const COOP_POINTS: u32 = 32u;

var<workgroup> coop_x: array<f16, COOP_X>;
var<workgroup> coop_d: array<f16, COOP_POINTS * MLP_MAX>;
var<workgroup> coop_acc: array<f32, COOP_ACC>;
// Largest magnitudes of the block, as f32 bits (non-negative floats order as u32).
var<workgroup> coop_max: array<atomic<u32>, 2>;

// v in f16, saturated at the largest finite f16 (65504) rather than overflowing to infinity
// (which the products would turn into NaN): the activations' conversion.
fn coop_f16(v: f32) -> f16 {
    return f16(clamp(v, -65504.0, 65504.0));
}

fn round_tile(x: u32) -> u32 {
    return (x + TILE - 1u) / TILE * TILE;
}

// Exponent e with m * 2^e in [2^13, 2^14) (0 for m = 0; clamped so the scale stays finite).
// f16 keeps 11 bits of mantissa but only 5 of exponent, and the gradients of a NeRF step lie
// near 1e-6: scaled so, they keep their precision.
fn coop_exponent(m: f32) -> f32 {
    if m <= 0.0 {
        return 0.0;
    }
    return clamp(floor(13.0 - log2(m)), -100.0, 100.0);
}

// The largest v over the workgroup (every thread passes its own).
fn coop_block_max(lid: u32, v: u32) -> u32 {
    // Every thread has read the previous result before the reset.
    workgroupBarrier();
    if lid == 0u {
        atomicStore(&coop_max[1], 0u);
    }
    workgroupBarrier();
    atomicMax(&coop_max[1], v);
    workgroupBarrier();
    return atomicLoad(&coop_max[1]);
}

// m (>= 0) as a block's scale sees it: a non-finite magnitude counts as 0, so one point's
// infinite or NaN gradient does not flush the rest of its block to zero (its own values
// saturate, or stay NaN, in coop_f16).
fn coop_finite(m: f32) -> f32 {
    return select(0.0, m, m <= 3.4028235e38);
}

// coop_exponent of the largest finite m over the workgroup (m >= 0).
fn coop_block_exponent(lid: u32, m: f32) -> f32 {
    return coop_exponent(bitcast<f32>(coop_block_max(lid, bitcast<u32>(coop_finite(m)))));
}

// Whether any thread of the workgroup passes true: the same answer in every thread.
fn coop_any(lid: u32, v: bool) -> bool {
    return coop_block_max(lid, u32(v)) != 0u;
}

// Element offset of layer l's f16 weights.
fn coop_w_offset(s: MlpShape, l: u32) -> u32 {
    var off = 0u;
    for (var k = 0u; k < l; k += 1u) {
        off += round_tile(mlp_dim(s, k + 1u)) * round_tile(mlp_dim(s, k));
    }
    return off;
}

// The float offset, in common/mlp.wgsl's layout, of the weight that element e of an MLP's f16
// weights holds, or COOP_PAD for the padding and past the end.
const COOP_PAD: u32 = 0xffffffffu;

fn coop_w16_source(s: MlpShape, e: u32) -> u32 {
    var off = 0u;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nip = round_tile(ni);
        let size = round_tile(no) * nip;
        if e >= off && e < off + size {
            let o = (e - off) / nip;
            let j = (e - off) % nip;
            if o < no && j < ni {
                return mlp_offset(s, l) + o * ni + j;
            }
            return COOP_PAD;
        }
        off += size;
    }
    return COOP_PAD;
}

// coop_acc[r * nop + o] = sum over k of coop_x[r * nip + k] W[o][k] for the block's rows r,
// with the layer's f16 weights at element woff of w16. Starts with a barrier (the rows
// each thread staged are then visible to every subgroup) and ends with one.
fn coop_layer_forward(woff: u32, nip: u32, nop: u32, sg: u32, n_sg: u32) {
    workgroupBarrier();
    let cols = nop / TILE;
    for (var t = sg; t < (COOP_POINTS / TILE) * cols; t += n_sg) {
        let rt = t / cols;
        let ot = t % cols;
        var c = CoopC();
        for (var k = 0u; k < nip; k += TILE) {
            // A(r, k): activations, row-major with stride nip.
            let a = coopLoadT<CoopA>(&coop_x[rt * TILE * nip + k], nip);
            // B(k, o) = W[o][k]: column-major with stride nip.
            let b = coopLoad<CoopB>(&w16[woff + ot * TILE * nip + k], nip);
            c = coopMultiplyAdd(a, b, c);
        }
        // (A let: naga 30 does not emit an index computed inside coopStore's pointer.)
        let at_c = rt * TILE * nop + ot * TILE;
        coopStoreT(c, &coop_acc[at_c], nop);
    }
    workgroupBarrier();
}

// coop_acc[r * nip + j] = sum over o of coop_d[r * nop + o] W[o][j]: the block's scaled
// pre-activation gradients back to the layer's inputs. Starts and ends with a barrier.
fn coop_layer_backward(woff: u32, nip: u32, nop: u32, sg: u32, n_sg: u32) {
    workgroupBarrier();
    let cols = nip / TILE;
    for (var t = sg; t < (COOP_POINTS / TILE) * cols; t += n_sg) {
        let rt = t / cols;
        let jt = t % cols;
        var c = CoopC();
        for (var k = 0u; k < nop; k += TILE) {
            // A(r, o): scaled gradients, row-major with stride nop.
            let a = coopLoadT<CoopA>(&coop_d[rt * TILE * nop + k], nop);
            // B(o, j) = W[o][j]: row-major with stride nip.
            let b = coopLoadT<CoopB>(&w16[woff + k * nip + jt * TILE], nip);
            c = coopMultiplyAdd(a, b, c);
        }
        let at_c = rt * TILE * nip + jt * TILE;
        coopStoreT(c, &coop_acc[at_c], nip);
    }
    workgroupBarrier();
}

// After coop_layer_forward, each thread its own row: coop_acc row lid (stride nop) becomes the
// pre-activations, the products plus the f32 biases at float boff (zero past no), and unless
// `last`, coop_x row lid (stride nop) the next layer's input, their ReLU in f16. No tile reads
// coop_x any more, and each thread touches only its own rows: no barrier.
fn coop_bias_relu(lid: u32, no: u32, nop: u32, boff: u32, last: bool) {
    for (var o = 0u; o < nop; o += 1u) {
        var z = 0.0;
        if o < no {
            z = coop_acc[lid * nop + o] + coop_bias(boff + o);
        }
        coop_acc[lid * nop + o] = z;
        if !last {
            coop_x[lid * nop + o] = coop_f16(max(z, 0.0));
        }
    }
}

// The forward pass of an MLP (shape s, f16 weights at element wbase of w16, f32 parameters at
// float base of coop_bias's) on the block's rows, staged in coop_x with stride
// round_tile(inputs), without records. On return coop_acc holds the outputs, row lid at
// lid * round_tile(outputs).
fn coop_mlp_forward(s: MlpShape, wbase: u32, base: u32, lid: u32, sg: u32, n_sg: u32) {
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nop = round_tile(no);
        coop_layer_forward(wbase + coop_w_offset(s, l), round_tile(ni), nop, sg, n_sg);
        coop_bias_relu(lid, no, nop, base + mlp_offset(s, l) + no * ni, l + 1u == s.layers);
    }
}
