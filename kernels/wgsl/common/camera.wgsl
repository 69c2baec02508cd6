// Pinhole cameras in the OpenGL / NeRF convention (x right, y up, looking along -z) and NeRF's
// normalised device coordinates for forward-facing scenes.

struct GpuCamera {
    // Rows of the 3x4 camera-to-world matrix.
    c2w0: vec4<f32>,
    c2w1: vec4<f32>,
    c2w2: vec4<f32>,
    // fx, fy, cx, cy in pixels.
    intr: vec4<f32>,
    // width, height, unused, unused.
    size: vec4<u32>,
}

// Centre of pixel index `pixel` (= y * width + x) in pixel coordinates.
fn pixel_centre(cam: GpuCamera, pixel: u32) -> vec2<f32> {
    let w = cam.size.x;
    return vec2<f32>(f32(pixel % w) + 0.5, f32(pixel / w) + 0.5);
}

// Ray through pixel coordinates `px` (pixel centres at +0.5): origin, and direction scaled so
// that one unit of t is one unit of depth along the viewing axis.
fn camera_ray(cam: GpuCamera, px: vec2<f32>) -> array<vec3<f32>, 2> {
    let dc = vec3<f32>((px.x - cam.intr.z) / cam.intr.x, -(px.y - cam.intr.w) / cam.intr.y, -1.0);
    let d = vec3<f32>(dot(cam.c2w0.xyz, dc), dot(cam.c2w1.xyz, dc), dot(cam.c2w2.xyz, dc));
    let o = vec3<f32>(cam.c2w0.w, cam.c2w1.w, cam.c2w2.w);
    return array<vec3<f32>, 2>(o, d);
}

// The x and y scales of camera cam's NDC frame: NDC x = ax * x / z, y = ay * y / z.
fn ndc_scale(cam: GpuCamera) -> vec2<f32> {
    return vec2<f32>(-2.0 * cam.intr.x / f32(cam.size.x), -2.0 * cam.intr.y / f32(cam.size.y));
}

// NeRF's ndc_rays: moves the origin to the plane z = -near and maps the frustum to [-1, 1]^3
// (the far end at infinity becomes z = 1). A direction parallel to the near plane is nudged to
// a tiny -z component so the result stays finite.
fn ndc_ray(cam: GpuCamera, o_in: vec3<f32>, d_in: vec3<f32>, near: f32) -> array<vec3<f32>, 2> {
    var d = d_in;
    if abs(d.z) < 1e-12 {
        d.z = -1e-12;
    }
    let t = -(near + o_in.z) / d.z;
    let o = o_in + t * d;
    let a = ndc_scale(cam);
    let o_ndc = vec3<f32>(a.x * o.x / o.z, a.y * o.y / o.z, 1.0 + 2.0 * near / o.z);
    let d_ndc = vec3<f32>(a.x * (d.x / d.z - o.x / o.z), a.y * (d.y / d.z - o.y / o.z), -2.0 * near / o.z);
    return array<vec3<f32>, 2>(o_ndc, d_ndc);
}

fn camera_centre(c: GpuCamera) -> vec3<f32> {
    return vec3<f32>(c.c2w0.w, c.c2w1.w, c.c2w2.w);
}

// Pixel coordinates (centres at +0.5) and depth along the viewing axis of world point p in
// camera c; all 0 when p is not in front of it (or is NaN).
fn project_point(p: vec3<f32>, c: GpuCamera) -> vec3<f32> {
    let r = p - camera_centre(c);
    // Camera coordinates: the rotation's transpose (its columns) applied to r.
    let xc = c.c2w0.x * r.x + c.c2w1.x * r.y + c.c2w2.x * r.z;
    let yc = c.c2w0.y * r.x + c.c2w1.y * r.y + c.c2w2.y * r.z;
    let zc = c.c2w0.z * r.x + c.c2w1.z * r.y + c.c2w2.z * r.z;
    if !(zc < 0.0) {
        return vec3<f32>(0.0);
    }
    return vec3<f32>(c.intr.x * xc / -zc + c.intr.z, -c.intr.y * yc / -zc + c.intr.w, -zc);
}

// True when a projection q (project_point) is in front of camera c and inside its image
// (edges included).
fn in_image(q: vec3<f32>, c: GpuCamera) -> bool {
    return q.z > 0.0 && q.x >= 0.0 && q.x <= f32(c.size.x) && q.y >= 0.0 && q.y <= f32(c.size.y);
}
