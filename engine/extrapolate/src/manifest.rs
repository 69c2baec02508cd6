//! The run folder's manifest, `extrapolate.json`: the scene, and for each stage its resolved
//! configuration, whether it is done, its wall time and what it reported. A run resumes at
//! the first stage not done; a stage whose recorded configuration differs from the one asked
//! for is refused with the field that differs, so a run folder is never continued with another
//! scene or other settings.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use extranerf_nerf::mvs_depth::sha256_hex;
use extranerf_nerf::run::SceneSpec;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::error::{read_text, write_json, ExtrapolateError, Result};

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
    /// The fingerprints ([`Manifest::fingerprint`]) of the stages it read, as they were when
    /// it ran: when one differs now, that stage was made again since, and this one runs again.
    /// Absent in records of builds before fingerprints (their inputs count as unchanged).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inputs: Option<BTreeMap<String, String>>,
    /// What identifies its output once done: a SHA-256 of the checkpoint it reads or made
    /// where it has one ([`crate::stage::Stage::identity`]), else of its record and the moment
    /// it finished. Absent in records of older builds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output: Option<String>,
}

/// `extrapolate.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub format: String,
    /// The scene and split every stage used.
    pub scene: SceneSpec,
    /// The SHA-256 of the scene's cameras and images ([`extranerf_nerf::mvs_depth::views_key`]),
    /// which a resumed run must find unchanged. Absent in manifests of older builds (a resume
    /// records it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_sha256: Option<String>,
    pub stages: Vec<StageRecord>,
}

impl Manifest {
    /// A new manifest for `scene`.
    pub fn new(scene: SceneSpec) -> Manifest {
        Manifest {
            format: FORMAT.into(),
            scene,
            scene_sha256: None,
            stages: Vec::new(),
        }
    }

    /// The manifest path of run folder `dir`.
    pub fn path(dir: &Path) -> PathBuf {
        dir.join(MANIFEST_FILE)
    }

    /// Reads `dir`'s manifest, None when there is none.
    pub fn load(dir: &Path) -> Result<Option<Manifest>> {
        let path = Manifest::path(dir);
        if !path.exists() {
            return Ok(None);
        }
        let text = read_text(&path)?;
        let m: Manifest = serde_json::from_str(&text).map_err(|e| {
            ExtrapolateError::malformed(&path, format!("not an extrapolate manifest: {e}"))
        })?;
        if m.format != FORMAT {
            return Err(ExtrapolateError::malformed(
                &path,
                format!("format `{}`, this build reads `{FORMAT}`", m.format),
            ));
        }
        Ok(Some(m))
    }

    /// Writes the manifest into `dir` atomically.
    pub fn save(&self, dir: &Path) -> Result<()> {
        write_json(&Manifest::path(dir), self)
    }

    /// Checks that `scene` is the manifest's scene (`dir` names the folder in the error).
    pub fn check_scene(&self, dir: &Path, scene: &SceneSpec) -> Result<()> {
        if &self.scene != scene {
            let (a, b) = (json_of(&self.scene), json_of(scene));
            return Err(ExtrapolateError::resume(
                dir,
                format!(
                    "made from another scene or split ({}); choose a new --out",
                    difference(&a, &b, "scene").unwrap_or_else(|| "the scene differs".into())
                ),
            ));
        }
        Ok(())
    }

    /// The record of stage `name` after checking that it was made with settings that may
    /// resume as `config` ([`Recorded::check`]); None when the stage has not started.
    pub fn stage(&self, dir: &Path, name: &str, config: &Recorded) -> Result<Option<&StageRecord>> {
        let Some(r) = self.stages.iter().find(|s| s.name == name) else {
            return Ok(None);
        };
        config.check(dir, name, &r.config)?;
        Ok(Some(r))
    }

