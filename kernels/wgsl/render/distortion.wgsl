// Distortion loss of mip-NeRF 360 in its O(N) form, per ray, and its gradient with respect to
// the sample weights (fed to composite_bwd's d_weight):
//   L = lambda (sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 ds_i),
// with m_i, ds_i the (normalised) midpoint and width of sample i, samples in increasing m.
//   sum_{i,j} ... = 2 sum_i w_i (m_i W_<i - WM_<i)
//   dL/dw_i = lambda (2 (m_i W_<i - WM_<i) + 2 (WM_>i - m_i W_>i) + 2/3 w_i ds_i)
//!include common/dispatch.wgsl
//!include common/volume.wgsl

struct Params {
    n_rays: u32,
    lambda: f32,
}
var<immediate> params: Params;

@group(0) @binding(0) var<storage, read> rays: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read> sigma: array<f32>;
@group(0) @binding(2) var<storage, read> t_dt: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read> s_ds: array<vec2<f32>>;
@group(0) @binding(4) var<storage, read_write> loss: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_weight: array<f32>;

@compute @workgroup_size(64)
fn distortion(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let r = linear_group(wid, nwg) * 64u + lid;
    if r >= params.n_rays {
        return;
    }
    let span = rays[r];
    // Totals first, for the suffix sums.
    var tau = 0.0;
    var w_tot = 0.0;
    var wm_tot = 0.0;
    for (var s = span.x; s < span.x + span.y; s += 1u) {
        let w = next_weight(sigma[s], t_dt[s].y, &tau);
        w_tot += w;
        wm_tot += w * s_ds[s].x;
    }
    tau = 0.0;
    var w_lt = 0.0;
    var wm_lt = 0.0;
    var l = 0.0;
    for (var s = span.x; s < span.x + span.y; s += 1u) {
        let w = next_weight(sigma[s], t_dt[s].y, &tau);
        let m = s_ds[s].x;
        let ds = s_ds[s].y;
        let w_gt = w_tot - w_lt - w;
        let wm_gt = wm_tot - wm_lt - w * m;
        let below = m * w_lt - wm_lt;
        l += 2.0 * w * below + w * w * ds / 3.0;
        d_weight[s] = params.lambda * (2.0 * below + 2.0 * (wm_gt - m * w_gt) + 2.0 / 3.0 * w * ds);
        w_lt += w;
        wm_lt += w * m;
    }
    loss[r] = params.lambda * l;
}
