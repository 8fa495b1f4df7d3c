//! The trainer as a step API (after Brush's `SplatTrainer::step`): build a
//! [`Trainer`] from views and a start (fresh splats or a checkpoint's
//! state), call [`Trainer::step`] until it returns `None`, take
//! [`Trainer::checkpoint`] whenever a checkpoint is wanted, and
//! [`Trainer::finish`] for the model. One step renders one view, takes the
//! masked loss (see [`crate::train`]), steps Adam ([`crate::adam`]) and, on
//! refinement steps, lets the densification [`Strategy`] add and remove
//! splats; with pose refinement (`TrainConfig::pose`, [`crate::pose`]) it
//! renders the view at its corrected pose and steps the correction by the
//! camera's gradient. On the CPU renderer everything runs on the CPU; on a GPU the
//! parameters, moments and statistics stay on the device, where rendering,
//! gradients and Adam run, and come back only to refine, checkpoint and
//! finish; with pose refinement the camera gradient comes back with each
//! step's loss (as partial sums) and the corrections step on the host.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::adam::Adam;
use crate::backend::Renderer;
use crate::backward::{Wanted, backward_binned};
use crate::gpu::training::{DeviceState, HostState, LossTarget, StepRates, ViewTargets};
use crate::pose::{PoseCorrections, PoseRefiner, PoseState, rotation_centre};
use crate::raster::{bin_tiles, project, rasterize_binned};
use crate::sh::coefficients;
use crate::strategy::{Refinement, Strategy, moment_strides};
use crate::train::{
    LOG_SCALES_LR, OPACITIES_LR, QUATS_LR, SH_DC_LR, Start, StepLoss, TrainConfig, TrainState,
    step_loss,
};
use crate::view::{TrainingView, View};
use crate::{SplatError, Splats};

/// What one step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    /// The step's number, from 1.
    pub step: usize,
    pub loss: f32,
    /// PSNR of the step's render against its view, dB.
    pub psnr: f64,
    /// Whether the strategy refined the model after this step.
    pub refined: bool,
}

/// A training run in progress.
pub struct Trainer<'a, V: TrainingView> {
    views: &'a [V],
    config: TrainConfig,
    renderer: &'a Renderer,
    strategy: Box<dyn Strategy>,
    splats: Splats,
    /// The next step's number.
    next: usize,
    /// Scene extent measured at the start (it scales the position rate).
    extent: f32,
    adam: [Adam; 5],
    grad2d_sum: Vec<f32>,
    grad2d_count: Vec<u32>,
    /// Views still to visit in this epoch (taken from the back).
    order: Vec<usize>,
    rng: ChaCha8Rng,
    fingerprint: String,
    /// On a GPU: the parameters, moments and statistics on the device, and
    /// the views' loss targets kept there.
    device: Option<(DeviceState, ViewTargets)>,
    scratch: Option<View>,
    /// With `config.pose`: the views' pose corrections.
    pose: Option<PoseRefiner>,
}

impl<'a, V: TrainingView> Trainer<'a, V> {
    /// A run over `views` from `start` with `config`'s settings and
    /// densification strategy, rendering on `renderer`.
    pub fn new(
        views: &'a [V],
        start: Start,
        config: &TrainConfig,
        renderer: &'a Renderer,
    ) -> Result<Self, SplatError> {
        let strategy = crate::strategy::for_config(config);
        Self::with_strategy(views, start, config, renderer, strategy)
    }

    /// As [`Trainer::new`], with a strategy of the caller's.
    pub fn with_strategy(
        views: &'a [V],
        start: Start,
        config: &TrainConfig,
        renderer: &'a Renderer,
        strategy: Box<dyn Strategy>,
    ) -> Result<Self, SplatError> {
        if views.is_empty() {
            return Err(SplatError::Invalid("no training views".into()));
        }
        let rng = ChaCha8Rng::seed_from_u64(config.seed ^ 0x7a11);
        let fingerprint = crate::train::fingerprint(config, views);
        let mut trainer = Trainer {
            views,
            config: *config,
            renderer,
            strategy,
            splats: Splats::default(),
            next: 1,
            extent: 0.0,
            adam: std::array::from_fn(|_| Adam::new(0)),
            grad2d_sum: Vec::new(),
            grad2d_count: Vec::new(),
            order: Vec::new(),
            rng,
            fingerprint,
            device: None,
            scratch: None,
            pose: config.pose.map(|config| PoseRefiner {
                config,
                state: PoseState::new(views.len(), 1),
                group_of: vec![0; views.len()],
                centre: rotation_centre(views.iter().map(|v| v.camera())).into(),
            }),
        };
        match start {
            Start::Fresh(s) => trainer.init(s)?,
            Start::Resume(state) => trainer.resume(*state)?,
        }
        if let Renderer::Gpu(gpu) = renderer {
            let state = gpu.upload_state(&trainer.host_state())?;
            trainer.device = Some((state, ViewTargets::new(views.len(), gpu.view_memory())));
        }
        Ok(trainer)
    }

