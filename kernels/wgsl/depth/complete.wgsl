// Edge-aware depth completion (for supervising virtual views, whose inpainted regions have no
// rendered depth). One Jacobi step of the colour-weighted harmonic fill: known pixels keep
// their depth; every other pixel becomes the weighted mean of its 4 neighbours inside the image,
// w = exp(-|c_i - c_j|^2 / sigma^2) from the guide colours, so depth flows along regions of
// similar colour and hardly across colour edges. Iterated, it converges to the weighted
// harmonic interpolation, which reproduces any plane (in pixel coordinates) exactly when
// colours are uniform and the hole is enclosed by known pixels.
//!include common/dispatch.wgsl

struct Params {
    width: u32,
    height: u32,
    // 1 / sigma^2 of the colour weight (0: plain harmonic fill).
    inv_sigma2: f32,
    _pad: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> depth_in: array<f32>;
@group(0) @binding(1) var<storage, read_write> depth_out: array<f32>;
// 1 where the depth is known and kept.
@group(0) @binding(2) var<storage, read> known: array<u32>;
// Guide colour per pixel (rgb, w unused).
@group(0) @binding(3) var<storage, read> guide: array<vec4<f32>>;

@compute @workgroup_size(64)
fn complete_step(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    let w = params.width;
    let h = params.height;
    if i >= w * h {
        return;
    }
    if known[i] != 0u {
        depth_out[i] = depth_in[i];
        return;
    }
    let x = i % w;
    let y = i / w;
    let c = guide[i].xyz;
    var sum = 0.0;
    var wsum = 0.0;
    for (var k = 0u; k < 4u; k += 1u) {
        var nx = i32(x);
        var ny = i32(y);
        if k == 0u {
            nx -= 1;
        } else if k == 1u {
            nx += 1;
        } else if k == 2u {
            ny -= 1;
        } else {
            ny += 1;
        }
        if nx < 0 || ny < 0 || nx >= i32(w) || ny >= i32(h) {
            continue;
        }
        let j = u32(ny) * w + u32(nx);
        let d = guide[j].xyz - c;
        let wj = exp(-dot(d, d) * params.inv_sigma2);
        sum += wj * depth_in[j];
        wsum += wj;
    }
    // Weights that all underflow (a pixel walled in by strong edges) keep the current value.
    if wsum > 1e-30 {
        depth_out[i] = sum / wsum;
    } else {
        depth_out[i] = depth_in[i];
    }
}
