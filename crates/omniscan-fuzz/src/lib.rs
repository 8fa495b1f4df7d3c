//! Fuzzing omniscan's readers: every file format a user hands omniscan
//! (3DGS and point-cloud PLY, SPZ, glTF splats, PlayCanvas' compressed
//! PLY, PCD, XYZ, `capture.json`, nerfstudio's
//! `transforms.json`, `cameras.json`, training checkpoints, PNG) is read
//! from mutated copies of valid files, and any panic, hang or accepted
//! file that breaks the reader's own promise (a model that does not pass
//! `validate`, or does not survive a write and read back) is a failure,
//! saved for replay.
//!
//! Why our own harness rather than `cargo fuzz`: cargo-fuzz needs a
//! nightly toolchain (libFuzzer's sanitizer coverage), and omniscan builds,
//! tests and runs CI on stable only. What this harness gives up is
//! coverage guidance; it makes up part of it two ways. The mutator knows
//! the formats' shape (numbers in text are swapped for extreme ones, lines
//! dropped or repeated, floats in binary bodies overwritten with NaN, ∞,
//! 3·10³⁸), as the trial that found issue 55's readers' faults did by hand.
//! And an input whose outcome is new (an error message not seen before,
//! digits ignored) joins the corpus, so the search spreads over the
//! readers' distinct paths rather than their first check.
//!
//! Each input is written to a file and read through the public reader by
//! path, as a user's file is, on a worker thread watched by the caller: a
//! panic is caught and reported with its message, an input running past
//! the time limit is reported as a hang. An input that aborts the process
//! (an allocation failure) survives as the target's `input` file in the
//! work folder, which `scripts/fuzz` names when the run dies.

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod seeds;

/// A reader under test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Target {
    /// A 3DGS splat model (`omniscan_splat::ply::read_splats`).
    PlySplats,
    /// A `.splat` web-viewer model.
    DotSplat,
    /// Niantic's SPZ, every version.
    Spz,
    /// glTF binary with `KHR_gaussian_splatting`.
    Glb,
    /// PlayCanvas' compressed PLY.
    CompressedPly,
    /// A point cloud in PLY (`omniscan_register::cloud::read_cloud`).
    PlyCloud,
    /// A PCL point cloud, ASCII, binary and compressed.
    Pcd,
    /// Plain-text points.
    Xyz,
    /// A capture's `capture.json`, with the capture's images beside it.
    Capture,
    /// nerfstudio's `transforms.json`, images beside it; the first view read.
    TransformsJson,
    /// A `cameras.json` photo set, images beside it; the first view read.
    CamerasJson,
    /// A training checkpoint (safetensors).
    Checkpoint,
    /// PNG images read as colour, mask and depth.
    Png,
}

impl Target {
    pub const ALL: [Target; 13] = [
        Target::PlySplats,
        Target::DotSplat,
        Target::Spz,
        Target::Glb,
        Target::CompressedPly,
        Target::PlyCloud,
        Target::Pcd,
        Target::Xyz,
        Target::Capture,
        Target::TransformsJson,
        Target::CamerasJson,
        Target::Checkpoint,
        Target::Png,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Target::PlySplats => "ply-splats",
            Target::DotSplat => "dot-splat",
            Target::Spz => "spz",
            Target::Glb => "glb",
            Target::CompressedPly => "compressed-ply",
            Target::PlyCloud => "ply-cloud",
            Target::Pcd => "pcd",
            Target::Xyz => "xyz",
            Target::Capture => "capture",
            Target::TransformsJson => "transforms-json",
            Target::CamerasJson => "cameras-json",
            Target::Checkpoint => "checkpoint",
            Target::Png => "png",
        }
    }

    pub fn from_name(name: &str) -> Option<Target> {
        Target::ALL.into_iter().find(|t| t.name() == name)
    }

    /// The file name an input is written under (the readers look at the
    /// extension, and the JSON targets at the name).
    fn file_name(self) -> &'static str {
        match self {
            Target::PlySplats | Target::PlyCloud => "input.ply",
            Target::DotSplat => "input.splat",
            Target::Spz => "input.spz",
            Target::Glb => "input.glb",
            Target::CompressedPly => "input.compressed.ply",
            Target::Pcd => "input.pcd",
            Target::Xyz => "input.xyz",
            Target::Capture => "capture.json",
            Target::TransformsJson => "transforms.json",
            Target::CamerasJson => "cameras.json",
            Target::Checkpoint => "input.safetensors",
            Target::Png => "input.png",
        }
    }
}