    /// Checks that the scene's cameras and images hash to `key` as when the run began, and
    /// records it where the manifest (of an older build) has none.
    pub fn check_scene_content(&mut self, dir: &Path, key: &str) -> Result<()> {
        match &self.scene_sha256 {
            Some(k) if k != key => Err(ExtrapolateError::resume(
                dir,
                format!(
                    "the cameras or images of the scene {} changed since this run began \
                     (SHA-256 {} -> {}); choose a new --out",
                    self.scene.dir.display(),
                    &k[..12.min(k.len())],
                    &key[..12.min(key.len())]
                ),
            )),
            Some(_) => Ok(()),
            None => {
                self.scene_sha256 = Some(key.to_string());
                Ok(())
            }
        }
    }

    /// The fingerprint of stage `name` when it is done: its recorded output, or for a record
    /// of an older build, the SHA-256 of the record. None when it is not done.
    pub fn fingerprint(&self, name: &str) -> Option<String> {
        let r = self.stages.iter().find(|s| s.name == name && s.done)?;
        Some(r.output.clone().unwrap_or_else(|| {
            sha256_hex(
                serde_json::json!({"name": r.name, "config": r.config, "report": r.report})
                    .to_string()
                    .as_bytes(),
            )
        }))
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
    differences(a, b, path).into_iter().next().map(|d| d.text)
}

/// A field that differs between two JSON values.
#[derive(Clone, Debug, PartialEq)]
pub struct Difference {
    /// Its dotted path below the values' root (`settings.threshold`).
    pub field: String,
    /// `path.field: recorded -> asked`.
    pub text: String,
}

/// Every differing field of two JSON values (objects compared key by key, anything else as a
/// whole), in key order; `path` prefixes the texts.
pub fn differences(a: &Value, b: &Value, path: &str) -> Vec<Difference> {
    let mut out = Vec::new();
    walk(a, b, path, "", &mut out);
    out
}

fn walk(a: &Value, b: &Value, path: &str, field: &str, out: &mut Vec<Difference>) {
    let join = |p: &str, k: &str| {
        if p.is_empty() {
            k.to_string()
        } else {
            format!("{p}.{k}")
        }
    };
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            for k in keys {
                let (p, f) = (join(path, k), join(field, k));
                match (x.get(k), y.get(k)) {
                    (Some(u), Some(v)) => walk(u, v, &p, &f, out),
                    (u, v) => out.push(Difference {
                        text: format!(
                            "{p}: {} -> {}",
                            u.map_or("absent".into(), Value::to_string),
                            v.map_or("absent".into(), Value::to_string)
                        ),
                        field: f,
                    }),
                }
            }
        }
        _ if a == b => {}
        _ => out.push(Difference {
            field: field.to_string(),
            text: format!("{path}: {a} -> {b}"),
        }),
    }
}

/// How a resumed run meets a changed setting of a stage it finds recorded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OnResume {
    /// The stage's output does not depend on it (where a model runs, how work is chunked): a
    /// resumed run may change it, and the stage is not run again for it.
    MayChange,
    /// The stage's output depends on it: a resumed run that changes it is refused unless the
    /// stage is redone (`--redo NAME`).
    Rerun,
}

/// A stage's settings as its manifest record holds them: a serde type, and the declaration of
/// which of its fields may change on resume and which force the stage to run again.
pub trait StageSpec: Serialize + DeserializeOwned {
    /// Every field of the record, by its serialised name (a dotted path for a field inside
    /// one, which overrides its parent's rule), and how a resumed run meets a change of it.
    const ON_RESUME: &'static [(&'static str, OnResume)];

    /// Reads a record of these settings, those written by older builds included (by default
    /// the serde layout, whose defaults fill the fields an older build did not record).
    fn from_record(v: &Value) -> std::result::Result<Self, String> {
        Self::deserialize(v).map_err(|e| e.to_string())
    }
}

/// The rule of `field` in `rules`: the longest declared path that is it or holds it; fields
/// not declared force a rerun.
pub fn on_resume(rules: &[(&str, OnResume)], field: &str) -> OnResume {
    rules
        .iter()
        .filter(|(p, _)| {
            field == *p || (field.starts_with(p) && field.as_bytes().get(p.len()) == Some(&b'.'))
        })
        .max_by_key(|(p, _)| p.len())
        .map_or(OnResume::Rerun, |&(_, r)| r)
}

