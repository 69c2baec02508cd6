// fill: data[0..n] = value (32-bit words; f32 fills pass the bit pattern). One vec4 per thread.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
    value: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read_write> data: array<vec4<u32>>;

@compute @workgroup_size(64)
fn fill(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    let base = i * 4u;
    if base >= params.n {
        return;
    }
    let v = params.value;
    if base + 3u < params.n {
        data[i] = vec4<u32>(v);
    } else {
        for (var k = 0u; base + k < params.n; k += 1u) {
            data[i][k] = v;
        }
    }
}
