// common/mlp_block.wgsl's mlp_uni for kernels whose push constants hold `lut`, the identity table
// (0, 1, 2, 3): x (< 2^bits, bits even) rebuilt two bits at a time from push-constant loads.
// Mesa's gallivm (25.0) counts a value as the same in every lane only when it derives from
// constants and push constants alone (nir_src_is_always_uniform); a push-constant load counts
// whatever its index. So the result, equal to x, lets a uniform-block load at an offset built
// from it run once as a scalar instead of once per lane. x must be the same in every lane.
fn mlp_uni(x: u32, bits: u32) -> u32 {
    var r = 0u;
    for (var b = 0u; b < bits; b += 2u) {
        r |= params.lut[(x >> b) & 3u] << b;
    }
    return r;
}
