//! COLMAP sparse models: `cameras`, `images` and `points3D`, in COLMAP's binary (`.bin`) and
//! text (`.txt`) formats, read and written. The scene loader is [`super::colmap_scene`].

use std::path::Path;

use glam::DVec3;

use super::{read_file, DataError, Result};

/// COLMAP camera models with their parameter counts (COLMAP's model ids 0..=10).
const MODELS: [(&str, usize); 11] = [
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
];

/// The model name of a COLMAP camera model, as COLMAP spells it; None for a name it does not
/// define.
pub fn model_named(name: &str) -> Option<(&'static str, usize)> {
    MODELS.iter().copied().find(|(n, _)| *n == name)
}

/// One camera of `cameras.bin` / `cameras.txt`.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    /// COLMAP camera id.
    pub id: u32,
    /// Model name, e.g. `SIMPLE_RADIAL`.
    pub model: &'static str,
    /// Image width.
    pub width: u64,
    /// Image height.
    pub height: u64,
    /// The model's parameters in COLMAP's order (focal(s), principal point, distortion).
    pub params: Vec<f64>,
}

/// One image of `images.bin` / `images.txt`: its world-to-camera pose (COLMAP's camera: x
/// right, y down, looking along +z).
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    /// COLMAP image id.
    pub id: u32,
    /// Rotation world -> camera as a unit quaternion (w, x, y, z).
    pub qvec: [f64; 4],
    /// Translation world -> camera.
    pub tvec: DVec3,
    /// The camera it was taken with.
    pub camera_id: u32,
    /// The image's file name, relative to the image folder.
    pub name: String,
    /// Its 2-D points: pixel position and the 3-D point it observes, if any.
    pub points2d: Vec<([f64; 2], Option<u64>)>,
}

/// One point of `points3D.bin` / `points3D.txt`.
#[derive(Clone, Debug, PartialEq)]
pub struct Point3D {
    /// COLMAP point id.
    pub id: u64,
    /// Position in COLMAP's world.
    pub xyz: DVec3,
    /// Colour.
    pub rgb: [u8; 3],
    /// Mean reprojection error in pixels.
    pub error: f64,
    /// (image id, 2-D point index) observations.
    pub track: Vec<(u32, u32)>,
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
    path: &'a Path,
}

impl Reader<'_> {
    fn take(&mut self, n: usize, what: &str) -> Result<&[u8]> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len());
        let Some(end) = end else {
            return Err(DataError::malformed(
                self.path,
                format!(
                    "truncated: {what} at byte {} needs {n} bytes, the file has {}",
                    self.at,
                    self.bytes.len()
                ),
            ));
        };
        let s = &self.bytes[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(
            self.take(8, what)?.try_into().expect("8 bytes"),
        ))
    }
    fn u32(&mut self, what: &str) -> Result<u32> {
        Ok(u32::from_le_bytes(
            self.take(4, what)?.try_into().expect("4 bytes"),
        ))
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        let v = f64::from_le_bytes(self.take(8, what)?.try_into().expect("8 bytes"));
        if !v.is_finite() {
            return Err(DataError::malformed(
                self.path,
                format!("{what} at byte {} is not finite ({v})", self.at - 8),
            ));
        }
        Ok(v)
    }
    /// Refuses bytes left after the `n` records (`what`) the file said it holds.
    fn finish(&self, n: usize, what: &str) -> Result<()> {
        if self.at != self.bytes.len() {
            return Err(DataError::malformed(
                self.path,
                format!("{} bytes left after {n} {what}", self.bytes.len() - self.at),
            ));
        }
        Ok(())
    }
    /// A count, refused when even the smallest records could not fit in the rest of the file.
    fn count(&mut self, what: &str, min_record: usize) -> Result<usize> {
        let n = self.u64(what)?;
        let left = (self.bytes.len() - self.at) as u64;
        if n.saturating_mul(min_record as u64) > left {
            return Err(DataError::malformed(
                self.path,
                format!("truncated or corrupt: {what} says {n}, but only {left} bytes follow"),
            ));
        }
        Ok(n as usize)
    }
}

