// The BaseNeRF field evaluated in registers by one thread (the fused kernels: render/march.wgsl,
// render/visibility.wgsl). Textual include: the including file declares `params` with the
// fields read here (features, levels, contraction, spacing, near, far, occ_res, occ_cascades,
// center, inv_radius)
// and the bindings `level_info`, `table`, `table_hi` (a split table's second part, see
// common/hash_grid.wgsl), `density_shape`, `occ_bits` and the uniform `mlp` block, and includes
// common/{hash_grid,mlp_block,contract,heads,occupancy}.wgsl before this.

// Entry e of the table part `hi` selects; a branch, so the other binding is never read out of
// its range.
fn table_at(hi: bool, e: u32) -> f32 {
    if hi {
        return table_hi[e];
    }
    return table[e];
}

// Hash-grid features of the contracted point x into a[0 .. levels * features]. A NaN point
// has all-zero features, as in the standalone kernel.
fn encode(x: vec3<f32>, a: ptr<function, Act>) {
    let F = params.features;
    for (var j = 0u; j < 16u; j += 1u) {
        (*a)[j] = vec4<f32>(0.0);
    }
    if !hg_valid(x) {
        return;
    }
    for (var l = 0u; l < params.levels; l += 1u) {
        let lv = level_info[l];
        let cell = hg_cell(x, lv);
        let hi = hg_part(lv) != 0u;
        if F == 2u {
            // The paper's setting: one hash per corner for both features.
            var acc = vec2<f32>(0.0);
            for (var k = 0u; k < 8u; k += 1u) {
                let e = lv.offset + hg_index(hg_corner(cell.corner, k), lv) * 2u;
                acc += hg_weight(cell.frac, k) * vec2<f32>(table_at(hi, e), table_at(hi, e + 1u));
            }
            act_set(a, 2u * l, acc.x);
            act_set(a, 2u * l + 1u, acc.y);
            continue;
        }
        for (var f = 0u; f < F; f += 1u) {
            var acc = 0.0;
            for (var k = 0u; k < 8u; k += 1u) {
                let e = lv.offset + hg_index(hg_corner(cell.corner, k), lv) * F;
                acc += hg_weight(cell.frac, k) * table_at(hi, e + f);
            }
            act_set(a, l * F + f, acc);
        }
    }
}

// Density at the scene-normalised point u, leaving the density MLP's output row in a.
fn density_at(u: vec3<f32>, a: ptr<function, Act>) -> f32 {
    encode(contract_unit(u, params.contraction), a);
    mlp_forward(density_shape[0], 0u, a);
    return trunc_exp((*a)[0].x);
}

// Distance at normalised position s in [0, 1] (render/sample.wgsl's t_of). The including
// kernel defines sample_spacing(): 0 linear in t, 1 linear in disparity.
fn t_of(s: f32) -> f32 {
    if sample_spacing() == 1u {
        return 1.0 / mix(1.0 / params.near, 1.0 / params.far, s);
    }
    return mix(params.near, params.far, s);
}

// False only inside a cell the grid marks empty: points outside the grid (or NaN) are
// evaluated, so a grid smaller than the scene costs speed, never content.
fn occupied(u: vec3<f32>) -> bool {
    if params.occ_cascades == 0u {
        return true;
    }
    let cell = occ_cell(u, OccGrid(params.occ_res, params.occ_cascades));
    return cell == OCC_NONE || ((occ_bits[cell / 32u] >> (cell % 32u)) & 1u) != 0u;
}

// The colour MLP's input rows of a group: each slot's density-MLP output row (already in
// a[k], geo_dims wide) followed by SH4 of the ray direction.
fn color_input_group(a: ptr<function, ActGroup>, sh: array<f32, 16>) {
    let ds = density_shape[0];
    let g4 = mlp_dim(ds, ds.layers) >> 2u;
    for (var k = 0u; k < MLP_GROUP; k += 1u) {
        for (var r = 0u; r < 4u; r += 1u) {
            (*a)[k][g4 + r] = vec4<f32>(sh[4u * r], sh[4u * r + 1u], sh[4u * r + 2u], sh[4u * r + 3u]);
        }
    }
}

// The scene-normalised point at distance t along ray (origin, direction).
fn scene_point(ray: array<vec3<f32>, 2>, t: f32) -> vec3<f32> {
    return (ray[0] + t * ray[1] - params.center.xyz) * params.inv_radius;
}
