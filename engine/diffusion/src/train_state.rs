//! Resumable training: [`crate::train::train`] saves its whole state at an interval (the
//! trained parameters with their identities, both AdamW states, the host RNG, the loss curve)
//! and continues from it, so a killed job loses at most one interval and ends where an
//! uninterrupted one ends.
//!
//! A save writes `step_NNNNNNNN.model.bpk`, `step_NNNNNNNN.adamw_unet.bpk` and
//! `step_NNNNNNNN.adamw_tokens.bpk` (burnpack, which keeps parameter ids, so the optimiser
//! states find their parameters again), each atomically, then `state.json`, atomically, which
//! names them; files of other steps are removed after that. A crash at any point leaves a
//! `state.json` whose files are complete.

use std::path::{Path, PathBuf};

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::ModuleOptimizer;
use burn::store::{BurnpackStore, ModuleSnapshot, PathFilter};
use burn::tensor::{Bytes, Tensor};
use serde::{Deserialize, Serialize};

use crate::lora::count_lora;
use crate::train_spec::{Augment, TrainImage, TrainSettings, Trainable};
use crate::weights::is_lora_path;
use crate::{DiffusionError, Result};

/// File that names the saved step.
pub const STATE_FILE: &str = "state.json";
const FORMAT: &str = "extranerf-diffusion-train-state";
const VERSION: u32 = 1;

/// Where [`crate::train::train`] keeps its resumable state and how often it saves it.
#[derive(Clone, Debug)]
pub struct Checkpointing {
    /// Folder of the state (created on the first save).
    pub dir: PathBuf,
    /// Steps between saves (the last step always saves).
    pub every: usize,
    /// Continue from the state in `dir`; without it, a state there is an error (it is
    /// someone's unfinished work).
    pub resume: bool,
    /// What else must be the same to continue (architecture, base model, ...): compared
    /// field by field on resume.
    pub identity: serde_json::Value,
}

/// What `state.json` holds.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SavedState {
    /// Always [`FORMAT`].
    pub format: String,
    /// Layout version.
    pub version: u32,
    /// Optimiser steps done.
    pub step: usize,
    /// State of the host generator after `step` steps.
    pub rng: u64,
    /// Loss reports so far (step, mean loss).
    pub curve: Vec<(usize, f64)>,
    /// Sum and count of the losses since the last report.
    pub pending: (f64, usize),
    /// Training seconds so far.
    pub seconds: f64,
    /// The settings (any `steps`: a run may be extended).
    pub settings: TrainSettings,
    /// The augmentation.
    pub augment: Augment,
    /// FNV-1a hash of the training images, known flags and masks.
    pub images: String,
    /// The caller's [`Checkpointing::identity`].
    pub identity: serde_json::Value,
    /// Trained parameters (burnpack).
    pub model: String,
    /// AdamW state of the U-Net (burnpack).
    pub adamw_unet: String,
    /// AdamW state of the tokens (burnpack).
    pub adamw_tokens: String,
}

/// What [`load`] restores.
pub(crate) struct Restored {
    /// The state file's contents.
    pub state: SavedState,
    /// The model with the saved parameters (and their ids).
    pub model: Trainable,
    /// The U-Net's optimiser.
    pub opt_unet: ModuleOptimizer,
    /// The tokens' optimiser.
    pub opt_tokens: ModuleOptimizer,
}

fn state_err(path: &Path, problem: impl std::fmt::Display) -> DiffusionError {
    DiffusionError::Input(format!("{}: {problem}", path.display()))
}

/// FNV-1a over the images' sizes and values: a resume on other images is refused.
pub fn images_hash(images: &[TrainImage]) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for b in bytes {
            h ^= u64::from(*b);
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
    };
    eat(&(images.len() as u64).to_le_bytes());
    for im in images {
        eat(&(im.width as u64).to_le_bytes());
        eat(&(im.height as u64).to_le_bytes());
        eat(&(im.masks.len() as u64).to_le_bytes());
        for v in im
            .rgb
            .iter()
            .chain(&im.known)
            .chain(im.masks.iter().flatten())
        {
            eat(&v.to_bits().to_le_bytes());
        }
        // An enhancer's corrupted versions (absent for an inpainter, whose hash is as before).
        if !im.guides.is_empty() {
            eat(&(im.guides.len() as u64).to_le_bytes());
            for g in &im.guides {
                for v in g.rgb.iter().chain(&g.mask) {
                    eat(&v.to_bits().to_le_bytes());
                }
            }
        }
    }
    format!("{h:016x}")
}

