//! Noise schedules: DDPM training noise (linear, scaled-linear and cosine betas; epsilon and v
//! prediction) and DDIM sampling from an image noised to a strength, with optional
//! classifier-free guidance. The coefficients are computed on the host in f64 and applied to
//! device tensors per batch item, so a sampling loop never reads a tensor back.

use std::path::Path;

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use burn::tensor::{Device, Tensor};

use crate::DiffusionError;

/// How betas grow over the training timesteps.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BetaSchedule {
    /// Linear from beta_start to beta_end.
    Linear,
    /// Linear in sqrt(beta) (Stable Diffusion).
    ScaledLinear,
    /// The cosine schedule of Nichol & Dhariwal, betas capped at 0.999.
    #[serde(rename = "squaredcos_cap_v2")]
    SquaredCosCapV2,
}

/// The largest `num_train_timesteps` a schedule takes.
pub const MAX_TRAIN_TIMESTEPS: usize = 1 << 20;

/// What the network predicts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Prediction {
    /// The added noise.
    Epsilon,
    /// v = sqrt(a) eps - sqrt(1 - a) x0 (Salimans & Ho).
    #[serde(rename = "v_prediction")]
    #[cfg_attr(feature = "clap", value(name = "v_prediction"))]
    V,
    /// The clean image x0 itself (diffusers' "sample").
    Sample,
}

fn d_t() -> usize {
    1000
}
fn d_bs() -> f64 {
    0.00085
}
fn d_be() -> f64 {
    0.012
}
fn d_sched() -> BetaSchedule {
    BetaSchedule::ScaledLinear
}
fn d_pred() -> Prediction {
    Prediction::Epsilon
}

/// diffusers' `scheduler_config.json` (DDPM/DDIM/PNDM fields that define the noise process).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SchedulerConfig {
    /// Training timesteps.
    #[serde(default = "d_t")]
    pub num_train_timesteps: usize,
    /// First beta.
    #[serde(default = "d_bs")]
    pub beta_start: f64,
    /// Last beta.
    #[serde(default = "d_be")]
    pub beta_end: f64,
    /// Beta schedule.
    #[serde(default = "d_sched")]
    pub beta_schedule: BetaSchedule,
    /// What the model predicts.
    #[serde(default = "d_pred")]
    pub prediction_type: Prediction,
    /// Sampler-specific keys (spacing, offsets, clipping): not used by this DDIM, which
    /// defines its own spacing from a strength ([`ddim_timesteps`]).
    #[serde(flatten)]
    pub other: Map<String, Value>,
}

impl Default for SchedulerConfig {
    /// Stable Diffusion's: 1000 steps, scaled-linear 0.00085..0.012, epsilon.
    fn default() -> Self {
        serde_json::from_str("{}").unwrap_or_else(|_| unreachable!("all fields have defaults"))
    }
}

impl SchedulerConfig {
    /// The noise process of the pixel-space models trained here: cosine betas and
    /// `prediction` (v-prediction is stable at every noise level for a small pixel model).
    pub fn pixel_space(prediction: Prediction) -> SchedulerConfig {
        SchedulerConfig {
            beta_schedule: BetaSchedule::SquaredCosCapV2,
            prediction_type: prediction,
            ..SchedulerConfig::default()
        }
    }

    /// Parses `scheduler_config.json`. Keys that change the noise process and are not
    /// modelled (`trained_betas`, `rescale_betas_zero_snr`, `thresholding`) must be off; the
    /// sampler-spacing keys (`timestep_spacing`, `steps_offset`, `set_alpha_to_one`,
    /// `clip_sample`, ...) are ignored because [`ddim_timesteps`] defines the spacing.
    pub fn from_file(path: &Path) -> Result<SchedulerConfig, DiffusionError> {
        let c: SchedulerConfig = crate::config::read_json(path)?;
        for (key, off) in [
            ("trained_betas", serde_json::Value::Null),
            ("rescale_betas_zero_snr", serde_json::Value::Bool(false)),
            ("thresholding", serde_json::Value::Bool(false)),
        ] {
            if let Some(v) = c.other.get(key) {
                if *v != off {
                    return Err(DiffusionError::Config {
                        path: path.to_path_buf(),
                        problem: format!("{key} = {v} is not supported (supported: {off})"),
                    });
                }
            }
        }
        Schedule::new(&c).map_err(|problem| DiffusionError::Config {
            path: path.to_path_buf(),
            problem,
        })?;
        Ok(c)
    }

