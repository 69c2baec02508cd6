// Tiny fully connected networks (Instant-NGP's density and colour MLPs): hidden width at most
// 64, ReLU between layers, linear output (the caller applies trunc-exp / sigmoid). Weights of
// all layers sit in one flat buffer: per layer W (rows = outputs, row-major) then b.
// Layer l maps dims[l] inputs to dims[l + 1] outputs; at most 4 layers, every width <= 64.

const MLP_MAX: u32 = 64u;

struct MlpShape {
    // dims[0] = inputs, dims[layers] = outputs, unused entries 0.
    dims: vec4<u32>,
    dims_hi: vec4<u32>,
    layers: u32,
    params: u32,
    _pad0: u32,
    _pad1: u32,
}

fn mlp_dim(s: MlpShape, i: u32) -> u32 {
    if i < 4u {
        return s.dims[i];
    }
    return s.dims_hi[i - 4u];
}

// Float offset of layer l's weights in the flat buffer (its bias follows the weights).
fn mlp_offset(s: MlpShape, l: u32) -> u32 {
    var off = 0u;
    for (var k = 0u; k < l; k += 1u) {
        off += (mlp_dim(s, k) + 1u) * mlp_dim(s, k + 1u);
    }
    return off;
}

// x rounded up to a multiple of 4.
fn pad4(x: u32) -> u32 {
    return (x + 3u) & ~3u;
}

// v, the floats 4 j4 .. 4 j4 + 3 of a record segment n wide, with the entries at n and past
// zeroed (the segment's padding).
fn below(v: vec4<f32>, j4: u32, n: u32) -> vec4<f32> {
    return select(vec4<f32>(0.0), v, vec4<u32>(4u * j4) + vec4<u32>(0u, 1u, 2u, 3u) < vec4<u32>(n));
}
