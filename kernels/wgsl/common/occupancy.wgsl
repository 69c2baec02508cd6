// Multi-cascade occupancy grid (Instant-NGP). Positions are scene-normalised, u = (x - centre)
// / radius; cascade c covers |u|_inf <= 2^c with res^3 cells, and a point belongs to the finest
// cascade that contains it. Cells are indexed cascade-major, then z, y, x. One bit per cell in
// `array<u32>` words marks cells whose density is above the threshold.

const OCC_NONE: u32 = 0xffffffffu;

struct OccGrid {
    res: u32,
    cascades: u32,
}

fn occ_cascade(u: vec3<f32>, g: OccGrid) -> u32 {
    // `u == u` is false for NaN; `u != u` compiles to an ordered compare that is false too.
    if !all(u == u) {
        return OCC_NONE;
    }
    let m = max(abs(u.x), max(abs(u.y), abs(u.z)));
    if m <= 1.0 {
        return 0u;
    }
    if !(m <= ldexp(1.0, i32(g.cascades - 1u))) {
        // NaN or outside the largest cascade.
        return OCC_NONE;
    }
    // ceil(log2(m)) exactly, from the exponent: m = f 2^e with f in [0.5, 1).
    let fe = frexp(m);
    return u32(select(fe.exp, fe.exp - 1, fe.fract == 0.5));
}

// Cell index of u, or OCC_NONE outside the grid.
fn occ_cell(u: vec3<f32>, g: OccGrid) -> u32 {
    let c = occ_cascade(u, g);
    if c == OCC_NONE {
        return OCC_NONE;
    }
    let r = f32(g.res);
    let p = clamp((ldexp(u, vec3<i32>(-i32(c))) * 0.5 + 0.5) * r, vec3<f32>(0.0), vec3<f32>(r - 1.0));
    let q = vec3<u32>(p);
    return ((c * g.res + q.z) * g.res + q.y) * g.res + q.x;
}

// Centre-relative position of a point inside cell `cell` at jitter `j` in [0, 1)^3.
fn occ_cell_point(cell: u32, j: vec3<f32>, g: OccGrid) -> vec3<f32> {
    let per = g.res * g.res * g.res;
    let c = cell / per;
    let i = cell % per;
    let q = vec3<f32>(f32(i % g.res), f32((i / g.res) % g.res), f32(i / (g.res * g.res)));
    let unit = (q + j) / f32(g.res);
    return ldexp(unit * 2.0 - 1.0, vec3<i32>(i32(c)));
}
