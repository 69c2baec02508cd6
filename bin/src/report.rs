//! How the command line shows the pipeline's progress: a progress bar with the loss, pace and
//! ETA on a terminal, one line per window otherwise (logs keep every line).

use std::io::IsTerminal;

use extranerf_extrapolate::driver::{Progress, Reporter};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// Progress on stderr.
pub struct Console {
    tty: bool,
    bar: Option<ProgressBar>,
}

impl Console {
    pub fn new() -> Console {
        Console {
            tty: std::io::stderr().is_terminal(),
            bar: None,
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
        if !self.tty {
            eprintln!(
                "step {:>5}/{}  loss {:.5}  psnr {:6.2} dB  {:.3e} samples/s  {:.1} s elapsed  ETA {:.0} s",
                p.step, p.total, p.loss, p.psnr, p.samples_per_s, p.secs, p.eta
            );
            return;
        }
        let bar = self.bar.get_or_insert_with(|| {
            let bar =
                ProgressBar::with_draw_target(Some(p.total as u64), ProgressDrawTarget::stderr());
            // The template is a constant that indicatif accepts.
            if let Ok(style) = ProgressStyle::with_template("{bar:30} {pos:>5}/{len} steps  {msg}")
            {
                bar.set_style(style);
            }
            bar
        });
        bar.set_length(p.total as u64);
        bar.set_position(p.step as u64);
        bar.set_message(format!(
            "loss {:.5}  psnr {:.2} dB  {:.2e} samples/s  {:.0} s, ETA {:.0} s",
            p.loss, p.psnr, p.samples_per_s, p.secs, p.eta
        ));
    }
}

impl Drop for Console {
    fn drop(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish();
        }
    }
}
