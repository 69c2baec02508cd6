// Stratified samples along a ray, shared by render/sample.wgsl and the fused training step
// (render/train_step.wgsl): k strata over the ray's normalised distance s in [0, 1], each
// sample jittered inside its stratum.
//
// Occupancy-aware strata: s is cut into `probes` equal intervals, each tested once, at its
// centre, against the occupancy grid; the ray's k strata are then spread over the occupied
// intervals only, as if the empty ones were cut out of [0, 1]. A ray with no occupied interval
// samples all of it. Points outside the grid count as occupied, as in the march.
//
// Textual include after common/rng.wgsl and common/occupancy.wgsl; the including file declares
// `occ_bits`.
//!include common/spacing.wgsl

const MAX_PROBES: u32 = 256u;

// The occupied probe intervals of one ray: one bit per interval, and how many are set.
struct ProbeMask {
    bits: array<u32, 8>,
    count: u32,
}


// Stratum i of k over the whole ray, at position `jit` in [0, 1) inside it: (t, dt, s).
// Each stratum's share of s is 1 / k.
fn ray_stratum(i: u32, k: u32, jit: f32, nf: vec2<f32>, spacing: u32) -> vec3<f32> {
    let inv_k = 1.0 / f32(k);
    let s0 = f32(i) * inv_k;
    let s1 = f32(i + 1u) * inv_k;
    let s = mix(s0, s1, jit);
    return vec3<f32>(strata_t(s, nf, spacing), strata_t(s1, nf, spacing) - strata_t(s0, nf, spacing), s);
}

// The probe mask of the ray o + t d (t between nf.x and nf.y); scene points are
// u = (p - centre.xyz) * centre.w.
fn probe_mask(o: vec3<f32>, d: vec3<f32>, nf: vec2<f32>, spacing: u32, probes: u32,
              centre: vec4<f32>, grid: OccGrid) -> ProbeMask {
    var mask: ProbeMask;
    for (var j = 0u; j < probes; j += 1u) {
        let s = (f32(j) + 0.5) / f32(probes);
        let u = (o + strata_t(s, nf, spacing) * d - centre.xyz) * centre.w;
        let cell = occ_cell(u, grid);
        if cell == OCC_NONE || ((occ_bits[cell / 32u] >> (cell % 32u)) & 1u) != 0u {
            mask.bits[j / 32u] |= 1u << (j % 32u);
            mask.count += 1u;
        }
    }
    if mask.count == 0u {
        for (var j = 0u; j < probes; j += 1u) {
            mask.bits[j / 32u] |= 1u << (j % 32u);
        }
        mask.count = probes;
    }
    return mask;
}

// The probe interval of occupied rank q (0-based) in the mask.
fn probe_of_rank(mask: ptr<function, ProbeMask>, q: u32) -> u32 {
    var left = q;
    for (var w = 0u; w < 8u; w += 1u) {
        let c = countOneBits((*mask).bits[w]);
        if left < c {
            var bits = (*mask).bits[w];
            for (var b = 0u; b < left; b += 1u) {
                // Clear the lowest set bit.
                bits &= bits - 1u;
            }
            return 32u * w + firstTrailingBit(bits);
        }
        left -= c;
    }
    return MAX_PROBES - 1u;
}

// s at occupied measure c (in probe intervals, 0 <= c <= count).
fn s_at(mask: ptr<function, ProbeMask>, c: f32, probes: u32) -> f32 {
    let q = min(u32(floor(c)), (*mask).count - 1u);
    return (f32(probe_of_rank(mask, q)) + (c - f32(q))) / f32(probes);
}

// Stratum i of k, at position `jit` in [0, 1) inside it: (t, dt, s), dt being the length in t
// of the stratum's occupied part. Its share of s (the distortion loss's ds) is
// strata_ds(mask, k, probes); the strata of a ray tile the occupied part of s.
fn occupied_stratum(mask: ptr<function, ProbeMask>, i: u32, k: u32, jit: f32, probes: u32,
                    nf: vec2<f32>, spacing: u32) -> vec3<f32> {
    let count = (*mask).count;
    let per = f32(count) / f32(k);
    let pm = 1.0 / f32(probes);
    let c0 = f32(i) * per;
    let c1 = f32(i + 1u) * per;
    let s = s_at(mask, mix(c0, c1, jit), probes);
    // The stratum's occupied pieces, one per probe interval it touches.
    var dt = 0.0;
    let q1 = min(u32(ceil(c1)), count);
    for (var q = u32(floor(c0)); q < q1; q += 1u) {
        let a = max(c0, f32(q));
        let b = min(c1, f32(q + 1u));
        if b > a {
            let j = f32(probe_of_rank(mask, q));
            dt += strata_t((j + b - f32(q)) * pm, nf, spacing) - strata_t((j + a - f32(q)) * pm, nf, spacing);
        }
    }
    return vec3<f32>(strata_t(s, nf, spacing), dt, s);
}

// Each stratum's share of s under occupied_stratum.
fn strata_ds(mask: ptr<function, ProbeMask>, k: u32, probes: u32) -> f32 {
    return f32((*mask).count) / f32(k) * (1.0 / f32(probes));
}
