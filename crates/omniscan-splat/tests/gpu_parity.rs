//! The GPU backend against the CPU reference (f32), on scenes these tests
//! generate. They need a Vulkan device: lavapipe will do (`apt-get install
//! mesa-vulkan-drivers`), which `.ci/run` installs before running them.

use omniscan_splat::gpu::{DeviceChoice, GpuRenderer};
use omniscan_splat::raster::{
    Appearance, Camera, Colors, Gaussians, Mode, Render, Settings, render,
};

struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }
}

/// `n` Gaussians in front of the camera (a few behind it and off-image),
/// colours as SH of `degree`, or plain RGB when `degree` is None.
fn scene(n: usize, degree: Option<usize>, seed: u64) -> Gaussians<f32> {
    let mut r = Lcg(seed);
    let means = (0..n)
        .map(|i| {
            let z = if i % 97 == 0 {
                -1.0
            } else {
                1.5 + 2.0 * r.next()
            };
            [3.0 * (r.next() - 0.5), 2.4 * (r.next() - 0.5), z]
        })
        .collect();
    let scales = (0..n)
        .map(|_| {
            [
                0.01 + 0.08 * r.next(),
                0.01 + 0.08 * r.next(),
                0.005 + 0.05 * r.next(),
            ]
        })
        .collect();
    let quats = (0..n)
        .map(|_| {
            [
                r.next() + 0.1,
                r.next() - 0.5,
                r.next() - 0.5,
                r.next() - 0.5,
            ]
        })
        .collect();
    // Every 50th fully opaque: alpha clamps at 0.999 where it is centred.
    let opacities = (0..n)
        .map(|i| {
            if i % 50 == 0 {
                1.0
            } else {
                0.05 + 0.94 * r.next()
            }
        })
        .collect();
    let colors = match degree {
        None => Colors::Rgb((0..n).map(|_| [r.next(), r.next(), r.next()]).collect()),
        Some(d) => {
            let k = (d + 1) * (d + 1);
            Colors::Sh {
                degree: d,
                coeffs: (0..n * k)
                    .map(|i| {
                        let s = if i % k == 0 { 1.5 } else { 0.3 };
                        [
                            s * (r.next() - 0.5),
                            s * (r.next() - 0.5),
                            s * (r.next() - 0.5),
                        ]
                    })
                    .collect(),
            }
        }
    };
    Gaussians {
        means,
        scales,
        quats,
        opacities,
        colors,
    }
}

fn camera(width: u32, height: u32) -> Camera<f32> {
    // Slightly rotated about y and shifted, so no axis is special.
    let (s, c) = (0.1f32.sin(), 0.1f32.cos());
    Camera {
        viewmat: [
            [c, 0.0, s, 0.05],
            [0.0, 1.0, 0.0, -0.02],
            [-s, 0.0, c, 0.3],
            [0.0, 0.0, 0.0, 1.0],
        ],
        fx: 0.9 * width as f32,
        fy: 0.9 * width as f32,
        cx: 0.5 * width as f32 + 1.3,
        cy: 0.5 * height as f32 - 0.7,
        width,
        height,
        near: 0.01,
        far: 100.0,
    }
}

/// Largest per-pixel difference of each output, and the share of pixels
/// whose colour differs by more than 1e-4.
fn compare(cpu: &Render<f32>, gpu: &Render<f32>) -> (f32, f32, f32, f64) {
    let mut rgb = 0f32;
    let mut alpha = 0f32;
    let mut depth = 0f32;
    let mut off = 0usize;
    for i in 0..cpu.alpha.len() {
        let d = (0..3)
            .map(|c| (cpu.rgb[i][c] - gpu.rgb[i][c]).abs())
            .fold(0f32, f32::max);
        rgb = rgb.max(d);
        if d > 1e-4 {
            off += 1;
        }
        alpha = alpha.max((cpu.alpha[i] - gpu.alpha[i]).abs());
        depth = depth.max((cpu.depth[i] - gpu.depth[i]).abs() / cpu.depth[i].abs().max(1.0));
        depth = depth.max(
            (cpu.median_depth[i] - gpu.median_depth[i]).abs() / cpu.median_depth[i].abs().max(1.0),
        );
    }
    (rgb, alpha, depth, off as f64 / cpu.alpha.len() as f64)
}

