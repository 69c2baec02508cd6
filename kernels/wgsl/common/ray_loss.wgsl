// The per-ray photometric and depth loss of render/loss.wgsl, shared with the fused training
// step (render/train_step.wgsl). RGB: L2 |e|^2 / 3 (kind 0) or Huber with threshold delta per
// channel (kind 1), e = rendered - target; depth: lambda * confidence * (d - d*)^2 where the
// confidence is positive. Neither is divided by the batch size here.

struct LossTerms {
    loss: f32,
    // dL/d rendered colour and dL/d rendered depth.
    d_rgb: vec3<f32>,
    d_depth: f32,
}

fn photo_depth_loss(rgb: vec3<f32>, depth: f32, target_c: vec3<f32>, target_d: vec2<f32>, kind: u32,
            delta: f32, depth_lambda: f32) -> LossTerms {
    let e = rgb - target_c;
    var out: LossTerms;
    if kind == 0u {
        out.loss = dot(e, e) / 3.0;
        out.d_rgb = 2.0 * e / 3.0;
    } else {
        let a = abs(e);
        let quad = a <= vec3<f32>(delta);
        let lv = select(delta * (a - 0.5 * delta), 0.5 * e * e, quad);
        out.loss = (lv.x + lv.y + lv.z) / 3.0;
        out.d_rgb = select(delta * sign(e), e, quad) / 3.0;
    }
    out.d_depth = 0.0;
    if target_d.y > 0.0 {
        let de = depth - target_d.x;
        out.loss += depth_lambda * target_d.y * de * de;
        out.d_depth = 2.0 * depth_lambda * target_d.y * de;
    }
    return out;
}
