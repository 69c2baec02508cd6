// The MLP backward pass with its saved activations in f16 (precision "f16"): the inputs of every
// layer and the gradients of every pre-activation, which the weight-gradient pass reads, are
// stored as f16 with one power-of-two scale per point and segment (block floating point), so
// that neither overflows nor underflows: a segment's largest magnitude m is stored in
// [2^14, 2^15) and values below m 2^-29 lose precision (f16 subnormals). The record is half the
// bytes of the f32 one. Arithmetic stays f32 (weights from the f32 uniform block), the
// forward pass is the f32 one, and Inf and NaN propagate as in f32.
//
// The f16 values are packed two to a word with pack2x16float (core SPIR-V, so no device
// feature is needed). On lavapipe this ran the backward as fast as `enable f16;` vec4<f16>
// loads or faster, with bit-identical results.
//
// One point's record, in units of 4 f16 values (2 words): 2 header units holding the exponents
// as small integers (layer l's input at header[l / 2][2 (l % 2)], its gradient at the next
// component), then the segments of the f32 layout (common/mlp_wgrad.wgsl) at a quarter of
// their offsets. Needs the uniform-block shape (common/mlp_block.wgsl; the host checks).
//!include common/dispatch.wgsl
//!include common/mlp_block.wgsl
//!include common/mlp_wgrad.wgsl

// The same block as mlp.wgsl; saved_stride counts units of 4 f16 values per point here.
struct Params {
    n: u32,
    chunk: u32,
    saved_stride: u32,
    groups: u32,
    // (0, 1, 2, 3): the identity table of common/mlp_block.wgsl's mlp_uni.
    lut: vec4<u32>,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> shape_buf: array<MlpShape>;
@group(0) @binding(2) var<storage, read> inputs: array<f32>;
@group(0) @binding(4) var<storage, read> d_outputs: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_inputs: array<f32>;
@group(0) @binding(6) var<storage, read_write> saved: array<vec2<u32>>;
@group(0) @binding(7) var<storage, read_write> d_weights: array<atomic<f32>>;
@group(0) @binding(8) var<uniform> mlp: array<vec4<f32>, 4096>;

// Header vec4s per record.
const HEAD: u32 = 2u;
// The smallest normal f16: stored ReLU outputs stay at least this (scaled), so their sign
// survives.
const F16_MIN_NORMAL: f32 = 6.1035156e-5;

// 2^k for k in [-126, 127].
fn pow2(k: i32) -> f32 {
    return bitcast<f32>(u32(k + 127) << 23u);
}

// 2^k, or 0 below the normal f32 range and Inf above it.
fn pow2_or_flush(k: i32) -> f32 {
    if k < -126 {
        return 0.0;
    }
    if k > 127 {
        return bitcast<f32>(0x7f800000u);
    }
    return pow2(k);
}

// The exponent k that puts m in [2^14, 2^15) as m 2^-k (clamped to [-126, 126]: 0 and f32
// subnormals take -126, Inf and NaN 114).
fn seg_exp(m: f32) -> i32 {
    let e = i32((bitcast<u32>(m) >> 23u) & 0xffu) - 127;
    return clamp(e - 14, -126, 126);
}

// Stores v[0 .. n] at saved[at ..] scaled by 2^-k (zeros past n); returns k. With `relu_out`
// (non-negative values whose sign backward reads) positive values stay positive.
fn store_seg(at: u32, v: ptr<function, Act>, n: u32, relu_out: bool) -> f32 {
    let lanes = vec4<u32>(0u, 1u, 2u, 3u);
    var m = 0.0;
    for (var j = 0u; j < 16u; j += 1u) {
        let x = select(vec4<f32>(0.0), abs((*v)[j]), vec4<u32>(4u * j) + lanes < vec4<u32>(n));
        m = max(m, max(max(x.x, x.y), max(x.z, x.w)));
    }
    let k = seg_exp(m);
    let sc = pow2(-k);
    let n4 = (n + 3u) >> 2u;
    for (var j = 0u; j < 16u; j += 1u) {
        if j < n4 {
            var x = select(vec4<f32>(0.0), (*v)[j] * sc, vec4<u32>(4u * j) + lanes < vec4<u32>(n));
            if relu_out {
                x = select(x, max(x, vec4<f32>(F16_MIN_NORMAL)), x > vec4<f32>(0.0));
            }
            saved[at + j] = pack4(x);
        }
    }
    return f32(k);
}

// mlp_bwd_data_block with the f16 record: recomputes the forward pass, back-propagates
// d_outputs into d_inputs and writes each layer's input and pre-activation gradient. ReLU'
// of a hidden layer comes from the sign of the next layer's stored input.
@compute @workgroup_size(64)
fn mlp_bwd_data_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                    @builtin(local_invocation_index) lid: u32) {
    let p = linear_group(wid, nwg) * 64u + lid;
    if p >= params.n {
        return;
    }
    let s = shape_buf[0];
    var a: Act;
    var z: Act;
    var head = array<vec4<f32>, 2>();
    let n_in = mlp_dim(s, 0u);
    for (var j = 0u; j < n_in; j += 1u) {
        act_set(&a, j, inputs[p * n_in + j]);
    }
    let base = p * params.saved_stride;
    var at = base + HEAD;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        head[l >> 1u][2u * (l & 1u)] = store_seg(at, &a, ni, l > 0u);
        at += (pad4(ni) + pad4(no)) / 4u;
        mlp_layer(mlp_offset(s, l), ni, no, &a, &z);
        mlp_activate(&z, &a, l + 1u < s.layers);
    }
    // Backward: g holds dL/d(layer output); walk the layers in reverse.
    var g: Act;
    let n_out = mlp_dim(s, s.layers);
    for (var o = 0u; o < n_out; o += 1u) {
        act_set(&g, o, d_outputs[p * n_out + o]);
    }
    for (var li = 0u; li < s.layers; li += 1u) {
        let l = s.layers - 1u - li;
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let no4 = pad4(no) / 4u;
        at -= no4;
        if l + 1u == s.layers {
            z = g;
        } else {
            // ReLU'(pre) = (the next layer's input > 0); that segment follows this one.
            for (var o4 = 0u; o4 < 16u; o4 += 1u) {
                if o4 < no4 {
                    let next = unpack4(saved[at + no4 + o4]);
                    z[o4] = select(vec4<f32>(0.0), g[o4], next > vec4<f32>(0.0));
                }
            }
        }
        head[l >> 1u][2u * (l & 1u) + 1u] = store_seg(at, &z, no, false);
        at -= pad4(ni) / 4u;
        mlp_layer_back(mlp_offset(s, l), ni, no, &z, &g);
    }
    saved[base] = pack4(head[0]);
    saved[base + 1u] = pack4(head[1]);
    for (var j = 0u; j < n_in; j += 1u) {
        d_inputs[p * n_in + j] = act_get(&g, j);
    }
}