fn renderer() -> GpuRenderer {
    GpuRenderer::new(DeviceChoice::AllowSoftware).expect("a Vulkan device (lavapipe will do)")
}

#[test]
#[ignore = "needs a Vulkan device (lavapipe: apt-get install mesa-vulkan-drivers)"]
fn gpu_images_match_the_cpu_reference() {
    let gpu = renderer();
    for (degree, mode, background, appearance) in [
        (
            Some(3),
            Mode::Classic,
            [0.0, 0.0, 0.0],
            Appearance::ViewDirection,
        ),
        (
            None,
            Mode::Antialiased,
            [0.2, 0.5, 0.9],
            Appearance::ViewDirection,
        ),
        (
            Some(1),
            Mode::Classic,
            [1.0, 1.0, 1.0],
            Appearance::ViewDirection,
        ),
        (
            Some(3),
            Mode::Classic,
            [0.0, 0.0, 0.0],
            Appearance::FixedRig,
        ),
    ] {
        // 100x75 leaves partial tiles at the right and bottom.
        let g = scene(3000, degree, 11);
        let cam = camera(100, 75);
        let settings = Settings {
            eps2d: 0.3,
            mode,
            background,
            appearance,
        };
        let (_, cpu) = render(&g, &cam, &settings);
        let got = gpu.render(&g, &cam, &settings).unwrap();
        let (rgb, alpha, depth, off) = compare(&cpu, &got);
        let label = format!("{} {degree:?} {mode:?} {appearance:?}", gpu.adapter());
        eprintln!(
            "{label}: max |Δrgb| {rgb:.2e}, |Δalpha| {alpha:.2e}, relative |Δdepth| {depth:.2e}, pixels off by > 1e-4: {:.3}%",
            100.0 * off
        );
        // Agreement to 1e-4, except that a pixel where a Gaussian sits within
        // rounding of alpha = 1/255 may keep it on one side and skip it on the
        // other (a GPU's exp need not round as the CPU's): allow a few such.
        assert!(
            off < 5e-4,
            "{label}: {:.3}% of pixels differ by more than 1e-4",
            100.0 * off
        );
        assert!(
            rgb < 0.01 && alpha < 0.01 && depth < 0.01,
            "{label}: rgb {rgb}, alpha {alpha}, depth {depth}"
        );
        let contributors_equal = cpu
            .contributors
            .iter()
            .zip(&got.contributors)
            .filter(|(a, b)| a == b)
            .count();
        assert!(
            contributors_equal as f64 > 0.999 * cpu.contributors.len() as f64,
            "{label}: contributor counts differ at {} pixels",
            cpu.contributors.len() - contributors_equal
        );
        assert!(
            cpu.alpha.iter().any(|&a| a > 0.5),
            "the scene covers the image"
        );
    }
}

#[test]
#[ignore = "needs a Vulkan device (lavapipe: apt-get install mesa-vulkan-drivers)"]
fn gpu_handles_empty_scenes_and_many_tiles() {
    let gpu = renderer();
    let settings = Settings {
        eps2d: 0.3,
        mode: Mode::Classic,
        background: [0.25, 0.5, 0.75],
        appearance: Appearance::ViewDirection,
    };
    // Nothing to draw: the background everywhere.
    let empty = scene(0, None, 1);
    let got = gpu.render(&empty, &camera(40, 30), &settings).unwrap();
    assert!(got.rgb.iter().all(|p| *p == [0.25, 0.5, 0.75]));
    assert!(got.alpha.iter().all(|&a| a == 0.0));
    // Enough intersections for several scan levels and every tile digit.
    let g = scene(20_000, Some(0), 5);
    let cam = camera(640, 480);
    let (_, cpu) = render(&g, &cam, &settings);
    let got = gpu.render(&g, &cam, &settings).unwrap();
    let (rgb, _, _, off) = compare(&cpu, &got);
    assert!(
        off < 5e-4 && rgb < 0.01,
        "{:.3}% of pixels off, max {rgb}",
        100.0 * off
    );
}

