//! Crash-safe file writes shared by every crate that saves user work (checkpoints, models,
//! reports): a crash leaves either the old or the new content, never a torn file.

use std::io::Write;
use std::path::{Path, PathBuf};

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

/// Writes `bytes` to `path` atomically ([`write_atomic_with`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_atomic_with(path, |f| f.write_all(bytes))
}

/// The temporary file an atomic write of `path` goes through: `.NAME.tmpPID` beside it.
pub fn temporary_of(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp{}", std::process::id()))
}

/// Writes `path` with `write` through a temporary file in the same folder (created if
/// missing), synced, renamed over `path`, and the folder synced, so that a crash or a full
/// disk leaves either the old or the new content, never a torn file, and the rename survives
/// a power cut. On failure the temporary file is removed; the error is the I/O error of
/// whichever step failed (the caller names the path).
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut std::fs::File) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let parent = path.parent().filter(|p| !p.as_os_str().is_empty());
    if let Some(d) = parent {
        std::fs::create_dir_all(d)?;
    }
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = temporary_of(path);
    let res = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        crash_test_full_disk(&name)?;
        write(&mut f)?;
        f.sync_all()?;
        drop(f);
        crash_test_pause(&name);
        std::fs::rename(&tmp, path)?;
        sync_dir(parent.unwrap_or(Path::new(".")))
    })();
    if res.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    res
}

/// Copies `from` to `to` atomically ([`write_atomic`]).
pub fn copy_atomic(from: &Path, to: &Path) -> std::io::Result<()> {
    write_atomic(to, &std::fs::read(from)?)
}

/// Syncs folder `dir`, so that the names created or renamed in it last.
pub fn sync_dir(dir: &Path) -> std::io::Result<()> {
    std::fs::File::open(dir)?.sync_all()
}

/// Fault injection for the crash tests: with `EXTRANERF_CRASH_TEST_FULL_DISK=NAME` in the
/// environment, an atomic write of a file named NAME fails as a full disk does (`ENOSPC`).
/// Unset, it does nothing.
pub fn crash_test_full_disk(name: &str) -> std::io::Result<()> {
    match std::env::var("EXTRANERF_CRASH_TEST_FULL_DISK") {
        Ok(v) if v == name => Err(std::io::Error::from_raw_os_error(28)),
        _ => Ok(()),
    }
}

/// Why a run folder could not be locked.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    /// Another process holds it.
    #[error("{}: in use by {holder}; wait for it to finish or stop it", dir.display())]
    Held {
        /// The run folder.
        dir: PathBuf,
        /// Who holds it, as its lock file says (`process 1234: extranerf extrapolate`).
        holder: String,
    },
    /// The lock file could not be created, locked or written.
    #[error("{}: {error}", path.display())]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
}

/// The lock file of a run folder.
pub const LOCK_FILE: &str = ".extranerf.lock";

/// A run folder held by this process: an exclusive advisory lock on `DIR/.extranerf.lock`,
/// which holds this process's id and command line. The operating system releases it when
/// the process ends, however it ends, so a killed run never leaves its folder locked.
#[derive(Debug)]
pub struct RunLock {
    _file: std::fs::File,
    /// The lock file.
    pub path: PathBuf,
}

impl RunLock {
    /// Locks run folder `dir` (created if missing) for this process, or says which process
    /// holds it.
    pub fn acquire(dir: &Path) -> Result<RunLock, LockError> {
        let path = dir.join(LOCK_FILE);
        let io = |error| LockError::Io {
            path: path.clone(),
            error,
        };
        std::fs::create_dir_all(dir).map_err(io)?;
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(io)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let holder = std::fs::read_to_string(&path).unwrap_or_default();
                let holder = holder.trim();
                return Err(LockError::Held {
                    dir: dir.to_path_buf(),
                    holder: if holder.is_empty() {
                        "another process".into()
                    } else {
                        holder.to_string()
                    },
                });
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(io(e)),
        }
        let args: Vec<String> = std::env::args().collect();
        let who = format!("process {}: {}\n", std::process::id(), args.join(" "));
        (|| {
            file.set_len(0)?;
            file.write_all(who.as_bytes())?;
            file.sync_all()
        })()
        .map_err(io)?;
        Ok(RunLock { _file: file, path })
    }
}

/// Removes what interrupted writes left in `dir` and its subfolders: the temporary files of
/// atomic writes (`.NAME.tmpPID`) and unfinished videos (`NAME.partial`). Call it holding
/// the folder's [`RunLock`], so that no live writer's files are taken. Returns the files
/// removed.
pub fn remove_stale_temporaries(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut removed = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let entries = match std::fs::read_dir(&d) {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(e),
        };
        for e in entries {
            let e = e?;
            let ty = e.file_type()?;
            let p = e.path();
            if ty.is_dir() {
                stack.push(p);
            } else if ty.is_file() && is_temporary(&e.file_name().to_string_lossy()) {
                std::fs::remove_file(&p)?;
                removed.push(p);
            }
        }
    }
    removed.sort();
    Ok(removed)
}

/// Whether `name` is an interrupted write's: `.NAME.tmpDIGITS` or `NAME.partial`.
fn is_temporary(name: &str) -> bool {
    if name.ends_with(".partial") {
        return true;
    }
    let Some(rest) = name.strip_prefix('.') else {
        return false;
    };
    match rest.rfind(".tmp") {
        Some(i) => {
            let digits = &rest[i + 4..];
            !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit())
        }
        None => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("extranerf-files-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn a_second_lock_names_the_holder_and_the_lock_goes_with_its_holder() {
        let d = scratch("lock");
        let held = RunLock::acquire(&d).unwrap();
        let e = RunLock::acquire(&d).unwrap_err().to_string();
        assert!(
            e.contains(&format!("in use by process {}", std::process::id()))
                && e.contains(&d.display().to_string()),
            "{e}"
        );
        drop(held);
        let again = RunLock::acquire(&d).unwrap();
        drop(again);
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn stale_temporaries_go_and_nothing_else_does() {
        let d = scratch("stale");
        let sub = d.join("stage2-harmonic");
        std::fs::create_dir_all(&sub).unwrap();
        for f in [
            d.join(".extrapolate.json.tmp123"),
            sub.join(".checkpoint.safetensors.tmp9"),
            d.join("flythrough.mp4.partial"),
            d.join("keep.png"),
            d.join(".tmp"),
            d.join(".notes.tmpx"),
            sub.join("round.json"),
        ] {
            std::fs::write(&f, b"x").unwrap();
        }
        let removed = remove_stale_temporaries(&d).unwrap();
        let names: Vec<String> = removed
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names.len(), 3, "{names:?}");
        for keep in ["keep.png", ".tmp", ".notes.tmpx"] {
            assert!(d.join(keep).exists(), "{keep}");
        }
        assert!(sub.join("round.json").exists());
        assert!(remove_stale_temporaries(&d.join("none"))
            .unwrap()
            .is_empty());
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_full_disk_leaves_the_old_file_and_no_temporary() {
        let d = scratch("atomic");
        let p = d.join("eval.md");
        write_atomic(&p, b"old").unwrap();
        let res = write_atomic_with(&p, |f| {
            f.write_all(b"new, half")?;
            Err(std::io::Error::from_raw_os_error(28))
        });
        assert_eq!(res.unwrap_err().raw_os_error(), Some(28));
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert!(!temporary_of(&p).exists());
        write_atomic(&p, b"new").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new");
        std::fs::remove_dir_all(&d).unwrap();
    }
}
