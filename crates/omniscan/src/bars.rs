//! The command line's view of a stage's progress: a bar with the step,
//! the stage's figures and an ETA, and notes printed above it.

use std::sync::Mutex;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// Draws [`omniscan_pipeline::Progress`] on stderr.
pub struct Bars {
    bar: Mutex<Option<ProgressBar>>,
}

impl Bars {
    pub fn new() -> Bars {
        Bars {
            bar: Mutex::new(None),
        }
    }

    fn with(&self, f: impl FnOnce(&ProgressBar)) {
        if let Some(bar) = self.bar.lock().expect("progress lock").as_ref() {
            f(bar);
        }
    }
}

impl omniscan_pipeline::Progress for Bars {
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