/// What reading one input came to.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    Accepted,
    Refused(String),
    /// A panic, or an accepted file that broke the reader's promise.
    Failed(String),
}

/// Reads the file at `path` as `target` does, and checks what it accepts.
fn read(target: Target, path: &Path) -> Outcome {
    let refused = |e: &dyn std::fmt::Display| Outcome::Refused(e.to_string());
    match target {
        Target::PlySplats
        | Target::DotSplat
        | Target::Spz
        | Target::Glb
        | Target::CompressedPly => match omniscan_splat::ply::read_splats(path) {
            Err(e) => refused(&e),
            Ok(splats) => splats_keep_their_promise(&splats, path),
        },
        Target::PlyCloud | Target::Pcd | Target::Xyz => {
            match omniscan_register::cloud::read_cloud(path) {
                Err(e) => refused(&e),
                Ok(cloud) => match cloud.validate("the cloud") {
                    Ok(()) => Outcome::Accepted,
                    Err(e) => Outcome::Failed(format!("accepted a cloud that fails validate: {e}")),
                },
            }
        }
        Target::Capture => match omniscan_core::Capture::load(path.parent().unwrap()) {
            Err(e) => refused(&e),
            Ok(capture) => match capture.file.camera.intrinsics.validate() {
                Ok(()) => Outcome::Accepted,
                Err(e) => Outcome::Failed(format!("accepted a camera that fails validate: {e}")),
            },
        },
        Target::TransformsJson | Target::CamerasJson => read_photo_set(path),
        Target::Checkpoint => match omniscan_splat::checkpoint::load(path) {
            Err(e) => refused(&e),
            Ok(state) => splats_keep_their_promise(&state.splats, path),
        },
        Target::Png => {
            use omniscan_core::image_io::{read_depth, read_mask, read_rgb};
            // A PNG is read as what its pixels are; the others refuse it.
            let results = [
                read_rgb(path).map(drop),
                read_mask(path).map(drop),
                read_depth(path).map(drop),
            ];
            if results.iter().any(Result::is_ok) {
                Outcome::Accepted
            } else {
                let errors: Vec<String> = results
                    .into_iter()
                    .filter_map(|r| r.err().map(|e| e.to_string()))
                    .collect();
                Outcome::Refused(errors.join("; "))
            }
        }
    }
}

fn read_photo_set(path: &Path) -> Outcome {
    use omniscan_splat::views::ViewSource;
    let source = match ViewSource::from_photo_set(path, 1) {
        Ok(source) => source,
        Err(e) => return Outcome::Refused(e.to_string()),
    };
    if let Err(e) = source.check_photos(false) {
        return Outcome::Refused(e.to_string());
    }
    match source.load(0) {
        Err(e) => Outcome::Refused(e.to_string()),
        Ok(view) => {
            let finite = view.image.iter().flatten().all(|v| v.is_finite())
                && view.camera.viewmat.iter().flatten().all(|v| v.is_finite());
            if finite {
                Outcome::Accepted
            } else {
                Outcome::Failed("accepted a view with NaN pixels or camera".into())
            }
        }
    }
}

/// An accepted model passes `validate` and reads back as written.
fn splats_keep_their_promise(splats: &omniscan_splat::Splats, path: &Path) -> Outcome {
    if let Err(e) = splats.validate() {
        return Outcome::Failed(format!("accepted a model that fails validate: {e}"));
    }
    let again = path.with_extension("again.ply");
    let back = omniscan_splat::ply::write_splats(&again, splats)
        .and_then(|()| omniscan_splat::ply::read_splats(&again));
    match back {
        Ok(back) if &back == splats => Outcome::Accepted,
        Ok(_) => Outcome::Failed("an accepted model reads back different".into()),
        Err(e) => Outcome::Failed(format!("an accepted model does not read back: {e}")),
    }
}

