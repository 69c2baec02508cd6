// saxpy: y[0..n] = a * x[0..n] + y[0..n] on f32, one vec4 per thread.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
    a: f32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> x: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read_write> y: array<vec4<f32>>;

@compute @workgroup_size(64)
fn saxpy(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    let base = i * 4u;
    if base >= params.n {
        return;
    }
    let r = fma(vec4<f32>(params.a), x[i], y[i]);
    if base + 3u < params.n {
        y[i] = r;
    } else {
        for (var k = 0u; base + k < params.n; k += 1u) {
            y[i][k] = r[k];
        }
    }
}
