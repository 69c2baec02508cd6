// The weight-gradient pass of the tiny MLPs as a tiled reduction, shared by the f32 and
// f16-saved kernels: dW_l = sum over points of delta_l (x) input_l, db_l = sum of delta_l.
//
// A workgroup of WGRAD_THREADS threads owns one tile of one layer's dW, WGRAD_ROWS output rows
// by WGRAD_COLS input columns, and one chunk of points (params.chunk points; the chunk is the
// workgroup index divided by params.groups, the tiles per chunk). Thread c owns columns c and
// c + 8 of the tile: per point it does 2 x WGRAD_ROWS FMAs into registers, the tile's deltas
// times its two inputs. Every load has the same address in every thread (the tile's 16 deltas
// and 16 inputs, of which each thread keeps its own two with selects): lavapipe, which runs a
// subgroup's threads as the lanes of a CPU vector register, makes such a load one scalar load,
// where an address that varies across the lanes costs a gather per load (the kernel this one
// replaced: one 4 x 16 block per thread, the points spread over the threads, five gathered
// vec4s per point). The points are unrolled WGRAD_UNROLL to an iteration, since lavapipe's
// loop bookkeeping costs about as much as a point's work. The tiles of the first 16 columns
// also sum the biases (the deltas alone), alike in every thread; thread 0 adds them. The tile
// is written once per chunk, one f32 atomic per element, so atomics add across chunks only.
// The including file declares `d_weights: array<atomic<f32>>`.
//!include common/mlp.wgsl

// Threads per workgroup; each owns two columns of the tile, c and c + 8.
const WGRAD_THREADS: u32 = 8u;
// Input columns per tile.
const WGRAD_COLS: u32 = 16u;
// Output rows per tile (4 vec4s of deltas per point).
const WGRAD_ROWS: u32 = 16u;
// Points per iteration of the point loops.
const WGRAD_UNROLL: u32 = 4u;

struct WgradTile {
    valid: bool,
    // The layer, its weights' float offset and its widths.
    layer: u32,
    off: u32,
    ni: u32,
    no: u32,
    // Float offsets, within one point's f32 record, of the tile's first input and of its
    // first delta (the f32 layout: per layer its input then its pre-activation gradient, each
    // padded to 4 floats).
    x_at: u32,
    d_at: u32,
    // The tile's first output row and first input column; its vec4s of deltas (1 to 4) and
    // of inputs (1 to 4).
    o0: u32,
    j0: u32,
    nd: u32,
    nx: u32,
}

// Tiles of a layer with ni inputs and no outputs.
fn wgrad_layer_tiles(ni: u32, no: u32) -> u32 {
    return ((no + WGRAD_ROWS - 1u) / WGRAD_ROWS) * ((ni + WGRAD_COLS - 1u) / WGRAD_COLS);
}

// Tile `task` of MLP `s` (invalid past the last one).
fn wgrad_tile(s: MlpShape, task: u32) -> WgradTile {
    var t: WgradTile;
    t.valid = false;
    t.ni = 1u;
    t.nd = 1u;
    t.nx = 1u;
    var first = 0u;
    var at = 0u;
    for (var l = 0u; l < s.layers; l += 1u) {
        let ni = mlp_dim(s, l);
        let no = mlp_dim(s, l + 1u);
        let nt = wgrad_layer_tiles(ni, no);
        if !t.valid && task < first + nt {
            let local = task - first;
            let cols = (ni + WGRAD_COLS - 1u) / WGRAD_COLS;
            t.valid = true;
            t.layer = l;
            t.off = mlp_offset(s, l);
            t.ni = ni;
            t.no = no;
            t.o0 = (local / cols) * WGRAD_ROWS;
            t.j0 = (local % cols) * WGRAD_COLS;
            t.x_at = at + t.j0;
            t.d_at = at + pad4(ni) + t.o0;
            t.nd = min(4u, (pad4(no) - t.o0) / 4u);
            t.nx = min(4u, (pad4(ni) - t.j0) / 4u);
        }
        at += pad4(ni) + pad4(no);
        first += nt;
    }
    return t;
}

// The record units (vec4s of the f32 record, groups of 4 f16 values of the f16 one) of the
// tile's 16 inputs (`x`) and 16 deltas (`d`), after `head` header units; units past t.nx and
// t.nd repeat the last one (their columns and rows are never written).
struct WgradUnits {
    x: array<u32, 4>,
    d: array<u32, 4>,
}

fn wgrad_units(t: WgradTile, head: u32) -> WgradUnits {
    var u: WgradUnits;
    for (var k = 0u; k < 4u; k += 1u) {
        u.x[k] = head + t.x_at / 4u + min(k, t.nx - 1u);
        u.d[k] = head + t.d_at / 4u + min(k, t.nd - 1u);
    }
    return u;
}

// Thread c's values of the tile's inputs x (columns j0 .. j0 + 15): columns j0 + c and
// j0 + 8 + c.
fn wgrad_pick(x: array<vec4<f32>, 4>, c: u32) -> vec2<f32> {
    let k = c & 3u;
    let h0 = select(x[0], x[1], c >= 4u);
    let h1 = select(x[2], x[3], c >= 4u);
    return vec2<f32>(
        select(select(h0.x, h0.y, k == 1u), select(h0.z, h0.w, k == 3u), k >= 2u),
        select(select(h1.x, h1.y, k == 1u), select(h1.z, h1.w, k == 3u), k >= 2u),
    );
}

// One point's contribution: the thread's inputs `x` and the tile's deltas `d`, their product
// scaled by `s` and, with `with_bias`, the deltas by `sd` for the biases (1 and 1 for the f32
// record; the f16 record's power-of-two scales).
fn wgrad_tile_add(x: vec2<f32>, d: array<vec4<f32>, 4>, s: f32, sd: f32, with_bias: bool,
                  acc: ptr<function, array<vec4<f32>, 8>>,
                  bias: ptr<function, array<vec4<f32>, 4>>) {
    let xs = x * s;
    for (var k = 0u; k < 4u; k += 1u) {
        (*acc)[k] = fma(d[k], vec4<f32>(xs.x), (*acc)[k]);
        (*acc)[4u + k] = fma(d[k], vec4<f32>(xs.y), (*acc)[4u + k]);
    }
    if with_bias {
        for (var k = 0u; k < 4u; k += 1u) {
            (*bias)[k] = fma(d[k], vec4<f32>(sd), (*bias)[k]);
        }
    }
}

// Adds thread c's sums to d_weights: acc[4 e + k][r] is row o0 + 4 k + r, column j0 + c + 8 e;
// thread 0 of the first column tile also adds the bias sums bias[k][r] of the same rows.
fn wgrad_tile_flush(t: WgradTile, c: u32, acc: ptr<function, array<vec4<f32>, 8>>,
                    bias: ptr<function, array<vec4<f32>, 4>>) {
    if !t.valid {
        return;
    }
    for (var i = 0u; i < WGRAD_ROWS; i += 1u) {
        let o = t.o0 + i;
        if o < t.no {
            for (var e = 0u; e < 2u; e += 1u) {
                let j = t.j0 + c + 8u * e;
                if j < t.ni {
                    atomicAdd(&d_weights[t.off + o * t.ni + j], (*acc)[4u * e + i / 4u][i % 4u]);
                }
            }
            if t.j0 == 0u && c == 0u {
                atomicAdd(&d_weights[t.off + t.no * t.ni + o], (*bias)[i / 4u][i % 4u]);
            }
        }
    }
}
