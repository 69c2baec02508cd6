// Sparse Adam (tiny-cuda-nn's rule) over a hash table: only the vec4s whose bit is set in
// `touched` (bit i of word w: vec4 32 w + i of the bound range) are updated, with the dense
// kernel's arithmetic (`common/adam_update.wgsl`); the others keep their parameters and moments,
// so an entry no sample reached stands still instead of drifting on its momentum, and gets no
// hash decay (it does not affect any render either). The backward passes set the bits of every
// vec4 they add a gradient to; this kernel zeroes the gradient of each vec4 it updates and
// the host then empties the mask (a buffer fill), so the next step starts from a zero gradient and
// an empty mask without zeroing the table's gradient. Its threads still read a mask bit per
// vec4, and on a CPU device a SIMD group pays for its lanes' scattered loads whenever one of
// them is touched: with about half the table reached per step (fern, 1024 x 32) it costs what
// the dense update does (results/adam_pairs_lavapipe/).
//
// Bits past the range are ignored.
//!include common/adam_update.wgsl

@group(0) @binding(1) var<storage, read_write> grad: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> touched: array<u32>;

@compute @workgroup_size(64)
fn adam_sparse(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    // As the dense kernel: ITEMS vec4s per thread, a workgroup's lanes on neighbouring vec4s,
    // so a lane whose bit is clear costs a read of a mask word its neighbours share.
    let g0 = linear_group(wid, nwg);
    for (var k = 0u; k < ITEMS; k += 1u) {
        let i = (g0 * ITEMS + k) * WG + lid;
        let base = i * 4u;
        if base >= params.n {
            return;
        }
        if (touched[i / 32u] & (1u << (i % 32u))) == 0u {
            continue;
        }
        adam_update(i, base, grad[i]);
        // A partial last vec4 keeps its floats past n, as adam_update does.
        if base + 3u < params.n {
            grad[i] = vec4<f32>(0.0);
        } else {
            for (var c = 0u; base + c < params.n; c += 1u) {
                grad[i][c] = 0.0;
            }
        }
    }
}
