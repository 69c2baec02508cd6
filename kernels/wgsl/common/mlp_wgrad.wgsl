// The weight-gradient pass of the tiny MLPs, shared by the f32 and f16-saved kernels:
// dW_l = sum over points of delta_l (x) input_l, db_l = sum of delta_l. One thread per (block of
// 4 rows x 4 columns of one layer, group of points); the column block past the last one holds
// the biases. Lanes of a subgroup that share a block (the group count is a multiple of the
// subgroup size) sum in the subgroup; one lane adds the 16 sums with f32 atomics. The including
// file declares `d_weights: array<atomic<f32>>`.
//!include common/mlp.wgsl

struct WgradBlock {
    valid: bool,
    // The block's layer, its weights' float offset and its widths.
    layer: u32,
    off: u32,
    ni: u32,
    no: u32,
    // Float offset of the layer's input segment within one point's saved record (the f32
    // layout: per layer its input then its pre-activation gradient, each padded to 4).
    at: u32,
    // First output row and first input column of the block; `bias` for the bias column.
    o0: u32,
    j0: u32,
    bias: bool,
}

// Weight block `blk` of MLP `s` (invalid past the last block), with blocks of 4 rows x `cw`
// columns (cw a multiple of 4).
fn wgrad_block_cols(s: MlpShape, blk: u32, cw: u32) -> WgradBlock {
    var b: WgradBlock;
    b.valid = false;
    b.ni = 1u;
    b.no = 1u;
    var local = 0u;
    var first = 0u;
    var at = 0u;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nb = (pad4(no) / 4u) * ((pad4(ni) + cw - 1u) / cw + 1u);
        if !b.valid && blk < first + nb {
            b.valid = true;
            b.layer = l;
            b.off = mlp_offset(s, l);
            b.ni = ni;
            b.no = no;
            b.at = at;
            local = blk - first;
        }
        at += pad4(ni) + pad4(no);
        first += nb;
    }
    let cols = (pad4(b.ni) + cw - 1u) / cw + 1u;
    b.o0 = (local / cols) * 4u;
    let jc = local % cols;
    b.bias = jc + 1u == cols;
    b.j0 = jc * cw;
    return b;
}

// The f16 record's 4x4 blocks.
fn wgrad_block(s: MlpShape, blk: u32) -> WgradBlock {
    return wgrad_block_cols(s, blk, 4u);
}

// Adds a thread's 4x4 sums (acc[r][c]: row o0 + r, column j0 + c; column 0 for the bias) to
// d_weights: summed over the subgroup when all its lanes share the block. Every lane of the
// subgroup must call it (no early return before).
fn wgrad_flush(b: WgradBlock, blk: u32, lane: u32, acc_in: array<vec4<f32>, 4>) {
    var acc = acc_in;
    let shared_block = subgroupAll(subgroupBroadcastFirst(blk) == blk);
    if shared_block {
        acc[0] = subgroupAdd(acc[0]);
        acc[1] = subgroupAdd(acc[1]);
        acc[2] = subgroupAdd(acc[2]);
        acc[3] = subgroupAdd(acc[3]);
    }
    if !b.valid || (shared_block && lane != subgroupBroadcastFirst(lane)) {
        return;
    }
    for (var r = 0u; r < 4u; r += 1u) {
        let o = b.o0 + r;
        if o >= b.no {
            break;
        }
        let v = acc[r];
        if b.bias {
            atomicAdd(&d_weights[b.off + b.no * b.ni + o], v.x);
            continue;
        }
        for (var c = 0u; c < 4u; c += 1u) {
            if b.j0 + c < b.ni {
                atomicAdd(&d_weights[b.off + o * b.ni + b.j0 + c], v[c]);
            }
        }
    }
}

// The f32 record's wider blocks: 4 rows x 16 columns per thread (4 input vec4s per delta vec4,
// 64 FMAs per 5 loads instead of 16 per 2; on lavapipe each load of a varying address is a
// per-lane loop, so loads dominate). The column block past the last one holds the biases.
fn wgrad_block_wide(s: MlpShape, blk: u32) -> WgradBlock {
    return wgrad_block_cols(s, blk, 16u);
}

// wgrad_flush for a wide block: acc[4 * r + v][c] is row o0 + r, column j0 + 4 v + c (column 0
// of acc[4 * r] for the bias). Every lane of the subgroup must call it.
fn wgrad_flush_wide(b: WgradBlock, blk: u32, lane: u32, acc_in: array<vec4<f32>, 16>) {
    var acc = acc_in;
    let shared_block = subgroupAll(subgroupBroadcastFirst(blk) == blk);
    if shared_block {
        for (var q = 0u; q < 16u; q += 1u) {
            acc[q] = subgroupAdd(acc[q]);
        }
    }
    if !b.valid || (shared_block && lane != subgroupBroadcastFirst(lane)) {
        return;
    }
    for (var r = 0u; r < 4u; r += 1u) {
        let o = b.o0 + r;
        if o >= b.no {
            break;
        }
        if b.bias {
            atomicAdd(&d_weights[b.off + b.no * b.ni + o], acc[4u * r].x);
            continue;
        }
        for (var v = 0u; v < 4u; v += 1u) {
            let a = acc[4u * r + v];
            for (var c = 0u; c < 4u; c += 1u) {
                let j = b.j0 + 4u * v + c;
                if j < b.ni {
                    atomicAdd(&d_weights[b.off + o * b.ni + j], a[c]);
                }
            }
        }
    }
}