/// Which parameters a save holds: the adapters and tokens when the U-Net carries LoRA factors
/// (its base is frozen and comes from the model folder), else everything.
fn filter(model: &Trainable) -> PathFilter {
    fn adapters_and_tokens(path: &str, _container: &str) -> bool {
        is_lora_path(path) || path.starts_with("tokens.")
    }
    if count_lora(&model.unet) > 0 {
        PathFilter::new().with_predicate(adapters_and_tokens)
    } else {
        PathFilter::new().match_all()
    }
}

/// Number of parameters that receive gradients.
fn trainable_count<M: Module>(m: &M) -> usize {
    struct V(usize);
    impl ModuleVisitor for V {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            if p.val().is_require_grad() {
                self.0 += 1;
            }
        }
    }
    let mut v = V(0);
    m.visit(&mut v);
    v.0
}

fn step_file(step: usize, what: &str) -> String {
    format!("step_{step:08}.{what}.bpk")
}

/// Everything a save needs besides the model and optimisers.
#[derive(Debug)]
pub struct Snapshot<'a> {
    /// Steps done.
    pub step: usize,
    /// Generator state.
    pub rng: u64,
    /// Loss curve.
    pub curve: &'a [(usize, f64)],
    /// Unreported loss sum and count.
    pub pending: (f64, usize),
    /// Training seconds so far.
    pub seconds: f64,
    /// Settings.
    pub settings: &'a TrainSettings,
    /// Augmentation.
    pub augment: &'a Augment,
    /// [`images_hash`] of the images.
    pub images: &'a str,
}

/// Saves the state after `snap.step` steps (see the module docs for the order of writes).
pub fn save(
    ck: &Checkpointing,
    snap: &Snapshot,
    model: &Trainable,
    opt_unet: &ModuleOptimizer,
    opt_tokens: &ModuleOptimizer,
) -> Result<()> {
    let dir = &ck.dir;
    let mut store = BurnpackStore::from_bytes(None).with_filter(filter(model));
    model
        .save_into(&mut store)
        .map_err(|e| state_err(dir, format!("saving the parameters: {e}")))?;
    let bytes = store
        .get_bytes()
        .map_err(|e| state_err(dir, format!("saving the parameters: {e}")))?;
    let names = [
        step_file(snap.step, "model"),
        step_file(snap.step, "adamw_unet"),
        step_file(snap.step, "adamw_tokens"),
    ];
    crate::write_atomic(&dir.join(&names[0]), &bytes)?;
    for (opt, name) in [(opt_unet, &names[1]), (opt_tokens, &names[2])] {
        let bytes = opt
            .into_bytes()
            .map_err(|e| state_err(dir, format!("saving the optimiser state: {e:?}")))?;
        crate::write_atomic(&dir.join(name), &bytes)?;
    }
    let mut settings = snap.settings.clone();
    settings.steps = 0;
    let state = SavedState {
        format: FORMAT.into(),
        version: VERSION,
        step: snap.step,
        rng: snap.rng,
        curve: snap.curve.to_vec(),
        pending: snap.pending,
        seconds: snap.seconds,
        settings,
        augment: snap.augment.clone(),
        images: snap.images.into(),
        identity: ck.identity.clone(),
        model: names[0].clone(),
        adamw_unet: names[1].clone(),
        adamw_tokens: names[2].clone(),
    };
    let text = serde_json::to_string_pretty(&state)
        .map_err(|e| state_err(dir, format!("encoding the state: {e}")))?;
    crate::write_atomic(&dir.join(STATE_FILE), text.as_bytes())?;
    // The new state is in place: older steps' files, and the temporary files of a write a
    // crash cut short, can go (the folder holds nothing else).
    if let Ok(entries) = std::fs::read_dir(dir) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let old_step =
                name.starts_with("step_") && name.ends_with(".bpk") && !names.contains(&name);
            let torn = name.starts_with('.') && name.contains(".tmp");
            if old_step || torn {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    Ok(())
}

/// Reads `dir/state.json` alone (no weights): `None` when there is none.
pub fn peek(dir: &Path) -> Result<Option<SavedState>> {
    let path = dir.join(STATE_FILE);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(DiffusionError::io(&path, e)),
    };
    let state: SavedState = serde_json::from_str(&text)
        .map_err(|e| state_err(&path, format!("not a training state: {e}")))?;
    if state.format != FORMAT || state.version != VERSION {
        return Err(state_err(
            &path,
            format!(
                "format {:?} version {}, expected {FORMAT:?} version {VERSION}",
                state.format, state.version
            ),
        ));
    }
    for name in [&state.model, &state.adamw_unet, &state.adamw_tokens] {
        if name.contains(['/', '\\']) || !name.ends_with(".bpk") {
            return Err(state_err(&path, format!("names an odd file {name:?}")));
        }
    }
    if state.curve.iter().any(|c| c.0 > state.step) || state.pending.1 > state.step {
        return Err(state_err(
            &path,
            format!("a loss report past its step {}", state.step),
        ));
    }
    Ok(Some(state))
}

