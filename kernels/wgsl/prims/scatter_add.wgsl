// f32 scatter-add: acc[indices[i]] += values[i] with f32 atomicAdd. Indices at or past
// acc_len are skipped. mode 0: one atomic per element. mode 1: lanes of a subgroup that hit
// the same index first sum their values (subgroupAdd) and one lane issues the atomic, which
// removes most of the contention when many elements share an index.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
    acc_len: u32,
    mode: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> indices: array<u32>;
@group(0) @binding(1) var<storage, read> values: array<f32>;
@group(0) @binding(2) var<storage, read_write> acc: array<atomic<f32>>;

const NONE: u32 = 0xffffffffu;

@compute @workgroup_size(64)
fn scatter_add(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32,
               @builtin(subgroup_invocation_id) lane: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    var pending = false;
    var idx = NONE;
    var v = 0.0;
    if i < params.n {
        idx = indices[i];
        v = values[i];
        pending = idx < params.acc_len;
    }
    if params.mode == 0u {
        if pending {
            atomicAdd(&acc[idx], v);
        }
        return;
    }
    // Every lane stays in the loop until the whole subgroup is done, so the subgroup operations
    // run in subgroup-uniform control flow.
    loop {
        let leader = subgroupMin(select(NONE, idx, pending));
        if leader == NONE {
            break;
        }
        let mine = pending && idx == leader;
        let s = subgroupAdd(select(0.0, v, mine));
        let first = subgroupMin(select(NONE, lane, mine));
        if lane == first {
            atomicAdd(&acc[leader], s);
        }
        pending = pending && !mine;
    }
}