/// The corpus of one target: seed files and inputs with new outcomes.
#[derive(Debug, Default)]
struct Corpus {
    inputs: Vec<Vec<u8>>,
    /// Outcome classes seen (error messages with their digits dropped).
    seen: std::collections::HashSet<String>,
}

const MAX_CORPUS: usize = 2000;

/// What an error message says, without what it quotes: only its words
/// ([`is_word`]) are kept, the first seven after the file's path, so
/// "bad number `x1` in `POINTS 9`" and "bad number `y2` in `WIDTH 1`" are
/// one outcome and the corpus keeps inputs that reach other checks.
fn message_class(message: &str) -> String {
    let mut words = Vec::new();
    let mut quoted = None;
    let mut word = String::new();
    let after_path = message.split_once(": ").map_or(message, |(_, rest)| rest);
    for c in after_path.chars().chain([' ']) {
        match quoted {
            Some(end) if c == end => quoted = None,
            Some(_) => {}
            None if c == '`' || c == '"' => quoted = Some(c),
            None if c.is_alphabetic() => word.push(c),
            None if c.is_whitespace() || ".,:;()[]{}!?".contains(c) => {
                if is_word(&word) {
                    words.push(std::mem::take(&mut word));
                }
                word.clear();
            }
            // A token with digits or signs in it is a value, not a word.
            None => word.push('0'),
        }
    }
    words.truncate(7);
    words.join(" ")
}

/// Letters written as words are: lower case, capitalised, or a short
/// capital name (PLY, DATA); a mutated value quoted without its quotes
/// ("commLaNb", "NaHWIDTH") is not one.
fn is_word(token: &str) -> bool {
    let mut chars = token.chars();
    let Some(first) = chars.next() else {
        return false;
    };
    let rest: Vec<char> = chars.collect();
    token.chars().all(char::is_alphabetic)
        && !rest.is_empty()
        && (rest.iter().all(|c| c.is_lowercase())
            || (first.is_uppercase() && rest.iter().all(|c| c.is_uppercase()) && rest.len() < 6))
}

impl Corpus {
    /// Keeps `input` when its outcome is one not seen before.
    fn offer(&mut self, input: &[u8], outcome: &Outcome) {
        let class = match outcome {
            Outcome::Accepted => "accepted".to_string(),
            Outcome::Refused(m) | Outcome::Failed(m) => message_class(m),
        };
        if self.seen.insert(class) && self.inputs.len() < MAX_CORPUS {
            self.inputs.push(input.to_vec());
        }
    }
}

/// Numbers that readers have mishandled: zero, negatives, overflow of
/// 32 and 64 bits, the float extremes and non-numbers.
const NUMBERS: [&str; 16] = [
    "0",
    "-1",
    "1",
    "-0",
    "1e30",
    "-1e30",
    "3e38",
    "1e-300",
    "NaN",
    "inf",
    "-inf",
    "4294967296",
    "18446744073709551616",
    "2147483648",
    "9999999999999",
    "0.5",
];

/// Float bit patterns for binary bodies.
const FLOATS: [f32; 8] = [
    f32::NAN,
    f32::INFINITY,
    f32::NEG_INFINITY,
    3e38,
    -3e38,
    0.0,
    -0.0,
    1e-45,
];

/// One to four mutations of `input`, some borrowing from `corpus`.
pub fn mutate(rng: &mut ChaCha8Rng, input: &[u8], corpus: &[Vec<u8>]) -> Vec<u8> {
    let mut data = input.to_vec();
    for _ in 0..rng.random_range(1..=4) {
        mutate_once(rng, &mut data, corpus);
    }
    data
}

