// What the fused cooperative-matrix kernels (common/step_coop.wgsl, common/march_coop.wgsl)
// share: one row of workgroup memory per point, both MLPs' f16 weights in one buffer, the f32
// biases from the uniform block, the staging of a block's rows, and the weights' conversion.
// Textual include after common/coop_tiles.wgsl; the including file declares `params` with
// `color_base`, and the bindings `density_shape`, `color_shape` and the uniform `mlp` block
// (common/mlp_block.wgsl).

// Workgroup memory of common/coop_tiles.wgsl: one row of at most MLP_MAX per point.
const COOP_X: u32 = COOP_POINTS * MLP_MAX;
const COOP_ACC: u32 = COOP_POINTS * MLP_MAX;

// Both MLPs' weights in f16, per layer [round_tile(outputs)][round_tile(inputs)], zero padded:
// the density MLP's, then the colour MLP's at element coop_w_offset(density, layers).
@group(0) @binding(21) var<storage, read> w16: array<f16>;
// w16, written by coop_fused_weights (each file's weights kernel).
@group(0) @binding(22) var<storage, read_write> w16_out: array<f16>;

fn coop_bias(e: u32) -> f32 {
    return mlp_block_at(e);
}

// Writes element e of w16_out: both MLPs' weights from the uniform block (density at float 0,
// colour at params.color_base) in f16; nothing past the end.
fn coop_fused_weights(e: u32) {
    if e >= arrayLength(&w16_out) {
        return;
    }
    let d = density_shape[0];
    var at = e;
    var s = d;
    var base = 0u;
    let cw = coop_w_offset(d, d.layers);
    if e >= cw {
        at -= cw;
        s = color_shape[0];
        base = params.color_base;
    }
    let src = coop_w16_source(s, at);
    var v = f16(0.0);
    if src != COOP_PAD {
        v = coop_f16(mlp_block_at(base + src));
    }
    w16_out[e] = v;
}

// The density MLP's input row of this thread's point: its encoding e (zeros for a thread with
// no sample), in f16, padded to the tile.
fn coop_stage_encoding(lid: u32, e: ptr<function, Act>) {
    let nip = round_tile(mlp_dim(density_shape[0], 0u));
    for (var q = 0u; q < nip; q += 1u) {
        coop_x[lid * nip + q] = coop_f16(act_get(e, q));
    }
}

// The colour MLP's input row of this thread's point after the density MLP's forward pass: the
// density MLP's output row (in coop_acc), then SH4 of the ray direction; zeros when not
// `live`.
fn coop_stage_color(lid: u32, live: bool, sh: array<f32, 16>) {
    let ds = density_shape[0];
    let geo = mlp_dim(ds, ds.layers);
    let nop_d = round_tile(geo);
    let nip_c = round_tile(mlp_dim(color_shape[0], 0u));
    for (var q = 0u; q < nip_c; q += 1u) {
        var v = 0.0;
        if live && q < geo {
            v = coop_acc[lid * nop_d + q];
        } else if live && q < geo + 16u {
            v = sh[q - geo];
        }
        coop_x[lid * nip_c + q] = coop_f16(v);
    }
}
