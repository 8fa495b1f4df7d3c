//! Training with the parameters resident on the device: the splats, Adam's
//! moments and the densification statistics live in GPU buffers; each step
//! renders (`forward`), computes the loss and its gradient (`loss.wgsl`,
//! the CPU trainer's `step_loss` in f32), and runs the backward pass, the
//! statistics and the Adam steps on the device (`optimise.wgsl`). Only the
//! loss and PSNR come back each step; everything else comes back only where
//! the CPU trainer's logic needs it: densification, opacity resets,
//! checkpoints and the end.
//!
//! The views' loss targets stay on the device too ([`ViewTargets`]): a view
//! is unpacked, packed for the loss and sent once, at its first step, while
//! the kept targets fit their budget. Done at every step, that host work
//! is serial with the device's work and grows with the image (figures in
//! docs/results.md); kept, a view costs it once. The loss's working planes are kept from step to step as well
//! (`LossBuffers`).

use super::{
    GROUP, GpuFrame, GpuRenderer, SceneBuffers, compute_pipeline, gpu_error, grid, shader,
};
use crate::SplatError;
use crate::raster::{Camera, Settings};
use crate::views::{TrainingView, View};
use crate::{Splats, sh};
use rayon::prelude::*;

const OPTIMISE: &str = include_str!("optimise.wgsl");
const LOSS: &str = include_str!("loss.wgsl");

/// The optimiser's and the loss's kernels.
pub(crate) struct OptimiseKernels {
    activate: wgpu::ComputePipeline,
    statistics: wgpu::ComputePipeline,
    adam: wgpu::ComputePipeline,
    noise: wgpu::ComputePipeline,
    prepare: wgpu::ComputePipeline,
    blur: wgpu::ComputePipeline,
    ssim_terms: wgpu::ComputePipeline,
    gradient: wgpu::ComputePipeline,
    /// The CPU SSIM's f32 window taps, as `loss.wgsl`'s `Params.window` holds them.
    window: [[f32; 4]; 3],
}

