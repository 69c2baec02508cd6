// Workgroup-wide exclusive scan of one u32 per invocation, for workgroups of up to 256
// invocations and subgroups of at least 4 lanes: lanes scan within the subgroup, subgroup totals
// meet in shared memory. Call from workgroup-uniform control flow (it has barriers).

var<workgroup> wg_scan_sg: array<u32, 64>;
var<workgroup> wg_scan_total: u32;

// Returns (exclusive prefix of `v` over the workgroup, workgroup total).
fn wg_exclusive_scan(v: u32, lid: u32, sg_id: u32, sg_count: u32, lane: u32) -> vec2<u32> {
    let excl = subgroupExclusiveAdd(v);
    let sg_total = subgroupAdd(v);
    if lane == 0u {
        wg_scan_sg[sg_id] = sg_total;
    }
    workgroupBarrier();
    if lid == 0u {
        var run = 0u;
        for (var k = 0u; k < sg_count; k += 1u) {
            let t = wg_scan_sg[k];
            wg_scan_sg[k] = run;
            run += t;
        }
        wg_scan_total = run;
    }
    workgroupBarrier();
    let r = vec2<u32>(wg_scan_sg[sg_id] + excl, wg_scan_total);
    // Keep the next call from overwriting the slots before everyone has read them.
    workgroupBarrier();
    return r;
}
