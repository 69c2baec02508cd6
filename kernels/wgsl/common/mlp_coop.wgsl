// The tiny MLPs' weight gradient through cooperative matrices (VK_KHR_cooperative_matrix), from
// the f32 records that field/mlp.wgsl's mlp_bwd_data and the fused training step write (per
// point and layer: the layer's input, then the gradient of its pre-activation, each padded to
// 4 floats; common/mlp_wgrad.wgsl describes the layout).
//
// dW_l = sum over points of delta (x) input is a matrix product D^T X with the points as the
// inner dimension. A workgroup owns a chunk of points and walks it in blocks of COOP_POINTS:
// the block's deltas and inputs are converted to f16 in workgroup memory, each scaled by a
// power of two that puts the block's largest magnitude just under 2^14 (f16 keeps 11 bits of
// mantissa but only 5 of exponent, and the gradients of a NeRF step lie near 1e-6); every
// subgroup then multiplies TILE x TILE tiles, f16 inputs with f32 accumulation, and adds the
// unscaled tile to the workgroup's f32 sum of the layer. The bias is one more column of ones.
// At the end of the chunk one f32 atomic per parameter adds the sums to d_weights.
//
// The including file enables f16 and wgpu_cooperative_matrix and declares TILE (8 or 16) and
// the matrix types CoopA (f16, role A), CoopB (f16, role B) and CoopC (f32, accumulator).
//!include common/dispatch.wgsl
//!include common/mlp.wgsl

// Points per block: the workgroup size, one point per thread while staging. (64 would put the
// workgroup memory past lavapipe's 32 KiB.)
const COOP_POINTS: u32 = 32u;
// Widest padded layer input plus the bias tile.
const COOP_XW: u32 = MLP_MAX + TILE;

