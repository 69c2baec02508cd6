// Stable LSD radix sort of u32 keys with u32 values, 4 bits per pass, tiles of 1024 elements
// (64 threads, PER = 16 contiguous elements each: lavapipe pays per invocation and per barrier,
// and this ran about 2x faster there than 256 threads x 4). Per pass: `histogram` counts digits per tile into a
// digit-major table hist[d * ntiles + tile]; the host scans it exclusively; `scatter` sorts each
// tile locally by the digit (four stable 1-bit splits in shared memory) and writes every element
// to offsets[d * ntiles + tile] + its rank among the tile's elements with digit d.
//!include common/dispatch.wgsl
//!include common/wg_scan.wgsl

struct Params {
    n: u32,
    shift: u32,
    ntiles: u32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> keys_in: array<u32>;
@group(0) @binding(1) var<storage, read> vals_in: array<u32>;
@group(0) @binding(2) var<storage, read_write> hist: array<u32>;
@group(0) @binding(3) var<storage, read> offsets: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> vals_out: array<u32>;

const TILE: u32 = 1024u;
const SENTINEL: u32 = 0xffffffffu;
const PER: u32 = 16u;

var<workgroup> counts: array<atomic<u32>, 16>;
var<workgroup> s_keys: array<u32, 1024>;
var<workgroup> s_vals: array<u32, 1024>;
var<workgroup> s_start: array<u32, 16>;

fn digit(k: u32) -> u32 {
    return (k >> params.shift) & 15u;
}

@compute @workgroup_size(64)
fn histogram(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let tile = linear_group(wid, nwg);
    if tile >= params.ntiles {
        return;
    }
    if lid < 16u {
        atomicStore(&counts[lid], 0u);
    }
    workgroupBarrier();
    for (var j = 0u; j < PER; j += 1u) {
        let idx = tile * TILE + lid * PER + j;
        if idx < params.n {
            atomicAdd(&counts[digit(keys_in[idx])], 1u);
        }
    }
    workgroupBarrier();
    if lid < 16u {
        hist[lid * params.ntiles + tile] = atomicLoad(&counts[lid]);
    }
}

@compute @workgroup_size(64)
fn scatter(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32,
           @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32,
              @builtin(subgroup_invocation_id) lane: u32) {
    let tile = linear_group(wid, nwg);
    if tile >= params.ntiles {
        return;
    }
    let count = min(TILE, params.n - tile * TILE);
    var k: array<u32, 16>;
    var v: array<u32, 16>;
    for (var j = 0u; j < PER; j += 1u) {
        let p = lid * PER + j;
        if p < count {
            k[j] = keys_in[tile * TILE + p];
            v[j] = vals_in[tile * TILE + p];
        } else {
            // Padding sorts after every real element of the tile (largest digit, last in order).
            k[j] = SENTINEL;
            v[j] = 0u;
        }
    }
    for (var b = 0u; b < 4u; b += 1u) {
        let bit = params.shift + b;
        var zeros = 0u;
        for (var j = 0u; j < PER; j += 1u) {
            zeros += 1u - ((k[j] >> bit) & 1u);
        }
        let s = wg_exclusive_scan(zeros, lid, sg_id, sg_count, lane);
        var z = s.x;
        for (var j = 0u; j < PER; j += 1u) {
            let p = lid * PER + j;
            var dst: u32;
            if ((k[j] >> bit) & 1u) == 0u {
                dst = z;
                z += 1u;
            } else {
                dst = s.y + (p - z);
            }
            s_keys[dst] = k[j];
            s_vals[dst] = v[j];
        }
        workgroupBarrier();
        for (var j = 0u; j < PER; j += 1u) {
            k[j] = s_keys[lid * PER + j];
            v[j] = s_vals[lid * PER + j];
        }
        workgroupBarrier();
    }
    // The tile is now stably sorted by digit; find where each digit's run starts.
    for (var j = 0u; j < PER; j += 1u) {
        let p = lid * PER + j;
        let d = digit(k[j]);
        if p == 0u || digit(s_keys[p - 1u]) != d {
            s_start[d] = p;
        }
    }
    workgroupBarrier();
    for (var j = 0u; j < PER; j += 1u) {
        let p = lid * PER + j;
        if p < count {
            let d = digit(k[j]);
            let dst = offsets[d * params.ntiles + tile] + p - s_start[d];
            keys_out[dst] = k[j];
            vals_out[dst] = v[j];
        }
    }
}
