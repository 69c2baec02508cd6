// Scene contraction (mip-NeRF 360): x -> x inside the unit ball, (2 - 1/|x|) x/|x| outside, so
// all of space lands in the ball of radius 2; the L-inf variant uses the max norm (a cube).
// Then [-2, 2]^3 -> [0, 1]^3 for the hash grid. Bounded scenes skip the contraction and map
// [-1, 1]^3 -> [0, 1]^3. Norms are computed scaled by the largest component, so coordinates
// up to 1e37 neither overflow nor lose the direction.

const CONTRACT_NONE: u32 = 0u;
const CONTRACT_L2: u32 = 1u;
const CONTRACT_LINF: u32 = 2u;

fn safe_norm(x: vec3<f32>, linf: bool) -> f32 {
    let a = abs(x);
    let m = max(a.x, max(a.y, a.z));
    if linf || m == 0.0 {
        return m;
    }
    return m * length(x / m);
}

// `x` already centred and divided by the scene radius.
fn contract_unit(x_in: vec3<f32>, mode: u32) -> vec3<f32> {
    let x = clamp(x_in, vec3<f32>(-1e37), vec3<f32>(1e37));
    if mode == CONTRACT_NONE {
        return clamp(x * 0.5 + 0.5, vec3<f32>(0.0), vec3<f32>(1.0));
    }
    let n = safe_norm(x, mode == CONTRACT_LINF);
    var c = x;
    if n > 1.0 {
        c = (2.0 - 1.0 / n) * (x / n);
    }
    return clamp(c * 0.25 + 0.5, vec3<f32>(0.0), vec3<f32>(1.0));
}