    /// Writes `scheduler_config.json`.
    pub fn save(&self, path: &Path) -> Result<(), DiffusionError> {
        crate::config::write_json(path, self)
    }
}

/// The noise process: cumulative alphas per training timestep.
#[derive(Clone, Debug)]
pub struct Schedule {
    alphas_cumprod: Vec<f64>,
    prediction: Prediction,
}

impl Schedule {
    /// The schedule of a config, or what is wrong with it.
    pub fn new(c: &SchedulerConfig) -> Result<Schedule, String> {
        let n = c.num_train_timesteps;
        // Diffusers trains with 1000; a table of more than a million steps is a corrupt file
        // (it would also be allocated here whole).
        if !(2..=MAX_TRAIN_TIMESTEPS).contains(&n) {
            return Err(format!(
                "num_train_timesteps = {n} must be 2 to {MAX_TRAIN_TIMESTEPS}"
            ));
        }
        let betas: Vec<f64> = match c.beta_schedule {
            BetaSchedule::Linear => (0..n)
                .map(|i| c.beta_start + (c.beta_end - c.beta_start) * i as f64 / (n - 1) as f64)
                .collect(),
            BetaSchedule::ScaledLinear => {
                let (a, b) = (c.beta_start.sqrt(), c.beta_end.sqrt());
                (0..n)
                    .map(|i| (a + (b - a) * i as f64 / (n - 1) as f64).powi(2))
                    .collect()
            }
            BetaSchedule::SquaredCosCapV2 => {
                let f = |t: f64| {
                    ((t + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2)
                        .cos()
                        .powi(2)
                };
                (0..n)
                    .map(|i| {
                        let (t1, t2) = (i as f64 / n as f64, (i + 1) as f64 / n as f64);
                        (1.0 - f(t2) / f(t1)).min(0.999)
                    })
                    .collect()
            }
        };
        if let Some(b) = betas.iter().find(|b| !(**b > 0.0 && **b < 1.0)) {
            return Err(format!(
                "betas must lie in (0, 1); beta_start = {}, beta_end = {} give {b}",
                c.beta_start, c.beta_end
            ));
        }
        let mut acc = 1.0;
        let alphas_cumprod = betas
            .iter()
            .map(|b| {
                acc *= 1.0 - b;
                acc
            })
            .collect();
        Ok(Schedule {
            alphas_cumprod,
            prediction: c.prediction_type,
        })
    }

    /// Training timesteps.
    pub fn len(&self) -> usize {
        self.alphas_cumprod.len()
    }

    /// Never empty (at least 2 timesteps).
    pub fn is_empty(&self) -> bool {
        false
    }

    /// What the model predicts.
    pub fn prediction(&self) -> Prediction {
        self.prediction
    }

    /// Cumulative alpha at timestep t (1 for None: the clean image).
    pub fn alpha_bar(&self, t: Option<usize>) -> f64 {
        t.map_or(1.0, |t| self.alphas_cumprod[t.min(self.len() - 1)])
    }

    /// Noise standard deviation sqrt(1 - alpha_bar) at t: the noise level a NeRF loss weights
    /// its diffusion targets by (w(t)).
    pub fn noise_level(&self, t: usize) -> f64 {
        (1.0 - self.alpha_bar(Some(t))).sqrt()
    }

    /// The starting timestep for a strength in (0, 1]: linear in the timestep index, as
    /// diffusers' img2img and inpainting pipelines map it (strength 1 = the last timestep,
    /// sampled from pure noise). The noise level there is [`Schedule::noise_level`].
    pub fn timestep_for_strength(&self, strength: f64) -> usize {
        let s = strength.clamp(0.0, 1.0);
        ((s * (self.len() - 1) as f64).round() as usize).min(self.len() - 1)
    }

    fn per_item(values: impl Iterator<Item = f64>, device: &Device) -> Tensor<4> {
        let v: Vec<f32> = values.map(|x| x as f32).collect();
        let n = v.len();
        Tensor::<1>::from_floats(v.as_slice(), device).reshape([n, 1, 1, 1])
    }

    /// x_t = sqrt(a) x0 + sqrt(1 - a) eps, one timestep per batch item.
    pub fn add_noise(&self, x0: Tensor<4>, noise: Tensor<4>, t: &[usize]) -> Tensor<4> {
        let d = x0.device();
        let a = Self::per_item(t.iter().map(|&t| self.alpha_bar(Some(t)).sqrt()), &d);
        let b = Self::per_item(
            t.iter().map(|&t| (1.0 - self.alpha_bar(Some(t))).sqrt()),
            &d,
        );
        x0 * a + noise * b
    }

    /// The training target: the noise, v = sqrt(a) eps - sqrt(1 - a) x0, or x0.
    pub fn target(&self, x0: Tensor<4>, noise: Tensor<4>, t: &[usize]) -> Tensor<4> {
        match self.prediction {
            Prediction::Epsilon => noise,
            Prediction::Sample => x0,
            Prediction::V => {
                let d = x0.device();
                let a = Self::per_item(t.iter().map(|&t| self.alpha_bar(Some(t)).sqrt()), &d);
                let b = Self::per_item(
                    t.iter().map(|&t| (1.0 - self.alpha_bar(Some(t))).sqrt()),
                    &d,
                );
                noise * a - x0 * b
            }
        }
    }

    /// (predicted noise, predicted x0) from the model output at x_t (one shared timestep).
    pub fn split(&self, out: Tensor<4>, x_t: Tensor<4>, t: usize) -> (Tensor<4>, Tensor<4>) {
        let a = self.alpha_bar(Some(t));
        let (sa, sb) = (a.sqrt(), (1.0 - a).sqrt());
        match self.prediction {
            Prediction::Epsilon => {
                let x0 = (x_t - out.clone() * sb) / sa;
                (out, x0)
            }
            Prediction::V => {
                let x0 = x_t.clone() * sa - out.clone() * sb;
                let eps = out * sa + x_t * sb;
                (eps, x0)
            }
            Prediction::Sample => {
                // sqrt(1 - a) > 0 at every training timestep (betas in (0, 1)).
                let eps = (x_t - out.clone() * sa) / sb.max(1e-12);
                (eps, out)
            }
        }
    }

    /// One deterministic DDIM step (eta = 0) from t to `t_prev` (None = the clean image):
    /// x_prev = sqrt(a_prev) x0 + sqrt(1 - a_prev) eps.
    pub fn ddim_step(
        &self,
        out: Tensor<4>,
        x_t: Tensor<4>,
        t: usize,
        t_prev: Option<usize>,
    ) -> Tensor<4> {
        let (eps, x0) = self.split(out, x_t, t);
        let ap = self.alpha_bar(t_prev);
        x0 * ap.sqrt() + eps * (1.0 - ap).sqrt()
    }
}

/// The DDIM timesteps that start from an image noised to `strength` (the training timestep
/// [`Schedule::timestep_for_strength`]) and reach the clean image in `steps` steps, evenly
/// spaced and descending; the step after the last one is the clean image.
/// With more steps than timesteps below the start, every timestep from the start down to 0 is
/// visited once.
pub fn ddim_timesteps(schedule: &Schedule, strength: f64, steps: usize) -> Vec<usize> {
    let start = schedule.timestep_for_strength(strength);
    if steps > start {
        return (0..=start).rev().collect();
    }
    // Spacing start / steps >= 1, so the rounded timesteps are distinct.
    let steps = steps.max(1);
    (0..steps)
        .map(|i| {
            let f = 1.0 - i as f64 / steps as f64;
            (start as f64 * f).round() as usize
        })
        .collect()
}

/// Classifier-free guidance: uncond + g (cond - uncond).
pub fn guide(cond: Tensor<4>, uncond: Tensor<4>, scale: f64) -> Tensor<4> {
    uncond.clone() + (cond - uncond) * scale
}
