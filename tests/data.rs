//! Scene loaders and splits on the real fern capture, and their errors on bad input.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::path::Path;

use extranerf_nerf::data::colmap::{read_cameras_bin, read_points3d_bin};
use extranerf_nerf::data::llff::{load_llff, LlffOptions};
use extranerf_nerf::data::npy::read_npy;
use extranerf_nerf::data::split::Split;
use extranerf_nerf::data::transforms::load_transforms;
use extranerf_nerf::data::{load_image, DataError};
use extranerf_tests::{scratch_dir, shared_data};
use glam::DVec3;

fn fern() -> std::path::PathBuf {
    shared_data().join("llff").join("fern")
}

#[test]
fn fern_llff_loads_in_the_nerf_convention() {
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    assert_eq!(scene.cameras.len(), 20);
    let c = &scene.cameras[0];
    assert_eq!((c.width, c.height), (504, 378));
    assert!(
        (c.fx - 3260.5263328805895 / 8.0).abs() < 1e-9,
        "fx {}",
        c.fx
    );
    assert!(c.image.ends_with("images_8/image000.png"));
    // bd_factor 0.75: the nearest bound becomes 1/0.75.
    let near = scene
        .cameras
        .iter()
        .map(|c| c.bounds.unwrap().0)
        .fold(f64::INFINITY, f64::min);
    assert!((near - 1.0 / 0.75).abs() < 1e-9, "near {near}");
    for c in &scene.cameras {
        let r = glam::DMat3::from_mat4(c.c2w);
        assert!(
            (r.transpose() * r - glam::DMat3::IDENTITY)
                .abs()
                .to_cols_array()
                .iter()
                .all(|&v| v < 1e-6),
            "rotation not orthonormal"
        );
        assert!(
            (r.determinant() - 1.0).abs() < 1e-6,
            "not a right-handed rotation"
        );
        // Forward-facing: every camera looks along about -z after recentring.
        assert!(c.c2w.z_axis.z > 0.9, "viewing axis {:?}", c.c2w.z_axis);
    }
    // Recentred: the average pose is the identity.
    let c2ws: Vec<_> = scene.cameras.iter().map(|c| c.c2w).collect();
    let avg = extranerf_nerf::data::llff::average_pose(&c2ws);
    assert!(avg.abs_diff_eq(glam::DMat4::IDENTITY, 1e-9), "{avg:?}");
}

#[test]
fn fern_sparse_points_project_into_the_views_within_bounds() {
    let sparse = fern().join("sparse").join("0");
    let cams = read_cameras_bin(&sparse.join("cameras.bin")).unwrap();
    assert_eq!(cams.len(), 1);
    assert_eq!(
        (cams[0].model, cams[0].width, cams[0].height),
        ("SIMPLE_RADIAL", 4032, 3024)
    );
    let raw = read_npy(&fern().join("poses_bounds.npy")).unwrap();
    assert!(
        (cams[0].params[0] - raw.data[14]).abs() < 1e-6,
        "COLMAP focal {} vs LLFF {}",
        cams[0].params[0],
        raw.data[14]
    );
    let points = read_points3d_bin(&sparse.join("points3D.bin")).unwrap();
    assert_eq!(points.len(), 10091);
    assert!(points.iter().all(|p| p.track.len() >= 2 && p.error >= 0.0));
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let world = scene.transform_points(&points);
    // A correct axis conversion and scaling puts nearly every point in front of each camera,
    // inside the depth bounds, and most of them inside the image.
    for (i, cam) in scene.cameras.iter().enumerate() {
        let (near, far) = cam.bounds.unwrap();
        let mut in_bounds = 0;
        let mut in_image = 0;
        for &p in &world {
            let (x, y, d) = cam.project(p);
            if d >= near * 0.9 && d <= far * 1.1 {
                in_bounds += 1;
            }
            if d > 0.0
                && (0.0..cam.width as f64).contains(&x)
                && (0.0..cam.height as f64).contains(&y)
            {
                in_image += 1;
            }
        }
        let n = world.len() as f64;
        assert!(
            in_bounds as f64 > 0.98 * n,
            "view {i}: {in_bounds} of {n} points within the depth bounds"
        );
        assert!(
            in_image as f64 > 0.6 * n,
            "view {i}: {in_image} of {n} points inside the image"
        );
    }
}

#[test]
fn extrapolation_split_matches_raw_camera_distances() {
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let s = Split::Extrapolation.apply(&scene.cameras).unwrap();
    assert_eq!((s.train.len(), s.test.len()), (6, 8));
    assert!(s.train.iter().all(|i| !s.test.contains(i)));
    // Independent check on the raw file: translation columns, no conversion (distances to the
    // mean centre are unchanged by the rigid recentring and the uniform scale).
    let raw = read_npy(&fern().join("poses_bounds.npy")).unwrap();
    let centres: Vec<DVec3> = raw
        .data
        .chunks_exact(17)
        .map(|r| DVec3::new(r[3], r[8], r[13]))
        .collect();
    let mean = centres.iter().sum::<DVec3>() / 20.0;
    let d: Vec<f64> = centres.iter().map(|c| c.distance(mean)).collect();
    let max_train = s.train.iter().map(|&i| d[i]).fold(0.0, f64::max);
    let min_test = s.test.iter().map(|&i| d[i]).fold(f64::INFINITY, f64::min);
    let others: Vec<usize> = (0..20).filter(|i| !s.train.contains(i)).collect();
    assert!(
        others.iter().all(|&i| d[i] >= max_train),
        "a non-training view is nearer than a training view"
    );
    let non_test: Vec<usize> = (0..20).filter(|i| !s.test.contains(i)).collect();
    assert!(
        non_test.iter().all(|&i| d[i] <= min_test),
        "a non-test view is farther than a test view"
    );
}

