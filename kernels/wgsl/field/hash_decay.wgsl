// Hash decay (Zip-NeRF): L = lambda * sum over levels of mean(V_l^2), the mean over the level's
// table entries and features. Adds dL/dV = 2 lambda V / (size_l F) to the table gradient and
// writes per-workgroup partial losses (sum them with reduce_sum). One thread per table float.
// Training steps fold the gradient into Adam instead (optim/adam.wgsl, TableDecay) and do
// not compute the loss value.
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
