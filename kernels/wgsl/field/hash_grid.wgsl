// Standalone hash-grid encoding, forward and backward, one thread per (point, level). The fused
// march kernels use the same functions (common/hash_grid.wgsl); these entry points serve tests,
// benchmarks and fields queried outside a march.
//!include common/dispatch.wgsl
//!include common/hash_grid.wgsl

struct Params {
    n: u32,
    levels: u32,
    features: u32,
    _pad: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> positions: array<f32>;
@group(0) @binding(1) var<storage, read> level_info: array<HashLevel>;
@group(0) @binding(2) var<storage, read> table: array<f32>;
@group(0) @binding(3) var<storage, read_write> encoded: array<f32>;
@group(0) @binding(4) var<storage, read> d_encoded: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_table: array<atomic<f32>>;
// The second part of a split table (common/hash_grid.wgsl).
@group(0) @binding(6) var<storage, read> table_hi: array<f32>;
@group(0) @binding(7) var<storage, read_write> d_table_hi: array<atomic<f32>>;

const MAX_F: u32 = 8u;

// Entry e of the table part that holds a level (a branch, so the other binding is never read
// out of its range).
fn table_at(hi: bool, e: u32) -> f32 {
    if hi {
        return table_hi[e];
    }
    return table[e];
}

// encoded[i * L * F + l * F + f] = trilinear interpolation of level l's feature f at point i.
@compute @workgroup_size(64)
fn encode_fwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let t = linear_group(wid, nwg) * 64u + lid;
    let L = params.levels;
    let F = params.features;
    if t >= params.n * L {
        return;
    }
    let i = t / L;
    let l = t % L;
    let x = vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
    let out = t * F;
    var acc: array<f32, 8>;
    for (var f = 0u; f < MAX_F; f += 1u) {
        acc[f] = 0.0;
    }
    if hg_valid(x) {
        let lv = level_info[l];
        let cell = hg_cell(x, lv);
        let hi = hg_part(lv) != 0u;
        for (var k = 0u; k < 8u; k += 1u) {
            let w = hg_weight(cell.frac, k);
            let e = lv.offset + hg_index(hg_corner(cell.corner, k), lv) * F;
            for (var f = 0u; f < F; f += 1u) {
                acc[f] += w * table_at(hi, e + f);
            }
        }
    }
    for (var f = 0u; f < F; f += 1u) {
        encoded[out + f] = acc[f];
    }
}

// d_table[entry] += weight * d_encoded for every corner a point touched (f32 atomics).
@compute @workgroup_size(64)
fn encode_bwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let t = linear_group(wid, nwg) * 64u + lid;
    let L = params.levels;
    let F = params.features;
    if t >= params.n * L {
        return;
    }
    let i = t / L;
    let l = t % L;
    let x = vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
    if !hg_valid(x) {
        return;
    }
    let lv = level_info[l];
    let cell = hg_cell(x, lv);
    let hi = hg_part(lv) != 0u;
    for (var k = 0u; k < 8u; k += 1u) {
        let w = hg_weight(cell.frac, k);
        let e = lv.offset + hg_index(hg_corner(cell.corner, k), lv) * F;
        for (var f = 0u; f < F; f += 1u) {
            let g = w * d_encoded[t * F + f];
            if g != 0.0 {
                if hi {
                    atomicAdd(&d_table_hi[e + f], g);
                } else {
                    atomicAdd(&d_table[e + f], g);
                }
            }
        }
    }
}
