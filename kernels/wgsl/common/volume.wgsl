// Volume rendering along one ray (NeRF quadrature): optical depth x_i = sigma_i * dt_i,
// transmittance T_i = exp(-sum_{k<i} x_k), alpha_i = 1 - exp(-x_i), weight w_i = T_i alpha_i.
// Stable at the extremes: alpha uses a series for tiny x (no 1 - exp cancellation), huge x
// saturates to alpha = 1, and a zero interval contributes nothing even for infinite sigma.

fn optical_depth(sigma: f32, dt: f32) -> f32 {
    if dt <= 0.0 || sigma <= 0.0 {
        return 0.0;
    }
    return sigma * dt;
}

// 1 - exp(-x) for x >= 0 without cancellation.
fn alpha_of(x: f32) -> f32 {
    if x < 1e-3 {
        return x * (1.0 - x * (0.5 - x * (1.0 / 6.0)));
    }
    return 1.0 - exp(-x);
}

// Weight of the next sample of a ray, given the optical depth `tau` accumulated before it;
// advances `tau` past the sample.
fn next_weight(sigma: f32, dt: f32, tau: ptr<function, f32>) -> f32 {
    let x = optical_depth(sigma, dt);
    let w = exp(-*tau) * alpha_of(x);
    *tau += x;
    return w;
}
