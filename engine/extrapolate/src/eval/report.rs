//! `RUN/report.html`: one self-contained page per extrapolate run (every image inlined as a
//! data URI, no script, nothing fetched): the stages with their wall times, `eval`'s table, and
//! for each held-out view the ground truth, the BaseNeRF's render, the final field's render and
//! the visibility map, then the fly-through video.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::error::{ExtrapolateError, Result};

use crate::eval::table::Table;
use crate::manifest::Manifest;

/// The report's file name inside a run folder.
pub const REPORT_FILE: &str = "report.html";

/// Standard base64 (RFC 4648, with padding).
pub fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let n = (u32::from(c[0]) << 16)
            | (u32::from(*c.get(1).unwrap_or(&0)) << 8)
            | u32::from(*c.get(2).unwrap_or(&0));
        for k in 0..4 {
            if k <= c.len() {
                s.push(A[(n >> (18 - 6 * k)) as usize & 63] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// An `<img>` of the file at `path`, inlined; a note when the file is missing.
fn img(path: &Path, alt: &str) -> Result<String> {
    if !path.is_file() {
        return Ok(format!(
            "<div class=\"missing\">{} missing</div>",
            escape(&path.display().to_string())
        ));
    }
    let bytes = std::fs::read(path).map_err(|e| ExtrapolateError::io("reading", path, e))?;
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let mime = match ext.as_str() {
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        _ => {
            return Err(ExtrapolateError::malformed(
                path,
                "not a PNG or JPEG image for the report",
            ))
        }
    };
    Ok(format!(
        "<img alt=\"{}\" title=\"{}\" src=\"data:{mime};base64,{}\">",
        escape(alt),
        escape(alt),
        base64(&bytes)
    ))
}

/// The field whose renders the report calls final: the last stage-3 field, else the last
/// stage-2 variant, else the BaseNeRF.
pub fn final_field(m: &Manifest) -> Option<String> {
    let done = |p: &str| {
        m.stages
            .iter()
            .rev()
            .filter(|s| s.done && s.name.starts_with(p))
            .filter(|s| {
                s.name != crate::stage::DATA_STAGE && s.name != crate::stage::ENHANCER_STAGE
            })
            .map(|s| s.name.clone())
            .next()
    };
    done("stage3-").or_else(|| done("stage2-"))
}

/// Writes `dir/report.html` from the manifest, `table` (eval's) and the run's images.
pub fn write_report(dir: &Path, table: Option<&Table>) -> Result<PathBuf> {
    let Some(m) = Manifest::load(dir)? else {
        return Err(ExtrapolateError::incomplete(dir, "no extrapolate manifest"));
    };
    let loaded = m.scene.load()?;
    let mut h = String::new();
    h += "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n";
    let _ = writeln!(
        h,
        "<title>extranerf run {}</title>",
        escape(&dir.display().to_string())
    );
    h += "<style>body{font-family:sans-serif;margin:1.5em;color:#222}table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th:first-child,td:first-child{text-align:left}figure{display:inline-block;margin:4px;text-align:center}figure img{max-width:320px;display:block}figcaption{font-size:0.85em}.missing{width:200px;height:60px;background:#eee;font-size:0.8em}</style>\n";
    h += "</head><body>\n";
    let _ = writeln!(
        h,
        "<h1>ExtraNeRF run</h1><p>{} &mdash; scene {} ({:?} split; {} training views, {} held out; depth targets: {})</p>",
        escape(&dir.display().to_string()),
        escape(&m.scene.dir.display().to_string()),
        m.scene.split,
        loaded.split.train.len(),
        loaded.split.test.len(),
        escape(&m.scene.depth_label())
    );
    h += "<h2>Stages</h2><table><tr><th>stage</th><th>done</th><th>wall seconds</th></tr>\n";
    let mut total = 0.0;
    for s in &m.stages {
        total += s.seconds;
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{:.1}</td></tr>",
            escape(&s.name),
            if s.done { "yes" } else { "no" },
            s.seconds
        );
    }
    let _ = writeln!(
        h,
        "<tr><th>all</th><td></td><th>{total:.1}</th></tr></table>"
    );
    let shown = crate::shown::Shown::of(&loaded.split);
    if shown.held_out {
        h += "<h2>Held-out views</h2>\n";
    } else {
        h += "<h2>Training views</h2>\n<p>The run's split holds no view out: below are its \
              training views beside the fields' renders at their cameras.</p>\n";
    }
    match table {
        Some(t) => {
            let _ = writeln!(
                h,
                "<table><tr><th>{}</th></tr>",
                t.columns().join("</th><th>")
            );
            for r in t.cells() {
                let cells: Vec<String> = r.iter().map(|c| escape(c)).collect();
                let _ = writeln!(h, "<tr><td>{}</td></tr>", cells.join("</td><td>"));
            }
            h += "</table>\n";
            if let Some(m) = &t.truth_masks {
                let _ = writeln!(h, "<p>{}</p>", escape(&m.describe()));
            }
            if let Some(k) = &t.kid {
                let _ = writeln!(h, "<p>{}</p>", escape(&k.describe()));
            }
            for n in &t.notes {
                let _ = writeln!(h, "<p>{}</p>", escape(n));
            }
        }
        None => h += "<p>No evaluation table (run <code>extranerf eval RUN</code>).</p>\n",
    }
    let fin = final_field(&m);
    let vis = dir.join("visibility");
    for &i in &shown.views {
        let cam = &loaded.scene.cameras[i];
        let name = shown.name(i);
        let _ = writeln!(h, "<h3>view {i}</h3><div>");
        let mut fig = |path: &Path, caption: &str| -> Result<()> {
            let _ = writeln!(
                h,
                "<figure>{}<figcaption>{}</figcaption></figure>",
                img(path, caption)?,
                escape(caption)
            );
            Ok(())
        };
        fig(&cam.image, "ground truth")?;
        fig(&vis.join(format!("{name}_base.png")), "BaseNeRF")?;
        if let Some(f) = &fin {
            fig(&dir.join(f).join(format!("{name}.png")), f)?;
        }
        fig(&vis.join(format!("{name}_vis.png")), "visibility")?;
        fig(&vis.join(format!("{name}_mask.png")), "not-visible mask")?;
        h += "</div>\n";
    }
    let video = dir
        .join("flythrough")
        .join(crate::stages::flythrough::VIDEO_FILE);
    if video.is_file() {
        let bytes =
            std::fs::read(&video).map_err(|e| ExtrapolateError::io("reading", &video, e))?;
        let _ = writeln!(
            h,
            "<h2>Fly-through</h2>\n<p>The BaseNeRF and each variant along the virtual \
             trajectory, side by side ({}).</p>\n<video controls autoplay loop muted playsinline \
             title=\"fly-through\" src=\"data:video/mp4;base64,{}\"></video>",
            escape(&video.display().to_string()),
            base64(&bytes)
        );
    }
    h += "</body></html>\n";
    let path = dir.join(REPORT_FILE);
    extranerf_nerf::safetensors::write_atomic(&path, h.as_bytes())?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc_4648() {
        for (input, want) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(input.as_bytes()), want, "{input:?}");
        }
        assert_eq!(base64(&[0xff, 0xfe, 0x00]), "//4A");
    }

    #[test]
    fn text_is_escaped() {
        assert_eq!(
            escape("<a href=\"x\">&"),
            "&lt;a href=&quot;x&quot;&gt;&amp;"
        );
    }
}