/// Largest difference between two gradient arrays, relative to the largest
/// magnitude of the reference.
fn relative<const K: usize>(cpu: &[[f32; K]], gpu: &[[f32; K]]) -> f32 {
    assert_eq!(cpu.len(), gpu.len());
    let scale = cpu
        .iter()
        .flatten()
        .fold(0f32, |m, v| m.max(v.abs()))
        .max(1e-12);
    cpu.iter()
        .flatten()
        .zip(gpu.iter().flatten())
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()))
        / scale
}

#[test]
#[ignore = "needs a Vulkan device (lavapipe: apt-get install mesa-vulkan-drivers)"]
fn gpu_gradients_match_the_cpu_reference() {
    use omniscan_splat::backward::{backward, backward_with_camera};
    use omniscan_splat::raster::{project, rasterize};
    let gpu = renderer();
    for (degree, mode, appearance) in [
        (Some(3), Mode::Classic, Appearance::ViewDirection),
        (None, Mode::Antialiased, Appearance::ViewDirection),
        (Some(2), Mode::Antialiased, Appearance::ViewDirection),
        (Some(3), Mode::Classic, Appearance::FixedRig),
    ] {
        let g = scene(2000, degree, 23);
        let cam = camera(96, 72);
        let settings = Settings {
            eps2d: 0.3,
            mode,
            background: [0.3, 0.6, 0.1],
            appearance,
        };
        let p = project(&g, &cam, &settings);
        let cpu_render = rasterize(&p, cam.width, cam.height, settings.background);
        let mut r = Lcg(99);
        let pixels = (cam.width * cam.height) as usize;
        let d_rgb: Vec<[f32; 3]> = (0..pixels)
            .map(|_| [r.next() - 0.5, r.next() - 0.5, r.next() - 0.5])
            .collect();
        let d_alpha: Vec<f32> = (0..pixels).map(|_| r.next() - 0.5).collect();
        let cpu = backward(&g, &cam, &settings, &p, &d_rgb, &d_alpha);
        let frame = gpu.forward(&g, &cam, &settings).unwrap();
        let (rgb, ..) = compare(&cpu_render, &frame.render);
        assert!(rgb < 1e-4);
        let (got, visible) = gpu.backward(&frame, &d_rgb, &d_alpha).unwrap();
        let cpu_visible: Vec<bool> = (0..g.means.len()).map(|i| p.visible(i)).collect();
        assert_eq!(visible, cpu_visible, "visibility");
        let label = format!("{degree:?} {mode:?} {appearance:?}");
        let errors = [
            ("means2d", relative(&cpu.means2d, &got.means2d)),
            ("means2d_abs", relative(&cpu.means2d_abs, &got.means2d_abs)),
            ("conics", relative(&cpu.conics, &got.conics)),
            (
                "opacities_view",
                relative(
                    &cpu.opacities_view.iter().map(|&v| [v]).collect::<Vec<_>>(),
                    &got.opacities_view.iter().map(|&v| [v]).collect::<Vec<_>>(),
                ),
            ),
            ("colors_view", relative(&cpu.colors_view, &got.colors_view)),
            ("means", relative(&cpu.means, &got.means)),
            ("quats", relative(&cpu.quats, &got.quats)),
            ("scales", relative(&cpu.scales, &got.scales)),
            (
                "opacities",
                relative(
                    &cpu.opacities.iter().map(|&v| [v]).collect::<Vec<_>>(),
                    &got.opacities.iter().map(|&v| [v]).collect::<Vec<_>>(),
                ),
            ),
            ("colors", relative(&cpu.colors, &got.colors)),
        ];
        eprintln!("{label}: {errors:?}");
        for (name, e) in errors {
            assert!(
                e < 1e-4,
                "{label}: {name} differs by {e:e} of its largest magnitude"
            );
        }
        // The camera gradient (pose refinement), summed over the Gaussians.
        let (_, cpu_camera) = backward_with_camera(&g, &cam, &settings, &p, &d_rgb, &d_alpha);
        let gpu_camera = gpu.camera_gradient(&frame, &d_rgb, &d_alpha).unwrap();
        let (want, got) = (
            [cpu_camera.translation, cpu_camera.rotation].concat(),
            [gpu_camera.translation, gpu_camera.rotation].concat(),
        );
        let largest = want.iter().fold(0f64, |m, v| m.max(v.abs()));
        let worst = want
            .iter()
            .zip(&got)
            .fold(0f64, |m, (a, b)| m.max((a - b).abs()));
        eprintln!("{label}: camera gradient {want:?} vs {got:?}");
        assert!(largest > 0.0);
        assert!(
            worst < 1e-3 * largest,
            "{label}: the camera gradient differs by {worst:e} (largest {largest:e}): {want:?} vs {got:?}"
        );
    }
}

