//! What a diffusion training run is given: its images (with an enhancer's guides), the
//! augmentation, the settings, and the model it trains ([`crate::train::train`] runs it,
//! [`crate::train_state`] saves and resumes it).

use burn::module::Module;
use serde::{Deserialize, Serialize};

use crate::text::LearnedTokens;
use crate::unet::UNet2DConditionModel;
use crate::{DiffusionError, Result};

/// A training image with what is known of it.
#[derive(Clone, Debug)]
pub struct TrainImage {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// `[h, w, 3]` in [0, 1].
    pub rgb: Vec<f32>,
    /// `[h, w]`: 1 where the pixel may be seen and trained on, 0 where it is unknown.
    pub known: Vec<f32>,
    /// `[h, w]` hole masks to train with besides the random ones (pseudo-disocclusion masks):
    /// 1 = hole.
    pub masks: Vec<Vec<f32>>,
    /// Corrupted versions of this image for an enhancer ([`crate::inpaint::Task::Enhance`]):
    /// a batch item shows one of them, whole, as guidance and learns the image. Empty for an
    /// inpainter.
    pub guides: Vec<Guide>,
}

/// A corrupted version of a training image (a NeRF render of its view) and where an
/// earlier stage filled it in: the enhancer's input for that image.
#[derive(Clone, Debug)]
pub struct Guide {
    /// `[h, w, 3]` in [0, 1].
    pub rgb: Vec<f32>,
    /// `[h, w]`: 1 where the render's supervision came from an inpainter.
    pub mask: Vec<f32>,
}

impl TrainImage {
    /// An image that is entirely known, with no masks of its own.
    pub fn new(width: usize, height: usize, rgb: Vec<f32>) -> TrainImage {
        TrainImage {
            width,
            height,
            known: vec![1.0; width * height],
            rgb,
            masks: Vec::new(),
            guides: Vec::new(),
        }
    }

    pub(crate) fn check(&self, i: usize) -> Result<()> {
        let n = self.width * self.height;
        if self.rgb.len() != 3 * n
            || self.known.len() != n
            || self.masks.iter().any(|m| m.len() != n)
            || self
                .guides
                .iter()
                .any(|g| g.rgb.len() != 3 * n || g.mask.len() != n)
        {
            return Err(DiffusionError::Input(format!(
                "training image {i}: {}x{} but {} colour values, {} known flags, masks of {:?}, guides of {:?}",
                self.width,
                self.height,
                self.rgb.len(),
                self.known.len(),
                self.masks.iter().map(Vec::len).collect::<Vec<_>>(),
                self.guides
                    .iter()
                    .map(|g| (g.rgb.len(), g.mask.len()))
                    .collect::<Vec<_>>()
            )));
        }
        if let Some(v) = self
            .rgb
            .iter()
            .chain(self.guides.iter().flat_map(|g| &g.rgb))
            .find(|v| !v.is_finite())
        {
            return Err(DiffusionError::Input(format!(
                "training image {i} has a non-finite value {v}"
            )));
        }
        Ok(())
    }
}

/// Augmentation and masking of the training batches.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Augment {
    /// Crop side in pixels (a multiple of the model's size multiple).
    pub crop: usize,
    /// Random horizontal flips.
    pub flip: bool,
    /// Colour jitter: brightness and contrast factors in 1 +- this, saturation too.
    pub jitter: f64,
    /// Probability that an image's own mask (when it has any) is the hole instead of a random
    /// one.
    pub own_mask_probability: f64,
    /// Random holes: rectangles and strokes covering about this fraction of the crop at most.
    pub max_hole_fraction: f64,
}

impl Default for Augment {
    fn default() -> Self {
        Augment {
            crop: 64,
            flip: true,
            jitter: 0.1,
            own_mask_probability: 0.5,
            max_hole_fraction: 0.5,
        }
    }
}

/// What to train and how fast.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainSettings {
    /// Optimiser steps.
    pub steps: usize,
    /// Crops per step.
    pub batch: usize,
    /// AdamW learning rate of the U-Net's trainable parameters (all of them from scratch, the
    /// adapters when fine-tuning).
    pub lr: f64,
    /// Learning rate of the conditioning tokens.
    pub token_lr: f64,
    /// Linear warm-up steps.
    pub warmup: usize,
    /// Seed of crops, masks, timesteps and noise.
    pub seed: u64,
    /// Read the loss back every this many steps (each read waits for the device).
    pub log_every: usize,
    /// Gradient norm clip (0 = off), applied per parameter tensor (burn's Norm clipping), not
    /// to the global norm.
    pub clip: f64,
    /// Fraction of batch items conditioned on the null context (classifier-free guidance needs
    /// it trained; 0 for LoRA fine-tuning of a model that already has it).
    pub cond_dropout: f64,
    /// Train on the first this fraction of the schedule's timesteps only (an enhancer starts
    /// from a lightly noised render and never sees the rest); 1: all of them.
    #[serde(default = "all_timesteps")]
    pub max_strength: f64,
    /// The U-Net's output is added to its guidance before the loss
    /// ([`crate::inpaint::Task::EnhanceResidual`]; with an enhancer's guides and the
    /// `sample` prediction).
    #[serde(default)]
    pub residual: bool,
}

fn all_timesteps() -> f64 {
    1.0
}

impl Default for TrainSettings {
    fn default() -> Self {
        TrainSettings {
            steps: 1000,
            batch: 8,
            lr: 1e-3,
            token_lr: 1e-3,
            warmup: 50,
            seed: 0,
            log_every: 25,
            clip: 1.0,
            cond_dropout: 0.1,
            max_strength: 1.0,
            residual: false,
        }
    }
}

/// The model being trained: U-Net and conditioning tokens.
#[derive(Module, Debug)]
pub struct Trainable {
    /// The U-Net.
    pub unet: UNet2DConditionModel,
    /// The tokens.
    pub tokens: LearnedTokens,
}
