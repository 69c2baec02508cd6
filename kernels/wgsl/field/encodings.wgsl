// Standalone position contraction and direction encoding (the fused march uses the same
// functions): one thread per point.
//!include common/dispatch.wgsl
//!include common/contract.wgsl
//!include common/sh.wgsl

struct Params {
    n: u32,
    mode: u32,
    inv_radius: f32,
    _pad: u32,
    // Scene centre (xyz, w unused).
    center: vec4<f32>,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> points: array<f32>;
@group(0) @binding(1) var<storage, read_write> contracted: array<f32>;
@group(0) @binding(2) var<storage, read_write> sh: array<f32>;

fn load(i: u32) -> vec3<f32> {
    return vec3<f32>(points[3u * i], points[3u * i + 1u], points[3u * i + 2u]);
}

@compute @workgroup_size(64)
fn contract(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let c = contract_unit((load(i) - params.center.xyz) * params.inv_radius, params.mode);
    contracted[3u * i] = c.x;
    contracted[3u * i + 1u] = c.y;
    contracted[3u * i + 2u] = c.z;
}

@compute @workgroup_size(64)
fn sh_encode(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.n {
        return;
    }
    let o = sh4(unit_dir(load(i)));
    for (var k = 0u; k < 16u; k += 1u) {
        sh[16u * i + k] = o[k];
    }
}
