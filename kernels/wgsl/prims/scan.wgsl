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
// 64 threads, each scanning 4 consecutive vec4s (16 elements) serially: lavapipe pays per
// invocation, so few, full invocations; GPUs still read 64 contiguous bytes per thread.
const V: u32 = 4u;

@compute @workgroup_size(64)
fn scan_tiles(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32,
              @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32,
              @builtin(subgroup_invocation_id) lane: u32) {
    let tile = linear_group(wid, nwg);
    let n = params.n;
    if tile >= (n + TILE - 1u) / TILE {
        return;
    }
    let first = tile * (TILE / 4u) + lid * V;
    var v: array<vec4<u32>, 4>;
    var run = 0u;
    for (var k = 0u; k < V; k += 1u) {
        let i = first + k;
        let base = i * 4u;
        var a = vec4<u32>(0u);
        if base + 3u < n {
            a = input[i];
        } else if base < n {
            for (var c = 0u; base + c < n; c += 1u) {
                a[c] = input[i][c];
            }
        }
        if params.binarize != 0u {
            a = min(a, vec4<u32>(1u));
        }
        let incl = vec4<u32>(a.x, a.x + a.y, a.x + a.y + a.z, a.x + a.y + a.z + a.w);
        v[k] = vec4<u32>(run) + incl - a;
        run += incl.w;
    }
    let s = wg_exclusive_scan(run, lid, sg_id, sg_count, lane);
    for (var k = 0u; k < V; k += 1u) {
        let i = first + k;
        let base = i * 4u;
        let r = v[k] + vec4<u32>(s.x);
        if base + 3u < n {
            output[i] = r;
        } else if base < n {
            for (var c = 0u; base + c < n; c += 1u) {
                output[i][c] = r[c];
            }
        }
    }
    if lid == 0u {
        tile_sums[tile] = s.y;
    }
}

@compute @workgroup_size(64)
fn add_offsets(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let tile = linear_group(wid, nwg);
    let n = params.n;
    if tile * TILE >= n {
        return;
    }
    let o = vec4<u32>(tile_offsets[tile]);
    let first = tile * (TILE / 4u) + lid * V;
    for (var k = 0u; k < V; k += 1u) {
        let i = first + k;
        let base = i * 4u;
        if base + 3u < n {
            output[i] += o;
        } else if base < n {
            for (var c = 0u; base + c < n; c += 1u) {
                output[i][c] += o.x;
            }
        }
    }
}
