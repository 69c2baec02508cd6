// Standalone tiny-MLP kernels, one thread per point: forward; backward to the inputs (writing
// each layer's input and pre-activation gradient for the weight-gradient pass); and the weight
// gradient as a tiled reduction over chunks of points (common/mlp_wgrad.wgsl) with one f32
// atomic per parameter per chunk.
// The `_block` variants read the weights from a uniform block (common/mlp_block.wgsl), about 3x
// faster on lavapipe, for MLPs whose widths and offsets suit it (checked on the host).
//!include common/dispatch.wgsl
//!include common/mlp.wgsl
//!include common/mlp_block.wgsl
//!include common/mlp_wgrad.wgsl

struct Params {
    n: u32,
    // mlp_wgrad: points per chunk of the reduction.
    chunk: u32,
    // Floats per point in `saved`: per layer its inputs then its pre-activations, each segment
    // padded to a multiple of 4 floats (so mlp_wgrad reads them as vec4s).
    saved_stride: u32,
    // mlp_wgrad: tiles per chunk (a workgroup each).
    groups: u32,
    // (0, 1, 2, 3): the identity table of common/mlp_block.wgsl's mlp_uni.
    lut: vec4<u32>,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> shape_buf: array<MlpShape>;
@group(0) @binding(1) var<storage, read> weights: array<f32>;
@group(0) @binding(2) var<storage, read> inputs: array<f32>;
@group(0) @binding(3) var<storage, read_write> outputs: array<f32>;
@group(0) @binding(4) var<storage, read> d_outputs: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_inputs: array<f32>;
@group(0) @binding(6) var<storage, read_write> saved: array<f32>;
@group(0) @binding(7) var<storage, read_write> d_weights: array<atomic<f32>>;
// `saved` again as vec4s (mlp_wgrad).
@group(0) @binding(9) var<storage, read> saved4: array<vec4<f32>>;
// The weights again, copied into a uniform block, for the `_block` variants.
@group(0) @binding(8) var<uniform> mlp: array<vec4<f32>, 4096>;

@compute @workgroup_size(64)
fn mlp_fwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let p = linear_group(wid, nwg) * 64u + lid;
    if p >= params.n {
        return;
    }
    let s = shape_buf[0];
    var a: array<f32, 64>;
    var z: array<f32, 64>;
    let n_in = mlp_dim(s, 0u);
    for (var j = 0u; j < n_in; j += 1u) {
        a[j] = inputs[p * n_in + j];
    }
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let w = mlp_offset(s, l);
        let last = l + 1u == s.layers;
        for (var o = 0u; o < no; o += 1u) {
            var acc = weights[w + no * ni + o];
            for (var j = 0u; j < ni; j += 1u) {
                acc = fma(weights[w + o * ni + j], a[j], acc);
            }
            z[o] = select(max(acc, 0.0), acc, last);
        }
        for (var o = 0u; o < no; o += 1u) {
            a[o] = z[o];
        }
    }
    let n_out = mlp_dim(s, s.layers);
    for (var o = 0u; o < n_out; o += 1u) {
        outputs[p * n_out + o] = a[o];
    }
}

// Recomputes the forward pass, then back-propagates d_outputs: writes d_inputs and, per layer,
// the layer's input and the gradient of its pre-activation into `saved`.
@compute @workgroup_size(64)
fn mlp_bwd_data(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let p = linear_group(wid, nwg) * 64u + lid;
    if p >= params.n {
        return;
    }
    let s = shape_buf[0];
    // Layer inputs and pre-activations go to `saved` on the way forward.
    var a: array<f32, 64>;
    var z: array<f32, 64>;
    let n_in = mlp_dim(s, 0u);
    for (var j = 0u; j < n_in; j += 1u) {
        a[j] = inputs[p * n_in + j];
    }
    var at = p * params.saved_stride;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let w = mlp_offset(s, l);
        for (var j = 0u; j < ni; j += 1u) {
            saved[at + j] = a[j];
        }
        at += pad4(ni);
        for (var o = 0u; o < no; o += 1u) {
            var acc = weights[w + no * ni + o];
            for (var j = 0u; j < ni; j += 1u) {
                acc = fma(weights[w + o * ni + j], a[j], acc);
            }
            // Pre-activation for now; replaced by its gradient below.
            saved[at + o] = acc;
            z[o] = select(max(acc, 0.0), acc, l + 1u == s.layers);
        }
        at += pad4(no);
        for (var o = 0u; o < no; o += 1u) {
            a[o] = z[o];
        }
    }
    // Backward: g holds dL/d(layer output); walk the layers in reverse.
    var g: array<f32, 64>;
    let n_out = mlp_dim(s, s.layers);
    for (var o = 0u; o < n_out; o += 1u) {
        g[o] = d_outputs[p * n_out + o];
    }
    for (var li = 0u; li < s.layers; li += 1u) {
        let l = s.layers - 1u - li;
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let w = mlp_offset(s, l);
        at -= pad4(no);
        let last = l + 1u == s.layers;
        for (var o = 0u; o < no; o += 1u) {
            // ReLU'(pre) on hidden layers; identity on the output layer.
            let pre = saved[at + o];
            let d = select(select(0.0, g[o], pre > 0.0), g[o], last);
            saved[at + o] = d;
            z[o] = d;
        }
        at -= pad4(ni);
        for (var j = 0u; j < ni; j += 1u) {
            var acc = 0.0;
            for (var o = 0u; o < no; o += 1u) {
                acc = fma(weights[w + o * ni + j], z[o], acc);
            }
            g[j] = acc;
        }
    }
    for (var j = 0u; j < n_in; j += 1u) {
        d_inputs[p * n_in + j] = g[j];
    }
}

