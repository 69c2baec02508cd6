// saxpy: y[0..n] = a * x[0..n] + y[0..n] on f32. Each thread handles ITEMS vec4s, strided by the
// workgroup size (coalesced on GPUs); lavapipe pays per invocation, so fewer, fuller invocations
// ran about 2x faster there than one vec4 per thread.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
    a: f32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> x: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read_write> y: array<vec4<f32>>;

const WG: u32 = 64u;
const ITEMS: u32 = 16u;

@compute @workgroup_size(64)
fn saxpy(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let g = linear_group(wid, nwg);
    let a = vec4<f32>(params.a);
    for (var k = 0u; k < ITEMS; k += 1u) {
        let i = (g * ITEMS + k) * WG + lid;
        let base = i * 4u;
        if base + 3u < params.n {
            y[i] = fma(a, x[i], y[i]);
        } else if base < params.n {
            let r = fma(a, x[i], y[i]);
            for (var c = 0u; base + c < params.n; c += 1u) {
                y[i][c] = r[c];
            }
        }
    }
}