/// A stage's settings as they are recorded: the serialised [`StageSpec`], with its type's
/// reader of older records and its resume declaration.
#[derive(Clone, Debug)]
pub struct Recorded {
    /// The settings, serialised.
    pub value: Value,
    /// [`StageSpec::ON_RESUME`] of its type.
    pub rules: &'static [(&'static str, OnResume)],
    /// Reads a record through its type and serialises it again (the current layout).
    read: fn(&Value) -> std::result::Result<Value, String>,
}

impl Recorded {
    /// The record of `spec`.
    pub fn of<S: StageSpec>(spec: &S) -> Recorded {
        Recorded {
            value: serde_json::to_value(spec).expect("a stage spec serialises to JSON"),
            rules: S::ON_RESUME,
            read: |v| {
                let s = S::from_record(v)?;
                serde_json::to_value(&s).map_err(|e| e.to_string())
            },
        }
    }

    /// `record` read through the spec's type (an older layout included) and serialised in
    /// the current layout; why not where it does not read.
    pub fn read(&self, record: &Value) -> std::result::Result<Value, String> {
        (self.read)(record)
    }

    /// Checks that stage `name` of run folder `dir`, recorded as `recorded`, may resume with
    /// these settings: the record read through the spec's type (an older layout included)
    /// differs from them in no field declared [`OnResume::Rerun`].
    pub fn check(&self, dir: &Path, name: &str, recorded: &Value) -> Result<()> {
        let old = self.read(recorded).map_err(|e| {
            ExtrapolateError::resume(
                dir,
                format!(
                    "stage `{name}` was recorded in a layout this build does not read ({e}); \
                     run it again with --resume --redo {name}, or choose a new --out"
                ),
            )
        })?;
        let rerun: Vec<String> = differences(&old, &self.value, name)
            .into_iter()
            .filter(|d| on_resume(self.rules, &d.field) == OnResume::Rerun)
            .map(|d| d.text)
            .collect();
        if let Some(first) = rerun.first() {
            return Err(ExtrapolateError::resume(
                dir,
                format!(
                    "stage `{name}` was run with other settings ({first}{}); repeat the settings \
                     it was made with, run it again with --redo {name}, or choose a new --out",
                    if rerun.len() > 1 {
                        format!(", and {} more", rerun.len() - 1)
                    } else {
                        String::new()
                    }
                ),
            ));
        }
        Ok(())
    }
}

/// The SHA-256 of the file at `path` in hexadecimal.
pub fn file_sha256(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).map_err(|e| ExtrapolateError::io("reading", path, e))?;
    Ok(sha256_hex(&bytes))
}