// One point's contribution to a weight-gradient tile (common/mlp_wgrad.wgsl): the tile's 16
// inputs and 16 deltas at units `u` of the point's record at vec4 `base`.
fn wgrad_point(base: u32, u: WgradUnits, c: u32, with_bias: bool,
               acc: ptr<function, array<vec4<f32>, 8>>,
               bias: ptr<function, array<vec4<f32>, 4>>) {
    var x: array<vec4<f32>, 4>;
    for (var k = 0u; k < 4u; k += 1u) {
        x[k] = saved4[base + u.x[k]];
    }
    var d: array<vec4<f32>, 4>;
    for (var k = 0u; k < 4u; k += 1u) {
        d[k] = saved4[base + u.d[k]];
    }
    wgrad_tile_add(wgrad_pick(x, c), d, 1.0, 1.0, with_bias, acc, bias);
}

// Weight gradients (common/mlp_wgrad.wgsl's tiles): workgroup = (chunk of points, tile of 16
// rows x 16 columns); per point the threads load the tile's 16 inputs and 16 deltas, each
// thread keeps its two inputs and does 32 FMAs. WGRAD_UNROLL points per iteration: on
// lavapipe a loop's own bookkeeping costs about as much as one point.
@compute @workgroup_size(8)
fn mlp_wgrad(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let g = linear_group(wid, nwg);
    let t = wgrad_tile(shape_buf[0], g % params.groups);
    var acc = array<vec4<f32>, 8>();
    var bias = array<vec4<f32>, 4>();
    if t.valid {
        let p0 = (g / params.groups) * params.chunk;
        let p1 = min(p0 + params.chunk, params.n);
        let with_bias = t.j0 == 0u;
        let stride4 = params.saved_stride / 4u;
        let u = wgrad_units(t, 0u);
        var p = p0;
        for (; p + WGRAD_UNROLL <= p1; p += WGRAD_UNROLL) {
            for (var q = 0u; q < WGRAD_UNROLL; q += 1u) {
                wgrad_point((p + q) * stride4, u, lid, with_bias, &acc, &bias);
            }
        }
        for (; p < p1; p += 1u) {
            wgrad_point(p * stride4, u, lid, with_bias, &acc, &bias);
        }
    }
    wgrad_tile_flush(t, lid, &acc, &bias);
}

// mlp_fwd with the weights in the uniform block.
@compute @workgroup_size(64)
fn mlp_fwd_block(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let p = linear_group(wid, nwg) * 64u + lid;
    if p >= params.n {
        return;
    }
    let s = shape_buf[0];
    var a: Act;
    let n_in = mlp_dim(s, 0u);
    for (var j = 0u; j < n_in; j += 1u) {
        act_set(&a, j, inputs[p * n_in + j]);
    }
    mlp_forward(s, 0u, &a);
    let n_out = mlp_dim(s, s.layers);
    for (var o = 0u; o < n_out; o += 1u) {
        outputs[p * n_out + o] = act_get(&a, o);
    }
}

// mlp_bwd_data with the weights in the uniform block (the same `saved` layout).
@compute @workgroup_size(64)
fn mlp_bwd_data_block(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                      @builtin(local_invocation_index) lid: u32) {
    let p = linear_group(wid, nwg) * 64u + lid;
    if p >= params.n {
        return;
    }
    let s = shape_buf[0];
    var a: Act;
    var z: Act;
    let n_in = mlp_dim(s, 0u);
    for (var j = 0u; j < n_in; j += 1u) {
        act_set(&a, j, inputs[p * n_in + j]);
    }
    var at = p * params.saved_stride;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        for (var j = 0u; j < ni; j += 1u) {
            saved[at + j] = act_get(&a, j);
        }
        at += pad4(ni);
        mlp_layer(mlp_offset(s, l), ni, no, &a, &z);
        // Pre-activations for now; replaced by their gradients below.
        for (var o = 0u; o < no; o += 1u) {
            saved[at + o] = act_get(&z, o);
        }
        at += pad4(no);
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
        at -= pad4(no);
        let last = l + 1u == s.layers;
        for (var o = 0u; o < no; o += 1u) {
            // ReLU'(pre) on hidden layers; identity on the output layer.
            let go = act_get(&g, o);
            let d = select(select(0.0, go, saved[at + o] > 0.0), go, last);
            saved[at + o] = d;
            act_set(&z, o, d);
        }
        at -= pad4(ni);
        mlp_layer_back(mlp_offset(s, l), ni, no, &z, &g);
    }
    for (var j = 0u; j < n_in; j += 1u) {
        d_inputs[p * n_in + j] = act_get(&g, j);
    }
}