/// The fields of two JSON objects that differ, as "name: saved -> now".
fn differences(saved: &serde_json::Value, now: &serde_json::Value, prefix: &str) -> Vec<String> {
    match (saved, now) {
        (serde_json::Value::Object(a), serde_json::Value::Object(b)) => {
            let keys: std::collections::BTreeSet<&String> = a.keys().chain(b.keys()).collect();
            keys.into_iter()
                .flat_map(|k| {
                    let null = serde_json::Value::Null;
                    differences(
                        a.get(k).unwrap_or(&null),
                        b.get(k).unwrap_or(&null),
                        &format!("{prefix}{k}."),
                    )
                })
                .collect()
        }
        (a, b) if a == b => Vec::new(),
        (a, b) => vec![format!(
            "{}: {a} when saved, {b} now",
            prefix.trim_end_matches('.')
        )],
    }
}

/// Loads the state in `ck.dir` into `model` (built as for a fresh start) and two fresh
/// optimisers, after checking that it was saved by the same training: settings (but
/// `steps`), augmentation, images and identity.
pub(crate) fn load(
    ck: &Checkpointing,
    mut model: Trainable,
    opt_unet: ModuleOptimizer,
    opt_tokens: ModuleOptimizer,
    settings: &TrainSettings,
    augment: &Augment,
    images: &str,
) -> Result<Restored> {
    let dir = &ck.dir;
    let path = dir.join(STATE_FILE);
    let state = peek(dir)?.ok_or_else(|| {
        state_err(
            dir,
            "no training state to resume here (state.json is missing)",
        )
    })?;
    let mut now = settings.clone();
    now.steps = 0;
    fn to_json<T: Serialize>(v: &T) -> serde_json::Value {
        serde_json::to_value(v).unwrap_or(serde_json::Value::Null)
    }
    let mut diff = differences(&to_json(&state.settings), &to_json(&now), "");
    diff.extend(differences(
        &to_json(&state.augment),
        &to_json(augment),
        "augment.",
    ));
    diff.extend(differences(&state.identity, &ck.identity, ""));
    if state.images != images {
        diff.push(format!(
            "training images: hash {} when saved, {images} now (other views, holes or masks)",
            state.images
        ));
    }
    if !diff.is_empty() {
        return Err(state_err(
            &path,
            format!(
                "was saved by another training; resume with the same arguments (only --steps may change): {}",
                diff.join("; ")
            ),
        ));
    }
    if state.step > settings.steps {
        return Err(state_err(
            &path,
            format!(
                "holds step {}, past the {} steps asked for (raise --steps)",
                state.step, settings.steps
            ),
        ));
    }
    let read = |name: &str| -> Result<Bytes> {
        let p = dir.join(name);
        std::fs::read(&p)
            .map(Bytes::from_bytes_vec)
            .map_err(|e| DiffusionError::io(&p, e))
    };
    let mp = dir.join(&state.model);
    let mut store = BurnpackStore::from_bytes(Some(read(&state.model)?))
        .with_filter(filter(&model))
        .allow_partial(true)
        .validate(true);
    let res = model
        .load_from(&mut store)
        .map_err(|e| state_err(&mp, format!("loading the parameters: {e}")))?;
    let want = trainable_count(&model);
    if !res.errors.is_empty() || !res.unused.is_empty() || res.applied.len() < want {
        return Err(state_err(
            &mp,
            format!(
                "does not fit the model: {} of its {want} trained parameters applied, {} errors ({}), {} unused ({})",
                res.applied.len(),
                res.errors.len(),
                res.errors
                    .iter()
                    .take(3)
                    .map(|e| format!("{e:?}"))
                    .collect::<Vec<_>>()
                    .join("; "),
                res.unused.len(),
                res.unused.iter().take(3).cloned().collect::<Vec<_>>().join(", ")
            ),
        ));
    }
    let opt = |o: ModuleOptimizer, name: &str| -> Result<ModuleOptimizer> {
        o.from_bytes(read(name)?)
            .map_err(|e| state_err(&dir.join(name), format!("not an optimiser state: {e:?}")))
    };
    let opt_unet = opt(opt_unet, &state.adamw_unet)?;
    let opt_tokens = opt(opt_tokens, &state.adamw_tokens)?;
    Ok(Restored {
        state,
        model,
        opt_unet,
        opt_tokens,
    })
}
