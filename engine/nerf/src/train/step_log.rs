//! The per-step logs of a run folder (`progress.jsonl`, `curve.jsonl`): one JSON object per
//! line with its `step`. A fresh run starts them empty; a resumed one keeps the lines up to
//! the checkpoint it resumes from, so that steps trained again after a crash are logged once.

use std::fs::File;
use std::path::Path;

use crate::train::TrainError;

/// Opens the log at `path` for appending by a run that starts at step `start`: emptied when
/// `start` is 0, else cut to its lines of steps up to `start` (written atomically; a line
/// that is not a JSON object with a step, such as one cut short by a crash, is dropped).
pub fn open_step_log(path: &Path, start: u32) -> Result<File, TrainError> {
    if start == 0 {
        if path.exists() {
            std::fs::remove_file(path).map_err(|e| TrainError::io("replacing", path, e))?;
        }
    } else if path.exists() {
        let text = std::fs::read_to_string(path).map_err(|e| TrainError::io("reading", path, e))?;
        let kept = kept_lines(&text, start);
        if kept.len() != text.len() {
            crate::data::write_atomic(path, kept.as_bytes())?;
        }
    }
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(|e| TrainError::io("opening", path, e))
}

/// The lines of `text` whose step is at most `start`, each with its newline.
fn kept_lines(text: &str, start: u32) -> String {
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        let step = serde_json::from_str::<serde_json::Value>(line)
            .ok()
            .and_then(|v| v.get("step").and_then(serde_json::Value::as_u64));
        if step.is_some_and(|s| s <= start as u64) {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resumed_log_keeps_the_steps_up_to_its_checkpoint_and_a_fresh_one_starts_empty() {
        let dir = std::env::temp_dir().join(format!("extranerf-steplog-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("progress.jsonl");
        // Steps 5 to 45 and a line cut short by a crash.
        let mut text: String = (1..=9)
            .map(|k| format!("{{\"step\": {}, \"loss\": 0.5}}\n", 5 * k))
            .collect();
        text.push_str("{\"step\": 50, \"lo");
        std::fs::write(&path, &text).unwrap();
        use std::io::Write;
        let mut f = open_step_log(&path, 40).unwrap();
        writeln!(f, "{{\"step\": 45}}").unwrap();
        drop(f);
        let steps: Vec<u64> = std::fs::read_to_string(&path)
            .unwrap()
            .lines()
            .map(|l| {
                serde_json::from_str::<serde_json::Value>(l).unwrap()["step"]
                    .as_u64()
                    .unwrap()
            })
            .collect();
        assert_eq!(steps, [5, 10, 15, 20, 25, 30, 35, 40, 45]);
        // A fresh run (step 0) starts an empty log.
        let mut f = open_step_log(&path, 0).unwrap();
        writeln!(f, "{{\"step\": 5}}").unwrap();
        drop(f);
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "{\"step\": 5}\n");
        // No log yet: created.
        std::fs::remove_file(&path).unwrap();
        drop(open_step_log(&path, 20).unwrap());
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