struct Params {
    // Points.
    n: u32,
    // Points per workgroup (a multiple of COOP_POINTS).
    chunk: u32,
    // Floats per point of the records.
    saved_stride: u32,
    _pad: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> shape_buf: array<MlpShape>;
@group(0) @binding(1) var<storage, read> saved4: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> d_weights: array<atomic<f32>>;

// Block inputs [point][column] (stride xw: the padded inputs, then the bias tile whose first
// column is 1) and deltas [point][output] (stride nop), scaled, in f16.
var<workgroup> coop_x: array<f16, COOP_POINTS * COOP_XW>;
var<workgroup> coop_d: array<f16, COOP_POINTS * MLP_MAX>;
// The layer's sums [output][column] (stride xw), f32.
var<workgroup> coop_acc: array<f32, MLP_MAX * COOP_XW>;
// Largest |input| and |delta| of the block, as f32 bits (non-negative floats order as u32).
var<workgroup> coop_max: array<atomic<u32>, 2>;

fn round_tile(x: u32) -> u32 {
    return (x + TILE - 1u) / TILE * TILE;
}

// Exponent e with m * 2^e in [2^13, 2^14) (0 for m = 0; clamped so the scale stays finite).
fn coop_exponent(m: f32) -> f32 {
    if m <= 0.0 {
        return 0.0;
    }
    return clamp(floor(13.0 - log2(m)), -100.0, 100.0);
}

// v (the floats j..j+3 of a segment of n) with the lanes past n zeroed: the records' padding
// is not written.
fn coop_lanes(v: vec4<f32>, j: u32, n: u32) -> vec4<f32> {
    return select(vec4<f32>(0.0), v, vec4<u32>(j, j + 1u, j + 2u, j + 3u) < vec4<u32>(n));
}

@compute @workgroup_size(32)
fn mlp_wgrad_coop(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32,
                  @builtin(subgroup_id) sg: u32, @builtin(num_subgroups) n_sg: u32) {
    let s = shape_buf[0];
    let p0 = linear_group(wid, nwg) * params.chunk;
    let p1 = min(p0 + params.chunk, params.n);
    let stride4 = params.saved_stride / 4u;
    var at = 0u;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nip = round_tile(ni);
        let nop = round_tile(no);
        let xw = nip + TILE;
        let x_at = at / 4u;
        let d_at = (at + pad4(ni)) / 4u;
        for (var i = lid; i < nop * xw; i += COOP_POINTS) {
            coop_acc[i] = 0.0;
        }
        // The block loop runs the same number of times in every invocation (p0 < p1 or not).
        for (var b0 = p0; b0 < p1; b0 += COOP_POINTS) {
            if lid == 0u {
                atomicStore(&coop_max[0], 0u);
                atomicStore(&coop_max[1], 0u);
            }
            workgroupBarrier();
            let p = b0 + lid;
            let live = p < p1;
            var mx = 0.0;
            var md = 0.0;
            if live {
                for (var v = 0u; v < pad4(ni) / 4u; v += 1u) {
                    let x = abs(coop_lanes(saved4[p * stride4 + x_at + v], 4u * v, ni));
                    mx = max(mx, max(max(x.x, x.y), max(x.z, x.w)));
                }
                for (var v = 0u; v < pad4(no) / 4u; v += 1u) {
                    let d = abs(coop_lanes(saved4[p * stride4 + d_at + v], 4u * v, no));
                    md = max(md, max(max(d.x, d.y), max(d.z, d.w)));
                }
            }
            atomicMax(&coop_max[0], bitcast<u32>(mx));
            atomicMax(&coop_max[1], bitcast<u32>(md));
            workgroupBarrier();
            let ex = coop_exponent(bitcast<f32>(atomicLoad(&coop_max[0])));
            let ed = coop_exponent(bitcast<f32>(atomicLoad(&coop_max[1])));
            let sx = exp2(ex);
            let sd = exp2(ed);
            // Stage this thread's point (zeros past the end and in the padding).
            for (var j = 0u; j < xw; j += 4u) {
                var x = vec4<f32>(0.0);
                if live && j < pad4(ni) {
                    x = coop_lanes(saved4[p * stride4 + x_at + j / 4u], j, ni) * sx;
                } else if live && j == nip {
                    x = vec4<f32>(1.0, 0.0, 0.0, 0.0);
                }
                let o = lid * xw + j;
                coop_x[o] = f16(x.x);
                coop_x[o + 1u] = f16(x.y);
                coop_x[o + 2u] = f16(x.z);
                coop_x[o + 3u] = f16(x.w);
            }
            for (var j = 0u; j < nop; j += 4u) {
                var d = vec4<f32>(0.0);
                if live && j < pad4(no) {
                    d = coop_lanes(saved4[p * stride4 + d_at + j / 4u], j, no) * sd;
                }
                let o = lid * nop + j;
                coop_d[o] = f16(d.x);
                coop_d[o + 1u] = f16(d.y);
                coop_d[o + 2u] = f16(d.z);
                coop_d[o + 3u] = f16(d.w);
            }
            workgroupBarrier();
            // Tiles of [outputs] x [columns], round-robin over the subgroups (uniform within
            // each subgroup, as cooperative operations require).
            let cols = xw / TILE;
            for (var t = sg; t < (nop / TILE) * cols; t += n_sg) {
                let ot = t / cols;
                let jt = t % cols;
                var c = CoopC();
                for (var k = 0u; k < COOP_POINTS; k += TILE) {
                    // A(o, p) = delta of point p, output o: column-major with stride nop.
                    let a = coopLoad<CoopA>(&coop_d[k * nop + ot * TILE], nop);
                    // B(p, j) = input j of point p: row-major with stride xw.
                    let bm = coopLoadT<CoopB>(&coop_x[k * xw + jt * TILE], xw);
                    c = coopMultiplyAdd(a, bm, c);
                }
                // The bias tile carries unscaled ones.
                let e = select(ed + ex, ed, jt * TILE == nip);
                let at_acc = ot * TILE * xw + jt * TILE;
                let sum = coopLoadT<CoopC>(&coop_acc[at_acc], xw);
                coopStoreT(sum + c * exp2(-e), &coop_acc[at_acc], xw);
            }
            workgroupBarrier();
        }
        // One atomic per parameter: W (row-major, outputs x inputs) then b.
        let off = mlp_offset(s, l);
        for (var i = lid; i < no * (ni + 1u); i += COOP_POINTS) {
            let o = i / (ni + 1u);
            let j = i % (ni + 1u);
            if p0 < p1 {
                if j == ni {
                    atomicAdd(&d_weights[off + no * ni + o], coop_acc[o * xw + nip]);
                } else {
                    atomicAdd(&d_weights[off + o * ni + j], coop_acc[o * xw + j]);
                }
            }
        }
        workgroupBarrier();
        at += pad4(ni) + pad4(no);
    }
}
