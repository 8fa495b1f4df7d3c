//! omniscan's benchmarks, behind `omniscan bench`: figures go here, not in
//! tests (docs/results.md records them with the command that gave them).
//! Each benchmark measures its baseline in the same run where it claims a
//! ratio (Open3D for registration).

mod formats;
mod inspect;
mod mask;
mod mesh;
mod poses;
mod registration;
mod scans;
mod sim;
mod splat;

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};

/// The benchmarks.
#[derive(clap::Subcommand)]
pub enum BenchCommand {
    /// Registration speed and accuracy: local ICP on frag_115 halves (against Open3D when given), global registration on random rotations.
    Registration(registration::BenchArgs),
    /// Mask accuracy (IoU against ground truth) and time per image on simulated captures.
    Mask(mask::BenchArgs),
    /// Inspection accuracy and time on triplets of generated good and defective copies.
    Inspect(inspect::BenchArgs),
    /// Inspection of independently scanned copies: simulated scans (a defect planted in one copy's mesh), a twin trained per scan, the three twins inspected.
    Scans(scans::BenchArgs),
    /// Rasterizer time per view: CPU forward and forward+backward, GPU forward, on random scenes or models.
    Splat(splat::BenchArgs),
    /// What each model format keeps: renders after a round trip through SPZ, glb, .splat (and splat-transform's files) against the original's, file sizes.
    Formats(formats::BenchArgs),
    /// Mesh accuracy against the simulator's true mesh (Chamfer, F-score, volume), the twin's mesh against a TSDF of the sensor depth; asset time.
    Mesh(mesh::BenchArgs),
    /// Time a full simulated capture: both arms' trajectories plus the empty pass.
    Sim(sim::BenchArgs),
    /// Pose refinement against simulated calibration error: one arm trained on exact, noisy and refined noisy poses; held-out PSNR and the corrections against the truth.
    Poses(poses::BenchArgs),
}

/// Runs one benchmark; it prints its own figures.
pub fn run(command: BenchCommand) -> Result<()> {
    match command {
        BenchCommand::Registration(args) => registration::bench(args),
        BenchCommand::Mask(args) => mask::bench(args),
        BenchCommand::Inspect(args) => inspect::bench(args),
        BenchCommand::Scans(args) => scans::bench(args),
        BenchCommand::Splat(args) => splat::bench(args),
        BenchCommand::Sim(args) => sim::bench(args),
        BenchCommand::Formats(args) => formats::bench(args),
        BenchCommand::Mesh(args) => mesh::bench(args),
        BenchCommand::Poses(args) => poses::bench(args),
    }
}

/// A bar over `total` `items` (frames, views), labelled `what`.
fn progress_bar(total: usize, what: &str, items: &str) -> ProgressBar {
    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template(&format!(
            "{{msg}} [{{bar:40}}] {{pos}}/{{len}} {items}, {{elapsed_precise}} (eta {{eta}})"
        ))
        .expect("a valid template")
        .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}
