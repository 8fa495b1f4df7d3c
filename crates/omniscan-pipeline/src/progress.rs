//! How a stage tells its caller how far it is: the CLI draws bars, the
//! Python bindings call back, tests stay silent. Every method has a no-op
//! default, so a caller implements only what it shows.

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
