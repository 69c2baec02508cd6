// reduce_sum: partial[g] = sum of the f32 elements that workgroup g visits. Threads stride over
// vec4s (grid-stride), lanes sum within the subgroup, subgroup sums meet in shared memory. The
// host runs it twice: G workgroups over the input, then one workgroup over the G partials.
//!include common/dispatch.wgsl

struct Params {
    n: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> input: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read_write> partial: array<f32>;

const WG: u32 = 256u;
// Enough slots for subgroups as small as 4 lanes.
var<workgroup> sg_sums: array<f32, 64>;

@compute @workgroup_size(256)
fn reduce_sum(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32,
              @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32,
              @builtin(subgroup_invocation_id) sg_lane: u32) {
    let g = linear_group(wid, nwg);
    let groups = nwg.x * nwg.y;
    let nfull = params.n / 4u;
    let stride = groups * WG;
    var acc = vec4<f32>(0.0);
    var i = g * WG + lid;
    loop {
        if i >= nfull {
            break;
        }
        acc += input[i];
        i += stride;
    }
    // Exactly one thread ends its stride sequence on index nfull: it adds the partial vec4.
    if i == nfull && (params.n & 3u) != 0u {
        let k = vec4<u32>(0u, 1u, 2u, 3u) + vec4<u32>(nfull * 4u);
        acc += select(vec4<f32>(0.0), input[nfull], k < vec4<u32>(params.n));
    }
    let s = subgroupAdd((acc.x + acc.y) + (acc.z + acc.w));
    if sg_lane == 0u {
        sg_sums[sg_id] = s;
    }
    workgroupBarrier();
    if lid == 0u {
        var t = 0.0;
        for (var k = 0u; k < sg_count; k += 1u) {
            t += sg_sums[k];
        }
        partial[g] = t;
    }
}
