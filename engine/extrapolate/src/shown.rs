//! The views a run shows and scores: its held-out views, or where its split holds none out
//! (`--split all`) its training views, so that such a run still has renders beside the photos
//! in its report and a table, which then measures how well each field keeps what the cameras
//! saw rather than how it generalises.

use extranerf_nerf::data::SplitIndices;

/// The views a run renders for `eval` and its report, and how their files are named.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Shown {
    /// Scene indices of the views, ascending.
    pub views: Vec<usize>,
    /// True: the held-out views (`test_NNN`); false: the training views (`train_NNN`) of a
    /// split that holds none out.
    pub held_out: bool,
}

impl Shown {
    /// The held-out views of `split`, else its training views.
    pub fn of(split: &SplitIndices) -> Shown {
        if split.test.is_empty() {
            let mut views = split.train.clone();
            views.sort_unstable();
            Shown {
                views,
                held_out: false,
            }
        } else {
            Shown {
                views: split.test.clone(),
                held_out: true,
            }
        }
    }

    /// The file stem of view `i`: `test_NNN` or `train_NNN`.
    pub fn name(&self, i: usize) -> String {
        format!("{}_{i:03}", if self.held_out { "test" } else { "train" })
    }

    /// What the views are, in words (the table, the report and `eval`).
    pub fn label(&self) -> &'static str {
        if self.held_out {
            "held-out views"
        } else {
            "training views (the split holds no view out)"
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn held_out_views_else_the_training_views() {
        let split = |train: Vec<usize>, test: Vec<usize>| SplitIndices { train, test };
        let s = Shown::of(&split(vec![1, 2, 3], vec![0, 8]));
        assert_eq!((s.views.clone(), s.held_out), (vec![0, 8], true));
        assert_eq!(s.name(8), "test_008");
        let s = Shown::of(&split(vec![3, 1, 2], vec![]));
        assert_eq!((s.views.clone(), s.held_out), (vec![1, 2, 3], false));
        assert_eq!(s.name(12), "train_012");
        assert!(s.label().contains("no view out"));
    }
}