fn mutate_once(rng: &mut ChaCha8Rng, data: &mut Vec<u8>, corpus: &[Vec<u8>]) {
    if data.is_empty() {
        data.push(rng.random());
        return;
    }
    // A JSON file is mostly edited as JSON: a byte flip breaks its syntax,
    // which the first check refuses, and the checks behind it go untried.
    if rng.random_bool(0.7)
        && let Ok(mut value) = serde_json::from_slice::<serde_json::Value>(data)
    {
        mutate_json(rng, &mut value);
        *data = serde_json::to_vec_pretty(&value).unwrap_or_default();
        return;
    }
    let len = data.len();
    let at = rng.random_range(0..len);
    match rng.random_range(0..10) {
        0 => data[at] ^= 1 << rng.random_range(0..8),
        1 => {
            data[at] = *[0u8, 0xff, 0x7f, 0x80, b'\n', b' ', b'-', b'9']
                .get(rng.random_range(0..8))
                .unwrap()
        }
        2 => {
            let end = (at + rng.random_range(1..=16.max(len / 4))).min(len);
            data.drain(at..end);
        }
        3 => {
            let end = (at + rng.random_range(1..=64)).min(len);
            let copy = data[at..end].to_vec();
            let to = rng.random_range(0..=data.len());
            data.splice(to..to, copy);
        }
        4 => data.truncate(at),
        5 => {
            // The tail of another input of the same format after this one's head.
            let other = &corpus[rng.random_range(0..corpus.len())];
            if !other.is_empty() {
                let from = rng.random_range(0..other.len());
                data.truncate(at);
                data.extend_from_slice(&other[from..]);
            }
        }
        6 | 7 => replace_number(rng, data),
        8 => edit_line(rng, data),
        _ => {
            let at = at & !3;
            if at + 4 <= len {
                let v = FLOATS[rng.random_range(0..FLOATS.len())];
                data[at..at + 4].copy_from_slice(&v.to_le_bytes());
            }
        }
    }
}

/// Replaces, removes or repeats one value somewhere in `value`.
fn mutate_json(rng: &mut ChaCha8Rng, value: &mut serde_json::Value) {
    use serde_json::{Value, json};
    // Walk down a random path, stopping at a random depth.
    let mut at = value;
    loop {
        let children = match at {
            Value::Array(a) => a.len(),
            Value::Object(o) => o.len(),
            _ => 0,
        };
        if children == 0 || rng.random_bool(0.25) {
            break;
        }
        let i = rng.random_range(0..children);
        // Sometimes remove or repeat a child instead of going into it.
        match (rng.random_range(0..8), &mut *at) {
            (0, Value::Array(a)) => {
                a.remove(i);
                return;
            }
            (1, Value::Array(a)) => {
                let copy = a[i].clone();
                a.insert(i, copy);
                return;
            }
            (0, Value::Object(o)) => {
                let key = o.keys().nth(i).cloned().unwrap_or_default();
                o.remove(&key);
                return;
            }
            _ => {}
        }
        at = match at {
            Value::Array(a) => &mut a[i],
            Value::Object(o) => o.values_mut().nth(i).expect("i < len"),
            _ => unreachable!("a leaf has no children"),
        };
    }
    let replacements = [
        json!(0),
        json!(-1),
        json!(0.5),
        json!(1e30),
        json!(-1e30),
        json!(1e308),
        json!(4294967296u64),
        json!(u64::MAX),
        json!(1e-300),
        json!(null),
        json!(true),
        json!(""),
        json!("../outside.png"),
        json!("/etc/hostname"),
        json!("images/missing.png"),
        json!("capture.json"),
        json!([]),
        json!({}),
        json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]),
    ];
    *at = replacements[rng.random_range(0..replacements.len())].clone();
}