/// A random scene seen by cameras of the given sizes, one shifted along x
/// from the last: training views with object masks and nothing excluded.
fn training_views(sizes: &[(u32, u32)]) -> Vec<omniscan_splat::views::View> {
    let truth = scene(400, None, 31);
    sizes
        .iter()
        .enumerate()
        .map(|(i, &(width, height))| {
            let mut cam = camera(width, height);
            cam.viewmat[0][3] += 0.1 * i as f32;
            let (_, r) = render(&truth, &cam, &Settings::default());
            omniscan_splat::views::View {
                camera: cam,
                image: r.rgb.clone(),
                object: r
                    .alpha
                    .iter()
                    .map(|&a| if a > 0.5 { 1.0 } else { 0.0 })
                    .collect(),
                excluded: vec![0.0; r.alpha.len()],
                depth: Vec::new(),
            }
        })
        .collect()
}

/// A perturbed copy of another random scene, as a model to train from.
fn training_start() -> omniscan_splat::Splats {
    let start = scene(300, Some(1), 37);
    let Colors::Sh { coeffs, .. } = &start.colors else {
        panic!("SH scene")
    };
    omniscan_splat::Splats {
        means: start.means.clone(),
        log_scales: start.scales.iter().map(|s| s.map(f32::ln)).collect(),
        quats: start.quats.clone(),
        opacity_logits: start
            .opacities
            .iter()
            .map(|&o| (o.min(0.99) / (1.0 - o.min(0.99))).ln())
            .collect(),
        sh_degree: 1,
        sh: coeffs.clone(),
        antialiased: false,
        appearance: Appearance::ViewDirection,
    }
}

/// Every learning rate zero (Adam leaves the values as they are), with
/// MCMC's terms where given.
fn frozen(
    mcmc: Option<omniscan_splat::gpu::training::McmcStep>,
) -> omniscan_splat::gpu::training::StepRates {
    omniscan_splat::gpu::training::StepRates {
        means: 0.0,
        log_scales: 0.0,
        quats: 0.0,
        opacities: 0.0,
        sh_dc: 0.0,
        sh_rest: 0.0,
        mcmc,
        absolute_gradients: false,
        camera_gradient: false,
    }
}

/// Adaptive densification at steps 10 and 20, the SH degree rising every 10
/// steps: a short run that takes every path of a long one.
fn densifying(steps: usize) -> omniscan_splat::train::TrainConfig {
    omniscan_splat::train::TrainConfig {
        densify_from: 10,
        densify_every: 10,
        densify_until: 20,
        sh_interval: 10,
        ..omniscan_splat::train::TrainConfig::with_steps(steps)
    }
}

