//! `omniscan bench sim`: the time of a full simulated capture.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use serde_json::json;

use omniscan_sim::{SimConfig, Simulation};

#[derive(clap::Args)]
pub struct BenchArgs {
    #[arg(long, default_value_t = SimConfig::default().object)]
    object: String,
    /// Image width, pixels.
    #[arg(long, default_value_t = SimConfig::default().width)]
    width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = SimConfig::default().height)]
    height: u32,
    /// Directory for the capture (a temporary one if not given).
    #[arg(long)]
    out: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

pub fn bench(args: BenchArgs) -> Result<()> {
    let tmp;
    let dir = match args.out {
        Some(d) => d,
        None => {
            tmp = tempfile::tempdir()?;
            tmp.path().join("capture")
        }
    };
    let (width, height) = (args.width, args.height);
    let config = SimConfig {
        object: args.object,
        width,
        height,
        ..SimConfig::default()
    };
    let setup = Instant::now();
    let sim = Simulation::new(config)?;
    let setup_s = setup.elapsed().as_secs_f64();
    let bar = crate::progress_bar(sim.frames.len(), "bench sim", "frames");
    let summary = sim.run(&dir, &|done, _| bar.set_position(done as u64))?;
    bar.finish_and_clear();
    let total = setup_s + summary.seconds;
    let threads = rayon::current_num_threads();
    let per_frame = summary.seconds / (summary.frames + summary.empty_frames) as f64;
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({
                "object": sim.config.object, "width": width, "height": height,
                "frames": summary.frames, "empty_frames": summary.empty_frames,
                "setup_s": setup_s, "render_and_write_s": summary.seconds, "total_s": total,
                "seconds_per_frame": per_frame,
                "threads": threads,
            }))?
        );
    } else {
        println!(
            "{}x{} {}: {} frames + {} empty frames in {:.1} s total ({:.1} s setup, {:.3} s per frame, {} threads)",
            width,
            height,
            sim.config.object,
            summary.frames,
            summary.empty_frames,
            total,
            setup_s,
            per_frame,
            threads
        );
    }
    Ok(())
}
