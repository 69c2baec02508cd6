//! A loaded scene: its cameras, where they came from, and the split its data set gives.

use std::path::PathBuf;

use glam::{DMat4, DVec3};

use super::colmap;
use super::Camera;

/// Train and test views (indices into the scene's cameras, ascending).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SplitIndices {
    /// Training views.
    pub train: Vec<usize>,
    /// Held-out views.
    pub test: Vec<usize>,
}

/// A loaded scene: cameras in file order plus how the world was transformed on load.
#[derive(Clone, Debug)]
pub struct Scene {
    /// The folder or file it came from.
    pub source: PathBuf,
    /// One camera per image, in file order.
    pub cameras: Vec<Camera>,
    /// Maps the source's world coordinates (e.g. COLMAP points) into the scene's.
    pub world_from_source: DMat4,
    /// Forward-facing capture (LLFF): NDC applies; otherwise a 360 or object capture.
    pub forward_facing: bool,
    /// The split the data set gives (NeRF-synthetic's split files), for `--split given`.
    pub given: Option<SplitIndices>,
    /// An object on a transparent background (NeRF-synthetic): nothing lies beyond what the
    /// views frame around the rig's centre, so rays need sampling only there.
    pub bounded_object: bool,
    /// The depth file each view names (nerfstudio's `depth_file_path`, read by
    /// [`super::depth::read_capture_depth`]): one per camera, or empty where the capture names
    /// none.
    pub depth_files: Vec<PathBuf>,
}

impl Scene {
    /// Maps COLMAP sparse points into the scene's world and keeps their colours.
    pub fn transform_points(&self, points: &[colmap::Point3D]) -> Vec<DVec3> {
        points
            .iter()
            .map(|p| self.world_from_source.transform_point3(p.xyz))
            .collect()
    }
}
