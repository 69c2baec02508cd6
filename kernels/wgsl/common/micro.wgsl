// The parameters and the random sequence of the microbenchmarks (wgsl/micro/*.wgsl), the same
// in all three files so that the host sets them one way (extranerf_prims::micro).

struct Params {
    // Lanes (threads) that run; the others return at once.
    lanes: u32,
    // Operations per lane: a multiple of 8 (memory and atomics), of 32 (micro_fma's FMAs) or
    // dense layers (micro_dense*).
    ops: u32,
    // log2 of the entries of the table at the width read (random index: the sequence's top
    // log2_entries bits).
    log2_entries: u32,
    // Lanes that share one random sequence (1: each lane its own); with atomics, lanes of the
    // same share add to the same addresses, as neighbouring rays do at coarse grid levels.
    share: u32,
    // micro_fma: each accumulator becomes fma(a, m, c).
    m: f32,
    c: f32,
    _pad0: u32,
    _pad1: u32,
    // (0, 1, 2, 3): common/mlp_block.wgsl's identity table (micro_dense*).
    lut: vec4<u32>,
}
var<immediate> params: Params;

// The first state of lane i's sequence.
fn micro_seed(i: u32) -> u32 {
    return ((i / params.share) * 2654435769u) ^ 0x6d2b79f5u;
}

// The next state: a 32-bit linear congruential step (Numerical Recipes' constants).
fn micro_next(s: u32) -> u32 {
    return s * 1664525u + 1013904223u;
}