/// Reads COLMAP's `cameras.bin`.
pub fn read_cameras_bin(path: &Path) -> Result<Vec<ColmapCamera>> {
    let bytes = read_file(path)?;
    let mut r = Reader {
        bytes: &bytes,
        at: 0,
        path,
    };
    let n = r.count("camera count", 24)?;
    let mut cams = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u32("camera id")?;
        let model_id = r.u32("camera model")?;
        let &(model, nparams) = MODELS.get(model_id as usize).ok_or_else(|| {
            DataError::malformed(path, format!("camera {id} has unknown model id {model_id}"))
        })?;
        let width = r.u64("width")?;
        let height = r.u64("height")?;
        let params = (0..nparams)
            .map(|_| r.f64("camera parameter"))
            .collect::<Result<Vec<_>>>()?;
        cams.push(ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        });
    }
    r.finish(n, "cameras")?;
    Ok(cams)
}

/// Reads COLMAP's `points3D.bin`.
pub fn read_points3d_bin(path: &Path) -> Result<Vec<Point3D>> {
    let bytes = read_file(path)?;
    let mut r = Reader {
        bytes: &bytes,
        at: 0,
        path,
    };
    let n = r.count("point count", 43)?;
    let mut points = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u64("point id")?;
        let xyz = DVec3::new(r.f64("x")?, r.f64("y")?, r.f64("z")?);
        let c = r.take(3, "colour")?;
        let rgb = [c[0], c[1], c[2]];
        let error = r.f64("reprojection error")?;
        let len = r.count("track length", 8)?;
        let track = (0..len)
            .map(|_| Ok((r.u32("track image id")?, r.u32("track point index")?)))
            .collect::<Result<Vec<_>>>()?;
        points.push(Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    r.finish(n, "points")?;
    Ok(points)
}

/// Reads COLMAP's `images.bin`.
pub fn read_images_bin(path: &Path) -> Result<Vec<ColmapImage>> {
    let bytes = read_file(path)?;
    let mut r = Reader {
        bytes: &bytes,
        at: 0,
        path,
    };
    // id, quaternion, translation, camera id, an empty name's NUL and the point count.
    let n = r.count("image count", 4 + 32 + 24 + 4 + 1 + 8)?;
    let mut images = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u32("image id")?;
        let qvec = [r.f64("qw")?, r.f64("qx")?, r.f64("qy")?, r.f64("qz")?];
        let tvec = DVec3::new(r.f64("tx")?, r.f64("ty")?, r.f64("tz")?);
        let camera_id = r.u32("camera id")?;
        let rest = &r.bytes[r.at..];
        let Some(len) = rest.iter().position(|&b| b == 0) else {
            return Err(DataError::malformed(
                path,
                format!("truncated: image {id}'s name at byte {} has no end", r.at),
            ));
        };
        let name = String::from_utf8(rest[..len].to_vec())
            .map_err(|_| DataError::malformed(path, format!("image {id}'s name is not UTF-8")))?;
        r.at += len + 1;
        let np = r.count("2-D point count", 24)?;
        let points2d = (0..np)
            .map(|_| {
                let xy = [r.f64("2-D point x")?, r.f64("2-D point y")?];
                let p = r.u64("2-D point's 3-D point id")?;
                // COLMAP writes -1 (as an unsigned 64-bit integer) where no 3-D point is seen.
                Ok((xy, (p != u64::MAX).then_some(p)))
            })
            .collect::<Result<Vec<_>>>()?;
        images.push(ColmapImage {
            id,
            qvec,
            tvec,
            camera_id,
            name,
            points2d,
        });
    }
    r.finish(n, "images")?;
    Ok(images)
}

/// The lines of a COLMAP text file that are not comments, with their line numbers (from 1).
fn text_lines(path: &Path) -> Result<Vec<(usize, String)>> {
    let bytes = read_file(path)?;
    let text = String::from_utf8(bytes)
        .map_err(|e| DataError::malformed(path, format!("not UTF-8 text: {e}")))?;
    Ok(text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim_start().starts_with('#'))
        .map(|(i, l)| (i + 1, l.trim().to_string()))
        .collect())
}

/// The fields of a text line, each parsed with the name of what it is.
struct Fields<'a> {
    path: &'a Path,
    line: usize,
    it: std::str::SplitWhitespace<'a>,
}

