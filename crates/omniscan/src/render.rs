//! `omniscan render`: images of a splat model from orbiting cameras or from a
//! capture's or a photo set's cameras, on the CPU reference rasterizer or the
//! GPU (`--backend`).

use std::path::PathBuf;

use anyhow::{Result, bail};
use rayon::prelude::*;

use omniscan_core::image_io::{RgbImage, write_rgb};
use omniscan_splat::backend::{Backend, Renderer};
use omniscan_splat::ply::read_splats;
use omniscan_splat::raster::Camera;

#[derive(clap::Args)]
pub struct RenderArgs {
    /// The splat model (3DGS PLY).
    pub model: PathBuf,
    /// Output directory for the PNG images.
    #[arg(long)]
    pub out: PathBuf,
    /// Number of turntable views (ignored with --capture).
    #[arg(long, default_value_t = 8)]
    pub orbit: usize,
    /// Render the cameras of this capture instead (in the model's frame: the holding gripper's, the left one's for both arms), or of a photo set (a transforms.json, its directory, or a cameras.json), each at its image's size. A photo set's lens distortion is not applied: the renders are the pinhole camera's, which training compared with the undistorted photos.
    #[arg(long)]
    pub capture: Option<PathBuf>,
    /// Which arm's cameras of the capture.
    #[arg(long, value_enum, default_value = "left")]
    pub arm: crate::train::ArmSet,
    #[command(flatten)]
    pub merge: crate::train::RightToLeftArg,
    /// Image width for turntable views, pixels.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height for turntable views, pixels.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Background colour, three numbers in [0, 1].
    #[arg(long, value_delimiter = ',', default_values_t = [0.0, 0.0, 0.0])]
    pub background: Vec<f32>,
    /// Where to render: auto (a real GPU when there is one, else the CPU), cpu, or gpu (any Vulkan/Metal/DX12 device, software ones included).
    #[arg(long, default_value = "auto")]
    pub backend: Backend,
}

/// The largest image side rendered on request (turntables, `bench splat`), pixels.
pub const MAX_SIDE: u32 = 16384;

pub fn run(args: RenderArgs) -> Result<()> {
    let model = read_splats(&args.model)?;
    if args.background.len() != 3 {
        bail!("--background takes three numbers, e.g. 1,1,1");
    }
    if args.capture.is_none() {
        if args.orbit == 0 {
            bail!("--orbit must be at least 1 view");
        }
        // A mistyped size (10⁶ x 10⁶) rendered for minutes, then failed.
        if !(1..=MAX_SIDE).contains(&args.width) || !(1..=MAX_SIDE).contains(&args.height) {
            bail!(
                "--width and --height must be 1 to {MAX_SIDE} pixels, got {}x{}",
                args.width,
                args.height
            );
        }
    }
    let cameras: Vec<(String, Camera<f32>)> = match &args.capture {
        Some(c) => {
            let right_to_left = args.merge.read(args.arm)?;
            let (source, _) = crate::train::view_source(c, args.arm, right_to_left, 1)?;
            let mut cameras: Vec<(String, Camera<f32>)> = (0..source.len())
                .map(|i| source.camera(i))
                .collect::<Result<_, _>>()?;
            // Images named alike in different folders would overwrite each other.
            let names: std::collections::HashSet<&String> =
                cameras.iter().map(|(name, _)| name).collect();
            if names.len() < cameras.len() {
                for (i, (name, _)) in cameras.iter_mut().enumerate() {
                    *name = format!("{i:04}_{name}");
                }
            }
            cameras
        }
        None => omniscan_splat::orbit::orbit_cameras(&model, args.orbit, args.width, args.height)
            .into_iter()
            .enumerate()
            .map(|(i, c)| (format!("orbit_{i:03}"), c))
            .collect(),
    };
    let settings =
        model.render_settings([args.background[0], args.background[1], args.background[2]]);
    let gaussians = model.gaussians::<f32>();
    let renderer = Renderer::new(args.backend)?;
    tracing::info!("rendering on {}", renderer.describe());
    let bar = indicatif::ProgressBar::new(cameras.len() as u64);
    let one = |(name, camera): &(String, Camera<f32>)| -> Result<()> {
        let r = renderer.render(&gaussians, camera, &settings)?;
        let data = r
            .rgb
            .iter()
            .flat_map(|c| c.map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8))
            .collect();
        write_rgb(
            &args.out.join(format!("{name}.png")),
            &RgbImage {
                width: r.width,
                height: r.height,
                data,
            },
        )?;
        bar.inc(1);
        Ok(())
    };
    // One device serves views one at a time; the CPU renders them in parallel.
    if renderer.is_gpu() {
        cameras.iter().try_for_each(one)?;
    } else {
        cameras.par_iter().try_for_each(one)?;
    }
    bar.finish_and_clear();
    println!("wrote {} images to {}", cameras.len(), args.out.display());
    Ok(())
}
