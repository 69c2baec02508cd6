// The f16 path of the hash-grid encoding (F = 2): the table is kept in f32 (the master weights
// Adam updates) and copied to f16 before each forward pass; the forward reads the f16 copy
// (half the bytes per corner) and interpolates in f32. The backward pass does not read the
// table (the encoding is linear in it), so the f32 kernels serve both precisions.
//
// `table_to_f16`: values beyond the f16 range are clamped to +-65504 and NaN becomes 0, so the
// copy is always finite; values below 2^-24 in magnitude flush to 0 and values below 2^-14 lose
// precision (f16 subnormals).
enable f16;
//!include common/dispatch.wgsl
//!include common/hash_grid.wgsl

// The block of hash_grid.wgsl (features is always 2 here; n counts vec2 entries for
// table_to_f16), with the float offset of a split table's second part (0 when unsplit): the f16
// copy is one binding, so levels in the second part add it back (common/hash_grid.wgsl).
struct Params {
    n: u32,
    levels: u32,
    features: u32,
    hi_base: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> positions: array<f32>;
@group(0) @binding(1) var<storage, read> level_info: array<HashLevel>;
@group(0) @binding(2) var<storage, read> table_half: array<vec2<f16>>;
@group(0) @binding(3) var<storage, read_write> encoded: array<vec2<f32>>;
@group(0) @binding(6) var<storage, read> table: array<vec2<f32>>;
@group(0) @binding(7) var<storage, read_write> half_out: array<vec2<f16>>;

const F16_MAX: f32 = 65504.0;

@compute @workgroup_size(64)
fn table_to_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let v = table[i];
    let finite = select(vec2<f32>(0.0), v, v == v);
    half_out[i] = vec2<f16>(clamp(finite, vec2<f32>(-F16_MAX), vec2<f32>(F16_MAX)));
}

fn corner(base: u32, c: vec3<u32>, lv: HashLevel) -> vec2<f32> {
    return vec2<f32>(table_half[base + hg_index(c, lv)]);
}

@compute @workgroup_size(64)
fn encode_fwd_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let x = vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
    let valid = hg_valid(x);
    for (var l = 0u; l < params.levels; l += 1u) {
        var acc = vec2<f32>(0.0);
        if valid {
            let lv = level_info[l];
            let cell = hg_cell(x, lv);
            let base = (lv.offset + hg_part(lv) * params.hi_base) / 2u;
            let f = cell.frac;
            let g = vec3<f32>(1.0) - f;
            let c = cell.corner;
            acc += (g.x * g.y * g.z) * corner(base, c, lv);
            acc += (f.x * g.y * g.z) * corner(base, c + vec3<u32>(1u, 0u, 0u), lv);
            acc += (g.x * f.y * g.z) * corner(base, c + vec3<u32>(0u, 1u, 0u), lv);
            acc += (f.x * f.y * g.z) * corner(base, c + vec3<u32>(1u, 1u, 0u), lv);
            acc += (g.x * g.y * f.z) * corner(base, c + vec3<u32>(0u, 0u, 1u), lv);
            acc += (f.x * g.y * f.z) * corner(base, c + vec3<u32>(1u, 0u, 1u), lv);
            acc += (g.x * f.y * f.z) * corner(base, c + vec3<u32>(0u, 1u, 1u), lv);
            acc += (f.x * f.y * f.z) * corner(base, c + vec3<u32>(1u, 1u, 1u), lv);
        }
        encoded[i * params.levels + l] = acc;
    }
}