impl OptimiseKernels {
    pub(crate) fn new(device: &wgpu::Device) -> OptimiseKernels {
        let module = shader(device, "optimise", OPTIMISE);
        let loss = shader(device, "loss", LOSS);
        let pipeline =
            |module: &wgpu::ShaderModule, entry: &str| compute_pipeline(device, module, entry);
        OptimiseKernels {
            activate: pipeline(&module, "activate"),
            statistics: pipeline(&module, "statistics"),
            adam: pipeline(&module, "adam"),
            noise: pipeline(&module, "noise"),
            prepare: pipeline(&loss, "prepare"),
            blur: pipeline(&loss, "blur"),
            ssim_terms: pipeline(&loss, "ssim_terms"),
            gradient: pipeline(&loss, "gradient"),
            window: {
                let mut window = [[0.0f32; 4]; 3];
                for (k, tap) in crate::metrics::window::<f32>().into_iter().enumerate() {
                    window[k / 4][k % 4] = tap;
                }
                window
            },
        }
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct OptimiseParams {
    len: u32,
    kind: u32,
    stride: u32,
    _pad: u32,
    lr: f32,
    lr_rest: f32,
    bias1: f32,
    bias2: f32,
    half_width: f32,
    half_height: f32,
    beta1: f32,
    beta2: f32,
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    epsilon: f32,
    penalty: f32,
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct LossParams {
    width: u32,
    height: u32,
    planes: u32,
    horizontal: u32,
    background: [f32; 4],
    lambda_ssim: f32,
    lambda_opacity: f32,
    weight_sum: f32,
    _pad: f32,
    window: [[f32; 4]; 3],
}

/// Floats per pixel of a loss target: the photo's r, g, b (0..1), its object
/// coverage (1 on the object), its exclusion (1 where every term is zeroed:
/// the gripper, or what the lens did not see).
const TARGET_FLOATS: usize = 5;

/// A view's loss target on the device (`loss.wgsl`'s `target_data`) and the
/// weight its terms are averaged over.
#[derive(Debug)]
pub struct DeviceTarget {
    data: wgpu::Buffer,
    pixels: usize,
    /// The pixels not excluded (at least 1), summed as the CPU's loss sums them.
    weight_sum: f32,
}

/// What the loss of one step compares the render with.
#[derive(Debug, Clone, Copy)]
pub struct LossTarget<'a> {
    /// The view's photo and masks, from [`GpuRenderer::upload_target`] or [`ViewTargets`].
    pub target: &'a DeviceTarget,
    /// This step's random background colour.
    pub background: [f32; 3],
    pub lambda_ssim: f32,
    pub lambda_opacity: f32,
}

/// The loss's working buffers for one image size, kept from step to step
/// (made afresh, they were 192 bytes a pixel allocated and cleared at every
/// step: 59 MB at 640x480).
pub(crate) struct LossBuffers {
    pixels: usize,
    /// Loss, opacity loss, SSIM, squared error and pixel count sums.
    sums: wgpu::Buffer,
    /// The 15 planes SSIM blurs (per channel x, y, x², y², xy).
    planes: wgpu::Buffer,
    /// The blur's intermediate planes.
    scratch: wgpu::Buffer,
    /// SSIM's 9 gradient-term planes.
    terms: wgpu::Buffer,
    /// dL/d(rgb, alpha) per pixel, for the backward pass.
    d_image: wgpu::Buffer,
}

/// The default budget for the loss targets [`ViewTargets`] keeps on the
/// device, bytes: a 640x480 view takes 6.1 MB (651 fit), a 4K one 166 MB
/// (24 fit). Other views are sent at each of their steps.
pub const DEFAULT_VIEW_MEMORY: u64 = 4_000_000_000;

/// The trainer's loss targets on the device, one slot a view: a view's
/// target is kept from its first step on while the kept ones fit the budget
/// and the device has memory for it; the other views share one buffer,
/// filled again at each of their steps.
#[derive(Debug)]
pub struct ViewTargets {
    kept: Vec<Option<DeviceTarget>>,
    kept_bytes: u64,
    budget: u64,
    /// The target of the last step's view that is not kept.
    passing: Option<DeviceTarget>,
    /// Set when the device refused memory for a target: nothing more is kept.
    device_full: bool,
    /// Set when a view's target first did not fit the budget.
    over_budget: bool,
}

impl ViewTargets {
    /// Room for `views` views' targets, keeping up to `budget` bytes of them.
    pub fn new(views: usize, budget: u64) -> ViewTargets {
        ViewTargets {
            kept: (0..views).map(|_| None).collect(),
            kept_bytes: 0,
            budget,
            passing: None,
            device_full: false,
            over_budget: false,
        }
    }

    /// How many views' targets are kept, and their bytes.
    pub fn kept(&self) -> (usize, u64) {
        (self.kept.iter().flatten().count(), self.kept_bytes)
    }

    /// View `index`'s target: the kept one, or one made now from `view`'s
    /// pixels (unpacked into `scratch`), kept if it fits.
    pub fn target<'a>(
        &'a mut self,
        gpu: &GpuRenderer,
        index: usize,
        view: &impl TrainingView,
        scratch: &mut Option<View>,
    ) -> Result<&'a DeviceTarget, SplatError> {
        if index >= self.kept.len() {
            return Err(SplatError::Invalid(format!(
                "view {index} has no target slot ({} views)",
                self.kept.len()
            )));
        }
        if self.kept[index].is_none() {
            let pixels = view.pixels_in(scratch);
            let bytes = target_bytes(pixels_of(&pixels.camera));
            let fits = !self.device_full && self.kept_bytes + bytes <= self.budget;
            match fits.then(|| gpu.target_buffer(bytes)).flatten() {
                Some(buffer) => {
                    self.kept[index] = Some(gpu.fill_target(buffer, pixels)?);
                    self.kept_bytes += bytes;
                }
                None => {
                    if fits {
                        self.device_full = true;
                        tracing::warn!(
                            "GPU backend: the device has no memory for more views' targets ({} kept, {:.2} GB); the rest are sent at each of their steps (a smaller --gpu-view-memory-gb leaves more room for the model)",
                            self.kept().0,
                            self.kept_bytes as f64 / 1e9
                        );
                    } else if !self.over_budget {
                        self.over_budget = true;
                        tracing::info!(
                            "GPU backend: the views' targets outgrow their {:.2} GB budget ({} kept); the rest are sent at each of their steps",
                            self.budget as f64 / 1e9,
                            self.kept().0
                        );
                    }
                    let buffer = match self.passing.take() {
                        Some(t) if t.data.size() == bytes => t.data,
                        _ => gpu.required_target_buffer(bytes)?,
                    };
                    return Ok(self.passing.insert(gpu.fill_target(buffer, pixels)?));
                }
            }
        }
        self.kept[index]
            .as_ref()
            .ok_or_else(|| SplatError::Invalid(format!("view {index}'s target was not kept")))
    }
}

