// Microbenchmarks of the memory operations the fused training step is made of (issue 61;
// extranerf_prims::micro times them in `extranerf bench kernels --only micro`): random reads of
// 4, 8 and 16 bytes from a table the size of the hash grid's (and of 4 bytes from its first
// 256 KiB, as a coarse level's table; and two adjacent floats, a corner as the step reads it), a storage load at an address the
// same in every lane (the step's level_info[l]), and vec4 read-modify-writes of a lane's own
// region in workgroup memory and in a storage buffer (the step's per-sample MLP records).
//
// Every lane runs params.ops operations, 8 per iteration of its loop (a constant-trip inner
// loop, which lavapipe unrolls, so the loop's own bookkeeping is shared by 8), and writes one
// sum to out[lane] so that nothing is optimised away. Random indices are the top bits of a
// per-lane linear congruential sequence; micro_index draws the same indices and reads nothing:
// its time is the baseline that the reads' net cost is measured from. The table holds small
// integers, so every sum is exact in f32 (extranerf_prims::reference::micro_lane).
//!include common/dispatch.wgsl
//!include common/micro.wgsl

@group(0) @binding(0) var<storage, read> table4: array<f32>;
@group(0) @binding(1) var<storage, read> table8: array<vec2<f32>>;
@group(0) @binding(2) var<storage, read> table16: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> small: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> region: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> out: array<f32>;
// micro_read_pair_branch's second binding (the same table; never read).
@group(0) @binding(6) var<storage, read> table_hi: array<f32>;

// vec4s of a lane's own region (workgroup memory: 64 lanes x 32 x 16 B = 32 KiB).
const REGION: u32 = 32u;
var<workgroup> wg: array<vec4<f32>, 2048>;

@compute @workgroup_size(64)
fn micro_index(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var s = micro_seed(i);
    let shift = 32u - params.log2_entries;
    var acc = 0.0;
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            s = micro_next(s);
            acc += f32((s >> shift) & 7u);
        }
    }
    out[i] = acc;
}

@compute @workgroup_size(64)
fn micro_read4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var s = micro_seed(i);
    let shift = 32u - params.log2_entries;
    var acc = 0.0;
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            s = micro_next(s);
            acc += table4[s >> shift];
        }
    }
    out[i] = acc;
}

// A hash-grid corner as the step reads it: two adjacent 4-byte loads (its two features).
@compute @workgroup_size(64)
fn micro_read_pair(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var s = micro_seed(i);
    let shift = 32u - params.log2_entries;
    var acc = 0.0;
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            s = micro_next(s);
            let e = (s >> shift) * 2u;
            acc += table4[e] + 2.0 * table4[e + 1u];
        }
    }
    out[i] = acc;
}

// The same corner read through the step's branch between a table's two bindings
// (common/field_eval.wgsl's table_at): `hi` comes from a storage load at a loop-dependent
// address, as the step's from level_info[l], so the compiler cannot know it is the same in
// every lane (it is always false here: `small` holds values below 5).
@compute @workgroup_size(64)
fn micro_read_pair_branch(@builtin(workgroup_id) wid: vec3<u32>,
                          @builtin(num_workgroups) nwg: vec3<u32>,
                          @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var s = micro_seed(i);
    let shift = 32u - params.log2_entries;
    var acc = 0.0;
    for (var n = 0u; n < params.ops; n += 8u) {
        let hi = small[n & 15u].x > 100.0;
        for (var k = 0u; k < 8u; k += 1u) {
            s = micro_next(s);
            let e = (s >> shift) * 2u;
            var v = vec2<f32>(0.0);
            if hi {
                v = vec2<f32>(table_hi[e], table_hi[e + 1u]);
            } else {
                v = vec2<f32>(table4[e], table4[e + 1u]);
            }
            acc += v.x + 2.0 * v.y;
        }
    }
    out[i] = acc;
}

@compute @workgroup_size(64)
fn micro_read8(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var s = micro_seed(i);
    let shift = 32u - params.log2_entries;
    var acc = vec2<f32>(0.0);
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            s = micro_next(s);
            acc += table8[s >> shift];
        }
    }
    out[i] = acc.x + 2.0 * acc.y;
}

@compute @workgroup_size(64)
fn micro_read16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var s = micro_seed(i);
    let shift = 32u - params.log2_entries;
    var acc = vec4<f32>(0.0);
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            s = micro_next(s);
            acc += table16[s >> shift];
        }
    }
    out[i] = dot(acc, vec4<f32>(1.0, 2.0, 3.0, 4.0));
}

// A storage load whose address is the same in every lane but comes from a loop counter (as
// the step's level_info[l]): 16 vec4s read in turn.
@compute @workgroup_size(64)
fn micro_same_address(@builtin(workgroup_id) wid: vec3<u32>,
                      @builtin(num_workgroups) nwg: vec3<u32>,
                      @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    var acc = vec4<f32>(f32(i & 7u));
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            acc += small[(n + k) & 15u];
        }
    }
    out[i] = dot(acc, vec4<f32>(1.0, 2.0, 3.0, 4.0));
}

// vec4 read-modify-writes of the lane's own REGION vec4s of workgroup memory, at an offset
// the same in every lane (as the step's records: a lane's base plus a segment's offset).
@compute @workgroup_size(64)
fn micro_workgroup(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    let base = lid * REGION;
    for (var j = 0u; j < REGION; j += 1u) {
        wg[base + j] = vec4<f32>(0.0);
    }
    if i >= params.lanes {
        return;
    }
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            let e = base + ((n + k) & (REGION - 1u));
            wg[e] = wg[e] + vec4<f32>(1.0, 2.0, 3.0, 4.0);
        }
    }
    var acc = 0.0;
    for (var j = 0u; j < REGION; j += 1u) {
        acc += dot(wg[base + j], vec4<f32>(1.0));
    }
    out[i] = acc;
}

// The same in a storage buffer (the lane's region at lane * REGION, zeroed by the host).
@compute @workgroup_size(64)
fn micro_storage(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.lanes {
        return;
    }
    let base = i * REGION;
    for (var n = 0u; n < params.ops; n += 8u) {
        for (var k = 0u; k < 8u; k += 1u) {
            let e = base + ((n + k) & (REGION - 1u));
            region[e] = region[e] + vec4<f32>(1.0, 2.0, 3.0, 4.0);
        }
    }
    var acc = 0.0;
    for (var j = 0u; j < REGION; j += 1u) {
        acc += dot(region[base + j], vec4<f32>(1.0));
    }
    out[i] = acc;
}
