//! Crash-safe file writes shared by every crate that saves user work (checkpoints, models,
//! reports): a crash leaves either the old or the new content, never a torn file.

use std::io::Write;
use std::path::Path;

/// Fault injection for the crash tests: with `EXTRANERF_CRASH_TEST_PAUSE=NAME:MS` in the
/// environment, an atomic write of a file named NAME waits MS milliseconds between its synced
/// temporary file and the rename, so a test can kill the process there. Unset, it does nothing.
pub fn crash_test_pause(name: &str) {
    if let Ok(v) = std::env::var("EXTRANERF_CRASH_TEST_PAUSE") {
        if let Some((file, ms)) = v.rsplit_once(':') {
            if file == name {
                if let Ok(ms) = ms.parse::<u64>() {
                    std::thread::sleep(std::time::Duration::from_millis(ms));
                }
            }
        }
    }
}

/// Writes `bytes` to `path` through a synced temporary file in the same folder (created if
/// missing) and a rename. On failure the temporary file is removed; the error is the I/O error
/// of whichever step failed (the caller names the path).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    if let Some(d) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(d)?;
    }
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp{}", std::process::id()));
    let res = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        crash_test_pause(&name);
        std::fs::rename(&tmp, path)
    })();
    if res.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    res
}