/// Every step's loss on the GPU within 1e-3 (relative) of the CPU's.
fn assert_losses_follow(label: &str, cpu: &[f32], gpu: &[f32]) {
    assert_eq!(cpu.len(), gpu.len(), "{label}: the same number of steps");
    for (step, (a, b)) in cpu.iter().zip(gpu).enumerate() {
        assert!(
            (a - b).abs() <= 1e-3 * a.abs().max(1e-3),
            "{label} step {step}: loss {a} on the CPU, {b} on the GPU"
        );
    }
}

#[test]
#[ignore = "needs a Vulkan device (lavapipe: apt-get install mesa-vulkan-drivers)"]
fn training_on_the_gpu_follows_the_cpu_reference() {
    use omniscan_splat::Splats;
    use omniscan_splat::backend::Renderer;
    use omniscan_splat::train::TrainConfig;
    use omniscan_splat::trainer::train;
    let views = training_views(&[(64, 48); 4]);
    let splats = training_start();
    let adaptive = densifying(30);
    // AbsGS's statistic from the device's absolute sums.
    let absolute = adaptive.with_absolute_gradients();
    // MCMC: penalties in Adam, the noise kernel, relocation and growth on the host.
    let mcmc = TrainConfig {
        densify_from: 10,
        densify_every: 10,
        densify_until: 25,
        sh_interval: 10,
        max_splats: 320,
        ..TrainConfig::mcmc(30)
    };
    for (label, config, appearance) in [
        ("adaptive", adaptive, Appearance::ViewDirection),
        ("absolute gradients", absolute, Appearance::ViewDirection),
        ("mcmc", mcmc, Appearance::ViewDirection),
        ("fixed rig", adaptive, Appearance::FixedRig),
    ] {
        let splats = Splats {
            appearance,
            ..splats.clone()
        };
        let mut cpu_losses = Vec::new();
        let cpu = train(
            &views,
            splats.clone(),
            &config,
            &Renderer::Cpu,
            &mut |_, loss, _| cpu_losses.push(loss),
        )
        .unwrap();
        let mut gpu_losses = Vec::new();
        let gpu_renderer = Renderer::Gpu(Box::new(renderer()));
        let gpu = train(
            &views,
            splats.clone(),
            &config,
            &gpu_renderer,
            &mut |_, loss, _| gpu_losses.push(loss),
        )
        .unwrap();
        assert_eq!(
            cpu.len(),
            gpu.len(),
            "{label}: densification took the same decisions"
        );
        assert_losses_follow(label, &cpu_losses, &gpu_losses);
        let worst = cpu
            .means
            .iter()
            .flatten()
            .zip(gpu.means.iter().flatten())
            .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(worst < 1e-3, "{label}: means drifted apart by {worst}");
        assert!(cpu_losses.last() < cpu_losses.first(), "the loss falls");
    }
}

