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
