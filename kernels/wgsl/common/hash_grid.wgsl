// Multi-resolution hash encoding (Instant-NGP, Mueller et al. 2022), shared by the standalone
// encoding kernels and the fused march kernels. Level l has resolution N_l (grid vertices
// 0..=N_l per axis) and a table of `size` entries of F features at `offset` floats into the
// flat table: dense indexing when (N_l + 1)^3 fits in the table, else the spatial hash
// (x * 1) ^ (y * 2654435761) ^ (z * 805459861) mod size (size = T, a power of two). Positions are clamped to [0, 1]^3.

//
// Tables larger than one storage binding (lavapipe: 128 MiB) are split at a level boundary into
// two bindings, `table` and `table_hi`: a level in the second one has bit 1 of `dense` set and
// its offset counts from the start of that binding. Unsplit tables bind the same range twice.
struct HashLevel {
    // Float offset of the level in its binding, resolution N_l, table entries; bit 0 of flags:
    // dense, bit 1: in the second binding.
    offset: u32,
    res: u32,
    size: u32,
    dense: u32,
}

// Which table binding holds a level (0: `table`, 1: `table_hi`).
fn hg_part(lv: HashLevel) -> u32 {
    return lv.dense >> 1u;
}

// The table entry of grid vertex c at a level.
fn hg_index(c: vec3<u32>, lv: HashLevel) -> u32 {
    if (lv.dense & 1u) != 0u {
        let s = lv.res + 1u;
        return c.x + s * (c.y + s * c.z);
    }
    // Hashed levels have size T = 2^k, so the modulo is a mask (integer division is slow on
    // CPUs' SIMD units, where lavapipe runs).
    return ((c.x * 1u) ^ (c.y * 2654435761u) ^ (c.z * 805459861u)) & (lv.size - 1u);
}

// The cell and the position inside it of x (in [0, 1]^3) at a level.
struct HgCell {
    corner: vec3<u32>,
    frac: vec3<f32>,
}

fn hg_cell(x: vec3<f32>, lv: HashLevel) -> HgCell {
    let res = f32(lv.res);
    let p = clamp(x, vec3<f32>(0.0), vec3<f32>(1.0)) * res;
    // At x = 1 the cell is the last one with frac = 1, so vertex res + 1 is never touched.
    let c = min(floor(p), vec3<f32>(res - 1.0));
    return HgCell(vec3<u32>(c), p - c);
}

// Trilinear weight of corner k (bit 0: x, bit 1: y, bit 2: z).
fn hg_weight(frac: vec3<f32>, k: u32) -> f32 {
    let b = vec3<u32>(k & 1u, (k >> 1u) & 1u, (k >> 2u) & 1u);
    let w = select(vec3<f32>(1.0) - frac, frac, b == vec3<u32>(1u));
    return w.x * w.y * w.z;
}

fn hg_corner(corner: vec3<u32>, k: u32) -> vec3<u32> {
    return corner + vec3<u32>(k & 1u, (k >> 1u) & 1u, (k >> 2u) & 1u);
}

// NaN in any coordinate: the point has no features (and no gradient).
fn hg_valid(x: vec3<f32>) -> bool {
    return all(x == x);
}