    fn init(&mut self, mut s: Splats) -> Result<(), SplatError> {
        s.validate()?;
        // The cap is a hard one: densification never exceeds it, so
        // neither may the start (a 5000-splat start under a cap of 100
        // used to train on, and end with, 4664).
        if self.config.max_splats == 0 || s.len() > self.config.max_splats {
            return Err(SplatError::Invalid(format!(
                "the starting model has {} splats and the cap (max_splats) is {}: start from fewer points or raise the cap",
                s.len(),
                self.config.max_splats
            )));
        }
        self.strategy.prepare(&mut s);
        self.extent = extent(&s);
        let (n, k) = (s.len(), s.sh_coefficients());
        self.adam = moment_strides(k).map(|stride| Adam::new(n * stride));
        self.grad2d_sum = vec![0.0; n];
        self.grad2d_count = vec![0; n];
        self.splats = s;
        Ok(())
    }

    fn resume(&mut self, state: TrainState) -> Result<(), SplatError> {
        if state.fingerprint != self.fingerprint {
            return Err(SplatError::Invalid(format!(
                "the checkpoint was written with other settings or views ({}); now: {}",
                state.fingerprint, self.fingerprint
            )));
        }
        state.splats.validate()?;
        // The extent scales the position rate: a checkpoint's must be one
        // a fresh start could have measured.
        if !(state.extent.is_finite() && state.extent >= 1e-3) {
            return Err(SplatError::Invalid(format!(
                "the checkpoint's scene extent is {}, where training measures at least 0.001",
                state.extent
            )));
        }
        let finite = |v: &Vec<f32>| v.iter().all(|x| x.is_finite());
        if !state.moments.iter().all(|(m, v)| finite(m) && finite(v)) {
            return Err(SplatError::Invalid(
                "the checkpoint's Adam moments are not all finite numbers".into(),
            ));
        }
        if state.order.iter().any(|&i| i >= self.views.len()) {
            return Err(SplatError::Invalid(
                "the checkpoint's view order names views that do not exist".into(),
            ));
        }
        match (&mut self.pose, state.poses) {
            (None, None) => {}
            (Some(refiner), Some(poses)) if poses.views.len() == self.views.len() => {
                poses.validate()?;
                refiner.state = poses;
            }
            (Some(_), Some(poses)) => {
                return Err(SplatError::Invalid(format!(
                    "the checkpoint's pose corrections are for {} views, not {}",
                    poses.views.len(),
                    self.views.len()
                )));
            }
            (Some(_), None) | (None, Some(_)) => {
                return Err(SplatError::Invalid(
                    "the checkpoint and the settings disagree on pose refinement".into(),
                ));
            }
        }
        self.rng.set_word_pos(state.rng_word_pos);
        self.adam = state.moments.map(|(m, v)| Adam { m, v });
        self.splats = state.splats;
        self.next = state.step + 1;
        self.extent = state.extent;
        self.grad2d_sum = state.grad2d_sum;
        self.grad2d_count = state.grad2d_count;
        self.order = state.order;
        Ok(())
    }

    /// With pose refinement: puts view `i` in group `groups[i]` (an arm;
    /// each group learns one camera-side correction). Before the first
    /// step; all views are in group 0 until then.
    pub fn with_pose_groups(mut self, groups: &[usize]) -> Result<Self, SplatError> {
        let Some(refiner) = &mut self.pose else {
            return Ok(self);
        };
        if groups.len() != self.views.len() {
            return Err(SplatError::Invalid(format!(
                "{} pose groups for {} views",
                groups.len(),
                self.views.len()
            )));
        }
        let count = groups.iter().max().map_or(1, |g| g + 1);
        if self.next == 1 {
            refiner.state.groups = vec![Default::default(); count];
        } else if refiner.state.groups.len() != count {
            return Err(SplatError::Invalid(format!(
                "the checkpoint has {} pose groups, the views {count}",
                refiner.state.groups.len()
            )));
        }
        // The fingerprint stays: the groups are the views' arms, and the
        // views are in it.
        refiner.group_of = groups.to_vec();
        Ok(self)
    }