impl<'a> Fields<'a> {
    fn new(path: &'a Path, line: usize, text: &'a str) -> Fields<'a> {
        Fields {
            path,
            line,
            it: text.split_whitespace(),
        }
    }
    fn err(&self, problem: String) -> DataError {
        DataError::malformed(self.path, format!("line {}: {problem}", self.line))
    }
    fn next<T: std::str::FromStr>(&mut self, what: &str) -> Result<T> {
        let Some(t) = self.it.next() else {
            return Err(self.err(format!("{what} is missing")));
        };
        t.parse()
            .map_err(|_| self.err(format!("{what} `{t}` is not a valid number")))
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        let v: f64 = self.next(what)?;
        if !v.is_finite() {
            return Err(self.err(format!("{what} is not finite ({v})")));
        }
        Ok(v)
    }
    fn word(&mut self, what: &str) -> Result<&'a str> {
        self.it
            .next()
            .ok_or_else(|| self.err(format!("{what} is missing")))
    }
    fn rest(&mut self) -> Vec<&'a str> {
        self.it.by_ref().collect()
    }
}

/// Reads COLMAP's `cameras.txt`.
pub fn read_cameras_txt(path: &Path) -> Result<Vec<ColmapCamera>> {
    let mut cams = Vec::new();
    for (line, text) in text_lines(path)? {
        if text.is_empty() {
            continue;
        }
        let mut f = Fields::new(path, line, &text);
        let id = f.next("camera id")?;
        let name = f.word("camera model")?;
        let Some((model, nparams)) = model_named(name) else {
            return Err(f.err(format!(
                "camera {id} has unknown model `{name}` (COLMAP's models: {})",
                MODELS.map(|m| m.0).join(", ")
            )));
        };
        let width = f.next("width")?;
        let height = f.next("height")?;
        let rest = f.rest();
        if rest.len() != nparams {
            return Err(f.err(format!(
                "camera {id}: {model} has {nparams} parameters, the line gives {}",
                rest.len()
            )));
        }
        let mut params = Vec::with_capacity(nparams);
        for (k, t) in rest.iter().enumerate() {
            let mut p = Fields::new(path, line, t);
            params.push(p.f64(&format!("parameter {k}"))?);
        }
        cams.push(ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        });
    }
    Ok(cams)
}

/// Reads COLMAP's `images.txt`: per image a line of its pose, camera and name, then a line of
/// its 2-D points (`X Y POINT3D_ID`, -1 where none; the line may be empty).
pub fn read_images_txt(path: &Path) -> Result<Vec<ColmapImage>> {
    let lines = text_lines(path)?;
    let mut images = Vec::new();
    let mut k = 0;
    while k < lines.len() {
        let (line, text) = &lines[k];
        if text.is_empty() {
            k += 1;
            continue;
        }
        let mut f = Fields::new(path, *line, text);
        let id = f.next("image id")?;
        let qvec = [f.f64("qw")?, f.f64("qx")?, f.f64("qy")?, f.f64("qz")?];
        let tvec = DVec3::new(f.f64("tx")?, f.f64("ty")?, f.f64("tz")?);
        let camera_id = f.next("camera id")?;
        let name = f.rest().join(" ");
        if name.is_empty() {
            return Err(f.err(format!("image {id} has no name")));
        }
        // The points line; an image at the end of the file may have none.
        let mut points2d = Vec::new();
        if let Some((pline, ptext)) = lines.get(k + 1) {
            let mut p = Fields::new(path, *pline, ptext);
            let toks = p.rest();
            if !toks.len().is_multiple_of(3) {
                return Err(p.err(format!(
                    "image {id}'s 2-D points: {} values are not triples of X Y POINT3D_ID",
                    toks.len()
                )));
            }
            for t in toks.chunks(3) {
                let x = Fields::new(path, *pline, t[0]).f64("2-D point x")?;
                let y = Fields::new(path, *pline, t[1]).f64("2-D point y")?;
                let pid: i64 = Fields::new(path, *pline, t[2]).next("2-D point's 3-D point id")?;
                points2d.push(([x, y], u64::try_from(pid).ok()));
            }
        }
        images.push(ColmapImage {
            id,
            qvec,
            tvec,
            camera_id,
            name,
            points2d,
        });
        k += 2;
    }
    Ok(images)
}

