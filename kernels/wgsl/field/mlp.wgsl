// Standalone tiny-MLP kernels, one thread per point: forward; backward to the inputs (writing
// each layer's input and pre-activation gradient for the weight-gradient pass); and the weight
// gradient as a reduction over chunks of points with one f32 atomic per parameter per chunk.
// The `_block` variants read the weights from a uniform block (common/mlp_block.wgsl), about 3x
// faster on lavapipe, for MLPs whose widths and offsets suit it (checked on the host).
//!include common/dispatch.wgsl
//!include common/mlp.wgsl
//!include common/mlp_block.wgsl

struct Params {
    n: u32,
    // Points per chunk of the weight-gradient reduction.
    chunk: u32,
    // Floats per point in `saved` (sum over layers of inputs + outputs).
    saved_stride: u32,
    _pad: u32,
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
        at += ni;
        for (var o = 0u; o < no; o += 1u) {
            var acc = weights[w + no * ni + o];
            for (var j = 0u; j < ni; j += 1u) {
                acc = fma(weights[w + o * ni + j], a[j], acc);
            }
            // Pre-activation for now; replaced by its gradient below.
            saved[at + o] = acc;
            z[o] = select(max(acc, 0.0), acc, l + 1u == s.layers);
        }
        at += no;
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
        at -= no;
        let last = l + 1u == s.layers;
        for (var o = 0u; o < no; o += 1u) {
            // ReLU'(pre) on hidden layers; identity on the output layer.
            let pre = saved[at + o];
            let d = select(select(0.0, g[o], pre > 0.0), g[o], last);
            saved[at + o] = d;
            z[o] = d;
        }
        at -= ni;
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

// Where parameter `param` sits: (layer's offset in `saved`, inputs of the layer, output row o,
// input column j, is a bias).
struct WSlot {
    at: u32,
    ni: u32,
    o: u32,
    j: u32,
    bias: bool,
}

fn wslot(s: MlpShape, param: u32) -> WSlot {
    var l = 0u;
    var off = 0u;
    var at = 0u;
    loop {
        let size = (mlp_dim(s, l) + 1u) * mlp_dim(s, l + 1u);
        if param < off + size || l + 1u >= s.layers {
            break;
        }
        off += size;
        at += mlp_dim(s, l) + mlp_dim(s, l + 1u);
        l += 1u;
    }
    let ni = mlp_dim(s, l);
    let no = mlp_dim(s, l + 1u);
    let local = param - off;
    let bias = local >= no * ni;
    return WSlot(at, ni, select(local / ni, local - no * ni, bias), select(local % ni, 0u, bias), bias);
}

// One thread per (4 consecutive parameters, chunk of points): d_weights[param] += sum over the
// chunk of delta[o] * input[j] (weights) or delta[o] (biases). When the four are weights of one
// output row (the common case), each point costs one delta and four input loads for four FMAs.
@compute @workgroup_size(64)
fn mlp_wgrad(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let t = linear_group(wid, nwg) * 64u + lid;
    let s = shape_buf[0];
    let chunks = (params.n + params.chunk - 1u) / params.chunk;
    let quads = (s.params + 3u) / 4u;
    if t >= quads * chunks {
        return;
    }
    let q = t % quads;
    let chunk = t / quads;
    let p0 = 4u * q;
    let w0 = wslot(s, p0);
    let w3 = wslot(s, min(p0 + 3u, s.params - 1u));
    let row = p0 + 3u < s.params && !w0.bias && !w3.bias && w0.at == w3.at && w0.o == w3.o;
    let first = chunk * params.chunk;
    let last = min(first + params.chunk, params.n);
    var acc = vec4<f32>(0.0);
    if row {
        for (var p = first; p < last; p += 1u) {
            let base = p * params.saved_stride + w0.at;
            let d = saved[base + w0.ni + w0.o];
            let j = base + w0.j;
            acc = fma(vec4<f32>(d), vec4<f32>(saved[j], saved[j + 1u], saved[j + 2u], saved[j + 3u]), acc);
        }
    } else {
        for (var k = 0u; k < 4u; k += 1u) {
            if p0 + k >= s.params {
                break;
            }
            let w = wslot(s, p0 + k);
            var a = 0.0;
            for (var p = first; p < last; p += 1u) {
                let base = p * params.saved_stride + w.at;
                a = fma(saved[base + w.ni + w.o], select(saved[base + w.j], 1.0, w.bias), a);
            }
            acc[k] = a;
        }
    }
    for (var k = 0u; k < 4u; k += 1u) {
        if p0 + k < s.params && acc[k] != 0.0 {
            atomicAdd(&d_weights[p0 + k], acc[k]);
        }
    }
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
        at += ni;
        mlp_layer(mlp_offset(s, l), ni, no, &a, &z);
        // Pre-activations for now; replaced by their gradients below.
        for (var o = 0u; o < no; o += 1u) {
            saved[at + o] = act_get(&z, o);
        }
        at += no;
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
        at -= no;
        let last = l + 1u == s.layers;
        for (var o = 0u; o < no; o += 1u) {
            // ReLU'(pre) on hidden layers; identity on the output layer.
            let go = act_get(&g, o);
            let d = select(select(0.0, go, saved[at + o] > 0.0), go, last);
            saved[at + o] = d;
            act_set(&z, o, d);
        }
        at -= ni;
        mlp_layer_back(mlp_offset(s, l), ni, no, &z, &g);
    }
    for (var j = 0u; j < n_in; j += 1u) {
        d_inputs[p * n_in + j] = act_get(&g, j);
    }
}