    /// The pose corrections learned so far, with pose refinement.
    pub fn pose_corrections(&self) -> Option<PoseCorrections> {
        (self.pose.as_ref()).map(|r| r.state.corrections(r.centre.into()))
    }

    /// Steps done so far.
    pub fn steps_done(&self) -> usize {
        self.next - 1
    }

    /// Runs the next step (and the refinement due after it); `None` once
    /// all `config.steps` are done.
    pub fn step(&mut self) -> Result<Option<StepReport>, SplatError> {
        let step = self.next;
        if step > self.config.steps {
            return Ok(None);
        }
        if self.order.is_empty() {
            self.order = (0..self.views.len()).collect();
            for i in (1..self.order.len()).rev() {
                self.order.swap(i, self.rng.random_range(0..=i));
            }
        }
        let index = self.order.pop().expect("an epoch has views");
        let background = [
            self.rng.random::<f32>(),
            self.rng.random::<f32>(),
            self.rng.random::<f32>(),
        ];
        let progress_fraction = step as f32 / self.config.steps as f32;
        let means_lr = self.config.position_lr * self.extent * 0.01f32.powf(progress_fraction);
        // Both backends step with these rates (the CPU's MCMC terms come
        // from the same `mcmc` functions).
        let rates = StepRates {
            means: means_lr,
            log_scales: LOG_SCALES_LR,
            quats: QUATS_LR,
            opacities: OPACITIES_LR,
            sh_dc: SH_DC_LR,
            sh_rest: self.config.sh_rest_lr,
            mcmc: self
                .strategy
                .mcmc_step(&self.splats, &self.config, self.extent, means_lr, step),
            absolute_gradients: self.config.absolute_gradients,
            camera_gradient: self.pose.is_some(),
        };
        let (loss, psnr) = if self.device.is_some() {
            self.gpu_step(step, index, background, &rates)?
        } else {
            self.cpu_step(step, index, background, &rates)
        };
        let refined = self.refine_after(step)?;
        self.next += 1;
        Ok(Some(StepReport {
            step,
            loss,
            psnr,
            refined,
        }))
    }

    /// The SH degree in use at `step`.
    fn degree(&self, step: usize) -> usize {
        (step / self.config.sh_interval.max(1))
            .min(self.config.max_sh_degree)
            .min(self.splats.sh_degree)
    }

    fn gpu_step(
        &mut self,
        step: usize,
        index: usize,
        background: [f32; 3],
        rates: &StepRates,
    ) -> Result<(f32, f64), SplatError> {
        let Renderer::Gpu(gpu) = self.renderer else {
            unreachable!("a device state is only made on a GPU")
        };
        let degree = self.degree(step);
        let settings = self.splats.render_settings(background);
        let (device, targets) = self.device.as_mut().expect("checked by the caller");
        let view = &self.views[index];
        let target = targets.target(gpu, index, view, &mut self.scratch)?;
        let camera = match &self.pose {
            Some(refiner) => refiner.camera(index, view.camera()),
            None => *view.camera(),
        };
        let frame = gpu.forward_state(device, &camera, &settings, degree, false)?;
        let target = LossTarget {
            target,
            background,
            lambda_ssim: self.config.lambda_ssim,
            lambda_opacity: self.config.lambda_opacity,
        };
        let report = gpu.train_step(device, &frame, &target, rates, step as i32)?;
        if let (Some(refiner), Some(gradient)) = (&mut self.pose, &report.camera) {
            let extent = f64::from(self.extent);
            refiner.step(index, &camera, gradient, step, self.config.steps, extent);
        }
        Ok((report.loss, report.psnr))
    }

