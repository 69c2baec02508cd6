//! Where the training driver's and the pipeline's progress and notes go: a [`Reporter`] that
//! the caller supplies (the command line draws them as progress bars or log lines).

/// Where the driver's progress and notes go (the command line draws them).
pub trait Reporter {
    /// A line of information: the model, the budget's decisions, a held-out evaluation.
    fn note(&mut self, line: &str);
    /// Progress after a window of steps (or views: a stage's progress counts its own units).
    fn progress(&mut self, p: &Progress);
    /// A pipeline stage starts (progress from here on is that stage's).
    fn stage(&mut self, _name: &str) {}
}

/// What a [`Progress`] counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Unit {
    /// Training steps (loss, PSNR and pace apply).
    #[default]
    Steps,
    /// Views rendered, mapped or inpainted (only the counts and seconds apply).
    Views,
    /// Optimiser steps of a model without a batch PSNR or a pace in samples (the stage-3
    /// enhancer): the loss, seconds and ETA apply.
    ModelSteps,
}

/// A training loop's progress after a window of steps, or a stage's over its views.
#[derive(Clone, Debug, PartialEq)]
pub struct Progress {
    /// What `step` and `total` count.
    pub unit: Unit,
    /// Steps done and planned (a budget re-fits the plan).
    pub step: u32,
    pub total: u32,
    /// Mean loss and batch PSNR of the window.
    pub loss: f64,
    pub psnr: f64,
    /// Samples per second and training seconds of this run so far (evaluations left out).
    pub samples_per_s: f64,
    pub secs: f64,
    /// Seconds left at this pace.
    pub eta: f64,
}

/// A reporter that keeps nothing (probes, tests).
#[derive(Clone, Copy, Debug, Default)]
pub struct Quiet;

impl Reporter for Quiet {
    fn note(&mut self, _line: &str) {}
    fn progress(&mut self, _p: &Progress) {}
}
