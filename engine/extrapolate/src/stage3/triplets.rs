//! The enhancer's training data on disk: per training view its photo and pseudo mask, and the
//! corrupted renders (`RUN/stage3-data/triplets.*`).

use std::path::Path;

use extranerf_diffusion::train::{Guide, TrainImage};
use extranerf_nerf::safetensors::{SafeTensors, Tensor};
use serde::{Deserialize, Serialize};

use crate::error::{read_text, write_json, ExtrapolateError, Result};

/// The triplets' tensors.
pub const TRIPLETS_FILE: &str = "triplets.safetensors";
/// Where each triplet came from.
pub const TRIPLETS_INDEX: &str = "triplets.json";

/// One entry of [`TRIPLETS_INDEX`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TripletEntry {
    /// Key of its tensors (`KEY.render`, `KEY.mask`).
    pub key: String,
    /// The training view (its slot in the split's training list).
    pub slot: usize,
    /// What rendered it: `fresh@STEPS`, `base` or `inpainted@ROUND`.
    pub source: String,
}

/// The training data of the enhancer: per training view its photo and pseudo mask at the
/// virtual views' scale, and the corrupted renders.
#[derive(Clone, Debug)]
pub struct Triplets {
    pub width: usize,
    pub height: usize,
    /// `[h, w, 3]` per training view.
    pub photos: Vec<Vec<f32>>,
    /// `[h, w]` per training view: 1 where no other training camera saw it.
    pub masks: Vec<Vec<f32>>,
    pub entries: Vec<TripletEntry>,
    /// `[h, w, 3]` render and `[h, w]` mask (where the inpainter supervised it) per entry.
    pub renders: Vec<(Vec<f32>, Vec<f32>)>,
}

impl Triplets {
    /// Writes `dir/triplets.safetensors` and `dir/triplets.json`.
    pub fn save(&self, dir: &Path) -> Result<()> {
        let (w, h) = (self.width, self.height);
        let mut st = SafeTensors::default();
        let mut put = |name: String, shape: Vec<usize>, data: &[f32]| {
            st.tensors.insert(
                name,
                Tensor {
                    shape,
                    data: data.to_vec(),
                },
            );
        };
        for (i, (p, m)) in self.photos.iter().zip(&self.masks).enumerate() {
            put(format!("photo_{i:03}"), vec![h, w, 3], p);
            put(format!("pseudo_mask_{i:03}"), vec![h, w], m);
        }
        for (e, (r, m)) in self.entries.iter().zip(&self.renders) {
            put(format!("{}.render", e.key), vec![h, w, 3], r);
            put(format!("{}.mask", e.key), vec![h, w], m);
        }
        st.write(&dir.join(TRIPLETS_FILE))?;
        write_json(&dir.join(TRIPLETS_INDEX), &self.entries)
    }

    /// Reads what [`Triplets::save`] wrote.
    pub fn load(dir: &Path) -> Result<Triplets> {
        let path = dir.join(TRIPLETS_FILE);
        let index = dir.join(TRIPLETS_INDEX);
        let st = SafeTensors::read(&path)?;
        let entries: Vec<TripletEntry> = serde_json::from_str(&read_text(&index)?)
            .map_err(|e| ExtrapolateError::malformed(&index, e.to_string()))?;
        let get = |name: &str, want: &[usize]| -> Result<Vec<f32>> {
            let t = st
                .tensors
                .get(name)
                .ok_or_else(|| ExtrapolateError::malformed(&path, format!("no tensor {name}")))?;
            if t.shape != want {
                return Err(ExtrapolateError::malformed(
                    &path,
                    format!("{name} has shape {:?}, not {want:?}", t.shape),
                ));
            }
            Ok(t.data.clone())
        };
        let first = st
            .tensors
            .get("photo_000")
            .ok_or_else(|| ExtrapolateError::malformed(&path, "no photos"))?;
        let [h, w, 3] = first.shape[..] else {
            return Err(ExtrapolateError::malformed(
                &path,
                "photo_000 is not [h, w, 3]",
            ));
        };
        let mut photos = Vec::new();
        let mut masks = Vec::new();
        while st
            .tensors
            .contains_key(&format!("photo_{:03}", photos.len()))
        {
            let i = photos.len();
            photos.push(get(&format!("photo_{i:03}"), &[h, w, 3])?);
            masks.push(get(&format!("pseudo_mask_{i:03}"), &[h, w])?);
        }
        let mut renders = Vec::new();
        for e in &entries {
            if e.slot >= photos.len() {
                return Err(ExtrapolateError::malformed(
                    &index,
                    format!(
                        "triplet {} names training view {} of {}",
                        e.key,
                        e.slot,
                        photos.len()
                    ),
                ));
            }
            renders.push((
                get(&format!("{}.render", e.key), &[h, w, 3])?,
                get(&format!("{}.mask", e.key), &[h, w])?,
            ));
        }
        Ok(Triplets {
            width: w,
            height: h,
            photos,
            masks,
            entries,
            renders,
        })
    }

    /// The enhancer's training images: each photo with its corrupted renders.
    pub fn train_images(&self) -> Vec<TrainImage> {
        self.photos
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let mut im = TrainImage::new(self.width, self.height, p.clone());
                im.guides = self
                    .entries
                    .iter()
                    .zip(&self.renders)
                    .filter(|(e, _)| e.slot == i)
                    .map(|(_, (r, m))| Guide {
                        rgb: r.clone(),
                        mask: m.clone(),
                    })
                    .collect();
                im
            })
            .collect()
    }
}
