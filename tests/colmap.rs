//! Captures as COLMAP and nerfstudio leave them. COLMAP sparse models read as scenes: hand-made
//! models written in both of COLMAP's formats
//! (text and binary read back equal), a capture whose 3-D points project onto the pixels its
//! images observe them at, fern converted to a COLMAP text model (its poses and bounds match
//! `poses_bounds.npy`), and malformed models (truncated, wrong counts, unknown or distorted
//! camera models): errors naming the file and the field. nerfstudio's `transforms.json`: its
//! camera model, its applied transform, the OpenGL convention, its downscaled image folders and
//! the depth files its frames name (millimetres; `depths_N/` twins).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::path::Path;

use extranerf_nerf::data::colmap::{
    read_points3d_bin, ColmapCamera, ColmapImage, Model, ModelFormat,
};
use extranerf_nerf::data::colmap_scene::{forward_facing, load_colmap};
use extranerf_nerf::data::llff::{load_llff, LlffOptions};
use extranerf_nerf::data::npy::read_npy;
use extranerf_nerf::data::split::SplitKind;
use extranerf_nerf::run::SceneSpec;
use extranerf_tests::{
    colmap_model, colmap_qvec, colmap_rig, scratch_dir, shared_data, write_colmap_capture,
};
use glam::{DMat3, DVec3};

