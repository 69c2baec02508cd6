//! Which of a scene's views a command reads.

use super::{Result, TrainError};
use crate::data::SplitIndices;

/// Which of a scene's views a command reads: `test`, `train`, `all` or indices such as
/// `0,8,16`, parsed when the command line is (before any device or file is touched).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ViewSet {
    /// The split's held-out views.
    Test,
    /// The split's training views.
    Train,
    /// The held-out views, then the training views.
    All,
    /// These views, in this order.
    Indices(Vec<usize>),
}

impl std::str::FromStr for ViewSet {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<ViewSet, String> {
        match s.trim() {
            "test" => Ok(ViewSet::Test),
            "train" => Ok(ViewSet::Train),
            "all" => Ok(ViewSet::All),
            list => list
                .split(',')
                .map(|v| v.trim().parse::<usize>())
                .collect::<std::result::Result<Vec<_>, _>>()
                .map(ViewSet::Indices)
                .map_err(|_| format!("`{s}`: use test, train, all or view indices like 0,8,16")),
        }
    }
}

impl std::fmt::Display for ViewSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ViewSet::Test => f.write_str("test"),
            ViewSet::Train => f.write_str("train"),
            ViewSet::All => f.write_str("all"),
            ViewSet::Indices(v) => {
                let s: Vec<String> = v.iter().map(usize::to_string).collect();
                f.write_str(&s.join(","))
            }
        }
    }
}

impl ViewSet {
    /// The view indices in `split` of a scene of `n` views; an index past the scene is an error
    /// naming `flag`.
    pub fn indices(&self, split: &SplitIndices, n: usize, flag: &str) -> Result<Vec<usize>> {
        Ok(match self {
            ViewSet::Test => split.test.clone(),
            ViewSet::Train => split.train.clone(),
            ViewSet::All => split.test.iter().chain(&split.train).copied().collect(),
            ViewSet::Indices(v) => {
                if let Some(i) = v.iter().find(|&&i| i >= n) {
                    return Err(TrainError::Usage(format!(
                        "{flag}: view {i} does not exist (the scene has {n})"
                    )));
                }
                v.clone()
            }
        })
    }
}
