// fill: data[0..n] = value (32-bit words; f32 fills pass the bit pattern). Each thread writes
// ITEMS vec4s strided by the workgroup size, like saxpy.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
    value: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read_write> data: array<vec4<u32>>;

const WG: u32 = 64u;
const ITEMS: u32 = 16u;

@compute @workgroup_size(64)
fn fill(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let g = linear_group(wid, nwg);
    let v = params.value;
    for (var k = 0u; k < ITEMS; k += 1u) {
        let i = (g * ITEMS + k) * WG + lid;
        let base = i * 4u;
        if base + 3u < params.n {
            data[i] = vec4<u32>(v);
        } else if base < params.n {
            for (var c = 0u; base + c < params.n; c += 1u) {
                data[i][c] = v;
            }
        }
    }
}
