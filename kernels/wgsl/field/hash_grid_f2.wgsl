// Hash-grid encoding specialised for F = 2 features per level (the Instant-NGP default): one
// thread per point walks every level, the 8 corners are unrolled and each corner is one vec2
// load. The generic kernels (hash_grid.wgsl) handle F = 1, 4, 8 one thread per (point, level).
//!include common/dispatch.wgsl
//!include common/hash_grid.wgsl

// The same block as hash_grid.wgsl (features is always 2 here), so the host passes one struct.
struct Params {
    n: u32,
    levels: u32,
    features: u32,
    _pad: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> positions: array<f32>;
@group(0) @binding(1) var<storage, read> level_info: array<HashLevel>;
@group(0) @binding(2) var<storage, read> table: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read_write> encoded: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read> d_encoded: array<vec2<f32>>;
@group(0) @binding(5) var<storage, read_write> d_table: array<atomic<f32>>;
// The second part of a split table (common/hash_grid.wgsl).
@group(0) @binding(6) var<storage, read> table_hi: array<vec2<f32>>;
@group(0) @binding(7) var<storage, read_write> d_table_hi: array<atomic<f32>>;

// Entry e (a feature pair) of the table part that holds a level; a branch, so the other
// binding is never read out of its range.
fn entry(hi: bool, e: u32) -> vec2<f32> {
    if hi {
        return table_hi[e];
    }
    return table[e];
}

fn load_point(i: u32) -> vec3<f32> {
    return vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
}

@compute @workgroup_size(64)
fn encode_fwd_f2(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let x = load_point(i);
    let valid = hg_valid(x);
    for (var l = 0u; l < params.levels; l += 1u) {
        var acc = vec2<f32>(0.0);
        if valid {
            let lv = level_info[l];
            let cell = hg_cell(x, lv);
            let base = lv.offset / 2u;
            let hi = hg_part(lv) != 0u;
            let f = cell.frac;
            let g = vec3<f32>(1.0) - f;
            let c = cell.corner;
            acc += (g.x * g.y * g.z) * entry(hi, base + hg_index(c, lv));
            acc += (f.x * g.y * g.z) * entry(hi, base + hg_index(c + vec3<u32>(1u, 0u, 0u), lv));
            acc += (g.x * f.y * g.z) * entry(hi, base + hg_index(c + vec3<u32>(0u, 1u, 0u), lv));
            acc += (f.x * f.y * g.z) * entry(hi, base + hg_index(c + vec3<u32>(1u, 1u, 0u), lv));
            acc += (g.x * g.y * f.z) * entry(hi, base + hg_index(c + vec3<u32>(0u, 0u, 1u), lv));
            acc += (f.x * g.y * f.z) * entry(hi, base + hg_index(c + vec3<u32>(1u, 0u, 1u), lv));
            acc += (g.x * f.y * f.z) * entry(hi, base + hg_index(c + vec3<u32>(0u, 1u, 1u), lv));
            acc += (f.x * f.y * f.z) * entry(hi, base + hg_index(c + vec3<u32>(1u, 1u, 1u), lv));
        }
        encoded[i * params.levels + l] = acc;
    }
}

fn add2(hi: bool, e: u32, g: vec2<f32>) {
    if hi {
        if g.x != 0.0 {
            atomicAdd(&d_table_hi[2u * e], g.x);
        }
        if g.y != 0.0 {
            atomicAdd(&d_table_hi[2u * e + 1u], g.y);
        }
        return;
    }
    if g.x != 0.0 {
        atomicAdd(&d_table[2u * e], g.x);
    }
    if g.y != 0.0 {
        atomicAdd(&d_table[2u * e + 1u], g.y);
    }
}

@compute @workgroup_size(64)
fn encode_bwd_f2(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let x = load_point(i);
    if !hg_valid(x) {
        return;
    }
    for (var l = 0u; l < params.levels; l += 1u) {
        let lv = level_info[l];
        let cell = hg_cell(x, lv);
        let base = lv.offset / 2u;
        let hi = hg_part(lv) != 0u;
        let d = d_encoded[i * params.levels + l];
        let f = cell.frac;
        let g = vec3<f32>(1.0) - f;
        let c = cell.corner;
        add2(hi, base + hg_index(c, lv), (g.x * g.y * g.z) * d);
        add2(hi, base + hg_index(c + vec3<u32>(1u, 0u, 0u), lv), (f.x * g.y * g.z) * d);
        add2(hi, base + hg_index(c + vec3<u32>(0u, 1u, 0u), lv), (g.x * f.y * g.z) * d);
        add2(hi, base + hg_index(c + vec3<u32>(1u, 1u, 0u), lv), (f.x * f.y * g.z) * d);
        add2(hi, base + hg_index(c + vec3<u32>(0u, 0u, 1u), lv), (g.x * g.y * f.z) * d);
        add2(hi, base + hg_index(c + vec3<u32>(1u, 0u, 1u), lv), (f.x * g.y * f.z) * d);
        add2(hi, base + hg_index(c + vec3<u32>(0u, 1u, 1u), lv), (g.x * f.y * f.z) * d);
        add2(hi, base + hg_index(c + vec3<u32>(1u, 1u, 1u), lv), (f.x * f.y * f.z) * d);
    }
}
