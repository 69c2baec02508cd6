//! Evaluation splits: LLFF-style protocols computed from the cameras, and the split a data set
//! gives (NeRF-synthetic's split files).

use std::path::Path;

pub use super::scene::SplitIndices;
use super::{Camera, DataError, Result, Scene};

/// Which split to use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Split {
    /// ExtraNeRF view extrapolation: train on the 6 views whose centres are nearest the mean
    /// centre, test on the 8 farthest.
    Extrapolation,
    /// RegNeRF few-shot: test on every 8th view, train on `n` views spread evenly over the rest.
    FewShot(usize),
    /// LLFF's hold-out: test on every 8th view (0, 8, 16, ...), train on all the others.
    Holdout,
    /// Train on every view, test on none.
    All,
    /// The data set's own split (NeRF-synthetic: train on `transforms_train.json`, test on
    /// `transforms_test.json`).
    Given,
}

/// The split's name, as configs and the command line give it (the few-shot count apart).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum SplitKind {
    /// A capture's own views: every 8th view is held out for evaluation (LLFF's convention),
    /// all the others train. The default for a scene without split files.
    Holdout,
    /// ExtraNeRF's benchmark: the 6 views nearest the rig's centre train, the 8 farthest are
    /// held out.
    Extrapolation,
    /// RegNeRF's: every 8th view held out, the few-shot count spread over the rest.
    #[cfg_attr(feature = "clap", value(name = "fewshot"))]
    FewShot,
    /// Every view trains, none is held out.
    All,
    /// The data set's own split files: NeRF-synthetic's transforms_train.json trains,
    /// transforms_test.json is held out.
    Given,
}

impl SplitKind {
    /// The default split for a scene folder: `given` when it holds split files
    /// (`transforms_train.json`), else `holdout` (the capture trains on its views; the
    /// benchmark splits are asked for by name).
    pub fn default_for(dir: &Path) -> SplitKind {
        if super::transforms::has_split_files(dir) {
            SplitKind::Given
        } else {
            SplitKind::Holdout
        }
    }

    /// The split, with `fewshot_views` training views for the few-shot one.
    pub fn split(self, fewshot_views: usize) -> Split {
        match self {
            SplitKind::Holdout => Split::Holdout,
            SplitKind::Extrapolation => Split::Extrapolation,
            SplitKind::FewShot => Split::FewShot(fewshot_views),
            SplitKind::All => Split::All,
            SplitKind::Given => Split::Given,
        }
    }

    /// The name in configs and reports.
    pub fn name(self) -> &'static str {
        match self {
            SplitKind::Holdout => "holdout",
            SplitKind::Extrapolation => "extrapolation",
            SplitKind::FewShot => "fewshot",
            SplitKind::All => "all",
            SplitKind::Given => "given",
        }
    }
}

/// Number of training views of the extrapolation protocol.
pub const EXTRAPOLATION_TRAIN: usize = 6;
/// Number of test views of the extrapolation protocol.
pub const EXTRAPOLATION_TEST: usize = 8;

impl Split {
    /// Applies the split to `scene`: the given split from its split files, the others from
    /// its cameras.
    pub fn apply_to(self, scene: &Scene) -> Result<SplitIndices> {
        if self != Split::Given {
            return self.apply(&scene.cameras);
        }
        let missing = |p: String| DataError::Malformed {
            path: scene.source.clone(),
            problem: p,
        };
        match &scene.given {
            None => Err(missing(format!(
                "--split given needs the data set's split files ({}, {}), which this scene \
                 does not have; choose extrapolation, fewshot or all",
                super::transforms::SPLIT_FILES[0],
                super::transforms::SPLIT_FILES[2]
            ))),
            Some(g) if g.test.is_empty() => Err(DataError::Malformed {
                path: scene.source.join(super::transforms::SPLIT_FILES[2]),
                problem: "no such file: --split given tests on it (choose --split all to \
                          train without held-out views)"
                    .into(),
            }),
            Some(g) => Ok(g.clone()),
        }
    }

    /// Applies a split computed from the cameras (not [`Split::Given`]) to `cameras`.
    pub fn apply(self, cameras: &[Camera]) -> Result<SplitIndices> {
        let n = cameras.len();
        let err = |p: String| DataError::Malformed {
            path: "split".into(),
            problem: p,
        };
        match self {
            Split::Given => Err(err(
                "the given split comes from the scene's split files: use apply_to".into(),
            )),
            Split::All => Ok(SplitIndices {
                train: (0..n).collect(),
                test: vec![],
            }),
            Split::Holdout => {
                if n < 2 {
                    return Err(err(format!(
                        "holding out every 8th view needs at least 2 views, the scene has {n}; \
                         pass --split all to train on every view"
                    )));
                }
                Ok(SplitIndices {
                    train: (0..n).filter(|i| i % 8 != 0).collect(),
                    test: (0..n).step_by(8).collect(),
                })
            }
            Split::Extrapolation => {
                if n < EXTRAPOLATION_TRAIN + EXTRAPOLATION_TEST {
                    return Err(err(format!(
                        "the extrapolation split (ExtraNeRF's benchmark: 6 central views train, \
                         the 8 farthest are held out) needs at least 14 views, the scene has {n}; \
                         leave --split out to hold out every 8th view, or pass --split all to \
                         train on every view"
                    )));
                }
                let mean = cameras.iter().map(Camera::centre).sum::<glam::DVec3>() / n as f64;
                let mut order: Vec<usize> = (0..n).collect();
                // Ties keep file order, so the split is deterministic.
                order.sort_by(|&a, &b| {
                    cameras[a]
                        .centre()
                        .distance(mean)
                        .total_cmp(&cameras[b].centre().distance(mean))
                        .then(a.cmp(&b))
                });
                let mut train = order[..EXTRAPOLATION_TRAIN].to_vec();
                let mut test = order[n - EXTRAPOLATION_TEST..].to_vec();
                train.sort_unstable();
                test.sort_unstable();
                Ok(SplitIndices { train, test })
            }
            Split::FewShot(k) => {
                let test: Vec<usize> = (0..n).step_by(8).collect();
                let rest: Vec<usize> = (0..n).filter(|i| i % 8 != 0).collect();
                if k == 0 || k > rest.len() {
                    return Err(err(format!(
                        "few-shot with {k} training views: choose 1 to {} (--fewshot-views) for \
                         this scene of {n} views, or leave --split out to train on every view \
                         but every 8th",
                        rest.len()
                    )));
                }
                // RegNeRF: indices round(linspace(0, len - 1, k)) with Python's round-half-even.
                let train = (0..k)
                    .map(|j| {
                        let x = if k == 1 {
                            0.0
                        } else {
                            j as f64 * (rest.len() - 1) as f64 / (k - 1) as f64
                        };
                        rest[x.round_ties_even() as usize]
                    })
                    .collect();
                Ok(SplitIndices { train, test })
            }
        }
    }
}