/// Pose refinement on the device: views whose recorded poses are off by
/// 2 cm, the corrections stepped from the device's camera
/// gradient, follow the CPU trainer's, step for step.
#[test]
#[ignore = "needs a Vulkan device (lavapipe: apt-get install mesa-vulkan-drivers)"]
fn pose_refinement_on_the_gpu_follows_the_cpu_reference() {
    use omniscan_splat::backend::Renderer;
    use omniscan_splat::pose::PoseConfig;
    use omniscan_splat::train::{Start, TrainConfig};
    use omniscan_splat::trainer::{Trainer, run_to_end};
    let mut views = training_views(&[(64, 48); 4]);
    // Record two of the views 2 cm off along x.
    for view in views.iter_mut().skip(1).step_by(2) {
        view.camera.viewmat[0][3] += 0.02;
    }
    let config = TrainConfig {
        pose: Some(PoseConfig {
            from_step: 0,
            rotation_lr: 5e-3,
            translation_lr: 2e-2,
            ..PoseConfig::default()
        }),
        ..densifying(30)
    };
    let run = |renderer: &Renderer| {
        let mut losses = Vec::new();
        let mut trainer =
            Trainer::new(&views, Start::Fresh(training_start()), &config, renderer).unwrap();
        run_to_end(&mut trainer, None, &mut |_, loss, _| losses.push(loss)).unwrap();
        (losses, trainer.pose_corrections().unwrap())
    };
    let (cpu_losses, cpu) = run(&Renderer::Cpu);
    let (gpu_losses, gpu) = run(&Renderer::Gpu(Box::new(renderer())));
    assert_losses_follow("pose refinement", &cpu_losses, &gpu_losses);
    let moved = cpu
        .views
        .iter()
        .map(|c| c.translation_m.iter().map(|t| t.abs()).fold(0.0, f64::max))
        .fold(0.0, f64::max);
    assert!(moved > 1e-4, "the corrections moved: {moved} m");
    for (c, g) in cpu.views.iter().zip(&gpu.views) {
        let apart = (0..3)
            .map(|a| (c.translation_m[a] - g.translation_m[a]).abs())
            .fold(0.0, f64::max);
        assert!(apart < 0.1 * moved, "{c:?} vs {g:?}");
    }
}

/// The trainer keeps the loss targets of as many views as its budget holds on
/// the device and sends the others at each of their steps; with views of two
/// sizes the loss's working buffers change size from step to step. Kept or
/// sent, every step's loss follows the CPU's.
#[test]
#[ignore = "needs a Vulkan device (lavapipe: apt-get install mesa-vulkan-drivers)"]
fn views_kept_on_the_device_or_sent_each_step_train_alike() {
    use omniscan_splat::backend::Renderer;
    use omniscan_splat::gpu::training::{DEFAULT_VIEW_MEMORY, ViewTargets};
    use omniscan_splat::trainer::train;
    let views = training_views(&[(64, 48), (48, 36), (64, 48), (48, 36)]);
    // A target is 5 floats a pixel.
    let bytes = |(w, h): (u64, u64)| 20 * w * h;
    let first_two = bytes((64, 48)) + bytes((48, 36));
    let gpu = renderer();
    for (budget, kept) in [(0, (0, 0)), (first_two, (2, first_two))] {
        let mut targets = ViewTargets::new(views.len(), budget);
        let mut scratch = None;
        for _ in 0..2 {
            for (i, view) in views.iter().enumerate() {
                targets.target(&gpu, i, view, &mut scratch).unwrap();
            }
        }
        assert_eq!(targets.kept(), kept, "budget {budget} bytes");
    }
    let config = densifying(24);
    let mut cpu_losses = Vec::new();
    train(
        &views,
        training_start(),
        &config,
        &Renderer::Cpu,
        &mut |_, loss, _| cpu_losses.push(loss),
    )
    .unwrap();
    for budget in [0, first_two, DEFAULT_VIEW_MEMORY] {
        let mut gpu = renderer();
        gpu.set_view_memory(budget);
        let mut gpu_losses = Vec::new();
        train(
            &views,
            training_start(),
            &config,
            &Renderer::Gpu(Box::new(gpu)),
            &mut |_, loss, _| gpu_losses.push(loss),
        )
        .unwrap();
        assert_losses_follow(&format!("budget {budget}"), &cpu_losses, &gpu_losses);
    }
}

