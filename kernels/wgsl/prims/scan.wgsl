// Exclusive prefix sum of u32 over arbitrary lengths (reduce-then-scan in tiles of 1024):
// scan_tiles scans each tile (vec4 per thread) and writes the tile's total; the host scans the
// totals with the same kernel (recursively) and add_offsets adds them back.
// With `binarize` != 0 every input element counts as min(x, 1) (flags for compaction).
//!include common/dispatch.wgsl
//!include common/wg_scan.wgsl

struct Params {
    n: u32,
    binarize: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> input: array<vec4<u32>>;
@group(0) @binding(1) var<storage, read_write> output: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> tile_sums: array<u32>;
@group(0) @binding(3) var<storage, read> tile_offsets: array<u32>;

const TILE: u32 = 1024u;

@compute @workgroup_size(256)
fn scan_tiles(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32,
              @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32,
              @builtin(subgroup_invocation_id) lane: u32) {
    let tile = linear_group(wid, nwg);
    let n = params.n;
    if tile >= (n + TILE - 1u) / TILE {
        return;
    }
    let i = tile * 256u + lid;
    let base = i * 4u;
    var v = vec4<u32>(0u);
    if base + 3u < n {
        v = input[i];
    } else if base < n {
        for (var k = 0u; base + k < n; k += 1u) {
            v[k] = input[i][k];
        }
    }
    if params.binarize != 0u {
        v = min(v, vec4<u32>(1u));
    }
    let incl = vec4<u32>(v.x, v.x + v.y, v.x + v.y + v.z, v.x + v.y + v.z + v.w);
    let s = wg_exclusive_scan(incl.w, lid, sg_id, sg_count, lane);
    let off = s.x;
    let r = vec4<u32>(off, off + incl.x, off + incl.y, off + incl.z);
    if base + 3u < n {
        output[i] = r;
    } else if base < n {
        for (var k = 0u; base + k < n; k += 1u) {
            output[i][k] = r[k];
        }
    }
    if lid == 0u {
        tile_sums[tile] = s.y;
    }
}

@compute @workgroup_size(256)
fn add_offsets(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let tile = linear_group(wid, nwg);
    let i = tile * 256u + lid;
    let base = i * 4u;
    let n = params.n;
    if base >= n {
        return;
    }
    let o = tile_offsets[tile];
    if base + 3u < n {
        output[i] += vec4<u32>(o);
    } else {
        for (var k = 0u; base + k < n; k += 1u) {
            output[i][k] += o;
        }
    }
}
