// The ray of a (camera, pixel) pair for the fused kernels (common/step.wgsl,
// common/march_body.wgsl). Textual include: the including file declares the binding
// `cameras: array<GpuCamera>` and includes common/{camera,sh}.wgsl before this.

struct PixelRay {
    // False for an out-of-range camera or pixel index (the rest is then unset).
    valid: bool,
    // The ray marched: in NDC (near plane ndc_near) when `ndc`, else in world space.
    ray: array<vec3<f32>, 2>,
    // SH4 of the world direction.
    sh: array<f32, 16>,
}

fn pixel_ray(pc: vec2<u32>, n_cameras: u32, ndc: bool, ndc_near: f32) -> PixelRay {
    var r: PixelRay;
    r.valid = pc.x < n_cameras;
    var cam: GpuCamera;
    if r.valid {
        cam = cameras[pc.x];
        r.valid = pc.y < cam.size.x * cam.size.y;
    }
    if !r.valid {
        return r;
    }
    let world = camera_ray(cam, pixel_centre(cam, pc.y));
    r.ray = world;
    if ndc {
        r.ray = ndc_ray(cam, world[0], world[1], ndc_near);
    }
    r.sh = sh4(unit_dir(world[1]));
    return r;
}