    fn cpu_step(
        &mut self,
        step: usize,
        index: usize,
        background: [f32; 3],
        rates: &StepRates,
    ) -> (f32, f64) {
        let degree = self.degree(step);
        let settings = self.splats.render_settings(background);
        let config = &self.config;
        let s = &mut self.splats;
        let k = s.sh_coefficients();
        let t = step as i32;
        let view = self.views[index].pixels_in(&mut self.scratch);
        let camera = match &self.pose {
            Some(refiner) => refiner.camera(index, &view.camera),
            None => view.camera,
        };
        let g = s.gaussians_up_to::<f32>(degree);
        let p = project(&g, &camera, &settings);
        let (width, height) = (view.camera.width, view.camera.height);
        let bins = bin_tiles(&p, width, height);
        let r = rasterize_binned(&bins, width, height, background);
        let (w, h) = (width as usize, height as usize);
        let StepLoss {
            loss,
            d_rgb,
            d_alpha,
            psnr,
        } = step_loss(view, &r, background, config);
        let (grads, camera_gradient) = backward_binned(
            &g,
            &camera,
            &settings,
            &p,
            &bins,
            &d_rgb,
            &d_alpha,
            Wanted {
                absolute: config.absolute_gradients,
                camera: self.pose.is_some(),
            },
        );
        if let Some(refiner) = &mut self.pose {
            let extent = f64::from(self.extent);
            refiner.step(index, &camera, &camera_gradient, step, config.steps, extent);
        }
        if self.strategy.uses_gradient_statistics() {
            // Screen-space gradient statistics for densification (gsplat
            // scales by half the image size).
            let screen_gradients = if config.absolute_gradients {
                &grads.means2d_abs
            } else {
                &grads.means2d
            };
            self.grad2d_sum
                .par_iter_mut()
                .zip(self.grad2d_count.par_iter_mut())
                .enumerate()
                .filter(|(i, _)| p.visible(*i))
                .for_each(|(i, (sum, count))| {
                    let gx = screen_gradients[i][0] * w as f32 * 0.5;
                    let gy = screen_gradients[i][1] * h as f32 * 0.5;
                    *sum += (gx * gx + gy * gy).sqrt();
                    *count += 1;
                });
        }
        // Adam steps, in place on the parameters' flattened storage.
        let adam = &mut self.adam;
        adam[0].step(
            s.means.as_flattened_mut(),
            grads.means.as_flattened(),
            rates.means,
            t,
        );
        let mut log_scale_grads = grads.log_scales(&g);
        let mut opacity_grads = grads.opacity_logits(&g);
        self.strategy
            .regularise(s, self.extent, &mut opacity_grads, &mut log_scale_grads);
        adam[1].step(
            s.log_scales.as_flattened_mut(),
            log_scale_grads.as_flattened(),
            rates.log_scales,
            t,
        );
        adam[2].step(
            s.quats.as_flattened_mut(),
            grads.quats.as_flattened(),
            rates.quats,
            t,
        );
        adam[3].step(&mut s.opacity_logits, &opacity_grads, rates.opacities, t);
        // Bands above the current degree get zero gradients (their moments
        // still decay); DC and higher bands use different rates.
        let ka = coefficients(degree);
        let mut sh_rates = vec![rates.sh_rest; 3 * k];
        sh_rates[..3].fill(rates.sh_dc);
        adam[4].step_rows(
            s.sh.as_flattened_mut(),
            grads.colors.as_flattened(),
            3 * ka,
            &sh_rates,
            t,
        );
        self.strategy
            .after_step(s, config, step, rates.means, self.extent);
        (loss, psnr)
    }

    /// The refinement and opacity reset due after `step`, on the host (a
    /// device's state comes back first and goes out again after).
    fn refine_after(&mut self, step: usize) -> Result<bool, SplatError> {
        let config = &self.config;
        let in_window = step >= config.densify_from && step <= config.densify_until;
        let refine_now = in_window && step.is_multiple_of(config.densify_every);
        let reset_now = self.strategy.resets_opacities()
            && config.reset_every > 0
            && step.is_multiple_of(config.reset_every)
            && step < config.densify_until;
        if !(refine_now || reset_now) {
            return Ok(false);
        }
        self.download()?;
        if refine_now {
            self.strategy.refine(
                Refinement {
                    splats: &mut self.splats,
                    adam: &mut self.adam,
                    grad2d_sum: &self.grad2d_sum,
                    grad2d_count: &self.grad2d_count,
                    rng: &mut self.rng,
                },
                &self.config,
                self.extent,
            );
            self.grad2d_sum = vec![0.0; self.splats.len()];
            self.grad2d_count = vec![0; self.splats.len()];
        }
        if reset_now {
            let cap = (0.01f32 / 0.99).ln();
            for o in &mut self.splats.opacity_logits {
                *o = o.min(cap);
            }
        }
        if let (Renderer::Gpu(gpu), Some((device, _))) = (self.renderer, self.device.as_mut()) {
            *device = gpu.upload_state(&host_state(
                &self.splats,
                &self.adam,
                &self.grad2d_sum,
                &self.grad2d_count,
            ))?;
        }
        Ok(refine_now)
    }