/// The default split of a capture: every 8th view held out, the others train; splits that
/// cannot be made say why and what to pass.
#[test]
fn holdout_split_holds_out_every_eighth_view() {
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let s = Split::Holdout.apply(&scene.cameras).unwrap();
    assert_eq!(s.test, [0, 8, 16]);
    assert_eq!(s.train.len(), 17);
    assert!(s.train.iter().all(|i| i % 8 != 0));
    let one = &scene.cameras[..1];
    let e = err_text(Split::Holdout.apply(one).unwrap_err());
    assert!(
        e.contains("at least 2 views") && e.contains("--split all"),
        "{e}"
    );
    assert_eq!(Split::Holdout.apply(&scene.cameras[..2]).unwrap().test, [0]);
    let e = err_text(
        Split::Extrapolation
            .apply(&scene.cameras[..13])
            .unwrap_err(),
    );
    assert!(
        e.contains("needs at least 14 views, the scene has 13")
            && e.contains("leave --split out")
            && e.contains("--split all"),
        "{e}"
    );
    let e = err_text(Split::FewShot(40).apply(&scene.cameras).unwrap_err());
    assert!(
        e.contains("choose 1 to 17") && e.contains("leave --split out"),
        "{e}"
    );
}

#[test]
fn fewshot_split_follows_regnerf() {
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let s = Split::FewShot(3).apply(&scene.cameras).unwrap();
    assert_eq!(s.test, vec![0, 8, 16]);
    // The 17 remaining views, linspace(0, 16, 3) = 0, 8, 16 -> views 1, 10, 19.
    assert_eq!(s.train, vec![1, 10, 19]);
    let s = Split::FewShot(9).apply(&scene.cameras).unwrap();
    // linspace(0, 16, 9) = 0, 2, ..., 16 -> views 1, 3, 5, 7, 10, 12, 14, 17, 19.
    assert_eq!(s.train, vec![1, 3, 5, 7, 10, 12, 14, 17, 19]);
    assert!(Split::FewShot(0).apply(&scene.cameras).is_err());
    assert!(Split::FewShot(18).apply(&scene.cameras).is_err());
    assert!(Split::Extrapolation.apply(&scene.cameras[..13]).is_err());
    assert_eq!(Split::All.apply(&scene.cameras).unwrap().train.len(), 20);
}

#[test]
fn fern_images_decode() {
    let img = load_image(&fern().join("images_8").join("image000.png")).unwrap();
    assert_eq!(
        (img.width, img.height, img.rgb.len()),
        (504, 378, 504 * 378 * 3)
    );
    assert!(img.rgb.iter().all(|v| (0.0..=1.0).contains(v)));
    let mean = img.rgb.iter().map(|&v| v as f64).sum::<f64>() / img.rgb.len() as f64;
    assert!(mean > 0.05 && mean < 0.95, "mean {mean}");
}

fn copy_fern_subset(dir: &Path, images: usize) {
    std::fs::copy(
        fern().join("poses_bounds.npy"),
        dir.join("poses_bounds.npy"),
    )
    .unwrap();
    std::fs::create_dir_all(dir.join("images_8")).unwrap();
    for i in 0..images {
        let name = format!("image{i:03}.png");
        std::fs::copy(
            fern().join("images_8").join(&name),
            dir.join("images_8").join(&name),
        )
        .unwrap();
    }
}

fn err_text(e: DataError) -> String {
    e.to_string()
}

#[test]
fn bad_llff_input_gives_errors_naming_the_file() {
    let opts = LlffOptions::default();
    let missing = scratch_dir("llff-missing");
    let e = err_text(load_llff(&missing, &opts).unwrap_err());
    assert!(e.contains("poses_bounds.npy"), "{e}");

    let short = scratch_dir("llff-count");
    copy_fern_subset(&short, 19);
    let e = err_text(load_llff(&short, &opts).unwrap_err());
    assert!(
        e.contains("images_8") && e.contains("19 images") && e.contains("20 poses"),
        "{e}"
    );

    let nan = scratch_dir("llff-nan");
    copy_fern_subset(&nan, 20);
    let mut bytes = std::fs::read(nan.join("poses_bounds.npy")).unwrap();
    let header = 10 + u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let at = header + (3 * 17 + 5) * 8; // row 3, column 5
    bytes[at..at + 8].copy_from_slice(&f64::NAN.to_le_bytes());
    std::fs::write(nan.join("poses_bounds.npy"), &bytes).unwrap();
    let e = err_text(load_llff(&nan, &opts).unwrap_err());
    assert!(
        e.contains("poses_bounds.npy") && e.contains("row 3") && e.contains("non-finite"),
        "{e}"
    );

    // A degenerate rotation (row 5's first column zeroed; then a mirror: one column negated)
    // is refused where it is read, not later as a NaN loss.
    for (name, edit) in [("llff-rot-zero", 0.0f64), ("llff-rot-mirror", -1.0)] {
        let dir = scratch_dir(name);
        copy_fern_subset(&dir, 20);
        let mut bytes = std::fs::read(dir.join("poses_bounds.npy")).unwrap();
        for r in 0..3 {
            let at = header + (5 * 17 + 5 * r) * 8; // row 5, rotation column 0
            let v = f64::from_le_bytes(bytes[at..at + 8].try_into().unwrap());
            bytes[at..at + 8].copy_from_slice(&(v * edit).to_le_bytes());
        }
        std::fs::write(dir.join("poses_bounds.npy"), &bytes).unwrap();
        let e = err_text(load_llff(&dir, &opts).unwrap_err());
        assert!(
            e.contains("poses_bounds.npy") && e.contains("row 5") && e.contains("rotation"),
            "{name}: {e}"
        );
        let _ = std::fs::remove_dir_all(dir);
    }

    let wrong_shape = scratch_dir("llff-shape");
    copy_fern_subset(&wrong_shape, 20);
    let mut bytes = std::fs::read(wrong_shape.join("poses_bounds.npy")).unwrap();
    let h = String::from_utf8_lossy(&bytes[10..header]).replace("(20, 17)", "(17, 20)");
    bytes[10..header].copy_from_slice(h.as_bytes());
    std::fs::write(wrong_shape.join("poses_bounds.npy"), &bytes).unwrap();
    let e = err_text(load_llff(&wrong_shape, &opts).unwrap_err());
    assert!(
        e.contains("poses_bounds.npy") && e.contains("(N, 17)"),
        "{e}"
    );

    let corrupt = scratch_dir("llff-image");
    copy_fern_subset(&corrupt, 20);
    std::fs::write(corrupt.join("images_8").join("image007.png"), b"not a png").unwrap();
    let e = err_text(load_llff(&corrupt, &opts).unwrap_err());
    assert!(e.contains("image007.png"), "{e}");

    for d in [missing, short, nan, wrong_shape, corrupt] {
        let _ = std::fs::remove_dir_all(d);
    }
}

