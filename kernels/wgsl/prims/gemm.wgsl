// Tiled matrix product C[M, N] = A[M, K] * B[K, N] (row-major f32): the shape of an MLP layer
// over a batch (W[out, in] times activations[in, points]). A workgroup of 64 threads computes
// a 32 x 32 tile of C, each thread a 4 x 4 block (one vec4 of 4 rows); 32 x 16 slices of A and
// 16 x 32 slices of B are staged in workgroup memory. M and N are multiples of 32 and K of 16
// (the host checks). Workgroups are numbered row of tiles first.
//
// Measured on lavapipe (bench kernels --only gemm,mlp): 2.6 GFLOP/s for 64x64 by 64x65536,
// against 6.7 GFLOP/s for the per-thread uniform-block MLP in the same run. Workgroup memory
// and barriers are expensive there, so the MLPs do not use this; it is the tiled reference
// for devices where they are cheap (GPUs).
//!include common/dispatch.wgsl

struct Params {
    m: u32,
    n: u32,
    k: u32,
    _pad: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> a: array<f32>;
@group(0) @binding(1) var<storage, read> b: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> c: array<vec4<f32>>;

// 32 rows x 16 of A; 16 rows x 8 vec4s of B.
var<workgroup> sa: array<f32, 512>;
var<workgroup> sb: array<vec4<f32>, 128>;

@compute @workgroup_size(64)
fn gemm(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let g = linear_group(wid, nwg);
    let tiles_n = params.n / 32u;
    if g >= (params.m / 32u) * tiles_n {
        return;
    }
    let tm = g / tiles_n;
    let tn = g % tiles_n;
    let tx = lid % 8u;
    let ty = lid / 8u;
    let n4 = params.n / 4u;
    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var acc2 = vec4<f32>(0.0);
    var acc3 = vec4<f32>(0.0);
    for (var k0 = 0u; k0 < params.k; k0 += 16u) {
        for (var q = 0u; q < 8u; q += 1u) {
            let e = lid + q * 64u;
            sa[e] = a[(tm * 32u + e / 16u) * params.k + k0 + e % 16u];
        }
        for (var q = 0u; q < 2u; q += 1u) {
            let e = lid + q * 64u;
            sb[e] = b[(k0 + e / 8u) * n4 + tn * 8u + e % 8u];
        }
        workgroupBarrier();
        for (var kk = 0u; kk < 16u; kk += 1u) {
            let bv = sb[kk * 8u + tx];
            let r = ty * 64u + kk;
            acc0 = fma(vec4<f32>(sa[r]), bv, acc0);
            acc1 = fma(vec4<f32>(sa[r + 16u]), bv, acc1);
            acc2 = fma(vec4<f32>(sa[r + 32u]), bv, acc2);
            acc3 = fma(vec4<f32>(sa[r + 48u]), bv, acc3);
        }
        workgroupBarrier();
    }
    let row = tm * 32u + ty * 4u;
    let col = tn * 8u + tx;
    c[row * n4 + col] = acc0;
    c[(row + 1u) * n4 + col] = acc1;
    c[(row + 2u) * n4 + col] = acc2;
    c[(row + 3u) * n4 + col] = acc3;
}