/// Serialises a value of this crate's types (which always serialise).
pub(crate) fn json_of<T: Serialize>(v: &T) -> Value {
    serde_json::to_value(v).expect("the manifest's types serialise to JSON")
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
            capture_depth: false,
        }
    }

    /// A stage spec of the tests: two settings that force a rerun, one that may change, and
    /// one an older layout did not record.
    #[derive(Serialize, Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Vis {
        rank: u32,
        threshold: f32,
        chunk: u32,
        #[serde(default)]
        later: u32,
    }

    impl StageSpec for Vis {
        const ON_RESUME: &'static [(&'static str, OnResume)] = &[
            ("rank", OnResume::Rerun),
            ("threshold", OnResume::Rerun),
            ("chunk", OnResume::MayChange),
            ("later", OnResume::Rerun),
        ];
    }

    fn vis(rank: u32, threshold: f32, chunk: u32) -> Recorded {
        Recorded::of(&Vis {
            rank,
            threshold,
            chunk,
            later: 0,
        })
    }

    #[test]
    fn another_scene_or_stage_config_is_refused_naming_the_field() {
        let dir = std::env::temp_dir().join(format!("extranerf-manifest-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut m = Manifest::new(scene("a/fern"));
        m.record(StageRecord {
            name: "visibility".into(),
            // An older layout: no `later`.
            config: json!({"rank": 2, "threshold": 0.5, "chunk": 64}),
            done: true,
            seconds: 3.0,
            report: Value::Null,
            inputs: None,
            output: None,
        });
        m.save(&dir).unwrap();
        let back = Manifest::load(&dir).unwrap().unwrap();
        assert_eq!(back, m);
        back.check_scene(&dir, &scene("a/fern")).unwrap();
        let e = back.check_scene(&dir, &scene("a/trex")).unwrap_err();
        assert!(matches!(e, ExtrapolateError::Resume { .. }), "{e:?}");
        assert!(
            format!("{e}").contains("scene.dir: \"a/fern\" -> \"a/trex\""),
            "{e}"
        );
        // The older record reads with the default of what it lacks; a setting that may change
        // does.
        let r = back
            .stage(&dir, "visibility", &vis(2, 0.5, 64))
            .unwrap()
            .unwrap();
        assert!(r.done);
        assert!(back.stage(&dir, "visibility", &vis(2, 0.5, 4096)).is_ok());
        let e = back
            .stage(&dir, "visibility", &vis(3, 0.5, 64))
            .unwrap_err();
        assert!(matches!(e, ExtrapolateError::Resume { .. }), "{e:?}");
        assert!(format!("{e}").contains("visibility.rank: 2 -> 3"), "{e}");
        assert!(format!("{e}").contains("--redo visibility"), "{e}");
        // Two that force a rerun: the first named, the count of the others.
        let e = back
            .stage(&dir, "visibility", &vis(3, 0.25, 8))
            .unwrap_err();
        assert!(
            format!("{e}").contains("visibility.rank: 2 -> 3, and 1 more"),
            "{e}"
        );
        let later = Recorded::of(&Vis {
            rank: 2,
            threshold: 0.5,
            chunk: 64,
            later: 1,
        });
        let e = back.stage(&dir, "visibility", &later).unwrap_err();
        assert!(format!("{e}").contains("visibility.later: 0 -> 1"), "{e}");
        assert!(back
            .stage(&dir, "stage2-harmonic", &vis(2, 0.5, 64))
            .unwrap()
            .is_none());
        // A record its type does not read: refused, saying how to go on.
        let mut odd = back.clone();
        odd.stages[0].config = json!({"rank": "two"});
        let e = odd.stage(&dir, "visibility", &vis(2, 0.5, 64)).unwrap_err();
        assert!(
            format!("{e}").contains("in a layout this build does not read")
                && format!("{e}").contains("--resume --redo visibility"),
            "{e}"
        );
        std::fs::write(Manifest::path(&dir), "{\"format\": 1}").unwrap();
        let e = Manifest::load(&dir).unwrap_err();
        assert!(matches!(e, ExtrapolateError::Malformed { .. }), "{e:?}");
        assert!(
            format!("{e:#}").contains("not an extrapolate manifest"),
            "{e:#}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_field_takes_the_rule_of_the_longest_declared_path_that_holds_it() {
        let rules = [
            ("settings", OnResume::Rerun),
            ("settings.chunk", OnResume::MayChange),
            ("settings.chunky", OnResume::Rerun),
        ];
        assert_eq!(on_resume(&rules, "settings.rank"), OnResume::Rerun);
        assert_eq!(on_resume(&rules, "settings.chunk"), OnResume::MayChange);
        assert_eq!(on_resume(&rules, "settings.chunk.x"), OnResume::MayChange);
        assert_eq!(on_resume(&rules, "settings.chunky"), OnResume::Rerun);
        assert_eq!(on_resume(&rules, "settingsx"), OnResume::Rerun);
        // Undeclared: a rerun.
        assert_eq!(on_resume(&rules, "other"), OnResume::Rerun);
        let d = differences(
            &json!({"a": {"b": 1, "c": 2}, "d": 3}),
            &json!({"a": {"b": 1, "c": 5}, "e": 3}),
            "s",
        );
        let fields: Vec<&str> = d.iter().map(|d| d.field.as_str()).collect();
        assert_eq!(fields, ["a.c", "d", "e"]);
        assert_eq!(d[1].text, "s.d: 3 -> absent");
    }
}
