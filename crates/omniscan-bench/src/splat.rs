//! `omniscan bench splat`: time of the rasterizer's forward pass (and the CPU
//! reference's forward + backward step) at a given size, on random scenes of
//! given sizes or on splat models, CPU against GPU in the same run.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Result, bail};
use serde_json::json;

use omniscan_splat::backend::{Backend, Renderer};
use omniscan_splat::backward::backward;
use omniscan_splat::ply::read_splats;
use omniscan_splat::raster::{Camera, Colors, Gaussians, Settings, project, rasterize};

#[derive(clap::Args)]
pub struct BenchArgs {
    /// Splat models (3DGS PLY) to time, seen from an orbit; without any, random scenes of --gaussians.
    pub models: Vec<PathBuf>,
    /// Sizes of the random scenes, Gaussians.
    #[arg(long, value_delimiter = ',', default_values_t = [50_000usize, 200_000])]
    pub gaussians: Vec<usize>,
    /// Image width, pixels.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Timed runs per measurement (the median is reported; one warm-up run first).
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// GPU to time against the CPU: auto (a real GPU if any, else none), gpu (any device, software included), cpu (CPU only).
    #[arg(long, default_value = "auto")]
    pub backend: Backend,
    #[arg(long)]
    pub json: bool,
}

/// A random object-like scene: `n` Gaussians in a 15 cm ball 1 m in front of
/// the camera, millimetre scales, SH degree 3.
fn random_scene(n: usize, seed: u64) -> Gaussians<f32> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut means = Vec::with_capacity(n);
    while means.len() < n {
        let p: [f32; 3] = [0, 1, 2].map(|_| rng.random_range(-1.0f32..1.0));
        if p.iter().map(|v| v * v).sum::<f32>() <= 1.0 {
            means.push([0.15 * p[0], 0.15 * p[1], 1.0 + 0.15 * p[2]]);
        }
    }
    let scales = (0..n)
        .map(|_| [0, 1, 2].map(|_| (rng.random_range(-7.0f32..-4.5)).exp()))
        .collect();
    let quats = (0..n)
        .map(|_| [0, 1, 2, 3].map(|_| rng.random_range(-1.0f32..1.0)))
        .collect();
    let opacities = (0..n).map(|_| rng.random_range(0.05f32..1.0)).collect();
    let coeffs = (0..n * 16)
        .map(|i| {
            let s = if i % 16 == 0 { 1.0 } else { 0.1 };
            [0, 1, 2].map(|_| s * rng.random_range(-1.0f32..1.0))
        })
        .collect();
    Gaussians {
        means,
        scales,
        quats,
        opacities,
        colors: Colors::Sh { degree: 3, coeffs },
    }
}

