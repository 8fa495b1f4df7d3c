//! Images of a splat model from orbiting cameras or from a capture's or a
//! photo set's cameras, on the CPU reference rasterizer or the GPU.

use std::path::{Path, PathBuf};

use anyhow::{Result, bail};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use omniscan_core::image_io::{RgbImage, write_rgb};
use omniscan_splat::backend::{Backend, Renderer};
use omniscan_splat::ply::read_splats;
use omniscan_splat::raster::Camera;

use crate::Progress;
use crate::settings::default_from_flags;
use crate::views::{ArmSet, Merge};

/// The largest image side rendered on request (turntables, `bench splat`), pixels.
pub const MAX_SIDE: u32 = 16384;

/// The most turntable views rendered on request: one every 0.1°.
pub const MAX_ORBIT: usize = 3600;

/// Everything `render` can be told besides the model and output folder.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RenderSettings {
    /// Number of turntable views (ignored with --capture).
    #[arg(long, default_value_t = 8)]
    pub orbit: usize,
    /// Render the cameras of this capture instead (in the model's frame: the holding gripper's, the left one's for both arms), or of a photo set (a transforms.json, its directory, or a cameras.json), each at its image's size. A photo set's lens distortion is not applied: the renders are the pinhole camera's, which training compared with the undistorted photos.
    #[arg(long)]
    pub capture: Option<PathBuf>,
    /// Which arm's cameras of the capture.
    #[arg(long, value_enum, default_value = "left")]
    pub arm: ArmSet,
    #[command(flatten)]
    #[serde(flatten)]
    pub merge: Merge,
    /// Image width for turntable views, pixels.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height for turntable views, pixels.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Background colour, three numbers in [0, 1] (`1,1,1` or `1 1 1`).
    #[arg(long, num_args = 1..=3, value_delimiter = ',', default_values_t = [0.0, 0.0, 0.0])]
    pub background: Vec<f32>,
    /// Where to render: auto (a real GPU when there is one, else the CPU), cpu, or gpu (any Vulkan/Metal/DX12 device, software ones included).
    #[arg(long, default_value = "auto")]
    pub backend: Backend,
}

default_from_flags!(RenderSettings);

/// What [`render`] wrote.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderReport {
    pub out: PathBuf,
    /// The images' file names, in camera order.
    pub images: Vec<String>,
}

/// Renders `model` into PNG images in `out`.
pub fn render(
    model: &Path,
    out: &Path,
    settings: &RenderSettings,
    progress: &dyn Progress,
) -> Result<RenderReport> {
    let splats = read_splats(model)?;
    let [r, g, b] = settings.background[..] else {
        bail!("--background takes three numbers in [0, 1], e.g. 1,1,1 or 1 1 1");
    };
    let cameras = cameras(&splats, settings)?;
    let render_settings = splats.render_settings([r, g, b]);
    let gaussians = splats.gaussians::<f32>();
    let renderer = Renderer::new(settings.backend)?;
    tracing::info!("rendering on {}", renderer.describe());
    progress.start("rendering", cameras.len() as u64, "views");
    let one = |(name, camera): &(String, Camera<f32>)| -> Result<()> {
        let r = renderer.render(&gaussians, camera, &render_settings)?;
        let data = r
            .rgb
            .iter()
            .flat_map(|c| c.map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8))
            .collect();
        write_rgb(
            &out.join(format!("{name}.png")),
            &RgbImage {
                width: r.width,
                height: r.height,
                data,
            },
        )?;
        progress.advance();
        Ok(())
    };
    // One device serves views one at a time; the CPU renders them in
    // parallel, as many at once as memory holds.
    let at_once = render_memory_check(
        &cameras,
        &renderer,
        settings.capture.is_some(),
        crate::memory::available(),
    )?;
    if renderer.is_gpu() {
        cameras.iter().try_for_each(one)?;
    } else {
        crate::memory::with_threads(at_once, || cameras.par_iter().try_for_each(one))??;
    }
    progress.finish();
    Ok(RenderReport {
        out: out.to_path_buf(),
        images: cameras.into_iter().map(|(name, _)| name + ".png").collect(),
    })
}

