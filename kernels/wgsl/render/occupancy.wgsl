// Occupancy grid maintenance, all on the device:
//   occ_sample: positions (scene-normalised u) of one jittered point in each cell of a window
//               [first, first + count) of cells, for the caller to evaluate the density at;
//   occ_update: grid[cell] = max(grid[cell] * decay, density) over the window (the EMA of
//               Instant-NGP);
//   occ_bits:   bit of each cell = grid > min(threshold, mean), the mean read from a device
//               buffer (reduce_sum of the grid divided by the cell count), no host round trip;
//   occ_query:  0/1 per point, what the march sees.
//!include common/dispatch.wgsl
//!include common/rng.wgsl
//!include common/occupancy.wgsl

struct Params {
    res: u32,
    cascades: u32,
    first: u32,
    count: u32,
    seed: u32,
    decay: f32,
    threshold: f32,
    _pad: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read_write> positions: array<f32>;
@group(0) @binding(1) var<storage, read> density: array<f32>;
@group(0) @binding(2) var<storage, read_write> grid: array<f32>;
@group(0) @binding(3) var<storage, read_write> bits: array<u32>;
// [sum of the grid] from reduce_sum.
@group(0) @binding(4) var<storage, read> grid_sum: array<f32>;
@group(0) @binding(5) var<storage, read> query: array<f32>;
@group(0) @binding(6) var<storage, read_write> occupied: array<u32>;

fn occ_params() -> OccGrid {
    return OccGrid(params.res, params.cascades);
}

fn total_cells() -> u32 {
    return params.res * params.res * params.res * params.cascades;
}

@compute @workgroup_size(64)
fn occ_sample(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let k = linear_group(wid, nwg) * 64u + lid;
    if k >= params.count {
        return;
    }
    let cell = (params.first + k) % total_cells();
    let h = params.seed * 3u * total_cells() + 3u * cell;
    let j = vec3<f32>(rand01(h), rand01(h + 1u), rand01(h + 2u));
    let u = occ_cell_point(cell, j, occ_params());
    positions[3u * k] = u.x;
    positions[3u * k + 1u] = u.y;
    positions[3u * k + 2u] = u.z;
}

@compute @workgroup_size(64)
fn occ_update(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let k = linear_group(wid, nwg) * 64u + lid;
    if k >= params.count {
        return;
    }
    let cell = (params.first + k) % total_cells();
    var d = density[k];
    // A non-finite density estimate must not freeze a cell as occupied forever.
    if !(d == d) || d < 0.0 {
        d = 0.0;
    }
    grid[cell] = max(grid[cell] * params.decay, min(d, 3.0e38));
}

@compute @workgroup_size(64)
fn occ_bits(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let w = linear_group(wid, nwg) * 64u + lid;
    let n = total_cells();
    if w * 32u >= n {
        return;
    }
    let thresh = min(params.threshold, grid_sum[0] / f32(n));
    var word = 0u;
    for (var b = 0u; b < 32u; b += 1u) {
        let cell = w * 32u + b;
        if cell < n && grid[cell] > thresh {
            word |= 1u << b;
        }
    }
    bits[w] = word;
}

@compute @workgroup_size(64)
fn occ_query(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let i = linear_group(wid, nwg) * 64u + lid;
    if i >= params.count {
        return;
    }
    let u = vec3<f32>(query[3u * i], query[3u * i + 1u], query[3u * i + 2u]);
    let cell = occ_cell(u, occ_params());
    var o = 0u;
    if cell != OCC_NONE && ((bits[cell / 32u] >> (cell % 32u)) & 1u) != 0u {
        o = 1u;
    }
    occupied[i] = o;
}