fn pixels_of(camera: &Camera<f32>) -> usize {
    camera.width as usize * camera.height as usize
}

/// A loss target's size on the device, bytes (never 0: empty bindings are invalid).
fn target_bytes(pixels: usize) -> u64 {
    (4 * TARGET_FLOATS * pixels.max(1)) as u64
}

/// The loss of a step and the PSNR outside the gripper.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    pub loss: f32,
    pub psnr: f64,
    /// With [`StepRates::camera_gradient`]: the loss's gradient with respect
    /// to a motion of the view's camera.
    pub camera: Option<crate::backward::CameraGradient>,
}

/// The trainer's state as the CPU holds it.
#[derive(Debug, Clone, PartialEq)]
pub struct HostState {
    pub splats: Splats,
    /// Adam's first and second moments of means, log-scales, quaternions,
    /// opacity logits and SH coefficients.
    pub moments: [(Vec<f32>, Vec<f32>); 5],
    pub grad_sum: Vec<f32>,
    pub grad_count: Vec<u32>,
}

impl HostState {
    /// A state that starts `splats` afresh: every moment and statistic zero.
    pub fn fresh(splats: Splats) -> HostState {
        let (n, k) = (splats.len(), splats.sh_coefficients());
        HostState {
            moments: [3 * n, 3 * n, 4 * n, n, 3 * k * n]
                .map(|len| (vec![0.0; len], vec![0.0; len])),
            grad_sum: vec![0.0; n],
            grad_count: vec![0; n],
            splats,
        }
    }
}

/// The same state on the device.
pub struct DeviceState {
    n: u32,
    stride: u32,
    sh_degree: usize,
    antialiased: bool,
    appearance: crate::raster::Appearance,
    /// Means, log-scales, quaternions, opacity logits, SH coefficients.
    values: [wgpu::Buffer; 5],
    first: [wgpu::Buffer; 5],
    second: [wgpu::Buffer; 5],
    scales: wgpu::Buffer,
    opacities: wgpu::Buffer,
    grad_sum: wgpu::Buffer,
    grad_count: wgpu::Buffer,
}

/// Learning rates of one step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepRates {
    pub means: f32,
    pub log_scales: f32,
    pub quats: f32,
    pub opacities: f32,
    pub sh_dc: f32,
    pub sh_rest: f32,
    /// MCMC's penalties and position noise ([`crate::mcmc`]); `None` without MCMC.
    pub mcmc: Option<McmcStep>,
    /// Densification statistics from the per-pixel absolute 2D mean
    /// gradients (AbsGS) instead of their sum.
    pub absolute_gradients: bool,
    /// Also the gradient with respect to the camera (pose refinement).
    pub camera_gradient: bool,
}

/// What MCMC adds to one step on the device, as the CPU trainer computes it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct McmcStep {
    /// Gradient weight on each opacity (the penalty's weight over the count).
    pub opacity_penalty: f32,
    /// Gradient weight on each scale (over three times the count and the extent).
    pub scale_penalty: f32,
    /// The noise's scale: NOISE_LR · position rate / extent².
    pub noise_scale: f32,
    pub seed: u32,
    pub step: u32,
}

fn flat<const K: usize>(v: &[[f32; K]]) -> Vec<f32> {
    v.iter().flatten().copied().collect()
}

impl GpuRenderer {
    fn optimise(&self) -> Result<&OptimiseKernels, SplatError> {
        match (&self.optimise, &self.backward) {
            (Some(k), Some(_)) => Ok(k),
            _ => Err(SplatError::Invalid(format!(
                "GPU backend: {} cannot run the backward pass (no subgroup operations); train with --backend cpu",
                self.adapter()
            ))),
        }
    }

