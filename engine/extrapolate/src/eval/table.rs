//! The comparison table of an extrapolate run: a row per field, its cells and its markdown.

use serde::Serialize;

use crate::eval::kid::KidReport;

/// One row of the table.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Row {
    pub variant: String,
    pub psnr: f64,
    pub ssim: f64,
    pub lpips: Option<f64>,
    pub psnr_masked: Option<f64>,
    pub ssim_masked: Option<f64>,
    pub lpips_masked: Option<f64>,
    pub psnr_visible: Option<f64>,
    /// Full-frame KID (mean and standard deviation over subsets).
    pub kid: Option<f64>,
    pub kid_std: Option<f64>,
    /// Patch KID on crops over the not-visible mask.
    pub kid_patch: Option<f64>,
    pub kid_patch_std: Option<f64>,
    /// Mean share of each view's pixels in the mask.
    pub masked_fraction: f64,
    /// With exact visibility masks ([`crate::eval::compare`]'s `truth_masks`): PSNR over the pixels that
    /// no two training cameras truly see, and over those they do (means over the views with
    /// a mask that has such pixels).
    pub psnr_not_visible_exact: Option<f64>,
    pub psnr_visible_exact: Option<f64>,
}

/// The table of an extrapolate run.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Table {
    /// The scored views: the held-out ones, or the training views where none is held out.
    pub views: Vec<usize>,
    /// Whether `views` are held out ([`crate::shown::Shown`]).
    pub held_out: bool,
    pub rows: Vec<Row>,
    /// How KID was measured (absent when it was not).
    pub kid: Option<KidReport>,
    /// What the run's stages said of a row (a stage 3 that its gate skipped).
    pub notes: Vec<String>,
    /// The exact visibility masks the table was also scored with, if any.
    pub truth_masks: Option<TruthMasks>,
}

/// The table's column headers (the two exact-visibility columns only where the table was
/// scored with exact masks, [`Table::columns`]).
pub const COLUMNS: [&str; 11] = [
    "variant",
    "PSNR",
    "SSIM",
    "LPIPS-alex",
    "PSNR masked",
    "SSIM masked",
    "LPIPS masked",
    "PSNR visible",
    "KID",
    "patch KID",
    "masked",
];

/// The headers of the exact-visibility columns.
pub const EXACT_COLUMNS: [&str; 2] = ["PSNR not visible (exact)", "PSNR visible (exact)"];

impl Row {
    /// The row's cells as the tables print them (`-` where a value is missing); with `exact`,
    /// the exact-visibility cells too.
    pub fn cells(&self, exact: bool) -> Vec<String> {
        let f = |v: Option<f64>, d: usize| v.map_or("-".into(), |x| format!("{x:.d$}"));
        let mut c = vec![
            self.variant.clone(),
            format!("{:.2}", self.psnr),
            format!("{:.3}", self.ssim),
            f(self.lpips, 3),
            f(self.psnr_masked, 2),
            f(self.ssim_masked, 3),
            f(self.lpips_masked, 3),
            f(self.psnr_visible, 2),
            f(self.kid, 4),
            f(self.kid_patch, 4),
            format!("{:.1}%", 100.0 * self.masked_fraction),
        ];
        if exact {
            c.push(f(self.psnr_not_visible_exact, 2));
            c.push(f(self.psnr_visible_exact, 2));
        }
        c
    }
}

impl Table {
    /// The column headers of this table.
    pub fn columns(&self) -> Vec<&'static str> {
        let mut c = COLUMNS.to_vec();
        if self.truth_masks.is_some() {
            c.extend(EXACT_COLUMNS);
        }
        c
    }

    /// Each row's cells, as [`Table::columns`] names them.
    pub fn cells(&self) -> Vec<Vec<String>> {
        let exact = self.truth_masks.is_some();
        self.rows.iter().map(|r| r.cells(exact)).collect()
    }

    /// The table in Markdown.
    pub fn markdown(&self) -> String {
        let cols = self.columns();
        let mut s = format!("| {} |\n|{}\n", cols.join(" | "), "---|".repeat(cols.len()));
        for r in self.cells() {
            s += &format!("| {} |\n", r.join(" | "));
        }
        if let Some(t) = &self.truth_masks {
            s += &format!("\n{}\n", t.describe());
        }
        if let Some(k) = &self.kid {
            s += &format!("\n{}\n", k.describe());
        }
        for n in &self.notes {
            s += &format!("\n{n}\n");
        }
        s
    }
}

/// Exact visibility masks of the held-out views (`../shared/data/synth2/gt_visibility`, or the
/// demo scene's): where they come from and how much of the views they mark unseen.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TruthMasks {
    pub dir: std::path::PathBuf,
    /// Held-out views that have a mask.
    pub views: Vec<usize>,
    /// Mean share of those views' pixels that is not visible.
    pub not_visible_fraction: f64,
}

impl TruthMasks {
    /// One line for the table's readers.
    pub fn describe(&self) -> String {
        format!(
            "Exact visibility from {} ({} of the held-out views; {:.1}% of their pixels not visible to two training cameras): `PSNR not visible (exact)` and `PSNR visible (exact)`.",
            self.dir.display(),
            self.views.len(),
            100.0 * self.not_visible_fraction
        )
    }
}
