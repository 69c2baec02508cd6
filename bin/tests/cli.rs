//! The `extranerf` command line end to end: `info`, a tiny `bench kernels` run writing JSON,
//! and clear errors for bad arguments.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use std::process::Command;

fn extranerf(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_extranerf"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn info_names_device_and_driver() {
    let (ok, out, err) = extranerf(&["info"]);
    assert!(ok, "{err}");
    for field in [
        "device",
        "driver",
        "vulkan",
        "heap 0",
        "subgroup size",
        "f32 atomic add",
        "validation",
    ] {
        assert!(out.contains(field), "`{field}` missing from:\n{out}");
    }
    let (ok, out, _) = extranerf(&["info", "--list"]);
    assert!(ok && out.starts_with("0: "), "{out}");
}

#[test]
fn bench_kernels_writes_a_table_and_json() {
    let dir = std::env::temp_dir().join(format!("extranerf-cli-{}", std::process::id()));
    let json = dir.join("bench.json");
    let (ok, out, err) = extranerf(&[
        "bench",
        "kernels",
        "--sizes",
        "4096",
        "--repeats",
        "1",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    for row in [
        "copy (vkCmdCopyBuffer, reference)",
        "saxpy",
        "radix sort",
        "scatter-add subgroup, all equal",
        "hash grid fwd",
        "mlp fwd",
        "adam",
    ] {
        assert!(out.contains(row), "row `{row}` missing:\n{out}");
    }
    let text = std::fs::read_to_string(&json).unwrap();
    assert!(
        text.contains("\"ratio_to_copy\"") && text.contains("\"median_ms\""),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn bad_arguments_are_clear_errors() {
    let (ok, _, err) = extranerf(&["bench", "kernels", "--sizes", "0"]);
    assert!(
        !ok && err.contains("--sizes") && err.contains("outside"),
        "{err}"
    );
    let (ok, _, err) = extranerf(&["--device", "no-such-gpu", "info"]);
    assert!(
        !ok && err.contains("no Vulkan device matches `no-such-gpu`"),
        "{err}"
    );
    let (ok, _, err) = extranerf(&["bench", "kernels", "--repeats", "0"]);
    assert!(!ok && err.contains("--repeats"), "{err}");
    let (ok, _, err) = extranerf(&["train"]);
    assert!(!ok && err.contains("unrecognized subcommand"), "{err}");
}
