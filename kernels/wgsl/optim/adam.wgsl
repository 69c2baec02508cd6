// Adam over one flat parameter buffer (Kingma & Ba), one thread per vec4, ITEMS vec4s per
// thread. The host passes the step's learning rate and the bias corrections 1 - beta^t, so a
// schedule costs nothing here. Gradients are multiplied by grad_scale (undo loss scaling);
// non-finite gradient components are treated as zero, so one bad sample cannot poison the
// moments. Optional L2 weight decay is added to the gradient.
//
// Hash decay (Zip-NeRF, L = lambda sum_l mean(V_l^2)) is folded in: for the decay_floats floats
// from decay_start (the hash table), 2 lambda V / (size_l F) is added to the gradient, with the
// level bounds from a uniform block (`decay_block[l] = (first float of level l relative to the
// table, size_l * F, _, _)`, `decay_levels` entries). That saves the separate gradient pass over
// the table, which reads and writes as many bytes as this kernel.
//
// Buffers larger than one storage binding are updated in ranges: `offset` is the first float of
// the bound range in the whole buffer (decay_start counts in the whole buffer too).
//!include common/adam_update.wgsl

@group(0) @binding(1) var<storage, read> grad: array<vec4<f32>>;

// Dense: every vec4 of the bound range.
@compute @workgroup_size(64)
fn adam(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let g0 = linear_group(wid, nwg);
    for (var k = 0u; k < ITEMS; k += 1u) {
        let i = (g0 * ITEMS + k) * WG + lid;
        let base = i * 4u;
        if base >= params.n {
            return;
        }
        adam_update(i, base, grad[i]);
    }
}
