// iota: data[i] = start + i for i < n (indices for sorts and gathers). One element per thread,
// 64 per workgroup: it is also the kernel whose tests cross 65535 workgroups (2-D folding).
//!include common/dispatch.wgsl

struct Params {
    n: u32,
    start: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read_write> data: array<u32>;

@compute @workgroup_size(64)
fn iota(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i < params.n {
        data[i] = params.start + i;
    }
}
