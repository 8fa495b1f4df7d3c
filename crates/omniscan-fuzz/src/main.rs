//! `omniscan-fuzz`: fuzzes omniscan's readers for a given time (see the
//! library's docs for what a failure is and why the harness is our own).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Result, bail};
use clap::Parser;

use omniscan_fuzz::{Target, fuzz};

#[derive(Parser)]
#[command(name = "omniscan-fuzz", about = "Fuzz omniscan's file readers")]
struct Args {
    /// Readers to fuzz (ply-splats, dot-splat, ply-cloud, pcd, xyz, capture, transforms-json, cameras-json, checkpoint, png), or `all`.
    #[arg(default_value = "all")]
    targets: Vec<String>,
    /// Seconds to fuzz each target.
    #[arg(long, default_value_t = 60)]
    seconds: u64,
    /// Seed of the mutations (a run is repeatable for a seed, up to timing).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Seconds one input may take before it counts as a hang.
    #[arg(long, default_value_t = 10)]
    hang_seconds: u64,
    /// Work folder: seeds, the input being read, and failures under failures/<target>/.
    #[arg(long, default_value = "target/fuzz")]
    work: PathBuf,
    /// Print the reports as JSON lines.
    #[arg(long)]
    json: bool,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let targets: Vec<Target> = if args.targets.iter().any(|t| t == "all") {
        Target::ALL.to_vec()
    } else {
        args.targets
            .iter()
            .map(|name| {
                Target::from_name(name).ok_or_else(|| anyhow::anyhow!("no fuzz target `{name}`"))
            })
            .collect::<Result<_>>()?
    };
    let mut failed = 0;
    for target in targets {
        let report = fuzz(
            target,
            &args.work,
            Duration::from_secs(args.seconds),
            u64::MAX,
            args.seed,
            Duration::from_secs(args.hang_seconds),
        )?;
        if args.json {
            println!("{}", serde_json::to_string(&report)?);
        } else {
            println!(
                "{}: {} inputs in {:.0} s ({:.0}/s), {} accepted, {} distinct outcomes, corpus {}, {} failures",
                report.target,
                report.executions,
                report.seconds,
                report.executions as f64 / report.seconds.max(1e-9),
                report.accepted,
                report.outcomes,
                report.corpus,
                report.failures.len()
            );
        }
        for (path, message) in &report.failures {
            eprintln!("  FAILURE {}: {message}", path.display());
        }
        failed += report.failures.len();
    }
    if failed > 0 {
        bail!(
            "{failed} failures (inputs saved under {}/failures)",
            args.work.display()
        );
    }
    Ok(())
}