/// One device steps through views of changing sizes, smaller and larger
/// than its last: each step's loss is the CPU's for that view (the loss's
/// working buffers are made again when the size changes).
#[test]
#[ignore = "needs a Vulkan device (lavapipe: apt-get install mesa-vulkan-drivers)"]
fn the_loss_follows_each_views_size() {
    use omniscan_splat::gpu::training::{HostState, LossTarget};
    use omniscan_splat::train::{TrainConfig, step_loss};
    let views = training_views(&[(48, 36), (64, 48), (32, 24), (64, 48)]);
    let splats = training_start();
    let gpu = renderer();
    let state = gpu.upload_state(&HostState::fresh(splats.clone())).unwrap();
    // Every rate zero: the model stays as it is from step to step.
    let rates = frozen(None);
    let config = TrainConfig::with_steps(1);
    let background = [0.2, 0.5, 0.7];
    let settings = splats.render_settings(background);
    let g = splats.gaussians_up_to::<f32>(1);
    for (i, view) in views.iter().enumerate() {
        let frame = gpu
            .forward_state(&state, &view.camera, &settings, 1, false)
            .unwrap();
        let target = gpu.upload_target(view).unwrap();
        let report = gpu
            .train_step(
                &state,
                &frame,
                &LossTarget {
                    target: &target,
                    background,
                    lambda_ssim: config.lambda_ssim,
                    lambda_opacity: config.lambda_opacity,
                },
                &rates,
                i as i32 + 1,
            )
            .unwrap();
        let (_, r) = render(&g, &view.camera, &settings);
        let cpu = step_loss(view, &r, background, &config).loss;
        assert!(
            (report.loss - cpu).abs() <= 1e-4 * cpu.abs(),
            "view {i} ({}x{}): loss {} on the GPU, {cpu} on the CPU",
            view.camera.width,
            view.camera.height,
            report.loss
        );
    }
}

/// MCMC's position noise: the device's kernel draws the same normals from
/// the same hash as the CPU's `mcmc::add_noise`, and moves the same splats
/// (opacities from 0.0005 to 0.02 span the gate from open to shut).
#[test]
#[ignore = "needs a Vulkan device (lavapipe: apt-get install mesa-vulkan-drivers)"]
fn mcmc_noise_on_the_gpu_matches_the_cpu() {
    use omniscan_splat::Splats;
    use omniscan_splat::gpu::training::{HostState, LossTarget, McmcStep};
    use omniscan_splat::mcmc;
    use omniscan_splat::views::View;
    let g = scene(300, Some(1), 41);
    let Colors::Sh { coeffs, .. } = &g.colors else {
        panic!("SH scene")
    };
    let n = g.means.len();
    let splats = Splats {
        means: g.means.clone(),
        log_scales: g.scales.iter().map(|s| s.map(f32::ln)).collect(),
        quats: g.quats.clone(),
        opacity_logits: (0..n)
            .map(|i| {
                let o = 0.0005 + 0.1995 * i as f32 / n as f32;
                (o / (1.0 - o)).ln()
            })
            .collect(),
        sh_degree: 1,
        sh: coeffs.clone(),
        antialiased: false,
        appearance: Appearance::ViewDirection,
    };
    let gpu = renderer();
    let state = gpu.upload_state(&HostState::fresh(splats.clone())).unwrap();
    let cam = camera(64, 48);
    let pixels = (cam.width * cam.height) as usize;
    let settings = Settings::default();
    let frame = gpu
        .forward_state(&state, &cam, &settings, 1, false)
        .unwrap();
    let (seed, step, rate, extent) = (7u64, 12usize, 1.6e-4f32, 0.5f32);
    // Every learning rate zero: Adam leaves the values as they are, and the noise alone moves the means.
    let rates = frozen(Some(McmcStep {
        opacity_penalty: 0.0,
        scale_penalty: 0.0,
        noise_scale: mcmc::noise_scale(rate, extent),
        seed: mcmc::noise_seed(seed),
        step: step as u32,
    }));
    let view = View {
        camera: cam,
        image: vec![[0.5f32; 3]; pixels],
        object: vec![1.0f32; pixels],
        excluded: vec![0.0f32; pixels],
        depth: Vec::new(),
    };
    let kept = gpu.upload_target(&view).unwrap();
    let target = LossTarget {
        target: &kept,
        background: [0.0; 3],
        lambda_ssim: 0.2,
        lambda_opacity: 1.0,
    };
    gpu.train_step(&state, &frame, &target, &rates, 1).unwrap();
    let moved = gpu.download_state(&state).unwrap().splats.means;
    let mut cpu = splats.clone();
    mcmc::add_noise(&mut cpu, seed, step, rate, extent);
    let mut largest = 0f32;
    for (i, (a, b)) in cpu.means.iter().zip(&moved).enumerate() {
        for c in 0..3 {
            let shift = (a[c] - splats.means[i][c]).abs();
            largest = largest.max(shift);
            assert!(
                (a[c] - b[c]).abs() <= 1e-4 * shift.max(1e-3) + 1e-7,
                "splat {i}: {a:?} on the CPU, {b:?} on the GPU (from {:?})",
                splats.means[i]
            );
        }
    }
    assert!(largest > 1e-4, "the noise moved something: {largest}");
    let last = (0..3)
        .map(|c| (cpu.means[n - 1][c] - splats.means[n - 1][c]).abs())
        .fold(0f32, f32::max);
    assert!(last < 1e-6 * largest, "an opaque splat stays: {last}");
}

