//! The run folder's manifest, `extrapolate.json`: the scene, and for each stage its resolved
//! configuration, whether it is done, its wall time and what it reported. A run resumes at
//! the first stage not done; a stage whose recorded configuration differs from the one asked
//! for is refused with the field that differs, so a run folder is never continued with another
//! scene or other settings.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _};
use extranerf_nerf::run::SceneSpec;
use serde::{Deserialize, Serialize};
use serde_json::Value;

/// The manifest's file name inside a run folder.
pub const MANIFEST_FILE: &str = "extrapolate.json";
/// Its format tag.
pub const FORMAT: &str = "extranerf-extrapolate-1";

/// One stage's record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageRecord {
    /// The stage's name (`base`, `visibility`, `stage2-harmonic`, ...).
    pub name: String,
    /// Its resolved configuration.
    pub config: Value,
    /// Finished.
    pub done: bool,
    /// Wall seconds of the run that finished it (summed over resumed attempts).
    pub seconds: f64,
    /// What it reported (timings, fractions, files).
    #[serde(default)]
    pub report: Value,
}

/// `extrapolate.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub format: String,
    /// The scene and split every stage used.
    pub scene: SceneSpec,
    pub stages: Vec<StageRecord>,
}

impl Manifest {
    /// A new manifest for `scene`.
    pub fn new(scene: SceneSpec) -> Manifest {
        Manifest {
            format: FORMAT.into(),
            scene,
            stages: Vec::new(),
        }
    }

    /// The manifest path of run folder `dir`.
    pub fn path(dir: &Path) -> PathBuf {
        dir.join(MANIFEST_FILE)
    }

    /// Reads `dir`'s manifest, None when there is none.
    pub fn load(dir: &Path) -> anyhow::Result<Option<Manifest>> {
        let path = Manifest::path(dir);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let m: Manifest = serde_json::from_str(&text)
            .with_context(|| format!("{}: not an extrapolate manifest", path.display()))?;
        if m.format != FORMAT {
            bail!(
                "{}: format `{}`, this build reads `{FORMAT}`",
                path.display(),
                m.format
            );
        }
        Ok(Some(m))
    }

    /// Writes the manifest into `dir` atomically.
    pub fn save(&self, dir: &Path) -> anyhow::Result<()> {
        let json = serde_json::to_string_pretty(self)?;
        extranerf_nerf::safetensors::write_atomic(&Manifest::path(dir), json.as_bytes())?;
        Ok(())
    }

    /// Checks that `scene` is the manifest's scene (`dir` names the folder in the error).
    pub fn check_scene(&self, dir: &Path, scene: &SceneSpec) -> anyhow::Result<()> {
        if &self.scene != scene {
            let a = serde_json::to_value(&self.scene)?;
            let b = serde_json::to_value(scene)?;
            bail!(
                "{} was made from another scene or split ({}); choose a new --out",
                dir.display(),
                difference(&a, &b, "scene").unwrap_or_else(|| "the scene differs".into())
            );
        }
        Ok(())
    }

    /// The record of stage `name` after checking that it was made with `config`; None when
    /// the stage has not started.
    pub fn stage(
        &self,
        dir: &Path,
        name: &str,
        config: &Value,
    ) -> anyhow::Result<Option<&StageRecord>> {
        let Some(r) = self.stages.iter().find(|s| s.name == name) else {
            return Ok(None);
        };
        if &r.config != config {
            bail!(
                "{}: stage `{name}` was run with other settings ({}); choose a new --out, or repeat the settings it was made with",
                dir.display(),
                difference(&r.config, config, name).unwrap_or_else(|| "they differ".into())
            );
        }
        Ok(Some(r))
    }

    /// Records stage `name` (replacing an earlier record of it).
    pub fn record(&mut self, rec: StageRecord) {
        if let Some(r) = self.stages.iter_mut().find(|s| s.name == rec.name) {
            *r = rec;
        } else {
            self.stages.push(rec);
        }
    }
}

/// The first differing field of two JSON values, as `path: recorded -> asked`.
pub fn difference(a: &Value, b: &Value, path: &str) -> Option<String> {
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            keys.into_iter().find_map(|k| match (x.get(k), y.get(k)) {
                (Some(u), Some(v)) => difference(u, v, &format!("{path}.{k}")),
                (u, v) => Some(format!(
                    "{path}.{k}: {} -> {}",
                    u.map_or("absent".into(), Value::to_string),
                    v.map_or("absent".into(), Value::to_string)
                )),
            })
        }
        _ if a == b => None,
        _ => Some(format!("{path}: {a} -> {b}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn scene(dir: &str) -> SceneSpec {
        SceneSpec {
            dir: dir.into(),
            split: extranerf_nerf::data::split::SplitKind::Extrapolation,
            fewshot_views: 3,
            factor: 8,
            sparse_depth: true,
            depth_dir: None,
            mvs_depth: None,
        }
    }

    #[test]
    fn another_scene_or_stage_config_is_refused_naming_the_field() {
        let dir = std::env::temp_dir().join(format!("extranerf-manifest-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut m = Manifest::new(scene("a/fern"));
        m.record(StageRecord {
            name: "visibility".into(),
            config: json!({"rank": 2, "threshold": 0.5}),
            done: true,
            seconds: 3.0,
            report: Value::Null,
        });
        m.save(&dir).unwrap();
        let back = Manifest::load(&dir).unwrap().unwrap();
        assert_eq!(back, m);
        back.check_scene(&dir, &scene("a/fern")).unwrap();
        let e = back.check_scene(&dir, &scene("a/trex")).unwrap_err();
        assert!(
            format!("{e}").contains("scene.dir: \"a/fern\" -> \"a/trex\""),
            "{e}"
        );
        let r = back
            .stage(&dir, "visibility", &json!({"rank": 2, "threshold": 0.5}))
            .unwrap()
            .unwrap();
        assert!(r.done);
        let e = back
            .stage(&dir, "visibility", &json!({"rank": 3, "threshold": 0.5}))
            .unwrap_err();
        assert!(format!("{e}").contains("visibility.rank: 2 -> 3"), "{e}");
        assert!(back
            .stage(&dir, "stage2-harmonic", &json!({}))
            .unwrap()
            .is_none());
        std::fs::write(Manifest::path(&dir), "{\"format\": 1}").unwrap();
        let e = Manifest::load(&dir).unwrap_err();
        assert!(
            format!("{e:#}").contains("not an extrapolate manifest"),
            "{e:#}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
