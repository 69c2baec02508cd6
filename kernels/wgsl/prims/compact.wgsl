// Stream compaction: given flags and their exclusive scan (binarized), move the flagged elements
// (or their indices) to the front of `out`, keeping their order.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> flags: array<u32>;
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
@group(0) @binding(2) var<storage, read> values: array<u32>;
@group(0) @binding(3) var<storage, read_write> out: array<u32>;

@compute @workgroup_size(256)
fn compact_values(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 256u + lid;
    if i < params.n && flags[i] != 0u {
        out[offsets[i]] = values[i];
    }
}

@compute @workgroup_size(256)
fn compact_indices(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 256u + lid;
    if i < params.n && flags[i] != 0u {
        out[offsets[i]] = i;
    }
}
