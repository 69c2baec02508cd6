//! How the command line shows the pipeline's progress: a progress bar with the loss, pace and
//! ETA on a terminal, one line per window otherwise (logs keep every line).

use std::io::IsTerminal;

use extranerf_nerf::train::{Progress, Reporter, Unit};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// Progress on stderr.
pub struct Console {
    tty: bool,
    bar: Option<ProgressBar>,
    /// The pipeline stage whose progress is shown (None: a plain training run).
    stage: Option<String>,
}

impl Console {
    pub fn new() -> Console {
        Console {
            tty: std::io::stderr().is_terminal(),
            bar: None,
            stage: None,
        }
    }
}

impl Reporter for Console {
    fn note(&mut self, line: &str) {
        match &self.bar {
            Some(bar) => bar.println(line),
            None => eprintln!("{line}"),
        }
    }

    fn progress(&mut self, p: &Progress) {
        let label = self.stage.clone().unwrap_or_else(|| "step".into());
        if p.unit == Unit::Views {
            if !self.tty {
                eprintln!(
                    "{label} view {:>3}/{}  {:.1} s  ETA {:.0} s",
                    p.step, p.total, p.secs, p.eta
                );
                return;
            }
        } else if p.unit == Unit::ModelSteps {
            if !self.tty {
                eprintln!(
                    "{label} {:>5}/{}  loss {:.5}  {:.1} s elapsed  ETA {:.0} s",
                    p.step, p.total, p.loss, p.secs, p.eta
                );
                return;
            }
        } else if !self.tty {
            eprintln!(
                "{label} {:>5}/{}  loss {:.5}  psnr {:6.2} dB  {:.3e} samples/s  {:.1} s elapsed  ETA {:.0} s",
                p.step, p.total, p.loss, p.psnr, p.samples_per_s, p.secs, p.eta
            );
            return;
        }
        let template = format!("{label:>16} {{bar:30}} {{pos:>5}}/{{len}}  {{msg}}");
        let bar = self.bar.get_or_insert_with(|| {
            let bar =
                ProgressBar::with_draw_target(Some(p.total as u64), ProgressDrawTarget::stderr());
            // The template is a constant that indicatif accepts.
            if let Ok(style) = ProgressStyle::with_template(&template) {
                bar.set_style(style);
            }
            bar
        });
        bar.set_length(p.total as u64);
        bar.set_position(p.step as u64);
        bar.set_message(match p.unit {
            Unit::Steps => format!(
                "steps  loss {:.5}  psnr {:.2} dB  {:.2e} samples/s  {:.0} s, ETA {:.0} s",
                p.loss, p.psnr, p.samples_per_s, p.secs, p.eta
            ),
            Unit::Views => format!("views  {:.0} s, ETA {:.0} s", p.secs, p.eta),
            Unit::ModelSteps => format!(
                "steps  loss {:.5}  {:.0} s, ETA {:.0} s",
                p.loss, p.secs, p.eta
            ),
        });
    }

    fn stage(&mut self, name: &str) {
        self.finish_bar();
        self.note(&format!("== stage {name}"));
        self.stage = Some(name.to_string());
    }
}

impl Console {
    /// Ends the current bar (the next progress starts a new one).
    fn finish_bar(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish();
        }
    }
}

impl Drop for Console {
    fn drop(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish();
        }
    }
}

/// A reporter that also appends every note (and each stage's last progress line) to a log
/// file, so the run folder keeps what the console showed.
pub struct Logged<R: Reporter> {
    pub inner: R,
    pub file: std::fs::File,
}

impl<R: Reporter> Reporter for Logged<R> {
    fn note(&mut self, line: &str) {
        use std::io::Write;
        // A log that cannot be written must not stop the run; the console still has it.
        let _ = writeln!(self.file, "{line}");
        self.inner.note(line);
    }

    fn progress(&mut self, p: &Progress) {
        if p.step == p.total {
            use std::io::Write;
            let _ = match p.unit {
                Unit::ModelSteps => writeln!(
                    self.file,
                    "  {}/{}  loss {:.5}  {:.1} s",
                    p.step, p.total, p.loss, p.secs
                ),
                _ => writeln!(
                    self.file,
                    "  {}/{}  loss {:.5}  psnr {:.2} dB  {:.3e} samples/s  {:.1} s",
                    p.step, p.total, p.loss, p.psnr, p.samples_per_s, p.secs
                ),
            };
        }
        self.inner.progress(p);
    }

    fn stage(&mut self, name: &str) {
        use std::io::Write;
        let _ = writeln!(self.file, "== stage {name}");
        self.inner.stage(name);
    }
}

#[cfg(test)]
mod tests {
    use super::Logged;
    use extranerf_nerf::train::{Progress, Quiet, Reporter, Unit};

    #[test]
    fn the_log_gives_model_steps_no_psnr_or_pace() {
        let path = std::env::temp_dir().join(format!("extranerf-log-{}.txt", std::process::id()));
        let file = std::fs::File::create(&path).unwrap();
        let mut log = Logged { inner: Quiet, file };
        let p = |unit| Progress {
            unit,
            step: 4,
            total: 4,
            loss: 0.25,
            psnr: 21.5,
            samples_per_s: 1e5,
            secs: 3.0,
            eta: 0.0,
        };
        log.progress(&p(Unit::Steps));
        log.progress(&p(Unit::ModelSteps));
        drop(log);
        let text = std::fs::read_to_string(&path).unwrap();
        let _ = std::fs::remove_file(&path);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(
            lines,
            [
                "  4/4  loss 0.25000  psnr 21.50 dB  1.000e5 samples/s  3.0 s",
                "  4/4  loss 0.25000  3.0 s"
            ]
        );
    }
}