    /// Brings a device's state back to the host.
    fn download(&mut self) -> Result<(), SplatError> {
        if let (Renderer::Gpu(gpu), Some((device, _))) = (self.renderer, self.device.as_ref()) {
            let host = gpu.download_state(device)?;
            self.splats = host.splats;
            self.adam = host.moments.map(|(m, v)| Adam { m, v });
            self.grad2d_sum = host.grad_sum;
            self.grad2d_count = host.grad_count;
        }
        Ok(())
    }

    fn host_state(&self) -> HostState {
        host_state(
            &self.splats,
            &self.adam,
            &self.grad2d_sum,
            &self.grad2d_count,
        )
    }

    /// Everything needed to go on exactly from here: a checkpoint.
    pub fn checkpoint(&mut self) -> Result<TrainState, SplatError> {
        self.download()?;
        Ok(TrainState {
            step: self.steps_done(),
            splats: self.splats.clone(),
            extent: self.extent,
            moments: self.adam.each_ref().map(|a| (a.m.clone(), a.v.clone())),
            grad2d_sum: self.grad2d_sum.clone(),
            grad2d_count: self.grad2d_count.clone(),
            order: self.order.clone(),
            rng_word_pos: self.rng.get_word_pos(),
            fingerprint: self.fingerprint.clone(),
            poses: self.pose.as_ref().map(|r| r.state.clone()),
        })
    }

    /// The trained model.
    pub fn finish(mut self) -> Result<Splats, SplatError> {
        self.download()?;
        self.splats.validate()?;
        Ok(self.splats)
    }
}

/// The scene extent: the splats' spread around their centre (at least 1 mm).
pub(crate) fn extent(s: &Splats) -> f32 {
    let n = s.len().max(1) as f32;
    let c = [0, 1, 2].map(|a| s.means.iter().map(|m| m[a]).sum::<f32>() / n);
    s.means
        .iter()
        .map(|m| ((m[0] - c[0]).powi(2) + (m[1] - c[1]).powi(2) + (m[2] - c[2]).powi(2)).sqrt())
        .fold(0.0, f32::max)
        .max(1e-3)
}

fn host_state(s: &Splats, adam: &[Adam; 5], sum: &[f32], count: &[u32]) -> HostState {
    HostState {
        splats: s.clone(),
        moments: adam.each_ref().map(|a| (a.m.clone(), a.v.clone())),
        grad_sum: sum.to_vec(),
        grad_count: count.to_vec(),
    }
}

/// Trains `splats` on `views`; `progress(step, loss, psnr)` is called every
/// step. On the CPU renderer everything runs on the CPU; on a GPU the
/// parameters stay on the device, where rendering, gradients and Adam run,
/// and the loss and densification run on the CPU.
pub fn train(
    views: &[impl TrainingView],
    s: Splats,
    config: &TrainConfig,
    renderer: &Renderer,
    progress: &mut dyn FnMut(usize, f32, f64),
) -> Result<Splats, SplatError> {
    train_resumable(views, Start::Fresh(s), config, renderer, None, progress)
}

/// Periodic checkpoints: `save` is called with the whole training state
/// every `every` steps.
pub struct Checkpoints<'a> {
    pub every: usize,
    pub save: &'a mut dyn FnMut(&TrainState) -> Result<(), SplatError>,
}

/// Training with optional resumption and checkpoints (see [`train`]): a
/// [`Trainer`] stepped to the end, its state saved
/// every `checkpoints.every` steps (not after the last).
pub fn train_resumable(
    views: &[impl TrainingView],
    start: Start,
    config: &TrainConfig,
    renderer: &Renderer,
    checkpoints: Option<Checkpoints<'_>>,
    progress: &mut dyn FnMut(usize, f32, f64),
) -> Result<Splats, SplatError> {
    let mut trainer = Trainer::new(views, start, config, renderer)?;
    run_to_end(&mut trainer, checkpoints, progress)?;
    trainer.finish()
}

/// Steps `trainer` to its last step, calling `progress(step, loss, psnr)`
/// every step and saving its state every `checkpoints.every` steps (not
/// after the last).
pub fn run_to_end<V: TrainingView>(
    trainer: &mut Trainer<'_, V>,
    mut checkpoints: Option<Checkpoints<'_>>,
    progress: &mut dyn FnMut(usize, f32, f64),
) -> Result<(), SplatError> {
    let steps = trainer.config.steps;
    while let Some(report) = trainer.step()? {
        progress(report.step, report.loss, report.psnr);
        if let Some(c) = checkpoints.as_mut()
            && c.every > 0
            && report.step % c.every == 0
            && report.step < steps
        {
            (c.save)(&trainer.checkpoint()?)?;
        }
    }
    Ok(())
}