#[test]
#[ignore = "needs a Vulkan device (lavapipe: apt-get install mesa-vulkan-drivers)"]
fn evaluation_on_the_gpu_matches_the_cpu() {
    use omniscan_splat::backend::Renderer;
    use omniscan_splat::evaluation::evaluate_views;
    use omniscan_splat::train::splats_from_points;
    use omniscan_splat::views::View;
    // A model of opaque splats at random points (SH degree 1), scored
    // against its own renders from cameras 8 cm off: a fair fit, so no
    // figure sits at its floor or its ceiling. Every view has a gripper band.
    let mut r = Lcg(5);
    let points: Vec<[f32; 3]> = (0..600)
        .map(|_| {
            [
                3.0 * (r.next() - 0.5),
                2.4 * (r.next() - 0.5),
                1.5 + 2.0 * r.next(),
            ]
        })
        .collect();
    let colours: Vec<[f32; 3]> = (0..600).map(|_| [r.next(), r.next(), r.next()]).collect();
    let mut model = splats_from_points(&points, &colours, 1).unwrap();
    model.opacity_logits.fill(3.0);
    let views: Vec<View> = (0..3)
        .map(|i| {
            let mut cam = camera(64, 48);
            cam.viewmat[1][3] += 0.1 * i as f32;
            let mut photographer = cam;
            photographer.viewmat[0][3] += 0.08;
            let (_, r) = render(
                &model.gaussians::<f32>(),
                &photographer,
                &model.render_settings([0.0; 3]),
            );
            View {
                camera: cam,
                image: r.rgb.clone(),
                object: r.alpha.iter().map(|&a| (a > 0.5) as u8 as f32).collect(),
                excluded: (0..r.alpha.len())
                    .map(|p| (p % 64 < 6) as u8 as f32)
                    .collect(),
                depth: Vec::new(),
            }
        })
        .collect();
    let score = |renderer: &Renderer| {
        evaluate_views(
            &model,
            renderer,
            views.len(),
            |i| Ok(std::borrow::Cow::Borrowed(&views[i])),
            None,
            |_, _, _| Ok(()),
        )
        .unwrap()
    };
    let cpu = score(&Renderer::Cpu);
    let gpu = score(&Renderer::Gpu(Box::new(renderer())));
    assert_eq!(gpu.views, 3);
    let figures = |e: &omniscan_splat::evaluation::Evaluation| {
        [
            ("psnr", e.psnr),
            ("ssim", e.ssim),
            ("psnr_masked", e.psnr_masked),
            ("ssim_masked", e.ssim_masked),
        ]
    };
    for ((key, a), (_, b)) in figures(&cpu).into_iter().zip(figures(&gpu)) {
        let (a, b) = (a.unwrap(), b.unwrap());
        assert!(
            (a - b).abs() <= 1e-4 * a.abs(),
            "{key}: CPU {a} against GPU {b}"
        );
    }
}
