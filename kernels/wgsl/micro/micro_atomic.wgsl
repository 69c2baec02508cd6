// Microbenchmark of the fused training step's hash-grid gradient scatter (issue 61;
// extranerf_prims::micro): f32 atomic adds of 1.0 at random addresses of a table the size of
// the hash grid's, 8 per iteration of each lane's loop. With params.share = 1 every lane has
// its own random sequence (distinct addresses, as at fine grid levels); with share = s the
// lanes of each run of s follow one sequence and add to the same address at once (as
// neighbouring rays' samples do at coarse levels). The host zeroes `acc` before each run; every
// entry then counts its hits exactly. micro_atomic_u32 does the same with u32 adds.
//!include common/dispatch.wgsl
//!include common/micro.wgsl

@group(0) @binding(0) var<storage, read_write> acc: array<atomic<f32>>;
@group(0) @binding(1) var<storage, read_write> acc_u32: array<atomic<u32>>;
// micro_atomic_prefetched's lane results: written only if a loaded count were negative (never),
// so that the loads stay.
@group(0) @binding(2) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(64)
fn micro_atomic(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var s = micro_seed(i);
    let shift = 32u - params.log2_entries;
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            s = micro_next(s);
            atomicAdd(&acc[s >> shift], 1.0);
        }
    }
}

// The same with u32 atomic adds (x86 has one instruction for them, `lock xadd`; an f32 add
// is a compare-exchange loop): the cost of accumulating gradients in fixed point instead.
@compute @workgroup_size(64)
fn micro_atomic_u32(@builtin(workgroup_id) wid: vec3<u32>,
                    @builtin(num_workgroups) nwg: vec3<u32>,
                    @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var s = micro_seed(i);
    let shift = 32u - params.log2_entries;
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            s = micro_next(s);
            atomicAdd(&acc_u32[s >> shift], 1u);
        }
    }
}

// f32 atomic adds whose lines a plain load brought in first: each iteration loads the 8 entries
// it will add to (loads, unlike locked compare-exchanges, can overlap their cache misses), then
// adds to them. What the step would pay if it read its 8 corners' gradient entries before
// adding to them.
@compute @workgroup_size(64)
fn micro_atomic_prefetched(@builtin(workgroup_id) wid: vec3<u32>,
                           @builtin(num_workgroups) nwg: vec3<u32>,
                           @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var s = micro_seed(i);
    let shift = 32u - params.log2_entries;
    var least = 0.0;
    for (var n = 0u; n < params.ops; n += 8u) {
        var e: array<u32, 8>;
        for (var k = 0u; k < 8u; k += 1u) {
            s = micro_next(s);
            e[k] = s >> shift;
            least = min(least, atomicLoad(&acc[e[k]]));
        }
        for (var k = 0u; k < 8u; k += 1u) {
            atomicAdd(&acc[e[k]], 1.0);
        }
    }
    if least < 0.0 {
        out[i] = least;
    }
}