#[test]
fn bad_colmap_input_gives_errors_naming_the_file() {
    let dir = scratch_dir("colmap");
    let src = std::fs::read(fern().join("sparse/0/points3D.bin")).unwrap();
    let truncated = dir.join("points3D.bin");
    std::fs::write(&truncated, &src[..src.len() - 5]).unwrap();
    let e = err_text(read_points3d_bin(&truncated).unwrap_err());
    assert!(e.contains("points3D.bin") && e.contains("truncated"), "{e}");
    let huge = dir.join("huge.bin");
    std::fs::write(&huge, u64::MAX.to_le_bytes()).unwrap();
    let e = err_text(read_points3d_bin(&huge).unwrap_err());
    assert!(e.contains("huge.bin") && e.contains("point count"), "{e}");
    let mut cams = std::fs::read(fern().join("sparse/0/cameras.bin")).unwrap();
    cams[12] = 42; // model id
    let bad_model = dir.join("cameras.bin");
    std::fs::write(&bad_model, &cams).unwrap();
    let e = err_text(read_cameras_bin(&bad_model).unwrap_err());
    assert!(
        e.contains("cameras.bin") && e.contains("unknown model id 42"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn transforms_json_loads_and_rejects_bad_input() {
    let dir = scratch_dir("transforms");
    let json = r#"{
        "camera_angle_x": 0.6911112070083618,
        "w": 800, "h": 600,
        "frames": [
            {"file_path": "./train/r_0", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]},
            {"file_path": "img.png", "fl_x": 500, "cx": 410,
             "transform_matrix": [[0,0,1,4],[1,0,0,0],[0,1,0,0],[0,0,0,1]]}
        ]
    }"#;
    let path = dir.join("transforms.json");
    std::fs::write(&path, json).unwrap();
    let scene = load_transforms(&path).unwrap();
    assert_eq!(scene.cameras.len(), 2);
    let c = &scene.cameras[0];
    assert!((c.fx - 400.0 / (0.5f64 * 0.6911112070083618).tan()).abs() < 1e-9);
    assert!(c.image.ends_with("train/r_0.png"));
    assert_eq!(c.centre(), DVec3::new(0.0, 0.0, 4.0));
    assert_eq!(
        (
            scene.cameras[1].fx,
            scene.cameras[1].cx,
            scene.cameras[1].cy
        ),
        (500.0, 410.0, 300.0)
    );
    // A point at the origin is 4 units in front of camera 0, at the image centre.
    let (x, y, d) = c.project(DVec3::ZERO);
    assert_eq!((x, y, d), (400.0, 300.0, 4.0));

    let cases = [
        ("{", "invalid JSON"),
        (r#"{"frames": []}"#, "empty"),
        (
            r#"{"w": 8, "h": 8, "fl_x": 5, "frames": [{"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#,
            "file_path",
        ),
        (
            r#"{"w": 8, "h": 8, "fl_x": 5, "frames": [{"file_path": "a.png", "transform_matrix": [[1,0,0],[0,1,0],[0,0,1]]}]}"#,
            "4 rows of 4",
        ),
        (
            r#"{"w": 8, "h": 8, "frames": [{"file_path": "a.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#,
            "no focal length",
        ),
        (
            r#"{"w": 8, "h": 8, "fl_x": 5, "k1": 0.1, "frames": [{"file_path": "a.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#,
            "distortion",
        ),
        (
            r#"{"w": 8, "h": 8, "fl_x": 5, "frames": [{"file_path": "a.png", "transform_matrix": [[0,0,0,0],[0,0,0,0],[0,0,0,0]]}]}"#,
            "singular",
        ),
    ];
    for (text, want) in cases {
        std::fs::write(&path, text).unwrap();
        let e = err_text(load_transforms(&path).unwrap_err());
        assert!(
            e.contains("transforms.json") && e.contains(want),
            "{want}: {e}"
        );
    }
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn fern_sparse_depth_targets() {
    use extranerf_nerf::data::depth::sparse_depth_all;
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let points = read_points3d_bin(&fern().join("sparse/0/points3D.bin")).unwrap();
    let all = sparse_depth_all(&scene, &points);
    assert_eq!(all.len(), 20);
    for (v, samples) in all.iter().enumerate() {
        let cam = &scene.cameras[v];
        let (near, far) = cam.bounds.unwrap();
        assert!(
            samples.len() > 2000,
            "view {v}: only {} depth samples",
            samples.len()
        );
        let mut seen = std::collections::HashSet::new();
        for s in samples {
            assert!(s.x < cam.width && s.y < cam.height);
            assert!(
                seen.insert((s.x, s.y)),
                "view {v}: two samples in pixel ({}, {})",
                s.x,
                s.y
            );
            assert!(
                s.depth >= 0.5 * near
                    && s.depth <= 2.0 * far
                    && s.confidence > 0.0
                    && s.confidence <= 1.0
            );
        }
        // Most points sit well inside the capture's bounds, as the loader test shows.
        let inside = samples
            .iter()
            .filter(|s| s.depth >= near * 0.9 && s.depth <= far * 1.1)
            .count();
        assert!(inside as f64 > 0.98 * samples.len() as f64, "view {v}");
    }
}

fn write_npy_f32(path: &Path, shape: &str, data: &[f32]) {
    let mut h = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + h.len() + 1) % 64 != 0 {
        h.push(' ');
    }
    h.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend((h.len() as u16).to_le_bytes());
    b.extend(h.as_bytes());
    b.extend(data.iter().flat_map(|v| v.to_le_bytes()));
    std::fs::write(path, b).unwrap();
}

#[test]
fn depth_maps_from_npy() {
    use extranerf_nerf::data::depth::read_depth_npy;
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let cam = &scene.cameras[0];
    let dir = scratch_dir("depth-npy");
    let n = (cam.width * cam.height) as usize;
    let mut data: Vec<f32> = (0..n).map(|i| 1.0 + (i % 97) as f32 * 0.01).collect();
    data[5] = f32::NAN;
    data[6] = -1.0;
    data[7] = f32::INFINITY;
    let ok = dir.join("depth.npy");
    write_npy_f32(&ok, "(378, 504)", &data);
    let d = read_depth_npy(&ok, cam).unwrap();
    assert_eq!(d.len(), n);
    assert_eq!((d[4], d[5], d[6], d[7]), (data[4], 0.0, 0.0, 0.0));
    let wrong = dir.join("small.npy");
    write_npy_f32(&wrong, "(10, 504)", &data[..5040]);
    let e = read_depth_npy(&wrong, cam).unwrap_err().to_string();
    assert!(e.contains("small.npy") && e.contains("504x10"), "{e}");
    let bad = dir.join("rgb.npy");
    write_npy_f32(&bad, "(378, 504, 3)", &vec![0.0; 3 * n]);
    let e = read_depth_npy(&bad, cam).unwrap_err().to_string();
    assert!(e.contains("rgb.npy") && e.contains("(H, W)"), "{e}");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn depth_maps_from_exr() {
    use exr::prelude::*;
    use extranerf_nerf::data::depth::read_depth_exr;
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let cam = &scene.cameras[0];
    let dir = scratch_dir("depth-exr");
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut z: Vec<f32> = (0..w * h).map(|i| 2.0 + (i % 101) as f32 * 0.01).collect();
    z[3] = f32::NAN;
    z[4] = -2.0;
    let write = |path: &Path, name: &str, data: FlatSamples, size: (usize, usize)| {
        let mut list = SmallVec::new();
        list.push(AnyChannel::new(name, data));
        let layer = Layer::new(
            size,
            LayerAttributes::named("depth"),
            Encoding::FAST_LOSSLESS,
            AnyChannels::sort(list),
        );
        Image::from_layer(layer).write().to_file(path).unwrap();
    };
    let f32_path = dir.join("z.exr");
    write(&f32_path, "Z", FlatSamples::F32(z.clone()), (w, h));
    let d = read_depth_exr(&f32_path, cam).unwrap();
    assert_eq!(
        (d.len(), d[0], d[3], d[4], d[5]),
        (w * h, z[0], 0.0, 0.0, z[5])
    );
    let f16_path = dir.join("half.exr");
    write(
        &f16_path,
        "depth",
        FlatSamples::F16(z.iter().map(|&v| f16::from_f32(v)).collect()),
        (w, h),
    );
    let d = read_depth_exr(&f16_path, cam).unwrap();
    assert!((d[7] - z[7]).abs() < 2e-3, "{} vs {}", d[7], z[7]);
    let small = dir.join("small.exr");
    write(&small, "Z", FlatSamples::F32(vec![1.0; 100]), (10, 10));
    let e = read_depth_exr(&small, cam).unwrap_err().to_string();
    assert!(e.contains("small.exr") && e.contains("10x10"), "{e}");
    let garbage = dir.join("garbage.exr");
    std::fs::write(&garbage, b"not an exr").unwrap();
    let e = read_depth_exr(&garbage, cam).unwrap_err().to_string();
    assert!(e.contains("garbage.exr") && e.contains("OpenEXR"), "{e}");
    let e = read_depth_exr(&dir.join("missing.exr"), cam)
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing.exr"), "{e}");
    let _ = std::fs::remove_dir_all(dir);
}

/// Virtual cameras beyond fern's 6-view extrapolation rig: each trajectory puts its cameras
/// where its definition says, the file round-trips through the transforms.json loader, and bad
/// requests are clear errors.
#[test]
fn virtual_cameras_extend_the_rig_and_round_trip() {
    use extranerf_nerf::cameras::{virtual_cameras, write_transforms, Trajectory};
    use extranerf_nerf::data::llff::average_pose;
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let s = Split::Extrapolation.apply(&scene.cameras).unwrap();
    let rig: Vec<_> = s.train.iter().map(|&i| scene.cameras[i].clone()).collect();
    let avg = average_pose(&rig.iter().map(|c| c.c2w).collect::<Vec<_>>());
    let (x, y, z) = (
        avg.x_axis.truncate(),
        avg.y_axis.truncate(),
        avg.z_axis.truncate(),
    );
    let centre = avg.w_axis.truncate();
    let ext = |a: DVec3| {
        rig.iter()
            .map(|c| (c.centre() - centre).dot(a).abs())
            .fold(0.0, f64::max)
    };
    let (rx, ry) = (ext(x), ext(y));
    assert!(rx > 0.0 && ry > 0.0);
    // Outward at twice the rig: on the ellipse of radii 2 rx, 2 ry in the rig's plane, with the
    // average orientation, so outside every training centre's offset box.
    let out = virtual_cameras(&rig, Trajectory::Outward, 8, 2.0).unwrap();
    assert_eq!(out.len(), 8);
    for c in &out {
        let d = c.centre() - centre;
        assert!(d.dot(z).abs() < 1e-9);
        let e = (d.dot(x) / (2.0 * rx)).powi(2) + (d.dot(y) / (2.0 * ry)).powi(2);
        assert!((e - 1.0).abs() < 1e-9, "ellipse {e}");
        assert!(d.dot(x).abs() > rx + 1e-9 || d.dot(y).abs() > ry + 1e-9);
        assert!((c.c2w.z_axis.truncate() - z).length() < 1e-12);
        assert_eq!((c.width, c.fx), (rig[0].width, rig[0].fx));
    }
    // Spiral: every camera looks at the one focus point on the average axis.
    let sp = virtual_cameras(&rig, Trajectory::Spiral, 12, 1.5).unwrap();
    let look = |c: &extranerf_nerf::data::Camera| -c.c2w.z_axis.truncate();
    for c in &sp {
        // Distance from the camera's viewing ray to the average axis line.
        let w = c.centre() - centre;
        let n = look(c).cross(z);
        let dist = w.dot(n).abs() / n.length().max(1e-12);
        assert!(dist < 1e-9, "viewing ray misses the axis by {dist}");
        assert!(
            (c.c2w.y_axis.truncate().dot(x)).abs() < 0.2,
            "up stays near the rig's up"
        );
    }
    // Rotate: the mean centre, turned up to twice the largest captured yaw each way.
    let yaw = |d: DVec3| d.dot(x).atan2(-d.dot(z));
    let captured = rig.iter().map(|c| yaw(look(c)).abs()).fold(0.0, f64::max);
    let rot = virtual_cameras(&rig, Trajectory::Rotate, 5, 2.0).unwrap();
    let yaws: Vec<f64> = rot.iter().map(|c| yaw(look(c))).collect();
    for (k, c) in rot.iter().enumerate() {
        assert!((c.centre() - centre).length() < 1e-12);
        let want = (k as f64 / 2.0 - 1.0) * 2.0 * captured;
        assert!(
            (yaws[k].abs() - want.abs()).abs() < 1e-9,
            "{yaws:?} vs {want}"
        );
    }
    assert!(yaws[0].abs() > captured && yaws[4].abs() > captured);
    // transforms.json round trip.
    let dir = scratch_dir("virtual-cameras");
    let path = dir.join("transforms.json");
    write_transforms(&path, &sp).unwrap();
    let back = load_transforms(&path).unwrap();
    assert_eq!(back.cameras.len(), sp.len());
    for (a, b) in sp.iter().zip(&back.cameras) {
        assert!((a.c2w - b.c2w)
            .to_cols_array()
            .iter()
            .all(|v| v.abs() < 1e-12));
        assert_eq!((a.width, a.height), (b.width, b.height));
        assert_eq!((a.fx, a.fy, a.cx, a.cy), (b.fx, b.fy, b.cx, b.cy));
    }
    // Bad requests.
    let err = |r: Result<
        Vec<extranerf_nerf::data::Camera>,
        extranerf_nerf::cameras::CameraError,
    >| { r.unwrap_err().to_string() };
    assert!(err(virtual_cameras(&rig, Trajectory::Outward, 0, 1.0)).contains("count 0"));
    assert!(err(virtual_cameras(&rig, Trajectory::Outward, 4, f64::NAN)).contains("range"));
    assert!(err(virtual_cameras(&[], Trajectory::Rotate, 4, 1.0)).contains("no training"));
    let one = vec![rig[0].clone(), rig[0].clone()];
    assert!(err(virtual_cameras(&one, Trajectory::Outward, 4, 1.0)).contains("one centre"));
    assert!(err(virtual_cameras(&one, Trajectory::Rotate, 4, 1.0)).contains("same way"));
    let mut nobounds = rig.clone();
    for c in &mut nobounds {
        c.bounds = None;
    }
    assert!(err(virtual_cameras(&nobounds, Trajectory::Spiral, 4, 1.0)).contains("bounds"));
    let _ = std::fs::remove_dir_all(dir);
}

/// The generated turntable scene in NeRF-synthetic's layout: the given split (train file's
/// views train, test file's are held out, and it is the default split of such a folder), the
/// intrinsics from `camera_angle_x`, RGBA images whose composite over any background is the
/// exact ray-traced view over it (within 8-bit rounding), and the rig centred on the object.
#[test]
fn nerf_synthetic_layout_loads_with_its_split_alpha_and_centre() {
    use extranerf_nerf::autoconfig::{model_for_scene, rig_centre, CentreFrom};
    use extranerf_nerf::data::load_image_over;
    use extranerf_nerf::data::split::SplitKind;
    use extranerf_nerf::demo::{
        turntable_view, write_turntable_scene, TURNTABLE_ANGLE_X, TURNTABLE_CENTRE,
    };
    use extranerf_nerf::run::SceneSpec;
    let dir = scratch_dir("turntable-layout");
    write_turntable_scene(&dir, 40, 30, 9, 4).unwrap();
    assert_eq!(SplitKind::default_for(&dir), SplitKind::Given);
    assert_eq!(SplitKind::default_for(&fern()), SplitKind::Holdout);
    let spec = |split| SceneSpec {
        dir: dir.clone(),
        split,
        fewshot_views: 3,
        factor: 1,
        sparse_depth: true,
        depth_dir: None,
        mvs_depth: None,
        capture_depth: false,
    };
    let loaded = spec(SplitKind::Given).load().unwrap();
    assert_eq!(loaded.scene.cameras.len(), 13);
    assert_eq!(loaded.split.train, (0..9).collect::<Vec<_>>());
    assert_eq!(loaded.split.test, (9..13).collect::<Vec<_>>());
    assert!(!loaded.scene.forward_facing);
    let c = &loaded.scene.cameras[9];
    assert!(c.image.ends_with("test/r_0.png"), "{}", c.image.display());
    assert_eq!((c.width, c.height), (40, 30));
    assert!((c.fx - 20.0 / (0.5 * TURNTABLE_ANGLE_X).tan()).abs() < 1e-9);
    // Other splits apply to all 13 cameras.
    assert_eq!(spec(SplitKind::All).load().unwrap().split.train.len(), 13);
    // The images: alpha kept, the composite over white and over a colour the exact view.
    assert!(load_image(&fern().join("images_8/image000.png"))
        .unwrap()
        .alpha
        .is_none());
    let img = load_image(&c.image).unwrap();
    let alpha = img.alpha.as_ref().expect("alpha kept");
    assert!(alpha.contains(&0.0) && alpha.contains(&1.0));
    let (rgb, a) = turntable_view(&c.c2w, 40, 30);
    for bg in [[1.0f32; 3], [0.1, 0.6, 0.3]] {
        let over = load_image_over(&c.image, bg).unwrap();
        assert!(over.alpha.is_none());
        let worst = (0..40 * 30 * 3)
            .map(|k| {
                let want = rgb[k] * a[k / 3] + bg[k % 3] * (1.0 - a[k / 3]);
                (over.rgb[k] - want).abs()
            })
            .fold(0f32, f32::max);
        // Colour and alpha are each rounded to 1/255.
        assert!(worst <= 1.0 / 255.0 + 1e-6, "over {bg:?}: off by {worst}");
    }
    // Every camera looks at the object's centre: the rig is centred there.
    let (centre, how) = rig_centre(&loaded.scene.cameras);
    assert!(matches!(how, CentreFrom::OpticalAxes { .. }), "{how:?}");
    assert!(centre.distance(TURNTABLE_CENTRE) < 1e-9, "centre {centre}");
    let m = model_for_scene(&loaded.scene);
    let mc = DVec3::new(m.center[0] as f64, m.center[1] as f64, m.center[2] as f64);
    assert!(mc.distance(TURNTABLE_CENTRE) < 1e-6, "model centre {mc}");
    // An object on a transparent background: samples only around it (the object lies within
    // 1.1 of the centre, the cameras 3.5 from it).
    assert!(loaded.scene.bounded_object);
    assert!(
        m.near < 2.4 && m.near > 0.5 && m.far > 4.6 && m.far < 8.0,
        "near {} far {}",
        m.near,
        m.far
    );
    let _ = std::fs::remove_dir_all(dir);
}

/// Split files that are missing or mixed up give clear errors naming the file: no test file
/// for `--split given`, a split asked of a scene that has no split files, an image whose size
/// is not its frame's `w` x `h`, a frame without `file_path`, an image that is not there.
#[test]
fn bad_split_files_give_errors_naming_the_file() {
    use extranerf_nerf::data::split::SplitKind;
    use extranerf_nerf::demo::write_turntable_scene;
    use extranerf_nerf::run::SceneSpec;
    let dir = scratch_dir("turntable-bad");
    write_turntable_scene(&dir, 16, 12, 3, 2).unwrap();
    let spec = |dir: &Path, split| SceneSpec {
        dir: dir.to_path_buf(),
        split,
        fewshot_views: 3,
        // The LLFF case reads images_8; the turntable scene has no factor.
        factor: 8,
        sparse_depth: false,
        depth_dir: None,
        mvs_depth: None,
        capture_depth: false,
    };
    let load = |dir: &Path, split| spec(dir, split).load().map(|_| ()).unwrap_err().to_string();
    let test_file = dir.join("transforms_test.json");
    let original = std::fs::read_to_string(&test_file).unwrap();
    std::fs::remove_file(&test_file).unwrap();
    let e = load(&dir, SplitKind::Given);
    assert!(
        e.contains("transforms_test.json") && e.contains("no such file"),
        "{e}"
    );
    // Without it the other splits still load the training file.
    assert_eq!(
        spec(&dir, SplitKind::All).load().unwrap().split.train.len(),
        3
    );
    // A frame saying 32x24 for a 16x12 image.
    let mut json: serde_json::Value = serde_json::from_str(&original).unwrap();
    json["frames"][1]["w"] = 32.into();
    json["frames"][1]["h"] = 24.into();
    std::fs::write(&test_file, json.to_string()).unwrap();
    let e = load(&dir, SplitKind::Given);
    assert!(
        e.contains("transforms_test.json") && e.contains("frame 1") && e.contains("16x12"),
        "{e}"
    );
    // No file_path.
    let mut json: serde_json::Value = serde_json::from_str(&original).unwrap();
    json["frames"][0]
        .as_object_mut()
        .unwrap()
        .remove("file_path");
    std::fs::write(&test_file, json.to_string()).unwrap();
    let e = load(&dir, SplitKind::Given);
    assert!(
        e.contains("transforms_test.json") && e.contains("frame 0") && e.contains("file_path"),
        "{e}"
    );
    // An image that is not there.
    let mut json: serde_json::Value = serde_json::from_str(&original).unwrap();
    json["frames"][1]["file_path"] = "./test/missing".into();
    std::fs::write(&test_file, json.to_string()).unwrap();
    let e = load(&dir, SplitKind::Given);
    assert!(e.contains("missing.png"), "{e}");
    // --split given on an LLFF scene.
    let e = load(&fern(), SplitKind::Given);
    assert!(e.contains("fern") && e.contains("split files"), "{e}");
    let _ = std::fs::remove_dir_all(dir);
}

/// On fern and synth2 (forward-facing, NDC) auto-config's grid box holds every sample of every
/// pixel of every camera, and of the virtual views `extrapolate` makes by default (an 8-view
/// spiral 1.5 times beyond the rig), and the samples span the scene's depth bounds. NDC's
/// unit cube, the box before, misses part of most views; t 0 to 1, the range before, put
/// about 13 of 32 fern samples outside the bounds.
#[test]
fn the_grid_box_holds_every_camera_and_samples_span_the_bounds() {
    use extranerf_nerf::autoconfig::{auto_model_covering, scene_depth_range, GridBox, NdcFit};
    use extranerf_nerf::cameras::{virtual_cameras, Trajectory};
    use extranerf_nerf::reference::ndc_ray;
    for (name, dir) in [("fern", fern()), ("synth2", shared_data().join("synth2"))] {
        let scene = load_llff(
            &dir,
            &LlffOptions {
                factor: 8,
                ..LlffOptions::default()
            },
        )
        .unwrap();
        assert!(scene.forward_facing, "{name}");
        let train: Vec<usize> = (0..scene.cameras.len()).step_by(2).collect();
        let train_cams: Vec<_> = train.iter().map(|&i| scene.cameras[i].clone()).collect();
        let virt = virtual_cameras(&train_cams, Trajectory::Spiral, 8, 1.5).unwrap();
        let m = auto_model_covering(&scene, &train, &virt, NdcFit::default()).model;
        m.validate().unwrap();
        let centre = DVec3::from(m.center.map(f64::from));
        let half = m.radius as f64;
        let (t0, t1) = (m.near as f64, m.far as f64);
        assert!(scene_depth_range(&scene.cameras).is_some(), "{name}");
        // NDC t of world z (near plane z = -1): nearer than the plane, 0 (the ray starts
        // there); at or behind z = 0, 1 (infinity).
        let t_near = |z: f64| if z <= -1.0 { 1.0 + 1.0 / z } else { 0.0 };
        let t_far = |z: f64| {
            if z < 0.0 {
                (1.0 + 1.0 / z).max(0.0)
            } else {
                1.0
            }
        };
        // `--grid-box training`: the same range, a cube no larger holding every sample of the
        // cameras trained on and of the virtual views (checked in the same pass).
        let fit = NdcFit {
            grid_box: GridBox::Training,
            ..NdcFit::default()
        };
        let mt = auto_model_covering(&scene, &train, &virt, fit).model;
        mt.validate().unwrap();
        assert_eq!((mt.near, mt.far), (m.near, m.far), "{name}");
        assert!(
            mt.radius <= m.radius,
            "{name}: {} > {}",
            mt.radius,
            m.radius
        );
        let centre_t = DVec3::from(mt.center.map(f64::from));
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut outside_unit, mut pixels) = (0u64, 0u64);
        for (k, c) in scene.cameras.iter().chain(&virt).enumerate() {
            let real = k < scene.cameras.len();
            let in_training_box = !real || train.contains(&k);
            for py in 0..=c.height {
                for px in 0..=c.width {
                    let (o, d) = c.ray(px as f64, py as f64);
                    let (no, nd) = ndc_ray(c, o.to_array(), d.to_array(), 1.0);
                    let mut out_unit = false;
                    for s in [t0, t1] {
                        let p = DVec3::from(no) + DVec3::from(nd) * s;
                        let off = (p - centre).abs().max_element();
                        assert!(off <= half, "{name} camera {k} ({px}, {py}) t {s}: {p}");
                        out_unit |= p.abs().max_element() > 1.0;
                        if in_training_box {
                            let off_t = (p - centre_t).abs().max_element();
                            assert!(
                                off_t <= mt.radius as f64,
                                "{name} training/virtual camera {k} ({px}, {py}) t {s}: {p}"
                            );
                        }
                    }
                    if real {
                        let (near, far) = c.bounds.unwrap();
                        lo = lo.min(t_near((o + d * 0.9 * near).z));
                        hi = hi.max(t_far((o + d * far).z));
                        outside_unit += u64::from(out_unit);
                        pixels += 1;
                    }
                }
            }
        }
        // The sampled range is that of the cameras' bounds (0.9 x near to far, each camera's
        // own) in the NDC frame's depth, no wider.
        assert!(
            (t0 - lo).abs() < 1e-5 && (t1 - hi).abs() < 1e-5,
            "{name}: {t0}..{t1} vs {lo}..{hi}"
        );
        assert!(t1 < 0.95, "{name}: {t0}..{t1}");
        if name == "fern" {
            assert!(t0 > 0.05, "{name}: {t0}..{t1}");
        }
        // NDC's unit cube missed samples of some pixels; the box is larger, with as many cells
        // per unit as the unit cube had per image pixel.
        assert!(
            outside_unit > pixels / 50,
            "{name}: {outside_unit} of {pixels}"
        );
        assert!(half > 1.0, "{name}: {half}");
        let widest = scene
            .cameras
            .iter()
            .map(|c| c.width.max(c.height))
            .max()
            .unwrap();
        let cells_per_unit = m.max_res as f64 / (2.0 * half);
        let want = widest.next_power_of_two() as f64 / 2.0;
        assert!(
            (cells_per_unit / want - 1.0).abs() < 0.01,
            "{name}: {cells_per_unit} vs {want}"
        );
        if name == "fern" {
            // Before: strata over t 0..1, of which the bounds hold about 77%.
            let inside = t1 - t0;
            assert!((0.7..0.85).contains(&inside), "{inside}");
            eprintln!(
                "{name}: t {t0:.3}..{t1:.3} (32 strata over 0..1 put {:.1} outside), box half side {half:.3}, {:.1}% of pixels reach outside the unit cube",
                32.0 * (1.0 - inside),
                100.0 * outside_unit as f64 / pixels as f64
            );
        }
    }
}

/// The named camera paths against their definitions (extranerf_nerf::camera_path), on fern's
/// rig: the spiral is LLFF's widened path; the ellipse's centres lie on its ellipse and each
/// looks at the rig's focus; the sweep crosses the rig past both ends looking along the average
/// axis; a line starts and ends at its two views; `--width` keeps the field of view.
#[test]
fn named_camera_paths_follow_their_definitions() {
    use extranerf_nerf::camera_path::{named_path, nearest_to_axes, resized, NamedPath};
    use extranerf_nerf::cameras::{virtual_cameras, Trajectory};
    use glam::DVec3;
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let all = &scene.cameras;
    let rig: Vec<_> = all.iter().take(17).cloned().collect();
    let c2ws: Vec<_> = rig.iter().map(|c| c.c2w).collect();
    let avg = extranerf_nerf::data::llff::average_pose(&c2ws);
    let (x, y, z) = (
        avg.x_axis.truncate(),
        avg.y_axis.truncate(),
        avg.z_axis.truncate(),
    );
    let centre = avg.w_axis.truncate();
    let extent = |axis: DVec3| {
        rig.iter()
            .map(|c| (c.centre() - centre).dot(axis).abs())
            .fold(0.0, f64::max)
    };
    let (rx, ry) = (extent(x), extent(y));
    let looks_at = |c: &extranerf_nerf::data::Camera, p: DVec3| {
        let d = (p - c.centre()).normalize();
        d.dot(-c.c2w.z_axis.truncate())
    };
    // Spiral: LLFF's path, as the virtual cameras' spiral.
    let spiral = named_path(&rig, all, NamedPath::Spiral, 12, 1.5).unwrap();
    let want = virtual_cameras(&rig, Trajectory::Spiral, 12, 1.5).unwrap();
    for (a, b) in spiral.iter().zip(&want) {
        assert!(a.c2w.abs_diff_eq(b.c2w, 1e-12));
    }
    assert_eq!(spiral[3].image.to_str(), Some("frame_0003.png"));
    // Ellipse: on range * (rx cos t, ry sin t) in the rig's plane, looking at the focus point.
    let (near, far) = extranerf_nerf::data::depth_bounds(&rig).unwrap();
    let focus = centre - z / (0.25 / near + 0.75 / far);
    let ellipse = named_path(&rig, all, NamedPath::Ellipse, 8, 2.0).unwrap();
    assert_eq!(ellipse.len(), 8);
    for (k, c) in ellipse.iter().enumerate() {
        let t = std::f64::consts::TAU * k as f64 / 8.0;
        let p = centre + 2.0 * (rx * t.cos() * x + ry * t.sin() * y);
        assert!(c.centre().abs_diff_eq(p, 1e-12), "frame {k}");
        assert!((looks_at(c, focus) - 1.0).abs() < 1e-12, "frame {k}");
        assert!(
            c.c2w.y_axis.truncate().dot(y) > 0.9,
            "frame {k} keeps the rig's up"
        );
    }
    // Sweep: from -range rx to +range rx along x, looking along the average axis.
    let sweep = named_path(&rig, all, NamedPath::Sweep, 5, 1.5).unwrap();
    assert!(sweep[0].centre().abs_diff_eq(centre - 1.5 * rx * x, 1e-12));
    assert!(sweep[2].centre().abs_diff_eq(centre, 1e-12));
    assert!(sweep[4].centre().abs_diff_eq(centre + 1.5 * rx * x, 1e-12));
    for c in &sweep {
        assert!(c.c2w.z_axis.truncate().abs_diff_eq(z, 1e-12));
    }
    // A line from view 0 to view 19: both ends exact, the middle halfway.
    let line = named_path(&rig, all, NamedPath::Line(0, 19), 5, 1.0).unwrap();
    assert!(line[0].c2w.abs_diff_eq(all[0].c2w, 1e-9));
    assert!(line[4].c2w.abs_diff_eq(all[19].c2w, 1e-9));
    assert!(line[2]
        .centre()
        .abs_diff_eq(0.5 * (all[0].centre() + all[19].centre()), 1e-12));
    let e = named_path(&rig, all, NamedPath::Line(0, 20), 5, 1.0).unwrap_err();
    assert!(e.to_string().contains("views 0 to 19"), "{e}");
    for (frames, range) in [(0, 1.0), (5, 0.0), (5, f64::NAN)] {
        assert!(named_path(&rig, all, NamedPath::Sweep, frames, range).is_err());
    }
    // Every named path takes up to the same number of frames, and says so past it in frames.
    let most = extranerf_nerf::cameras::MAX_PATH_CAMERAS;
    for path in [NamedPath::Spiral, NamedPath::Ellipse, NamedPath::Sweep] {
        assert_eq!(named_path(&rig, all, path, most, 1.0).unwrap().len(), most);
        let e = named_path(&rig, all, path, most + 1, 1.0).unwrap_err();
        assert!(
            e.to_string().contains(&format!("{} frames", most + 1)),
            "{e}"
        );
    }
    // A width keeps the field of view and the aspect.
    let r = resized(&all[0], 126);
    assert_eq!((r.width, r.height), (126, 95));
    assert!((r.fx / r.width as f64 - all[0].fx / all[0].width as f64).abs() < 1e-12);
    // The point nearest to the axes of cameras looking at one point is that point.
    let target = DVec3::new(0.3, -0.2, -4.0);
    let ring = named_path(&rig, all, NamedPath::Ellipse, 6, 1.0).unwrap();
    let aimed: Vec<_> = ring
        .iter()
        .map(|c| {
            let mut c = c.clone();
            let zc = (c.centre() - target).normalize();
            let xc = DVec3::Y.cross(zc).normalize();
            c.c2w = glam::DMat4::from_cols(
                xc.extend(0.0),
                zc.cross(xc).extend(0.0),
                zc.extend(0.0),
                c.centre().extend(1.0),
            );
            c
        })
        .collect();
    assert!(nearest_to_axes(&aimed).unwrap().abs_diff_eq(target, 1e-9));
    assert!(
        nearest_to_axes(&sweep).is_none(),
        "parallel axes meet nowhere"
    );
}

/// nerfstudio's camera_path.json: written and read back (poses, size, field of view, fps),
/// read as a path file beside the transforms.json `extranerf cameras` writes, and malformed
/// paths refused naming the entry and field.
#[test]
fn camera_path_json_round_trips_and_refuses_malformed_paths() {
    use extranerf_nerf::camera_path::{
        named_path, read_camera_path, read_path_file, write_camera_path, NamedPath,
    };
    let scene = load_llff(&fern(), &LlffOptions::default()).unwrap();
    let dir = scratch_dir("camera-path");
    let cams = named_path(&scene.cameras, &scene.cameras, NamedPath::Spiral, 7, 1.2).unwrap();
    let path = dir.join("camera_path.json");
    write_camera_path(&path, &cams, 24.0).unwrap();
    let (back, fps) = read_camera_path(&path).unwrap();
    assert_eq!(fps, Some(24.0));
    assert_eq!(back.len(), 7);
    for (a, b) in back.iter().zip(&cams) {
        assert!(a.c2w.abs_diff_eq(b.c2w, 1e-12));
        assert_eq!((a.width, a.height), (b.width, b.height));
        assert!((a.fy - b.fy).abs() < 1e-9 && (a.fx - b.fy).abs() < 1e-9);
        assert_eq!((a.cx, a.cy), (b.width as f64 / 2.0, b.height as f64 / 2.0));
    }
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    assert_eq!(doc["camera_type"], "perspective");
    assert_eq!(doc["render_width"], 504);
    assert!((doc["seconds"].as_f64().unwrap() - 7.0 / 24.0).abs() < 1e-12);
    // The transforms.json of `extranerf cameras` is a path file too.
    let t = dir.join("transforms.json");
    extranerf_nerf::cameras::write_transforms(&t, &cams).unwrap();
    let (from_t, none) = read_path_file(&t).unwrap();
    assert_eq!(none, None);
    assert!(from_t[6].c2w.abs_diff_eq(cams[6].c2w, 1e-12));
    assert_eq!(read_path_file(&path).unwrap().0.len(), 7);
    // Malformed.
    let bad = |edit: &dyn Fn(&mut serde_json::Value)| {
        let mut d = doc.clone();
        edit(&mut d);
        let p = dir.join("bad.json");
        std::fs::write(&p, serde_json::to_vec(&d).unwrap()).unwrap();
        read_path_file(&p).unwrap_err().to_string()
    };
    let e = bad(&|d| {
        d["camera_path"][2]["camera_to_world"]
            .as_array_mut()
            .unwrap()
            .pop();
    });
    assert!(
        e.contains("bad.json") && e.contains("camera_path[2].camera_to_world"),
        "{e}"
    );
    let e = bad(&|d| d["camera_path"][1]["fov"] = 0.0.into());
    assert!(e.contains("camera_path[1].fov"), "{e}");
    let e = bad(&|d| {
        d.as_object_mut().unwrap().remove("render_height");
    });
    assert!(e.contains("render_height"), "{e}");
    let e = bad(&|d| d["camera_path"] = serde_json::json!([]));
    assert!(e.contains("empty"), "{e}");
    let e = bad(&|d| *d = serde_json::json!({"poses": []}));
    assert!(e.contains("not a camera path"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