/// Reads COLMAP's `points3D.txt`.
pub fn read_points3d_txt(path: &Path) -> Result<Vec<Point3D>> {
    let mut points = Vec::new();
    for (line, text) in text_lines(path)? {
        if text.is_empty() {
            continue;
        }
        let mut f = Fields::new(path, line, &text);
        let id = f.next("point id")?;
        let xyz = DVec3::new(f.f64("x")?, f.f64("y")?, f.f64("z")?);
        let rgb = [f.next("red")?, f.next("green")?, f.next("blue")?];
        let error = f.f64("reprojection error")?;
        let rest = f.rest();
        if !rest.len().is_multiple_of(2) {
            return Err(f.err(format!(
                "point {id}'s track: {} values are not pairs of IMAGE_ID POINT2D_IDX",
                rest.len()
            )));
        }
        let track = rest
            .chunks(2)
            .map(|t| {
                Ok((
                    Fields::new(path, line, t[0]).next("track image id")?,
                    Fields::new(path, line, t[1]).next("track point index")?,
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        points.push(Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    Ok(points)
}

/// A COLMAP sparse model: its cameras, images and points.
#[derive(Clone, Debug, PartialEq)]
pub struct Model {
    pub cameras: Vec<ColmapCamera>,
    pub images: Vec<ColmapImage>,
    pub points: Vec<Point3D>,
}

/// The two formats COLMAP writes a model in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum ModelFormat {
    /// `cameras.bin`, `images.bin`, `points3D.bin`.
    Binary,
    /// `cameras.txt`, `images.txt`, `points3D.txt`.
    Text,
}

impl ModelFormat {
    fn ext(self) -> &'static str {
        match self {
            ModelFormat::Binary => "bin",
            ModelFormat::Text => "txt",
        }
    }

    /// The format of the model in `dir` (binary where both are there, as COLMAP reads it);
    /// None where it holds neither `cameras.bin` nor `cameras.txt`.
    pub fn of(dir: &Path) -> Option<ModelFormat> {
        [ModelFormat::Binary, ModelFormat::Text]
            .into_iter()
            .find(|f| dir.join(format!("cameras.{}", f.ext())).is_file())
    }
}

/// The path of `points3D` of the model in `dir`, in the format it has.
pub fn points_file(dir: &Path) -> Option<std::path::PathBuf> {
    ModelFormat::of(dir)
        .map(|f| dir.join(format!("points3D.{}", f.ext())))
        .filter(|p| p.is_file())
}

/// Reads a `points3D` file of either format (by its extension).
pub fn read_points3d(path: &Path) -> Result<Vec<Point3D>> {
    if path.extension().is_some_and(|e| e == "txt") {
        read_points3d_txt(path)
    } else {
        read_points3d_bin(path)
    }
}

impl Model {
    /// Reads the model in `dir` (cameras, images and points, binary or text), checking that
    /// every image names a camera of the model and every id is unique.
    pub fn read(dir: &Path) -> Result<Model> {
        let Some(format) = ModelFormat::of(dir) else {
            return Err(DataError::malformed(
                dir,
                "no COLMAP model: neither cameras.bin nor cameras.txt",
            ));
        };
        let file = |name: &str| dir.join(format!("{name}.{}", format.ext()));
        let (cameras, images, points) = match format {
            ModelFormat::Binary => (
                read_cameras_bin(&file("cameras"))?,
                read_images_bin(&file("images"))?,
                read_points3d_bin(&file("points3D"))?,
            ),
            ModelFormat::Text => (
                read_cameras_txt(&file("cameras"))?,
                read_images_txt(&file("images"))?,
                read_points3d_txt(&file("points3D"))?,
            ),
        };
        let mut ids = std::collections::HashSet::new();
        for c in &cameras {
            if !ids.insert(c.id) {
                return Err(DataError::malformed(
                    &file("cameras"),
                    format!("camera id {} appears twice", c.id),
                ));
            }
        }
        let mut image_ids = std::collections::HashSet::new();
        for im in &images {
            if !image_ids.insert(im.id) {
                return Err(DataError::malformed(
                    &file("images"),
                    format!("image id {} appears twice", im.id),
                ));
            }
            if !ids.contains(&im.camera_id) {
                return Err(DataError::malformed(
                    &file("images"),
                    format!(
                        "image {} ({}) names camera {}, which {} does not have",
                        im.id,
                        im.name,
                        im.camera_id,
                        file("cameras").display()
                    ),
                ));
            }
            let n = im.qvec.iter().map(|q| q * q).sum::<f64>().sqrt();
            if n <= 1e-6 || n.is_nan() {
                return Err(DataError::malformed(
                    &file("images"),
                    format!(
                        "image {} ({}) has a zero rotation quaternion",
                        im.id, im.name
                    ),
                ));
            }
        }
        Ok(Model {
            cameras,
            images,
            points,
        })
    }

    /// Writes the model into `dir` in `format` (COLMAP's own layout, as COLMAP reads it).
    pub fn write(&self, dir: &Path, format: ModelFormat) -> Result<()> {
        std::fs::create_dir_all(dir).map_err(|e| DataError::io(dir, e))?;
        let file = |name: &str| dir.join(format!("{name}.{}", format.ext()));
        let (c, i, p) = match format {
            ModelFormat::Binary => (self.cameras_bin(), self.images_bin(), self.points_bin()),
            ModelFormat::Text => (
                self.cameras_txt().into_bytes(),
                self.images_txt().into_bytes(),
                self.points_txt().into_bytes(),
            ),
        };
        super::write_atomic(&file("cameras"), &c)?;
        super::write_atomic(&file("images"), &i)?;
        super::write_atomic(&file("points3D"), &p)?;
        Ok(())
    }

    fn cameras_bin(&self) -> Vec<u8> {
        let mut b = (self.cameras.len() as u64).to_le_bytes().to_vec();
        for c in &self.cameras {
            let model = MODELS.iter().position(|m| m.0 == c.model).unwrap_or(0) as u32;
            b.extend(c.id.to_le_bytes());
            b.extend(model.to_le_bytes());
            b.extend(c.width.to_le_bytes());
            b.extend(c.height.to_le_bytes());
            for p in &c.params {
                b.extend(p.to_le_bytes());
            }
        }
        b
    }

    fn images_bin(&self) -> Vec<u8> {
        let mut b = (self.images.len() as u64).to_le_bytes().to_vec();
        for im in &self.images {
            b.extend(im.id.to_le_bytes());
            for q in im.qvec {
                b.extend(q.to_le_bytes());
            }
            for t in im.tvec.to_array() {
                b.extend(t.to_le_bytes());
            }
            b.extend(im.camera_id.to_le_bytes());
            b.extend(im.name.as_bytes());
            b.push(0);
            b.extend((im.points2d.len() as u64).to_le_bytes());
            for (xy, p) in &im.points2d {
                b.extend(xy[0].to_le_bytes());
                b.extend(xy[1].to_le_bytes());
                b.extend(p.unwrap_or(u64::MAX).to_le_bytes());
            }
        }
        b
    }

    fn points_bin(&self) -> Vec<u8> {
        let mut b = (self.points.len() as u64).to_le_bytes().to_vec();
        for p in &self.points {
            b.extend(p.id.to_le_bytes());
            for v in p.xyz.to_array() {
                b.extend(v.to_le_bytes());
            }
            b.extend(p.rgb);
            b.extend(p.error.to_le_bytes());
            b.extend((p.track.len() as u64).to_le_bytes());
            for (i, k) in &p.track {
                b.extend(i.to_le_bytes());
                b.extend(k.to_le_bytes());
            }
        }
        b
    }

    // Text: Rust's shortest round-trip formatting of f64, so text and binary read back equal.
    fn cameras_txt(&self) -> String {
        let mut s = String::from("# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
        for c in &self.cameras {
            s += &format!("{} {} {} {}", c.id, c.model, c.width, c.height);
            for p in &c.params {
                s += &format!(" {p:?}");
            }
            s.push('\n');
        }
        s
    }

    fn images_txt(&self) -> String {
        let mut s = String::from(
            "# Image list, two lines each: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
             # and POINTS2D[] as (X, Y, POINT3D_ID)\n",
        );
        for im in &self.images {
            let [w, x, y, z] = im.qvec;
            let t = im.tvec;
            s += &format!(
                "{} {w:?} {x:?} {y:?} {z:?} {:?} {:?} {:?} {} {}\n",
                im.id, t.x, t.y, t.z, im.camera_id, im.name
            );
            let pts: Vec<String> = im
                .points2d
                .iter()
                .map(|(xy, p)| format!("{:?} {:?} {}", xy[0], xy[1], p.map_or(-1, |p| p as i64)))
                .collect();
            s += &pts.join(" ");
            s.push('\n');
        }
        s
    }

    fn points_txt(&self) -> String {
        let mut s = String::from(
            "# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
        );
        for p in &self.points {
            s += &format!(
                "{} {:?} {:?} {:?} {} {} {} {:?}",
                p.id, p.xyz.x, p.xyz.y, p.xyz.z, p.rgb[0], p.rgb[1], p.rgb[2], p.error
            );
            for (i, k) in &p.track {
                s += &format!(" {i} {k}");
            }
            s.push('\n');
        }
        s
    }
}