/// Swaps a number written in text (the header of a PLY or PCD, a JSON
/// value) for one of [`NUMBERS`].
fn replace_number(rng: &mut ChaCha8Rng, data: &mut Vec<u8>) {
    let starts: Vec<usize> = (0..data.len())
        .filter(|&i| data[i].is_ascii_digit() && (i == 0 || !data[i - 1].is_ascii_digit()))
        .collect();
    if starts.is_empty() {
        return;
    }
    let start = starts[rng.random_range(0..starts.len())];
    let mut end = start;
    while end < data.len() && (data[end].is_ascii_digit() || b".eE-+".contains(&data[end])) {
        end += 1;
    }
    let start = if start > 0 && data[start - 1] == b'-' {
        start - 1
    } else {
        start
    };
    let number = NUMBERS[rng.random_range(0..NUMBERS.len())];
    data.splice(start..end, number.bytes());
}

/// Drops, repeats or swaps a line (of a header or a JSON file).
fn edit_line(rng: &mut ChaCha8Rng, data: &mut Vec<u8>) {
    let breaks: Vec<usize> = (0..data.len()).filter(|&i| data[i] == b'\n').collect();
    if breaks.len() < 2 {
        return;
    }
    let i = rng.random_range(0..breaks.len() - 1);
    let line = breaks[i] + 1..breaks[i + 1] + 1;
    let text = data[line.clone()].to_vec();
    match rng.random_range(0..3) {
        0 => {
            data.drain(line);
        }
        1 => {
            data.splice(line.start..line.start, text);
        }
        _ => {
            let j = rng.random_range(0..breaks.len() - 1);
            let other = breaks[j] + 1..breaks[j + 1] + 1;
            let other_text = data[other.clone()].to_vec();
            if other.start > line.end {
                data.splice(other, text);
                data.splice(line, other_text);
            } else if other.end < line.start {
                data.splice(line, other_text);
                data.splice(other, text);
            }
        }
    }
}

/// What a fuzzing run of one target did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Report {
    pub target: &'static str,
    pub executions: u64,
    pub seconds: f64,
    pub accepted: u64,
    pub corpus: usize,
    /// Outcome classes found (distinct error messages, and acceptance).
    pub outcomes: usize,
    /// Saved failures: the file and what went wrong.
    pub failures: Vec<(PathBuf, String)>,
}

/// Fuzzes `target` for `duration` (or `max_executions`), from `seed`,
/// working in `work` (seeds, the current input, saved failures under
/// `work/failures/<target>/`). Stops at the first failure, saved there
/// with its message. `hang` is how long one input may take.
pub fn fuzz(
    target: Target,
    work: &Path,
    duration: Duration,
    max_executions: u64,
    seed: u64,
    hang: Duration,
) -> Result<Report> {
    let dir = work.join(target.name());
    let seeds = seeds::write(target, &dir).with_context(|| format!("seeding {}", target.name()))?;
    let input_path = dir.join(target.file_name());
    let mut corpus = Corpus::default();
    let worker = Worker::start(target, input_path.clone());
    for s in &seeds {
        match worker.read(s, hang)? {
            Outcome::Failed(m) => bail!("{}: a seed fails: {m}", target.name()),
            outcome => corpus.offer(s, &outcome),
        }
    }
    corpus.inputs = seeds.clone();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let start = Instant::now();
    let mut report = Report {
        target: target.name(),
        executions: 0,
        seconds: 0.0,
        accepted: 0,
        corpus: 0,
        outcomes: 0,
        failures: Vec::new(),
    };
    while start.elapsed() < duration && report.executions < max_executions {
        // Often from a seed: descendants of inputs refused at the first
        // check (a JSON file's syntax) would mostly be refused there too.
        let pool = if rng.random_bool(0.4) {
            &seeds
        } else {
            &corpus.inputs
        };
        let parent = &pool[rng.random_range(0..pool.len())];
        let input = mutate(&mut rng, parent, &corpus.inputs);
        // A hang leaves the worker stuck on this input: it is saved, and the run ends.
        let outcome = worker
            .read(&input, hang)
            .unwrap_or_else(|e| Outcome::Failed(e.to_string()));
        report.executions += 1;
        match &outcome {
            Outcome::Accepted => report.accepted += 1,
            Outcome::Failed(m) => {
                let saved = save_failure(work, target, &input, m)?;
                report.failures.push((saved, m.clone()));
                break;
            }
            Outcome::Refused(_) => {}
        }
        corpus.offer(&input, &outcome);
    }
    report.seconds = start.elapsed().as_secs_f64();
    report.corpus = corpus.inputs.len();
    report.outcomes = corpus.seen.len();
    Ok(report)
}

