// The normalised position s in [0, 1] along a ray and its distance t, and the jitter of a
// sample inside its interval: shared by the strata (common/strata.wgsl) and the proposal
// sampler (render/proposal.wgsl). Textual include after common/rng.wgsl.

// Distance at normalised position s for a ray from nf.x to nf.y; spacing 1: linear in
// disparity, else linear in t.
fn strata_t(s: f32, nf: vec2<f32>, spacing: u32) -> f32 {
    if spacing == 1u {
        return 1.0 / mix(1.0 / nf.x, 1.0 / nf.y, s);
    }
    return mix(nf.x, nf.y, s);
}

// The position in [0, 1) of sample i of ray r inside its stratum for jitter seed `seed`.
fn strata_jitter(seed: u32, r: u32, i: u32) -> f32 {
    return rand01(pcg_hash(seed ^ pcg_hash(r)) + i);
}
