// The per-ray photometric and depth loss of render/loss.wgsl, shared with the fused training
// step (render/train_step.wgsl). Neither is divided by the batch size here.
//
// The target colour's w is the ray's signed colour weight (render/batch.wgsl copies it from the
// training pixel; trainer::colour_weight writes it):
//   w >= 0: the configured loss, scaled by w: L2 |e|^2 / 3 (kind 0) or Huber with threshold
//           delta per channel (kind 1), e = rendered - target;
//   w < 0:  L1 |e|_1 / 3 scaled by -w (the colour loss of virtual views, ExtraNeRF's
//           w(t)-weighted L1); with a core l1_core > 0 each channel's |e| becomes e^2 / (2 core)
//           below the core and |e| - core / 2 above it (smooth L1: the L1's slope for large
//           errors, a gradient that vanishes with the error instead of a constant-size sign);
//   w = 0:  no colour loss (a pixel the view does not supervise).
// Depth: lambda * confidence * (d - d*)^2 where the confidence is positive, whatever w is.

struct LossTerms {
    loss: f32,
    // dL/d rendered colour and dL/d rendered depth.
    d_rgb: vec3<f32>,
    d_depth: f32,
}

fn photo_depth_loss(rgb: vec3<f32>, depth: f32, target_c: vec4<f32>, target_d: vec2<f32>, kind: u32,
            delta: f32, depth_lambda: f32, l1_core: f32) -> LossTerms {
    let e = rgb - target_c.xyz;
    let w = abs(target_c.w);
    var out: LossTerms;
    if target_c.w < 0.0 && l1_core > 0.0 {
        let a = abs(e);
        let core = a <= vec3<f32>(l1_core);
        let lv = select(a - 0.5 * l1_core, 0.5 * e * e / l1_core, core);
        out.loss = w * (lv.x + lv.y + lv.z) / 3.0;
        out.d_rgb = w * select(sign(e), e / l1_core, core) / 3.0;
    } else if target_c.w < 0.0 {
        out.loss = w * (abs(e.x) + abs(e.y) + abs(e.z)) / 3.0;
        out.d_rgb = w * sign(e) / 3.0;
    } else if kind == 0u {
        out.loss = w * dot(e, e) / 3.0;
        out.d_rgb = w * 2.0 * e / 3.0;
    } else {
        let a = abs(e);
        let quad = a <= vec3<f32>(delta);
        let lv = select(delta * (a - 0.5 * delta), 0.5 * e * e, quad);
        out.loss = w * (lv.x + lv.y + lv.z) / 3.0;
        out.d_rgb = w * select(delta * sign(e), e, quad) / 3.0;
    }
    out.d_depth = 0.0;
    if target_d.y > 0.0 {
        let de = depth - target_d.x;
        out.loss += depth_lambda * target_d.y * de * de;
        out.d_depth = 2.0 * depth_lambda * target_d.y * de;
    }
    return out;
}
