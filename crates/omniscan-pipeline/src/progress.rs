//! How a stage tells its caller how far it is: the CLI draws bars, the
//! Python bindings call back, tests stay silent. Every method has a no-op
//! default, so a caller implements only what it shows. [`Bars`] is the
//! terminal's.

use std::sync::Mutex;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// Progress of a stage's long work. Implementations must be `Sync`: the
/// CPU paths report from rayon's threads.
pub trait Progress: Sync {
    /// A piece of work begins: `total` items of `unit` ("steps", "frames",
    /// "views"; a total of 0 means unknown), described by `label`.
    fn start(&self, label: &str, total: u64, unit: &str) {
        let _ = (label, total, unit);
    }
    /// `done` of the current work's items are done.
    fn set(&self, done: u64) {
        let _ = done;
    }
    /// One more item is done.
    fn advance(&self) {}
    /// The current work's figures ("loss 0.0312, PSNR 27.40 dB").
    fn message(&self, text: &str) {
        let _ = text;
    }
    /// The current work ended.
    fn finish(&self) {}
    /// A line for the user: what a stage decided (reused, resumed, fell
    /// back to the CPU).
    fn note(&self, line: &str) {
        let _ = line;
    }
}

/// Reports nothing.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Progress for Silent {}

/// Draws [`Progress`] on a terminal's stderr: a bar with the step, the
/// stage's figures and an ETA (a spinner where the total is unknown), and
/// notes printed above it. The command line and the benchmarks use it.
#[derive(Default)]
pub struct Bars {
    bar: Mutex<Option<ProgressBar>>,
}

impl Bars {
    pub fn new() -> Bars {
        Bars::default()
    }

    fn with(&self, f: impl FnOnce(&ProgressBar)) {
        if let Some(bar) = self.bar.lock().expect("progress lock").as_ref() {
            f(bar);
        }
    }
}

impl Progress for Bars {
    fn start(&self, label: &str, total: u64, unit: &str) {
        let bar = if total == 0 {
            let bar = ProgressBar::new_spinner();
            bar.set_style(
                ProgressStyle::with_template(&format!("{{spinner}} {label} [{{elapsed}}]"))
                    .expect("a valid template"),
            );
            bar.enable_steady_tick(std::time::Duration::from_millis(120));
            bar
        } else {
            let bar = ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::stderr());
            bar.set_style(
                ProgressStyle::with_template(&format!(
                    "{label} [{{bar:40}}] {{pos}}/{{len}} {unit} {{msg}} ({{elapsed_precise}}, eta {{eta}})"
                ))
                .expect("a valid template")
                .progress_chars("=> "),
            );
            bar
        };
        if let Some(old) = self.bar.lock().expect("progress lock").replace(bar) {
            old.finish_and_clear();
        }
    }
    fn set(&self, done: u64) {
        self.with(|bar| bar.set_position(done));
    }
    fn advance(&self) {
        self.with(|bar| bar.inc(1));
    }
    fn message(&self, text: &str) {
        self.with(|bar| bar.set_message(text.to_string()));
    }
    fn finish(&self) {
        if let Some(bar) = self.bar.lock().expect("progress lock").take() {
            bar.finish_and_clear();
        }
    }
    fn note(&self, line: &str) {
        match self.bar.lock().expect("progress lock").as_ref() {
            Some(bar) => bar.suspend(|| eprintln!("{line}")),
            None => eprintln!("{line}"),
        }
    }
}