/// Splats whose activated parameters are `g` (the bench's scenes are made activated).
fn splats_from(g: &Gaussians<f32>) -> omniscan_splat::Splats {
    let Colors::Sh { degree, coeffs } = &g.colors else {
        return omniscan_splat::Splats::default();
    };
    omniscan_splat::Splats {
        means: g.means.clone(),
        log_scales: g.scales.iter().map(|s| s.map(f32::ln)).collect(),
        quats: g.quats.clone(),
        opacity_logits: g
            .opacities
            .iter()
            .map(|&o| {
                let o = o.clamp(1e-4, 1.0 - 1e-4);
                (o / (1.0 - o)).ln()
            })
            .collect(),
        sh_degree: *degree,
        sh: coeffs.clone(),
        antialiased: false,
        appearance: Default::default(),
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn time(repeats: usize, mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    f()?;
    let mut times = Vec::with_capacity(repeats);
    for _ in 0..repeats {
        let start = Instant::now();
        f()?;
        times.push(start.elapsed().as_secs_f64());
    }
    Ok(median(times))
}

pub fn bench(args: BenchArgs) -> Result<()> {
    if args.repeats == 0 || args.width == 0 || args.height == 0 {
        bail!("--repeats, --width and --height must be at least 1");
    }
    // Beyond these a mistyped figure runs the machine out of memory (10⁹
    // Gaussians, 10⁶-pixel sides) rather than measuring anything.
    let most = omniscan_pipeline::render::MAX_SIDE;
    if args.width > most || args.height > most {
        bail!("--width and --height must be at most {most} pixels");
    }
    if let Some(&n) = args.gaussians.iter().find(|&&n| n > 20_000_000) {
        bail!("--gaussians {n} is more than 20,000,000");
    }
    let gpu = match args.backend {
        Backend::Cpu => None,
        backend => match Renderer::new(backend)? {
            Renderer::Gpu(g) => Some(Renderer::Gpu(g)),
            Renderer::Cpu => None,
        },
    };
    let mut scenes: Vec<(String, Gaussians<f32>, Camera<f32>)> = Vec::new();
    for path in &args.models {
        let model = read_splats(path)?;
        let camera = omniscan_splat::orbit::orbit_cameras(&model, 1, args.width, args.height)
            .into_iter()
            .next()
            .expect("one orbit camera");
        scenes.push((path.display().to_string(), model.gaussians(), camera));
    }
    if args.models.is_empty() {
        let f = 1.2 * args.width as f32;
        let camera = Camera {
            viewmat: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
            fx: f,
            fy: f,
            cx: 0.5 * args.width as f32,
            cy: 0.5 * args.height as f32,
            width: args.width,
            height: args.height,
            near: 0.01,
            far: 100.0,
        };
        for &n in &args.gaussians {
            scenes.push((format!("random {n}"), random_scene(n, n as u64), camera));
        }
    }
    let settings = Settings::<f32>::default();
    let mut rows = Vec::new();
    for (name, g, camera) in &scenes {
        let cpu_forward = time(args.repeats, || {
            let p = project(g, camera, &settings);
            rasterize(&p, camera.width, camera.height, settings.background);
            Ok(())
        })?;
        let pixels = (camera.width * camera.height) as usize;
        let d_rgb = vec![[1e-3f32; 3]; pixels];
        let d_alpha = vec![1e-3f32; pixels];
        let cpu_step = time(args.repeats, || {
            let p = project(g, camera, &settings);
            rasterize(&p, camera.width, camera.height, settings.background);
            backward(g, camera, &settings, &p, &d_rgb, &d_alpha);
            Ok(())
        })?;
        // A whole training step against a target (the scene's own render
        // with its colours shifted): CPU forward, loss, backward; GPU the same
        // plus Adam, all on the device.
        let (_, truth) = omniscan_splat::raster::render(g, camera, &settings);
        let view = omniscan_splat::views::View {
            camera: *camera,
            image: truth
                .rgb
                .iter()
                .map(|c| c.map(|v| (v * 0.9 + 0.05).min(1.0)))
                .collect(),
            object: truth
                .alpha
                .iter()
                .map(|&a| if a > 0.5 { 1.0 } else { 0.0 })
                .collect(),
            excluded: vec![0.0; pixels],
            depth: Vec::new(),
        };
        let config = omniscan_splat::train::TrainConfig::with_steps(1);
        let cpu_train_step = time(args.repeats, || {
            let p = project(g, camera, &settings);
            let r = rasterize(&p, camera.width, camera.height, settings.background);
            let l = omniscan_splat::train::step_loss(&view, &r, settings.background, &config);
            backward(g, camera, &settings, &p, &l.d_rgb, &l.d_alpha);
            Ok(())
        })?;
        let (gpu_forward, gpu_train_step, gpu_pose_step) = match &gpu {
            Some(Renderer::Gpu(device)) => {
                let forward = time(args.repeats, || {
                    device.render(g, camera, &settings)?;
                    Ok(())
                })?;
                let host = omniscan_splat::gpu::training::HostState::fresh(splats_from(g));
                let state = device.upload_state(&host)?;
                let rates = omniscan_splat::gpu::training::StepRates {
                    means: 1e-5,
                    log_scales: omniscan_splat::train::LOG_SCALES_LR,
                    quats: omniscan_splat::train::QUATS_LR,
                    opacities: omniscan_splat::train::OPACITIES_LR,
                    sh_dc: omniscan_splat::train::SH_DC_LR,
                    sh_rest: omniscan_splat::train::SH_REST_LR,
                    mcmc: None,
                    absolute_gradients: false,
                    camera_gradient: false,
                };
                // Sent once, as training keeps its views' targets on the device.
                let kept = device.upload_target(&view)?;
                let target = omniscan_splat::gpu::training::LossTarget {
                    target: &kept,
                    background: settings.background,
                    lambda_ssim: config.lambda_ssim,
                    lambda_opacity: config.lambda_opacity,
                };
                let mut t = 0;
                let mut step_with = |rates: &omniscan_splat::gpu::training::StepRates| {
                    time(args.repeats, || {
                        t += 1;
                        let frame = device.forward_state(&state, camera, &settings, 3, false)?;
                        device.train_step(&state, &frame, &target, rates, t)?;
                        Ok(())
                    })
                };
                let step = step_with(&rates)?;
                // With pose refinement: the camera gradient's shares, their
                // sum and its read-back.
                let pose_rates = omniscan_splat::gpu::training::StepRates {
                    camera_gradient: true,
                    ..rates
                };
                let pose_step = step_with(&pose_rates)?;
                (Some(forward), Some(step), Some(pose_step))
            }
            _ => (None, None, None),
        };
        let row = json!({
            "scene": name, "gaussians": g.means.len(), "width": camera.width, "height": camera.height,
            "cpu_forward_s": cpu_forward, "cpu_forward_backward_s": cpu_step,
            "cpu_train_step_s": cpu_train_step,
            "gpu": gpu.as_ref().map(|r| r.describe()),
            "gpu_forward_s": gpu_forward,
            "gpu_forward_speedup": gpu_forward.map(|t| cpu_forward / t),
            "gpu_train_step_s": gpu_train_step,
            "gpu_train_step_speedup": gpu_train_step.map(|t| cpu_train_step / t),
            "gpu_train_step_with_camera_gradient_s": gpu_pose_step,
        });
        if !args.json {
            println!(
                "{name:<28} {:>7} Gaussians {}x{}: CPU forward {:.1} ms, forward+backward {:.1} ms, training step {:.1} ms{}",
                g.means.len(),
                camera.width,
                camera.height,
                1e3 * cpu_forward,
                1e3 * cpu_step,
                1e3 * cpu_train_step,
                match (gpu_forward, gpu_train_step, &gpu) {
                    (Some(f), Some(t), Some(r)) => format!(
                        "; GPU forward {:.1} ms ({:.2}x the CPU), training step {:.1} ms ({:.2}x; {})",
                        1e3 * f,
                        cpu_forward / f,
                        1e3 * t,
                        cpu_train_step / t,
                        r.describe()
                    ),
                    _ => "; no GPU timed".into(),
                }
            );
        }
        rows.push(row);
    }
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({ "scenes": rows }))?
        );
    }
    Ok(())
}
