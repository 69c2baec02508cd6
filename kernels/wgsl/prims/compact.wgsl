// Stream compaction: given flags and their exclusive scan (binarized), move the flagged elements
// (or their indices) to the front of `out`, keeping their order.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
    with_values: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> flags: array<vec4<u32>>;
@group(0) @binding(1) var<storage, read> offsets: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> values: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read_write> out: array<u32>;

const WG: u32 = 64u;
// vec4s per thread, strided by the workgroup size (16 elements per thread).
const ITEMS: u32 = 4u;

// out[offsets[i]] = values[i] (with_values != 0) or i, for every flagged i < n.
@compute @workgroup_size(64)
fn compact(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let g = linear_group(wid, nwg);
    for (var k = 0u; k < ITEMS; k += 1u) {
        let i = (g * ITEMS + k) * WG + lid;
        let base = i * 4u;
        if base >= params.n {
            break;
        }
        let f = flags[i];
        if all(f == vec4<u32>(0u)) {
            continue;
        }
        let o = offsets[i];
        var v = vec4<u32>(base) + vec4<u32>(0u, 1u, 2u, 3u);
        if params.with_values != 0u {
            v = values[i];
        }
        for (var c = 0u; c < 4u && base + c < params.n; c += 1u) {
            if f[c] != 0u {
                out[o[c]] = v[c];
            }
        }
    }
}