    /// A buffer for a loss target of `bytes`, or `None` where the device has
    /// no memory left for it.
    fn target_buffer(&self, bytes: u64) -> Option<wgpu::Buffer> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let buffer = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("loss target"),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        pollster::block_on(scope.pop()).is_none().then_some(buffer)
    }

    /// `view`'s loss target, written into `buffer` (of [`target_bytes`] for
    /// its pixels): per pixel the photo's colour, its object coverage and its
    /// exclusion.
    fn fill_target(&self, buffer: wgpu::Buffer, view: &View) -> Result<DeviceTarget, SplatError> {
        let n = pixels_of(&view.camera);
        if view.image.len() != n || view.object.len() != n || view.excluded.len() != n {
            return Err(SplatError::Invalid(format!(
                "training step: the view's image and masks do not have its camera's {n} pixels"
            )));
        }
        let bytes = target_bytes(n);
        if buffer.size() != bytes {
            return Err(SplatError::Invalid(format!(
                "a {}-byte buffer cannot hold a {bytes}-byte view target",
                buffer.size()
            )));
        }
        // Summed in pixel order, as the CPU's loss sums its weights.
        let weight_sum = view.excluded.iter().map(|g| 1.0 - g).sum::<f32>().max(1.0);
        // Packed on all threads, then staged in one copy.
        let mut packed = vec![0u8; bytes as usize];
        packed
            .par_chunks_mut(4 * TARGET_FLOATS)
            .zip(view.image.par_iter())
            .zip(view.object.par_iter().zip(view.excluded.par_iter()))
            .for_each(|((out, c), (&object, &excluded))| {
                for (o, v) in out
                    .chunks_exact_mut(4)
                    .zip([c[0], c[1], c[2], object, excluded])
                {
                    o.copy_from_slice(&v.to_le_bytes());
                }
            });
        self.queue.write_buffer(&buffer, 0, &packed);
        Ok(DeviceTarget {
            data: buffer,
            pixels: n,
            weight_sum,
        })
    }

    /// `view`'s loss target on the device, for [`GpuRenderer::train_step`]
    /// (the trainer keeps its views' in [`ViewTargets`]).
    pub fn upload_target(&self, view: &View) -> Result<DeviceTarget, SplatError> {
        let buffer = self.required_target_buffer(target_bytes(pixels_of(&view.camera)))?;
        self.fill_target(buffer, view)
    }

    /// [`GpuRenderer::target_buffer`], where no memory for it is an error.
    fn required_target_buffer(&self, bytes: u64) -> Result<wgpu::Buffer, SplatError> {
        self.target_buffer(bytes).ok_or_else(|| {
            SplatError::Invalid(format!(
                "GPU backend: out of device memory for a {bytes}-byte view target"
            ))
        })
    }

    /// The loss's working buffers for `pixels` pixels: the kept ones if they
    /// have that size, else new ones.
    fn loss_buffers(&self, kept: Option<LossBuffers>, pixels: usize) -> LossBuffers {
        match kept {
            Some(b) if b.pixels == pixels => b,
            _ => {
                let p = pixels as u64;
                LossBuffers {
                    pixels,
                    sums: self.zeroed("loss sums", 5),
                    planes: self.zeroed("SSIM planes", 15 * p),
                    scratch: self.zeroed("blur scratch", 15 * p),
                    terms: self.zeroed("SSIM gradient terms", 9 * p),
                    d_image: self.zeroed("image gradients", 4 * p),
                }
            }
        }
    }

    /// Copies the trainer's state to the device.
    pub fn upload_state(&self, host: &HostState) -> Result<DeviceState, SplatError> {
        self.optimise()?;
        let s = &host.splats;
        let n = s.len() as u32;
        let stride = s.sh_coefficients() as u32;
        let values = [
            self.storage("means", &flat(&s.means)),
            self.storage("log-scales", &flat(&s.log_scales)),
            self.storage("quaternions", &flat(&s.quats)),
            self.storage("opacity logits", &s.opacity_logits),
            self.storage("SH coefficients", &flat(&s.sh)),
        ];
        let first = host
            .moments
            .each_ref()
            .map(|(m, _)| self.storage("Adam first moments", m));
        let second = host
            .moments
            .each_ref()
            .map(|(_, v)| self.storage("Adam second moments", v));
        Ok(DeviceState {
            n,
            stride,
            sh_degree: s.sh_degree,
            antialiased: s.antialiased,
            appearance: s.appearance,
            values,
            first,
            second,
            scales: self.zeroed("scales", 3 * n as u64),
            opacities: self.zeroed("opacities", n as u64),
            grad_sum: self.storage("gradient sums", &host.grad_sum),
            grad_count: self.storage("gradient counts", &host.grad_count),
        })
    }

    /// Reads the trainer's state back from the device.
    pub fn download_state(&self, device: &DeviceState) -> Result<HostState, SplatError> {
        let n = device.n as u64;
        let k = device.stride as u64;
        let sizes = [3 * n, 3 * n, 4 * n, n, 3 * k * n];
        let mut buffers: Vec<(&wgpu::Buffer, u64)> = Vec::new();
        for (g, &size) in sizes.iter().enumerate() {
            buffers.push((&device.values[g], size));
        }
        for (g, &size) in sizes.iter().enumerate() {
            buffers.push((&device.first[g], size));
            buffers.push((&device.second[g], size));
        }
        buffers.push((&device.grad_sum, n));
        buffers.push((&device.grad_count, n));
        let total: u64 = buffers.iter().map(|b| b.1).sum();
        let gathered = self.zeroed("state", total);
        let mut encoder = self.device.create_command_encoder(&Default::default());
        let mut offset = 0;
        for (buffer, size) in &buffers {
            if *size > 0 {
                encoder.copy_buffer_to_buffer(buffer, 0, &gathered, 4 * offset, 4 * size);
            }
            offset += size;
        }
        let bytes = self.submit_and_read(encoder, &gathered, 4 * total)?;
        let words: &[u32] = &bytes;
        let mut parts = Vec::new();
        let mut at = 0usize;
        for (_, size) in &buffers {
            parts.push(&words[at..at + *size as usize]);
            at += *size as usize;
        }
        let floats = |w: &[u32]| w.iter().map(|&b| f32::from_bits(b)).collect::<Vec<f32>>();
        let triples = |w: &[u32]| {
            floats(w)
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect::<Vec<_>>()
        };
        let splats = Splats {
            means: triples(parts[0]),
            log_scales: triples(parts[1]),
            quats: floats(parts[2])
                .chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect(),
            opacity_logits: floats(parts[3]),
            sh_degree: device.sh_degree,
            sh: triples(parts[4]),
            antialiased: device.antialiased,
            appearance: device.appearance,
        };
        let moments = [0, 1, 2, 3, 4].map(|g| (floats(parts[5 + 2 * g]), floats(parts[6 + 2 * g])));
        Ok(HostState {
            splats,
            moments,
            grad_sum: floats(parts[15]),
            grad_count: parts[16].to_vec(),
        })
    }

    /// Renders the device state with its first `degree` SH bands (the image
    /// comes back to the host only when `read_back`).
    pub fn forward_state(
        &self,
        state: &DeviceState,
        camera: &Camera<f32>,
        settings: &Settings<f32>,
        degree: usize,
        read_back: bool,
    ) -> Result<GpuFrame, SplatError> {
        let kernels = self.optimise()?;
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let params = self.uniform(
            "activation params",
            &OptimiseParams {
                len: state.n,
                ..bytemuck::Zeroable::zeroed()
            },
        );
        let mut encoder = self.device.create_command_encoder(&Default::default());
        let group = self.bind(
            &kernels.activate,
            &[
                (0, &params),
                (1, &state.values[1]),
                (2, &state.values[3]),
                (3, &state.scales),
                (4, &state.opacities),
            ],
        );
        Self::dispatch(
            &mut encoder,
            &kernels.activate,
            &group,
            grid(state.n.div_ceil(GROUP)),
        );
        self.queue.submit([encoder.finish()]);
        let scene = SceneBuffers {
            n: state.n,
            per_channel: sh::coefficients(degree.min(state.sh_degree)) as u32,
            stride: state.stride,
            plain: false,
            means: state.values[0].clone(),
            scales: state.scales.clone(),
            quats: state.values[2].clone(),
            opacities: state.opacities.clone(),
            coeffs: state.values[4].clone(),
        };
        let result = self.forward_scene(&scene, camera, settings, read_back);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_error("rendering failed", e));
        }
        result
    }

    /// Records the densification statistics and the Adam steps of every group.
    #[allow(clippy::too_many_arguments)]
    fn record_step(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        state: &DeviceState,
        frame: &GpuFrame,
        grads2d: &wgpu::Buffer,
        outputs: &[wgpu::Buffer; 5],
        rates: &StepRates,
        t: i32,
    ) -> Result<(), SplatError> {
        let kernels = self.optimise()?;
        let (b1, b2) = crate::adam::ADAM_BETAS;
        let base = OptimiseParams {
            len: state.n,
            kind: 0,
            stride: state.stride,
            _pad: 0,
            lr: 0.0,
            lr_rest: 0.0,
            bias1: 1.0 - b1.powi(t),
            bias2: 1.0 - b2.powi(t),
            half_width: frame.render.width as f32 * 0.5,
            half_height: frame.render.height as f32 * 0.5,
            beta1: b1,
            beta2: b2,
            one_minus_beta1: 1.0 - b1,
            one_minus_beta2: 1.0 - b2,
            epsilon: crate::adam::ADAM_EPSILON,
            penalty: 0.0,
        };
        let stats_params = self.uniform(
            "statistics params",
            &OptimiseParams {
                kind: rates.absolute_gradients.into(),
                ..base
            },
        );
        let group = self.bind(
            &kernels.statistics,
            &[
                (0, &stats_params),
                (5, grads2d),
                (6, &state.grad_sum),
                (7, &state.grad_count),
            ],
        );
        Self::dispatch(
            encoder,
            &kernels.statistics,
            &group,
            grid(state.n.div_ceil(GROUP)),
        );
        // Groups: (values, gradient output, length, kind, rates).
        let n = state.n;
        let k = state.stride;
        let (opacity_penalty, scale_penalty) = rates
            .mcmc
            .map_or((0.0, 0.0), |m| (m.opacity_penalty, m.scale_penalty));
        let groups = [
            (0, &outputs[0], 3 * n, 0, rates.means, rates.means, 0.0),
            (
                1,
                &outputs[2],
                3 * n,
                1,
                rates.log_scales,
                rates.log_scales,
                scale_penalty,
            ),
            (2, &outputs[1], 4 * n, 0, rates.quats, rates.quats, 0.0),
            (
                3,
                &outputs[3],
                n,
                2,
                rates.opacities,
                rates.opacities,
                opacity_penalty,
            ),
            (
                4,
                &outputs[4],
                3 * k * n,
                3,
                rates.sh_dc,
                rates.sh_rest,
                0.0,
            ),
        ];
        for (g, gradient, len, kind, lr, lr_rest, penalty) in groups {
            if len == 0 {
                continue;
            }
            let params = self.uniform(
                "Adam params",
                &OptimiseParams {
                    len,
                    kind,
                    lr,
                    lr_rest,
                    penalty,
                    ..base
                },
            );
            let group = self.bind(
                &kernels.adam,
                &[
                    (0, &params),
                    (8, &state.values[g]),
                    (9, gradient),
                    (10, &state.first[g]),
                    (11, &state.second[g]),
                ],
            );
            Self::dispatch(encoder, &kernels.adam, &group, grid(len.div_ceil(GROUP)));
        }
        if let Some(m) = rates.mcmc {
            let params = self.uniform(
                "noise params",
                &OptimiseParams {
                    kind: m.seed,
                    stride: m.step,
                    lr: m.noise_scale,
                    ..base
                },
            );
            let group = self.bind(
                &kernels.noise,
                &[
                    (0, &params),
                    (1, &state.values[1]),
                    (2, &state.values[3]),
                    (8, &state.values[0]),
                    (12, &state.values[2]),
                ],
            );
            Self::dispatch(encoder, &kernels.noise, &group, grid(n.div_ceil(GROUP)));
        }
        Ok(())
    }

    /// A whole training step on the device after [`GpuRenderer::forward_state`]
    /// (without read-back): the loss against `target` and its gradient, the
    /// backward pass, the statistics and the Adam steps. Only the loss and
    /// PSNR come back.
    pub fn train_step(
        &self,
        state: &DeviceState,
        frame: &GpuFrame,
        target: &LossTarget,
        rates: &StepRates,
        t: i32,
    ) -> Result<StepReport, SplatError> {
        let kernels = self.optimise()?;
        let (width, height) = (frame.render.width, frame.render.height);
        let n = (width * height) as usize;
        if target.target.pixels != n {
            return Err(SplatError::Invalid(format!(
                "training step: the view's target has {} pixels, the render {n}",
                target.target.pixels
            )));
        }
        // One step at a time uses the kept buffers (the lock is held to the end).
        let mut kept = self.loss_buffers.lock().map_err(|_| {
            SplatError::Invalid("GPU backend: an earlier step failed midway".into())
        })?;
        let reusable = kept.take();
        let buffers = kept.insert(self.loss_buffers(reusable, n));
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let target_data = &target.target.data;
        let weight_sum = target.target.weight_sum;
        let params = |planes: u32, horizontal: u32| {
            self.uniform(
                "loss params",
                &LossParams {
                    width,
                    height,
                    planes,
                    horizontal,
                    background: [
                        target.background[0],
                        target.background[1],
                        target.background[2],
                        0.0,
                    ],
                    lambda_ssim: target.lambda_ssim,
                    lambda_opacity: target.lambda_opacity,
                    weight_sum,
                    _pad: 0.0,
                    window: kernels.window,
                },
            )
        };
        let LossBuffers {
            sums,
            planes,
            scratch,
            terms,
            d_image,
            ..
        } = &*buffers;
        let mut encoder = self.device.create_command_encoder(&Default::default());
        encoder.clear_buffer(sums, 0, None);
        let pixel_groups = grid((n as u32).div_ceil(GROUP));
        let base = params(15, 0);
        let group = self.bind(
            &kernels.prepare,
            &[
                (0, &base),
                (1, sums),
                (2, &frame.image),
                (3, target_data),
                (4, planes),
            ],
        );
        Self::dispatch(&mut encoder, &kernels.prepare, &group, pixel_groups);
        let blur = |encoder: &mut wgpu::CommandEncoder, data: &wgpu::Buffer, count: u32| {
            let horizontal = params(count, 1);
            let vertical = params(count, 0);
            let groups = grid((n as u32 * count).div_ceil(GROUP));
            let g = self.bind(&kernels.blur, &[(0, &horizontal), (5, data), (6, scratch)]);
            Self::dispatch(encoder, &kernels.blur, &g, groups);
            let g = self.bind(&kernels.blur, &[(0, &vertical), (5, scratch), (6, data)]);
            Self::dispatch(encoder, &kernels.blur, &g, groups);
        };
        blur(&mut encoder, planes, 15);
        let group = self.bind(
            &kernels.ssim_terms,
            &[
                (0, &base),
                (1, sums),
                (3, target_data),
                (7, planes),
                (8, terms),
            ],
        );
        Self::dispatch(&mut encoder, &kernels.ssim_terms, &group, pixel_groups);
        blur(&mut encoder, terms, 9);
        let group = self.bind(
            &kernels.gradient,
            &[
                (0, &base),
                (2, &frame.image),
                (3, target_data),
                (9, terms),
                (10, d_image),
            ],
        );
        Self::dispatch(&mut encoder, &kernels.gradient, &group, pixel_groups);
        let (grads2d, outputs, partials) = self.record_backward_from(
            &mut encoder,
            frame,
            d_image,
            rates.absolute_gradients,
            rates.camera_gradient,
        )?;
        self.record_step(&mut encoder, state, frame, &grads2d, &outputs, rates, t)?;
        // The loss sums (5 words), then the camera gradient's partial sums.
        let camera_words = partials.as_ref().map_or(0, |p| p.words);
        let back = self.zeroed("step read-back", 5 + camera_words);
        encoder.copy_buffer_to_buffer(sums, 0, &back, 0, 20);
        if let Some(p) = &partials {
            encoder.copy_buffer_to_buffer(&p.buffer, 0, &back, 20, 4 * p.words);
        }
        let bytes = self.submit_and_read(encoder, &back, 4 * (5 + camera_words))?;
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_error("the training step failed", e));
        }
        let camera = partials.map(|_| super::camera_gradient_of(&bytes[5..]));
        let s: Vec<f32> = bytes[..5].iter().map(|&w| f32::from_bits(w)).collect();
        let lam = target.lambda_ssim;
        let loss = (1.0 - lam) * s[0] / (3.0 * weight_sum)
            + lam * (1.0 - s[2])
            + target.lambda_opacity * s[1] / weight_sum;
        let psnr = if s[4] > 0.0 && s[3] > 0.0 {
            -10.0 * ((s[3] as f64) / (3.0 * s[4] as f64)).log10()
        } else if s[4] > 0.0 {
            f64::INFINITY
        } else {
            0.0
        };
        Ok(StepReport { loss, psnr, camera })
    }
}