#[test]
fn text_and_binary_models_round_trip_and_agree() {
    let dir = scratch_dir("colmap-round-trip");
    let model = colmap_model(&colmap_rig(5));
    for format in [ModelFormat::Text, ModelFormat::Binary] {
        let d = dir.join(format!("{format:?}"));
        model.write(&d, format).unwrap();
        assert_eq!(ModelFormat::of(&d), Some(format));
        assert_eq!(Model::read(&d).unwrap(), model, "{format:?}");
    }
    // COLMAP's own text layout.
    let cams = std::fs::read_to_string(dir.join("Text/cameras.txt")).unwrap();
    assert!(
        cams.contains("\n1 PINHOLE 64 48 60.0 58.0 32.5 23.75\n"),
        "{cams}"
    );
    let images = std::fs::read_to_string(dir.join("Text/images.txt")).unwrap();
    let line = images.lines().find(|l| l.starts_with("10 ")).unwrap();
    assert!(line.ends_with(" 1 view_05.png"), "{line}");
    assert!(
        images.contains("1.5 2.5 -1 "),
        "no unmatched 2-D point: {images}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_colmap_capture_projects_its_points_onto_their_pixels() {
    let dir = scratch_dir("colmap-capture");
    let model = colmap_model(&colmap_rig(5));
    for format in [ModelFormat::Text, ModelFormat::Binary] {
        let d = dir.join(format!("{format:?}"));
        write_colmap_capture(&d, &model, format);
        let scene = load_colmap(&d, 1).unwrap();
        assert!(scene.forward_facing);
        assert_eq!(scene.cameras.len(), 5);
        // Ordered by name: view_01 is the last image of the model.
        let names: Vec<String> = scene
            .cameras
            .iter()
            .map(|c| c.image.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names[0], "view_01.png");
        let world = scene.transform_points(&model.points);
        let mut worst = 0f64;
        for cam in &scene.cameras {
            let im = model
                .images
                .iter()
                .find(|im| cam.image.ends_with(&im.name))
                .unwrap();
            assert_eq!((cam.width, cam.height), (32, 24));
            for (xy, p) in &im.points2d {
                let Some(p) = p else { continue };
                let k = model.points.iter().position(|q| q.id == *p).unwrap();
                let (x, y, d) = cam.project(world[k]);
                assert!(d > 0.0);
                // The images are half the cameras' size.
                worst = worst
                    .max((x - xy[0] / 2.0).abs())
                    .max((y - xy[1] / 2.0).abs());
            }
            let (near, far) = cam.bounds.unwrap();
            assert!(near > 0.0 && far > near, "{near} {far}");
        }
        assert!(worst < 1e-9, "{format:?}: reprojection off by {worst} px");
        // LLFF's normalisation: the nearest bound is 1 / 0.75, the average pose the identity.
        let near = scene
            .cameras
            .iter()
            .map(|c| c.bounds.unwrap().0)
            .fold(f64::INFINITY, f64::min);
        assert!((near - 1.0 / 0.75).abs() < 1e-9, "near {near}");
        let c2ws: Vec<_> = scene.cameras.iter().map(|c| c.c2w).collect();
        let avg = extranerf_nerf::data::llff::average_pose(&c2ws);
        assert!(avg.abs_diff_eq(glam::DMat4::IDENTITY, 1e-9), "{avg:?}");
        // Through the scene spec, as `--scene DIR` reads it.
        let spec = SceneSpec {
            dir: d.clone(),
            split: SplitKind::All,
            fewshot_views: 3,
            factor: 1,
            sparse_depth: true,
            depth_dir: None,
            mvs_depth: None,
            capture_depth: false,
        };
        let loaded = spec.load().unwrap();
        assert_eq!(loaded.split.train.len(), 5);
        assert!(extranerf_nerf::run::points_path(&d).exists());
    }
    // Cameras around the scene: not forward-facing.
    let orbit: Vec<DVec3> = (0..8)
        .map(|i| {
            let a = i as f64 * std::f64::consts::TAU / 8.0;
            DVec3::new(4.0 * a.cos(), 0.0, 4.0 * a.sin())
        })
        .collect();
    let d = dir.join("orbit");
    write_colmap_capture(&d, &colmap_model(&orbit), ModelFormat::Text);
    assert!(!load_colmap(&d, 1).unwrap().forward_facing);
    let half: Vec<_> = (0..5)
        .map(|i| {
            let a = i as f64 * std::f64::consts::PI / 4.0;
            let c = DVec3::new(a.cos(), 0.0, a.sin()) * 4.0;
            // OpenGL: looking along -z, so z points from the origin to the camera.
            let z = c.normalize();
            let x = DVec3::Y.cross(z).normalize();
            glam::DMat4::from_cols(
                x.extend(0.0),
                z.cross(x).extend(0.0),
                z.extend(0.0),
                c.extend(1.0),
            )
        })
        .collect();
    assert!(!forward_facing(&half), "a half orbit");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `poses_bounds.npy`'s row `i` as a COLMAP image: LLFF's rotation columns are COLMAP's camera
/// [down, right, backwards] axes in the world, its translation the camera centre.
fn llff_row_as_image(row: &[f64], id: u32, name: String) -> ColmapImage {
    let col = |c: usize| DVec3::new(row[c], row[5 + c], row[10 + c]);
    let (down, right, back, centre) = (col(0), col(1), col(2), col(3));
    let c2w = DMat3::from_cols(right, down, -back);
    let r = c2w.transpose();
    ColmapImage {
        id,
        qvec: colmap_qvec(r),
        tvec: -(r * centre),
        camera_id: 1,
        name,
        points2d: Vec::new(),
    }
}

#[test]
fn fern_as_a_colmap_text_model_matches_its_llff_poses_and_bounds() {
    let fern = shared_data().join("llff").join("fern");
    let dir = scratch_dir("colmap-fern");
    let raw = read_npy(&fern.join("poses_bounds.npy")).unwrap();
    let rows: Vec<&[f64]> = raw.data.chunks_exact(17).collect();
    let (h, w, focal) = (rows[0][4], rows[0][9], rows[0][14]);
    // Image ids in name order, as COLMAP gave them when it matched fern's photos.
    let names: Vec<String> = (0..rows.len())
        .map(|i| format!("image{i:03}.png"))
        .collect();
    let model = Model {
        cameras: vec![ColmapCamera {
            id: 1,
            model: "PINHOLE",
            width: w as u64,
            height: h as u64,
            params: vec![focal, focal, w / 2.0, h / 2.0],
        }],
        images: rows
            .iter()
            .enumerate()
            .map(|(i, r)| llff_row_as_image(r, i as u32 + 1, names[i].clone()))
            .collect(),
        points: read_points3d_bin(&fern.join("sparse/0/points3D.bin")).unwrap(),
    };
    model
        .write(&dir.join("sparse/0"), ModelFormat::Text)
        .unwrap();
    std::os::unix::fs::symlink(fern.join("images_8"), dir.join("images_8")).unwrap();
    let colmap = load_colmap(&dir, 8).unwrap();
    let llff = load_llff(&fern, &LlffOptions::default()).unwrap();
    assert!(colmap.forward_facing);
    assert_eq!(colmap.cameras.len(), llff.cameras.len());
    for (i, (a, b)) in colmap.cameras.iter().zip(&llff.cameras).enumerate() {
        assert_eq!(a.image, dir.join("images_8").join(&names[i]));
        assert_eq!((a.width, a.height), (b.width, b.height));
        assert!(
            (a.fx - b.fx).abs() < 1e-9 && (a.cx - b.cx).abs() < 1e-9,
            "view {i}"
        );
        let (ba, bb) = (a.bounds.unwrap(), b.bounds.unwrap());
        assert!(
            (ba.0 - bb.0).abs() < 1e-9 * bb.0 && (ba.1 - bb.1).abs() < 1e-9 * bb.1,
            "view {i}: bounds {ba:?} from the points, {bb:?} in poses_bounds.npy"
        );
        assert!(
            a.c2w.abs_diff_eq(b.c2w, 1e-9),
            "view {i}: {:?} vs {:?}",
            a.c2w,
            b.c2w
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn err(dir: &Path) -> String {
    load_colmap(dir, 1).unwrap_err().to_string()
}

#[test]
fn malformed_colmap_models_are_errors_naming_the_file_and_field() {
    let dir = scratch_dir("colmap-bad");
    let model = colmap_model(&colmap_rig(5));
    let fresh = |name: &str, format: ModelFormat| {
        let d = dir.join(name);
        write_colmap_capture(&d, &model, format);
        d
    };
    // Truncated binary files.
    let d = fresh("truncated", ModelFormat::Binary);
    let images = d.join("sparse/0/images.bin");
    let bytes = std::fs::read(&images).unwrap();
    std::fs::write(&images, &bytes[..bytes.len() - 5]).unwrap();
    let e = err(&d);
    assert!(e.contains("images.bin") && e.contains("truncated"), "{e}");
    // A count that the rest of the file cannot hold.
    let mut huge = bytes.clone();
    huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    std::fs::write(&images, &huge).unwrap();
    let e = err(&d);
    assert!(e.contains("images.bin") && e.contains("image count"), "{e}");
    // Text: a camera with the wrong number of parameters, an unknown model, a distorted one,
    // a fisheye; an image of a camera the model lacks; a 2-D point line that is not triples.
    let text = |name: &str, file: &str, from: &str, to: &str| {
        let d = fresh(name, ModelFormat::Text);
        let p = d.join("sparse/0").join(file);
        let t = std::fs::read_to_string(&p).unwrap();
        assert!(t.contains(from), "{from} not in {file}");
        std::fs::write(&p, t.replacen(from, to, 1)).unwrap();
        err(&d)
    };
    let e = text(
        "count",
        "cameras.txt",
        "60.0 58.0 32.5 23.75",
        "60.0 58.0 32.5",
    );
    assert!(
        e.contains("cameras.txt")
            && e.contains("line 2")
            && e.contains("PINHOLE has 4 parameters, the line gives 3"),
        "{e}"
    );
    let e = text("unknown", "cameras.txt", "PINHOLE", "PINHOLISH");
    assert!(
        e.contains("cameras.txt") && e.contains("unknown model `PINHOLISH`"),
        "{e}"
    );
    let e = text(
        "distorted",
        "cameras.txt",
        "55.0 31.0 24.0 0.0",
        "55.0 31.0 24.0 0.01",
    );
    assert!(
        e.contains("SIMPLE_RADIAL with distortion") && e.contains("image_undistorter"),
        "{e}"
    );
    let e = text(
        "fisheye",
        "cameras.txt",
        "7 SIMPLE_RADIAL 64 48 55.0 31.0 24.0 0.0",
        "7 SIMPLE_RADIAL_FISHEYE 64 48 55.0 31.0 24.0 0.0",
    );
    assert!(
        e.contains("SIMPLE_RADIAL_FISHEYE") && e.contains("fisheye"),
        "{e}"
    );
    let e = text("camera", "images.txt", " 1 view_05.png", " 9 view_05.png");
    assert!(
        e.contains("images.txt") && e.contains("names camera 9"),
        "{e}"
    );
    let e = text("points", "images.txt", "1.5 2.5 -1 ", "1.5 2.5 ");
    assert!(e.contains("images.txt") && e.contains("not triples"), "{e}");
    let e = text("number", "points3D.txt", "\n100 ", "\n1x0 ");
    assert!(
        e.contains("points3D.txt") && e.contains("point id `1x0`"),
        "{e}"
    );
    // An image the model names that is not in the image folder.
    let d = fresh("missing", ModelFormat::Text);
    std::fs::remove_file(d.join("images/view_03.png")).unwrap();
    let e = err(&d);
    assert!(e.contains("view_03.png"), "{e}");
    // A downscale the capture does not have.
    let e = load_colmap(&d, 8).unwrap_err().to_string();
    assert!(
        e.contains("images_8") && e.contains("pass --factor 1"),
        "{e}"
    );
    // No model at all.
    let e = err(&dir.join("missing/images"));
    assert!(e.contains("no COLMAP model"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A nerfstudio capture (`ns-process-data`'s layout): `transforms.json` with `camera_model`,
/// intrinsics at the full size, `applied_transform`, and the images in `images/` with their
/// half-size twins in `images_2/`.
fn nerfstudio_capture(dir: &Path, camera_model: &str) -> std::path::PathBuf {
    for (folder, w, h) in [("images", 64, 48), ("images_2", 32, 24)] {
        std::fs::create_dir_all(dir.join(folder)).unwrap();
        for k in 1..=2 {
            extranerf_nerf::run::write_png(
                &dir.join(folder).join(format!("frame_{k:05}.png")),
                w,
                h,
                &vec![0.5; (w * h * 3) as usize],
            )
            .unwrap();
        }
    }
    let frame = |k: usize, x: f64| {
        serde_json::json!({
            "file_path": format!("images/frame_{k:05}.png"),
            "transform_matrix": [[1.0, 0.0, 0.0, x], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]],
        })
    };
    let doc = serde_json::json!({
        "camera_model": camera_model,
        "fl_x": 60.0, "fl_y": 58.0, "cx": 32.5, "cy": 23.75, "w": 64, "h": 48,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "applied_transform": [[0.0, -1.0, 0.0, 0.5], [1.0, 0.0, 0.0, -0.25], [0.0, 0.0, 1.0, 2.0]],
        "frames": [frame(1, 0.0), frame(2, 1.0)],
    });
    let path = dir.join("transforms.json");
    std::fs::write(&path, serde_json::to_string_pretty(&doc).unwrap()).unwrap();
    path
}

#[test]
fn a_nerfstudio_capture_reads_its_camera_model_transform_and_downscaled_images() {
    use extranerf_nerf::data::transforms::load_transforms_at;
    let dir = scratch_dir("nerfstudio");
    let path = nerfstudio_capture(&dir.join("opencv"), "OPENCV");
    let full = load_transforms_at(&path, 1).unwrap();
    let c = &full.cameras[0];
    assert_eq!((c.width, c.height, c.fx, c.fy), (64, 48, 60.0, 58.0));
    assert!(c.image.ends_with("images/frame_00001.png"));
    // The OpenGL convention: an unrotated camera looks along -z with +y up: the origin, 4 in
    // front of it, lands on the principal point, a point above it higher in the image.
    let (x, y, d) = c.project(DVec3::ZERO);
    assert!((x - 32.5).abs() < 1e-12 && (y - 23.75).abs() < 1e-12 && (d - 4.0).abs() < 1e-12);
    assert!(c.project(DVec3::new(0.0, 0.5, 0.0)).1 < 23.75);
    assert!(
        full.cameras[1].project(DVec3::ZERO).0 < 32.5,
        "the second camera is to the right"
    );
    // The applied transform maps COLMAP's world (its points) into the poses' world.
    let want = glam::DMat4::from_cols_array_2d(&[
        [0.0, 1.0, 0.0, 0.0],
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.5, -0.25, 2.0, 1.0],
    ]);
    assert_eq!(full.world_from_source, want);
    // A downscale reads the twins, the intrinsics scaled to their size; one the capture does
    // not have reads the images as named.
    let half = load_transforms_at(&path, 2).unwrap();
    let h = &half.cameras[1];
    assert_eq!(
        (h.width, h.height, h.fx, h.fy, h.cx, h.cy),
        (32, 24, 30.0, 29.0, 16.25, 11.875)
    );
    assert!(h.image.ends_with("images_2/frame_00002.png"));
    let quarter = load_transforms_at(&path, 4).unwrap();
    assert_eq!(quarter.cameras[0].width, 64);
    // As `--scene DIR --factor 2` reads it.
    let spec = SceneSpec {
        dir: dir.join("opencv"),
        split: SplitKind::All,
        fewshot_views: 3,
        factor: 2,
        sparse_depth: false,
        depth_dir: None,
        mvs_depth: None,
        capture_depth: false,
    };
    assert_eq!(spec.load().unwrap().scene.cameras[0].width, 32);
    // Cameras that are not perspective ones are refused, naming the model.
    for model in ["OPENCV_FISHEYE", "EQUIRECTANGULAR"] {
        let p = nerfstudio_capture(&dir.join(model), model);
        let e = load_transforms_at(&p, 1).unwrap_err().to_string();
        assert!(
            e.contains(model)
                && e.contains("not a perspective camera")
                && e.contains("transforms.json"),
            "{e}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// nerfstudio's depth in millimetres at pixel `(x, y)` of a `w`-wide map (`salt` tells the
/// maps apart); 0 at the top-left pixel, "no depth".
fn depth_mm(x: u32, y: u32, w: u32, salt: u32) -> u16 {
    if x == 0 && y == 0 {
        0
    } else {
        (1000 + salt + x + w * y) as u16
    }
}

#[test]
fn a_nerfstudio_capture_reads_the_depth_files_its_frames_name() {
    use extranerf_nerf::data::depth::read_capture_depth;
    use extranerf_nerf::data::npy::write_npy_f64;
    use extranerf_nerf::data::transforms::load_transforms_at;
    use extranerf_nerf::model::{ModelConfig, Space};
    use extranerf_nerf::run::{training_views, DepthRequest};
    let dir = scratch_dir("nerfstudio-depth");
    let path = nerfstudio_capture(&dir, "PINHOLE");
    let png16 = |file: &Path, w: u32, h: u32, salt: u32| {
        std::fs::create_dir_all(file.parent().unwrap()).unwrap();
        image::ImageBuffer::<image::Luma<u16>, _>::from_fn(w, h, |x, y| {
            image::Luma([depth_mm(x, y, w, salt)])
        })
        .save(file)
        .unwrap();
    };
    // Frame 1: a 16-bit PNG with a downscaled twin in depths_2/; frame 2: a .npy without one.
    png16(&dir.join("depths/frame_00001.png"), 64, 48, 0);
    png16(&dir.join("depths_2/frame_00001.png"), 32, 24, 7);
    let npy: Vec<f64> = (0..48u32)
        .flat_map(|y| (0..64u32).map(move |x| f64::from(depth_mm(x, y, 64, 3))))
        .collect();
    write_npy_f64(&dir.join("depths/frame_00002.npy"), &[48, 64], &npy).unwrap();
    let mut doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let with_depth = |doc: &mut serde_json::Value, files: [Option<&str>; 2]| {
        for (f, d) in doc["frames"].as_array_mut().unwrap().iter_mut().zip(files) {
            match d {
                Some(d) => f["depth_file_path"] = d.into(),
                None => {
                    f.as_object_mut().unwrap().remove("depth_file_path");
                }
            }
        }
        std::fs::write(&path, serde_json::to_string(doc).unwrap()).unwrap();
    };
    with_depth(
        &mut doc,
        [
            Some("depths/frame_00001.png"),
            Some("depths/frame_00002.npy"),
        ],
    );
    // Full size: millimetres to the capture's units, 0 where there is no depth.
    let full = load_transforms_at(&path, 1).unwrap();
    assert_eq!(full.depth_files.len(), 2);
    assert!(full.depth_files[0].ends_with("depths/frame_00001.png"));
    for (k, salt) in [(0, 0), (1, 3)] {
        let d = read_capture_depth(&full.depth_files[k], &full.cameras[k]).unwrap();
        assert_eq!(d.len(), 64 * 48);
        for (y, x) in [(0, 0), (0, 1), (47, 63), (20, 33)] {
            let want = f64::from(depth_mm(x, y, 64, salt)) * 1e-3;
            assert_eq!(
                d[(y * 64 + x) as usize],
                want as f32,
                "view {k} pixel ({x}, {y})"
            );
        }
    }
    // A downscale reads depths_2/ where it is there; else the full map's nearest samples.
    let half = load_transforms_at(&path, 2).unwrap();
    assert!(half.depth_files[0].ends_with("depths_2/frame_00001.png"));
    let d0 = read_capture_depth(&half.depth_files[0], &half.cameras[0]).unwrap();
    assert_eq!(
        d0[32 * 5 + 9],
        (f64::from(depth_mm(9, 5, 32, 7)) * 1e-3) as f32
    );
    let d1 = read_capture_depth(&half.depth_files[1], &half.cameras[1]).unwrap();
    assert_eq!(d1.len(), 32 * 24);
    for (x, y) in [(0, 0), (9, 5), (31, 23)] {
        assert_eq!(
            d1[(y * 32 + x) as usize],
            (f64::from(depth_mm(2 * x + 1, 2 * y + 1, 64, 3)) * 1e-3) as f32,
            "pixel ({x}, {y}) of the resampled map"
        );
    }
    // Training reads them by default (auto) and as asked (capture): view depth targets, in
    // world space, equal to the files' with confidence 1.
    let mut spec = SceneSpec {
        dir: dir.clone(),
        split: SplitKind::All,
        fewshot_views: 3,
        factor: 1,
        sparse_depth: false,
        depth_dir: None,
        mvs_depth: None,
        capture_depth: false,
    };
    let loaded = spec.load().unwrap();
    let said = DepthRequest::Auto
        .resolve(&mut spec, &loaded, Default::default())
        .unwrap();
    assert!(
        spec.capture_depth && said.contains("depth_file_path"),
        "{said}"
    );
    let model = ModelConfig {
        space: Space::World,
        ..ModelConfig::default()
    };
    let views = training_views(&spec, &loaded, &model).unwrap();
    for (k, salt) in [(0usize, 0), (1, 3)] {
        let depth = views[k].depth.as_ref().unwrap();
        assert_eq!(depth[0], [0.0, 0.0], "no depth at the top-left pixel");
        let want = (f64::from(depth_mm(5, 7, 64, salt)) * 1e-3) as f32;
        assert_eq!(depth[7 * 64 + 5], [want, 1.0], "view {k}");
    }
    DepthRequest::Capture
        .resolve(&mut spec, &loaded, Default::default())
        .unwrap();
    assert!(spec.capture_depth);
    // A scene whose frames name no depth file: `capture` says so; auto does not pick it.
    let plain = nerfstudio_capture(&dir.join("plain"), "PINHOLE");
    let mut plain_spec = SceneSpec {
        dir: plain.parent().unwrap().to_path_buf(),
        ..spec.clone()
    };
    let plain_loaded = plain_spec.load().unwrap();
    let e = DepthRequest::Capture
        .resolve(&mut plain_spec, &plain_loaded, Default::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("depth_file_path"), "{e}");
    DepthRequest::Auto
        .resolve(&mut plain_spec, &plain_loaded, Default::default())
        .unwrap();
    assert!(!plain_spec.capture_depth);
    // Malformed: a frame without a depth file where the one before has one, and the reverse;
    // a file that is not there; a colour PNG; a map of another aspect; another format.
    let err = |doc: &mut serde_json::Value, files: [Option<&str>; 2]| {
        with_depth(doc, files);
        load_transforms_at(&path, 1).unwrap_err().to_string()
    };
    let e = err(&mut doc, [Some("depths/frame_00001.png"), None]);
    assert!(
        e.contains("frame 1") && e.contains("depth_file_path"),
        "{e}"
    );
    let e = err(&mut doc, [None, Some("depths/frame_00002.npy")]);
    assert!(e.contains("frame 1") && e.contains("lack"), "{e}");
    let e = err(
        &mut doc,
        [Some("depths/missing.png"), Some("depths/frame_00002.npy")],
    );
    assert!(
        e.contains("depths/missing.png") && e.contains("no such file"),
        "{e}"
    );
    let read_err = |file: &Path| {
        read_capture_depth(file, &full.cameras[0])
            .unwrap_err()
            .to_string()
    };
    let rgb = dir.join("images/frame_00001.png");
    let e = read_err(&rgb);
    assert!(
        e.contains("frame_00001.png") && e.contains("one grey channel"),
        "{e}"
    );
    let square = dir.join("depths/square.npy");
    write_npy_f64(&square, &[30, 30], &[1000.0; 900]).unwrap();
    let e = read_err(&square);
    assert!(e.contains("square.npy") && e.contains("aspect"), "{e}");
    let e = read_err(&dir.join("transforms.json"));
    assert!(e.contains(".png") && e.contains(".npy"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `a` and `b` are the same scene: cameras (poses to 1e-9, intrinsics, bounds, image names)
/// and the transform from the source's world.
fn assert_same_scene(a: &extranerf_nerf::data::Scene, b: &extranerf_nerf::data::Scene) {
    assert_eq!(a.cameras.len(), b.cameras.len());
    assert_eq!(a.forward_facing, b.forward_facing);
    assert!(
        a.world_from_source.abs_diff_eq(b.world_from_source, 1e-9),
        "{:?} vs {:?}",
        a.world_from_source,
        b.world_from_source
    );
    for (i, (p, q)) in a.cameras.iter().zip(&b.cameras).enumerate() {
        assert_eq!(p.image.file_name(), q.image.file_name(), "view {i}");
        assert_eq!((p.width, p.height), (q.width, q.height), "view {i}");
        for (u, v) in [(p.fx, q.fx), (p.fy, q.fy), (p.cx, q.cx), (p.cy, q.cy)] {
            assert!((u - v).abs() < 1e-9, "view {i}: intrinsics {u} vs {v}");
        }
        assert!(
            p.c2w.abs_diff_eq(q.c2w, 1e-9),
            "view {i}: {:?} vs {:?}",
            p.c2w,
            q.c2w
        );
        let (bp, bq) = (p.bounds.unwrap(), q.bounds.unwrap());
        assert!(
            (bp.0 - bq.0).abs() < 1e-9 * bq.0 && (bp.1 - bq.1).abs() < 1e-9 * bq.1,
            "view {i}: bounds {bp:?} vs {bq:?}"
        );
    }
}

#[test]
fn export_writes_a_colmap_capture_that_reads_back_as_the_same_scene() {
    use extranerf_nerf::data::colmap_scene::{export_colmap, sparse_of};
    let dir = scratch_dir("colmap-export");
    // A COLMAP capture (image ids out of name order) exported in the other format.
    let src = dir.join("capture");
    write_colmap_capture(&src, &colmap_model(&colmap_rig(5)), ModelFormat::Text);
    let scene = load_colmap(&src, 1).unwrap();
    let (points, ids) = sparse_of(&src).unwrap();
    assert_eq!(ids.len(), 5);
    let out = dir.join("exported");
    let done = export_colmap(&scene, &points, &ids, &out, ModelFormat::Binary).unwrap();
    assert_eq!((done.views, done.points), (5, points.len()));
    assert!(out.join("sparse/0/images.bin").is_file());
    let back = load_colmap(&out, 1).unwrap();
    assert_same_scene(&back, &scene);
    // The model is consistent as COLMAP reads it: the ids are the capture's, every track entry
    // names a 2-D point of its image that names the point back, at the point's projection.
    let model = Model::read(&out.join("sparse/0")).unwrap();
    let world = back.transform_points(&model.points);
    let mut observations = 0;
    for (k, p) in model.points.iter().enumerate() {
        for &(image_id, idx) in &p.track {
            let im = model.images.iter().find(|im| im.id == image_id).unwrap();
            assert_eq!(ids[&im.name], image_id);
            let (xy, id) = im.points2d[idx as usize];
            assert_eq!(id, Some(p.id));
            let cam = back
                .cameras
                .iter()
                .find(|c| c.image.ends_with(&im.name))
                .unwrap();
            let (x, y, _) = cam.project(world[k]);
            assert!((x - xy[0]).abs() < 1e-9 && (y - xy[1]).abs() < 1e-9);
            observations += 1;
        }
    }
    let written: usize = model.images.iter().map(|im| im.points2d.len()).sum();
    assert!(observations > 0 && observations == written);
    // fern, an LLFF scene, as a COLMAP text model: the COLMAP loader reads what the LLFF
    // loader did (its point tracks name images in name order, as imgs2poses numbered them).
    let fern = shared_data().join("llff").join("fern");
    let llff = load_llff(&fern, &LlffOptions::default()).unwrap();
    let (points, ids) = sparse_of(&fern).unwrap();
    assert!(ids.is_empty() && !points.is_empty());
    let out = dir.join("fern");
    export_colmap(&llff, &points, &ids, &out, ModelFormat::Text).unwrap();
    assert_same_scene(&load_colmap(&out, 1).unwrap(), &llff);
    // Never into a folder that holds something; never without points (nothing gives bounds).
    let e = export_colmap(&llff, &points, &ids, &out, ModelFormat::Text)
        .unwrap_err()
        .to_string();
    assert!(e.contains("fern") && e.contains("not empty"), "{e}");
    let ns = nerfstudio_capture(&dir.join("ns"), "PINHOLE");
    let ns_scene = extranerf_nerf::data::transforms::load_transforms_at(&ns, 1).unwrap();
    let (none, ns_ids) = sparse_of(ns.parent().unwrap()).unwrap();
    let e = export_colmap(
        &ns_scene,
        &none,
        &ns_ids,
        &dir.join("ns_out"),
        ModelFormat::Text,
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("transforms.json") && e.contains("no sparse points"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
