// Stateless random numbers: PCG hash of a counter (Jarzynski & Olano 2020). Deterministic and
// identical in the Rust reference.

fn pcg_hash(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

// Uniform in [0, 1): the top 24 bits of the hash.
fn rand01(v: u32) -> f32 {
    return f32(pcg_hash(v) >> 8u) * (1.0 / 16777216.0);
}

// The background colour of batch ray r: `fixed` unless `random` is non-zero, then uniform in
// [0, 1)^3 per ray from the step's seed (Instant-NGP's random background: a ray cannot pass
// for a dark or light surface by staying transparent). The Rust reference is
// reference::ray_background.
fn ray_background(fixed: vec3<f32>, random: u32, seed: u32, r: u32) -> vec3<f32> {
    if random == 0u {
        return fixed;
    }
    let h = pcg_hash(seed ^ 0x6a09e667u ^ pcg_hash(r ^ 0xbb67ae85u));
    return vec3<f32>(rand01(h), rand01(h + 1u), rand01(h + 2u));
}
