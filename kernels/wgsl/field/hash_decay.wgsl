// Hash decay (Zip-NeRF): L = lambda * sum over levels of mean(V_l^2), the mean over the level's
// table entries and features. Adds dL/dV = 2 lambda V / (size_l F) to the table gradient and
// writes per-workgroup partial losses (sum them with reduce_sum). One thread per table float.
//!include common/dispatch.wgsl
//!include common/hash_grid.wgsl

struct Params {
    n: u32,
    levels: u32,
    features: u32,
    lambda: f32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> level_info: array<HashLevel>;
@group(0) @binding(1) var<storage, read> table: array<f32>;
@group(0) @binding(2) var<storage, read_write> d_table: array<f32>;
@group(0) @binding(3) var<storage, read_write> partial: array<f32>;
// The same table and gradient as vec4s, and the level block (hash_decay_grad).
@group(0) @binding(4) var<storage, read> table4: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> d_table4: array<vec4<f32>>;
@group(0) @binding(6) var<uniform> level_block: array<vec4<u32>, 65>;

var<workgroup> sg_sums: array<f32, 64>;

@compute @workgroup_size(256)
fn hash_decay(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32,
              @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32,
              @builtin(subgroup_invocation_id) lane: u32) {
    let g = linear_group(wid, nwg);
    let i = g * 256u + lid;
    var l = 0.0;
    if i < params.n {
        // The level holding float i (levels are few; a linear scan is cheapest).
        var lv = level_info[0];
        for (var k = 1u; k < params.levels; k += 1u) {
            let next = level_info[k];
            if i >= next.offset {
                lv = next;
            }
        }
        let v = table[i];
        let scale = params.lambda / f32(lv.size * params.features);
        l = scale * v * v;
        d_table[i] += 2.0 * scale * v;
    }
    let s = subgroupAdd(l);
    if lane == 0u {
        sg_sums[sg_id] = s;
    }
    workgroupBarrier();
    // Extra workgroups of a 2-D folded grid have no slot.
    if lid == 0u && g < (params.n + 255u) / 256u {
        var t = 0.0;
        for (var k = 0u; k < sg_count; k += 1u) {
            t += sg_sums[k];
        }
        partial[g] = t;
    }
}

// The gradient alone (no loss value): what a training step needs. Four floats per thread, read
// and written as one vec4. The level's first float and its mean's divisor come from a uniform
// block (`level_block[l] = (offset, size * features, _, _)`, one entry past the last level
// holding (n, 1)). On lavapipe that avoids the per-lane branches of storage loads at
// loop-dependent offsets. A quad that straddles a level boundary, or the end, goes float by
// float.
@compute @workgroup_size(64)
fn hash_decay_grad(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    let q = linear_group(wid, nwg) * 64u + lid;
    let i0 = q * 4u;
    if i0 >= params.n {
        return;
    }
    var l = 0u;
    for (var k = 1u; k < params.levels; k += 1u) {
        if i0 >= level_block[k].x {
            l = k;
        }
    }
    let c = 2.0 * params.lambda / f32(level_block[l].y);
    if i0 + 4u <= level_block[l + 1u].x {
        d_table4[q] += c * table4[q];
        return;
    }
    for (var j = 0u; j < 4u; j += 1u) {
        let i = i0 + j;
        if i < params.n {
            var lj = l;
            if i >= level_block[l + 1u].x {
                lj = l + 1u;
            }
            d_table[i] += 2.0 * params.lambda / f32(level_block[lj].y) * table[i];
        }
    }
}
