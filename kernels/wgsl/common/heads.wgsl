// The field's output activations, shared by the standalone kernels (field/activation.wgsl,
// render/field_heads.wgsl) and the fused march: trunc_exp for density (exp(min(x, 15)), the
// gradient clamped alike by the callers) and sigmoid for colour, evaluated without overflow on
// both sides.

const TRUNC: f32 = 15.0;

fn trunc_exp(v: f32) -> f32 {
    return exp(min(v, TRUNC));
}

fn sigmoid(v: f32) -> f32 {
    if v >= 0.0 {
        return 1.0 / (1.0 + exp(-v));
    }
    let e = exp(v);
    return e / (1.0 + e);
}

// sigmoid of the first three components (the colour MLP's output).
fn sigmoid3(v: vec4<f32>) -> vec3<f32> {
    return vec3<f32>(sigmoid(v.x), sigmoid(v.y), sigmoid(v.z));
}