fn save_failure(work: &Path, target: Target, input: &[u8], message: &str) -> Result<PathBuf> {
    let dir = work.join("failures").join(target.name());
    std::fs::create_dir_all(&dir)?;
    let digest = omniscan_core::digest::Digest::of(input);
    let path = dir.join(format!("{digest}-{}", target.file_name()));
    std::fs::write(&path, input)?;
    std::fs::write(path.with_extension("txt"), message)?;
    Ok(path)
}

/// A thread that reads inputs as `target` and answers with the outcome,
/// catching panics; the caller waits for each answer up to a time limit.
struct Worker {
    inputs: mpsc::Sender<Vec<u8>>,
    outcomes: mpsc::Receiver<Outcome>,
}

impl Worker {
    fn start(target: Target, path: PathBuf) -> Worker {
        let (inputs, rx) = mpsc::channel::<Vec<u8>>();
        let (tx, outcomes) = mpsc::channel();
        // The default hook prints every caught panic; the message is
        // reported with the saved input instead.
        std::panic::set_hook(Box::new(|_| {}));
        std::thread::spawn(move || {
            for input in rx {
                let outcome = match std::fs::write(&path, &input) {
                    Err(e) => Outcome::Failed(format!("cannot write the input: {e}")),
                    Ok(()) => {
                        std::panic::catch_unwind(|| read(target, &path)).unwrap_or_else(|panic| {
                            let message = panic
                                .downcast_ref::<String>()
                                .cloned()
                                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                                .unwrap_or_default();
                            Outcome::Failed(format!("panicked: {message}"))
                        })
                    }
                };
                if tx.send(outcome).is_err() {
                    break;
                }
            }
        });
        Worker { inputs, outcomes }
    }

    /// The outcome of `input`, or an error when it takes over `hang`.
    fn read(&self, input: &[u8], hang: Duration) -> Result<Outcome> {
        self.inputs.send(input.to_vec())?;
        match self.outcomes.recv_timeout(hang) {
            Ok(outcome) => Ok(outcome),
            Err(_) => bail!("hung: no answer within {} s", hang.as_secs_f64()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mutations_are_deterministic_for_a_seed() {
        let input =
            b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n2\n";
        let run = |seed| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            (0..50)
                .map(|_| mutate(&mut rng, input, &[input.to_vec()]))
                .collect::<Vec<_>>()
        };
        assert_eq!(run(3), run(3));
        assert_ne!(run(3), run(4));
        assert!(run(3).iter().any(|m| m.as_slice() != input));
    }

    #[test]
    fn messages_are_classed_by_their_words() {
        let a =
            message_class("/tmp/a/input.pcd: bad number `x1` in `POINTS 9` (a count, 0 or more)");
        let b =
            message_class("/tmp/b/input.pcd: bad number `-e5` in `WIDTH -1` (a count, 0 or more)");
        assert_eq!(a, b);
        assert_eq!(a, "bad number in count or more");
        assert_ne!(
            a,
            message_class("/tmp/a/input.pcd: PCD header has no DATA line")
        );
    }

    #[test]
    fn numbers_in_text_are_swapped_for_extreme_ones() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut seen = std::collections::HashSet::new();
        for _ in 0..200 {
            let mut data = b"element vertex 12\n".to_vec();
            replace_number(&mut rng, &mut data);
            seen.insert(String::from_utf8(data).unwrap());
        }
        assert!(seen.contains("element vertex 4294967296\n"), "{seen:?}");
        assert!(seen.contains("element vertex -1\n"), "{seen:?}");
    }
}
