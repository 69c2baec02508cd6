// Real spherical harmonics up to degree 4 (16 coefficients) of a unit direction, in the order
// and sign convention of Instant-NGP's encoding.

fn sh4(d: vec3<f32>) -> array<f32, 16> {
    let x = d.x;
    let y = d.y;
    let z = d.z;
    let x2 = x * x;
    let y2 = y * y;
    let z2 = z * z;
    var o: array<f32, 16>;
    o[0] = 0.28209479177387814;
    o[1] = -0.48860251190291987 * y;
    o[2] = 0.48860251190291987 * z;
    o[3] = -0.48860251190291987 * x;
    o[4] = 1.0925484305920792 * x * y;
    o[5] = -1.0925484305920792 * y * z;
    o[6] = 0.94617469575755997 * z2 - 0.31539156525251999;
    o[7] = -1.0925484305920792 * x * z;
    o[8] = 0.54627421529603959 * (x2 - y2);
    o[9] = 0.59004358992664352 * y * (-3.0 * x2 + y2);
    o[10] = 2.8906114426405538 * x * y * z;
    o[11] = 0.45704579946446572 * y * (1.0 - 5.0 * z2);
    o[12] = 0.3731763325901154 * z * (5.0 * z2 - 3.0);
    o[13] = 0.45704579946446572 * x * (1.0 - 5.0 * z2);
    o[14] = 1.4453057213202769 * z * (x2 - y2);
    o[15] = 0.59004358992664352 * x * (-x2 + 3.0 * y2);
    return o;
}

// Unit direction of `d`; a zero or non-finite vector becomes +z so encodings stay finite.
fn unit_dir(d: vec3<f32>) -> vec3<f32> {
    let a = abs(d);
    let m = max(a.x, max(a.y, a.z));
    if !(m > 0.0) || m > 3.4e38 {
        return vec3<f32>(0.0, 0.0, 1.0);
    }
    return normalize(d / m);
}