/// How many views may be rendered at once in the memory available, or an
/// error naming a size that fits when not even the largest alone does.
fn render_memory_check(
    cameras: &[(String, Camera<f32>)],
    renderer: &Renderer,
    from_capture: bool,
    available: Option<u64>,
) -> Result<usize> {
    use crate::memory::{RENDER_BYTES_PER_PIXEL, side_that_fits};
    let Some(largest) = cameras
        .iter()
        .map(|(_, c)| c)
        .max_by_key(|c| c.width as u64 * c.height as u64)
    else {
        return Ok(1);
    };
    let (w, h) = (largest.width, largest.height);
    let wanted = if renderer.is_gpu() {
        1
    } else {
        rayon::current_num_threads()
    };
    crate::memory::views_at_once(
        &format!("rendering a {w}x{h} view"),
        u64::from(w) * u64::from(h) * RENDER_BYTES_PER_PIXEL,
        wanted,
        available,
        |available| {
            let (fw, fh) = side_that_fits(w, h, RENDER_BYTES_PER_PIXEL, available);
            if from_capture {
                format!(
                    "the cameras' images are too large for this machine (about {fw}x{fh} would fit)"
                )
            } else {
                format!("--width {fw} --height {fh} fits")
            }
        },
    )
}

/// The named cameras to render: the capture's (or photo set's), or a turntable.
fn cameras(
    splats: &omniscan_splat::Splats,
    settings: &RenderSettings,
) -> Result<Vec<(String, Camera<f32>)>> {
    let Some(capture) = &settings.capture else {
        if !(1..=MAX_ORBIT).contains(&settings.orbit) {
            bail!(
                "--orbit must be 1 to {MAX_ORBIT} views, got {}",
                settings.orbit
            );
        }
        // A mistyped size (10⁶ x 10⁶) rendered for minutes, then failed.
        let (w, h) = (settings.width, settings.height);
        if !(1..=MAX_SIDE).contains(&w) || !(1..=MAX_SIDE).contains(&h) {
            bail!("--width and --height must be 1 to {MAX_SIDE} pixels, got {w}x{h}");
        }
        let orbit = omniscan_splat::orbit::orbit_cameras(splats, settings.orbit, w, h);
        return Ok(orbit
            .into_iter()
            .enumerate()
            .map(|(i, c)| (format!("orbit_{i:03}"), c))
            .collect());
    };
    let right_to_left = settings.merge.read(settings.arm)?;
    let (source, _) = crate::views::view_source(capture, settings.arm, right_to_left, 1, true)?;
    let mut cameras: Vec<(String, Camera<f32>)> = (0..source.len())
        .map(|i| source.camera(i))
        .collect::<Result<_, _>>()?;
    // Images named alike in different folders would overwrite each other.
    let names: std::collections::HashSet<&String> = cameras.iter().map(|(name, _)| name).collect();
    if names.len() < cameras.len() {
        for (i, (name, _)) in cameras.iter_mut().enumerate() {
            *name = format!("{i:04}_{name}");
        }
    }
    Ok(cameras)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 16384² render needs about 26 GB: with 8 GB it is refused naming a
    /// size that fits, and with 60 GB two such views run at once.
    #[test]
    fn renders_that_do_not_fit_in_memory_are_refused_or_run_fewer_at_once() {
        let splats = omniscan_splat::Splats {
            means: vec![[0.0; 3]],
            log_scales: vec![[-3.0; 3]],
            quats: vec![[1.0, 0.0, 0.0, 0.0]],
            opacity_logits: vec![0.0],
            sh: vec![[0.5; 3]],
            ..Default::default()
        };
        let settings = RenderSettings {
            width: MAX_SIDE,
            height: MAX_SIDE,
            ..RenderSettings::default()
        };
        let cameras = cameras(&splats, &settings).unwrap();
        let gb = 1_000_000_000;
        let error = render_memory_check(&cameras, &Renderer::Cpu, false, Some(8 * gb))
            .unwrap_err()
            .to_string();
        assert!(
            error.starts_with("rendering a 16384x16384 view needs about 25.77 GB"),
            "{error}"
        );
        let (w, h): (u32, u32) = (9128, 9128);
        assert!(
            error.ends_with(&format!("--width {w} --height {h} fits")),
            "{error}"
        );
        assert!(u64::from(w * h) * crate::memory::RENDER_BYTES_PER_PIXEL <= 8 * gb);
        let at_once = render_memory_check(&cameras, &Renderer::Cpu, false, Some(60 * gb)).unwrap();
        assert_eq!(at_once, 2.min(rayon::current_num_threads()));
    }

    #[test]
    fn defaults_parse() {
        let s = RenderSettings::default();
        assert_eq!((s.orbit, s.width, s.height), (8, 640, 480));
        assert_eq!(s.background, vec![0.0; 3]);
    }
}
