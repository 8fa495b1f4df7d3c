//! Drives headless Chromium over one of omniscan's pages, through
//! `web/tests/screenshot.mjs` (playwright-core): loads it from `file://`,
//! waits until the viewer has drawn, screenshots the viewer's canvas and
//! reports console and page errors and any request that would leave the
//! page. For the browser tests and benchmarks; it needs Node.js, Debian's
//! Chromium and `web/node_modules` (`npm ci` in `web/`), which `.ci/run`
//! installs.

use std::path::{Path, PathBuf};
use std::process::Command;

/// What the page did while it was open.
#[derive(serde::Deserialize, Debug)]
#[serde(rename_all = "camelCase")]
pub struct Shot {
    pub console_errors: Vec<String>,
    pub page_errors: Vec<String>,
    /// Requests to anything but `file:`, `data:` and `blob:` (all refused).
    pub external_requests: Vec<String>,
    pub loaded: bool,
    pub error: Option<String>,
    pub frames_drawn: u64,
    /// From navigation to the models shown, milliseconds.
    pub load_ms: f64,
    /// Main-thread tasks over 50 ms (what makes a page freeze), and the
    /// longest of them.
    pub long_tasks: u64,
    pub longest_task_ms: f64,
}

impl Shot {
    /// Whether the page loaded and drew with no error and no request out.
    pub fn clean(&self) -> Result<(), String> {
        if !self.loaded {
            return Err(format!("the viewer did not load: {:?}", self.error));
        }
        for (what, list) in [
            ("console errors", &self.console_errors),
            ("page errors", &self.page_errors),
            ("requests leaving the page", &self.external_requests),
        ] {
            if !list.is_empty() {
                return Err(format!("{what}: {list:?}"));
            }
        }
        Ok(())
    }
}

/// The repository's `web/` folder (where `node_modules` is installed).
pub fn web_folder() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../web")
}

/// Opens `page`, applies `options` (`--width W --height H --camera JSON
/// --background r,g,b --show 0,1 --markers on|off`) and writes the canvas
/// to `out` (PNG).
pub fn screenshot(page: &Path, out: &Path, options: &[&str]) -> Result<Shot, String> {
    let web = web_folder();
    let output = Command::new("node")
        .arg(web.join("tests/screenshot.mjs"))
        .arg(page)
        .arg(out)
        .args(options)
        .current_dir(&web)
        .output()
        .map_err(|e| format!("node: {e}"))?;
    if !output.status.success() {
        return Err(format!(
            "screenshot.mjs failed: {}",
            String::from_utf8_lossy(&output.stderr)
        ));
    }
    let stdout = String::from_utf8_lossy(&output.stdout);
    let last = stdout.lines().last().unwrap_or_default();
    serde_json::from_str(last).map_err(|e| format!("screenshot.mjs printed {last:?}: {e}"))
}