// One point's contribution to a weight-gradient tile on the f16 record at unit `base`: the
// layer's two exponents from the header (unit hv, components hc and hc + 1), the tile's 16
// inputs and 16 deltas at units `u`.
fn wgrad_point_f16(base: u32, hv: u32, hc: u32, u: WgradUnits, c: u32, with_bias: bool,
                   acc: ptr<function, array<vec4<f32>, 8>>,
                   bias: ptr<function, array<vec4<f32>, 4>>) {
    let h = unpack4(saved[base + hv]);
    let kx = i32(h[hc]);
    let kd = i32(h[hc + 1u]);
    var x: array<vec4<f32>, 4>;
    var d: array<vec4<f32>, 4>;
    for (var k = 0u; k < 4u; k += 1u) {
        x[k] = unpack4(saved[base + u.x[k]]);
        d[k] = unpack4(saved[base + u.d[k]]);
    }
    wgrad_tile_add(wgrad_pick(x, c), d, pow2_or_flush(kx + kd), pow2_or_flush(kd), with_bias, acc,
                   bias);
}

// mlp_wgrad on the f16 record (common/mlp_wgrad.wgsl's tiles, the points unrolled as in
// field/mlp.wgsl): per point one header vec4, the tile's inputs and deltas (f16), their
// product unscaled by the two segments' scales.
@compute @workgroup_size(8)
fn mlp_wgrad_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let g = linear_group(wid, nwg);
    let t = wgrad_tile(shape_buf[0], g % params.groups);
    var acc = array<vec4<f32>, 8>();
    var bias = array<vec4<f32>, 4>();
    if t.valid {
        let p0 = (g / params.groups) * params.chunk;
        let p1 = min(p0 + params.chunk, params.n);
        let with_bias = t.j0 == 0u;
        let hv = t.layer >> 1u;
        let hc = 2u * (t.layer & 1u);
        let u = wgrad_units(t, HEAD);
        let stride = params.saved_stride;
        var p = p0;
        for (; p + WGRAD_UNROLL <= p1; p += WGRAD_UNROLL) {
            for (var q = 0u; q < WGRAD_UNROLL; q += 1u) {
                wgrad_point_f16((p + q) * stride, hv, hc, u, lid, with_bias, &acc, &bias);
            }
        }
        for (; p < p1; p += 1u) {
            wgrad_point_f16(p * stride, hv, hc, u, lid, with_bias, &acc, &bias);
        }
    }
    wgrad_tile_flush(t, lid, &acc, &bias);
}

// Four f16 values packed in two words, and back.
fn pack4(v: vec4<f32>) -> vec2<u32> {
    return vec2<u32>(pack2x16float(v.xy), pack2x16float(v.zw));
}

fn unpack4(w: vec2<u32>) -> vec4<f32> {
    return vec4<f32>(unpack2x16float(w.x), unpack2x16float(w.y));
}
