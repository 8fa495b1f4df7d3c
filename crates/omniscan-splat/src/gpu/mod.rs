//! The GPU backend of the rasterizer: the CPU reference's algorithm
//! (`crate::raster`) as hand-written WGSL compute kernels run through wgpu
//! (Vulkan, Metal or DX12; Mesa's lavapipe on machines without a GPU, which
//! is how CI checks the kernels).
//!
//! Forward pass, all on the device (paper, "3DGS Training", after Kerbl et
//! al. 2023 and gsplat's staging): `project.wgsl` projects every Gaussian and
//! counts the 16x16 tiles it can reach; `scan.wgsl` turns the counts into
//! offsets (the total is the one value read back, to size the intersection
//! buffers, as Brush does); `sort.wgsl` emits one (tile, depth, index) entry
//! per intersection and orders them with a stable 4-bit radix sort, first by
//! depth (8 passes), then by tile (as many passes as the tile count needs), so
//! each tile's list is front to back with ties by index, as on the CPU; it
//! then finds each tile's range; `rasterize.wgsl` composites one tile per
//! workgroup. Kernels are ours (WGSL has no 64-bit keys, hence the two
//! sorts; no crate provides these kernels for wgpu).
//!
//! Results match the CPU reference in f32 up to the order of floating-point
//! operations inside the projection: a Gaussian whose alpha sits within
//! rounding of 1/255 at a pixel can be kept by one and skipped by the other.

pub mod select;
pub mod training;

use std::sync::mpsc;

use wgpu::util::DeviceExt;

use crate::SplatError;
use crate::backward::Gradients;
use crate::raster::{Camera, Colors, Gaussians, Mode, Render, Settings, TILE, ViewGeometry};

const COMMON: &str = include_str!("common.wgsl");
/// Floats per pixel of the forward image (`PIXEL_FLOATS` in common.wgsl).
const PIXEL_FLOATS: u64 = 7;
/// Floats per Gaussian of the 2D gradients (`GRADS2D_FLOATS` in common.wgsl).
const GRADS2D_FLOATS: u64 = 12;
const PROJECT: &str = include_str!("project.wgsl");
const SCAN: &str = include_str!("scan.wgsl");
const SORT: &str = include_str!("sort.wgsl");
const RASTERIZE: &str = include_str!("rasterize.wgsl");
const RASTERIZE_BACKWARD: &str = include_str!("rasterize_backward.wgsl");
const PROJECT_BACKWARD: &str = include_str!("project_backward.wgsl");
const CAMERA_SUM: &str = include_str!("camera_sum.wgsl");

const GROUP: u32 = 256;
const SCAN_BLOCK: u32 = 1024;
const MAX_GROUPS_X: u32 = 65_535;

/// Which devices [`GpuRenderer::new`] may pick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeviceChoice {
    /// A real GPU only.
    Hardware,
    /// A real GPU, else a software rasterizer such as lavapipe.
    AllowSoftware,
}

/// The wgpu device and the compiled kernels.
pub struct GpuRenderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    project: wgpu::ComputePipeline,
    scan_blocks: wgpu::ComputePipeline,
    add_block_offsets: wgpu::ComputePipeline,
    depth_keys: wgpu::ComputePipeline,
    gather_counts: wgpu::ComputePipeline,
    emit: wgpu::ComputePipeline,
    radix_histogram: wgpu::ComputePipeline,
    radix_scatter: wgpu::ComputePipeline,
    tile_ranges: wgpu::ComputePipeline,
    rasterize: wgpu::ComputePipeline,
    /// The backward kernels, when the device has subgroup operations.
    backward: Option<BackwardKernels>,
    /// The optimiser's kernels (with the backward ones).
    optimise: Option<training::OptimiseKernels>,
    /// The training loss's working buffers, kept for the next step.
    loss_buffers: std::sync::Mutex<Option<training::LossBuffers>>,
    /// How many bytes of the views' loss targets training keeps on the device.
    view_memory: u64,
}

/// The backward pass's kernels: the compositing's, the projection's, and
/// the sum of the camera gradient's shares.
pub(crate) struct BackwardKernels {
    raster: wgpu::ComputePipeline,
    project: wgpu::ComputePipeline,
    camera_sum: wgpu::ComputePipeline,
}

/// The camera gradient's partial sums (6 per workgroup of 256 Gaussians) a
/// backward pass records, when asked for.
pub(crate) struct CameraPartials {
    pub buffer: wgpu::Buffer,
    pub words: u64,
}

/// Adds up the partial sums of the camera gradient, in f64, in order.
pub(crate) fn camera_gradient_of(words: &[u32]) -> crate::backward::CameraGradient {
    let mut sum = [0.0f64; 6];
    for chunk in words.chunks_exact(6) {
        for (s, w) in sum.iter_mut().zip(chunk) {
            *s += f64::from(f32::from_bits(*w));
        }
    }
    crate::backward::CameraGradient {
        translation: [sum[0], sum[1], sum[2]],
        rotation: [sum[3], sum[4], sum[5]],
    }
}

/// Gaussians on the device, as the kernels read them: activated scales and
/// opacities, colour coefficients `stride` per Gaussian of which the first
/// `per_channel` are used (or plain RGB).
#[derive(Debug, Clone)]
pub(crate) struct SceneBuffers {
    pub n: u32,
    pub per_channel: u32,
    pub stride: u32,
    pub plain: bool,
    pub means: wgpu::Buffer,
    pub scales: wgpu::Buffer,
    pub quats: wgpu::Buffer,
    pub opacities: wgpu::Buffer,
    pub coeffs: wgpu::Buffer,
}

/// What the forward pass leaves on the device for the backward pass.
pub struct GpuFrame {
    pub render: Render<f32>,
    gaussians: u32,
    sh_stride: u32,
    camera: wgpu::Buffer,
    inputs: [wgpu::Buffer; 5],
    projected: wgpu::Buffer,
    sorted_index: wgpu::Buffer,
    ranges: wgpu::Buffer,
    image: wgpu::Buffer,
    last_contributor: wgpu::Buffer,
    raster_params: wgpu::Buffer,
    tiles: (u32, u32),
}

impl std::fmt::Debug for GpuRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuRenderer({})", self.adapter())
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct CameraUniform {
    rot: [[f32; 4]; 3],
    campos: [f32; 4],
    intrinsics: [f32; 4],
    limits: [f32; 4],
    size: [f32; 4],
    footprint: [f32; 4],
    background: [f32; 4],
    counts: [u32; 4],
    counts2: [u32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SortParams {
    len: u32,
    shift: u32,
    blocks: u32,
    gaussians: u32,
    tiles_x: u32,
    tiles: u32,
    _pad: [u32; 2],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct RasterParams {
    width: u32,
    height: u32,
    tiles_x: u32,
    _pad: u32,
    background: [f32; 4],
}

/// A kernel module: `common.wgsl`'s declarations, then `source`.
fn shader(device: &wgpu::Device, label: &str, source: &str) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(format!("{COMMON}\n{source}").into()),
    })
}

/// The compute pipeline of `entry` in `module`, its layout derived from the kernel.
fn compute_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    entry: &str,
) -> wgpu::ComputePipeline {
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: None,
        module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

fn gpu_error(what: &str, e: impl std::fmt::Display) -> SplatError {
    SplatError::Invalid(format!("GPU backend: {what}: {e}"))
}

/// Workgroup counts for `groups` workgroups, folded into two dimensions
/// past the 65,535 limit of one (the kernels rebuild the flat index).
fn grid(groups: u32) -> (u32, u32) {
    if groups <= MAX_GROUPS_X {
        (groups.max(1), 1)
    } else {
        (MAX_GROUPS_X, groups.div_ceil(MAX_GROUPS_X))
    }
}

impl GpuRenderer {
    /// Opens a GPU (high-performance preference) and compiles the kernels.
    pub fn new(choice: DeviceChoice) -> Result<GpuRenderer, SplatError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle());
        let adapter = match select::selected() {
            select::GpuSelector::Preferred => {
                pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
                    power_preference: wgpu::PowerPreference::HighPerformance,
                    force_fallback_adapter: false,
                    compatible_surface: None,
                    apply_limit_buckets: false,
                }))
                .map_err(|e| gpu_error("no GPU adapter found (is a Vulkan driver installed?)", e))?
            }
            selector => {
                let adapters =
                    pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()))
                        .into_iter()
                        .map(|a| {
                            let info = a.get_info();
                            (a, info)
                        })
                        .collect();
                select::pick(&selector, adapters)?
            }
        };
        let info = adapter.get_info();
        if choice == DeviceChoice::Hardware && info.device_type == wgpu::DeviceType::Cpu {
            return Err(SplatError::Invalid(format!(
                "GPU backend: the only adapter is the software rasterizer {} ({:?}); the CPU backend is faster",
                info.name, info.backend
            )));
        }
        let adapter_limits = adapter.limits();
        let limits = wgpu::Limits {
            max_storage_buffer_binding_size: adapter_limits.max_storage_buffer_binding_size,
            max_buffer_size: adapter_limits.max_buffer_size,
            max_storage_buffers_per_shader_stage: adapter_limits
                .max_storage_buffers_per_shader_stage
                .max(8),
            ..wgpu::Limits::default()
        };
        // The backward pass sums gradients across subgroups.
        let subgroups = adapter.features().contains(wgpu::Features::SUBGROUP);
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("omniscan"),
            required_features: if subgroups {
                wgpu::Features::SUBGROUP
            } else {
                wgpu::Features::empty()
            },
            required_limits: limits,
            ..Default::default()
        }))
        .map_err(|e| gpu_error("the device refused to open", e))?;
        device.on_uncaptured_error(std::sync::Arc::new(|e| {
            tracing::error!("GPU backend: {e}");
        }));
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = |label: &str, source: &str| shader(&device, label, source);
        let project_module = module("project", PROJECT);
        let scan_module = module("scan", SCAN);
        let sort_module = module("sort", SORT);
        let raster_module = module("rasterize", RASTERIZE);
        let pipeline =
            |module: &wgpu::ShaderModule, entry: &str| compute_pipeline(&device, module, entry);
        let mut backward = None;
        if subgroups {
            // A device that cannot build the backward kernels can still render.
            let inner = device.push_error_scope(wgpu::ErrorFilter::Validation);
            let raster = pipeline(&module("rasterize backward", RASTERIZE_BACKWARD), "main");
            let project = pipeline(&module("project backward", PROJECT_BACKWARD), "main");
            let camera_sum = pipeline(&module("camera gradient sum", CAMERA_SUM), "main");
            let kernels = training::OptimiseKernels::new(&device);
            match pollster::block_on(inner.pop()) {
                None => {
                    backward = Some((
                        BackwardKernels {
                            raster,
                            project,
                            camera_sum,
                        },
                        kernels,
                    ))
                }
                Some(e) => tracing::warn!("GPU backend: no backward pass on this device: {e}"),
            }
        }
        let (backward, optimise) = match backward {
            Some((backward, kernels)) => (Some(backward), Some(kernels)),
            None => (None, None),
        };
        let renderer = GpuRenderer {
            project: pipeline(&project_module, "main"),
            scan_blocks: pipeline(&scan_module, "scan_blocks"),
            add_block_offsets: pipeline(&scan_module, "add_block_offsets"),
            depth_keys: pipeline(&sort_module, "depth_keys"),
            gather_counts: pipeline(&sort_module, "gather_counts"),
            emit: pipeline(&sort_module, "emit"),
            radix_histogram: pipeline(&sort_module, "radix_histogram"),
            radix_scatter: pipeline(&sort_module, "radix_scatter"),
            tile_ranges: pipeline(&sort_module, "tile_ranges"),
            rasterize: pipeline(&raster_module, "main"),
            backward,
            optimise,
            loss_buffers: std::sync::Mutex::new(None),
            view_memory: training::DEFAULT_VIEW_MEMORY,
            device,
            queue,
            info,
        };
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_error("the kernels did not compile", e));
        }
        Ok(renderer)
    }

    /// The adapter's name and API, e.g. "NVIDIA H100 (Vulkan)".
    pub fn adapter(&self) -> String {
        format!("{} ({:?})", self.info.name, self.info.backend)
    }

    /// How many bytes of the views' loss targets training keeps on the device
    /// (the rest are sent at each of their steps).
    pub fn view_memory(&self) -> u64 {
        self.view_memory
    }

    /// Sets [`GpuRenderer::view_memory`].
    pub fn set_view_memory(&mut self, bytes: u64) {
        self.view_memory = bytes;
    }

    /// Whether the device can train (the backward kernels need subgroup operations).
    pub fn can_train(&self) -> bool {
        self.backward.is_some() && self.optimise.is_some()
    }

    /// Whether the device is a software rasterizer (lavapipe).
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    fn storage<T: bytemuck::Pod>(&self, label: &str, data: &[T]) -> wgpu::Buffer {
        // Zero-length bindings are invalid; keep one element.
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let contents = if bytes.is_empty() {
            &[0u8; 4][..]
        } else {
            bytes
        };
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            })
    }

    fn zeroed(&self, label: &str, words: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: 4 * words.max(1),
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    fn uniform<T: bytemuck::Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::bytes_of(value),
                usage: wgpu::BufferUsages::UNIFORM,
            })
    }

    fn bind(
        &self,
        pipeline: &wgpu::ComputePipeline,
        entries: &[(u32, &wgpu::Buffer)],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = entries
            .iter()
            .map(|(binding, buffer)| wgpu::BindGroupEntry {
                binding: *binding,
                resource: buffer.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    fn dispatch(
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        bind_group: &wgpu::BindGroup,
        groups: (u32, u32),
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: None,
            timestamp_writes: None,
        });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        pass.dispatch_workgroups(groups.0, groups.1, 1);
    }

    fn sort_params(
        &self,
        len: u32,
        shift: u32,
        gaussians: u32,
        tiles_x: u32,
        tiles: u32,
    ) -> SortParams {
        SortParams {
            len,
            shift,
            blocks: len.div_ceil(GROUP).max(1),
            gaussians,
            tiles_x,
            tiles,
            _pad: [0; 2],
        }
    }

    /// Two sets of (tile, depth, index) buffers of `len` entries, for ping-pong sorting.
    fn key_sets(&self, len: u64) -> Vec<[wgpu::Buffer; 3]> {
        (0..2)
            .map(|_| {
                [
                    self.zeroed("tile keys", len),
                    self.zeroed("depth keys", len),
                    self.zeroed("indices", len),
                ]
            })
            .collect()
    }

    /// Records stable radix passes over the first `len` entries of `keys[0]`
    /// (ping-ponging with `keys[1]`), one per digit position in `shifts`
    /// (depth bits below 32, tile bits from 32); returns which set holds the result.
    #[allow(clippy::too_many_arguments)]
    fn record_radix(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        keys: &[[wgpu::Buffer; 3]],
        len: u32,
        shifts: &[u32],
        gaussians: u32,
        tiles_x: u32,
        tiles: u32,
    ) -> usize {
        let mut current = 0;
        if len == 0 {
            return current;
        }
        let blocks = len.div_ceil(GROUP).max(1);
        let histogram = self.zeroed("radix histogram", 16 * blocks as u64);
        for &shift in shifts {
            let pass_params = self.uniform(
                "radix params",
                &self.sort_params(len, shift, gaussians, tiles_x, tiles),
            );
            let (input, output_keys) = (&keys[current], &keys[1 - current]);
            let group = self.bind(
                &self.radix_histogram,
                &[
                    (0, &pass_params),
                    (10, &input[0]),
                    (11, &input[1]),
                    (13, &histogram),
                ],
            );
            Self::dispatch(encoder, &self.radix_histogram, &group, grid(blocks));
            self.record_scan(encoder, &histogram, 16 * blocks);
            let group = self.bind(
                &self.radix_scatter,
                &[
                    (0, &pass_params),
                    (10, &input[0]),
                    (11, &input[1]),
                    (12, &input[2]),
                    (13, &histogram),
                    (14, &output_keys[0]),
                    (15, &output_keys[1]),
                    (16, &output_keys[2]),
                ],
            );
            Self::dispatch(encoder, &self.radix_scatter, &group, grid(blocks));
            current = 1 - current;
        }
        current
    }

    /// Records an exclusive scan of the first `len` words of `data`, in place.
    fn record_scan(&self, encoder: &mut wgpu::CommandEncoder, data: &wgpu::Buffer, len: u32) {
        let blocks = len.div_ceil(SCAN_BLOCK).max(1);
        let sums = self.zeroed("scan block sums", blocks as u64);
        let params = self.uniform("scan params", &[len, 0u32, 0, 0]);
        let group = self.bind(&self.scan_blocks, &[(0, &params), (1, data), (2, &sums)]);
        Self::dispatch(encoder, &self.scan_blocks, &group, grid(blocks));
        if blocks > 1 {
            self.record_scan(encoder, &sums, blocks);
            let group = self.bind(
                &self.add_block_offsets,
                &[(0, &params), (1, data), (2, &sums)],
            );
            Self::dispatch(encoder, &self.add_block_offsets, &group, grid(blocks));
        }
    }

    fn submit_and_read(
        &self,
        encoder: wgpu::CommandEncoder,
        source: &wgpu::Buffer,
        bytes: u64,
    ) -> Result<Vec<u32>, SplatError> {
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: bytes.max(4),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut encoder = encoder;
        encoder.copy_buffer_to_buffer(source, 0, &staging, 0, bytes.max(4));
        self.queue.submit([encoder.finish()]);
        let (sender, receiver) = mpsc::channel();
        staging.slice(..).map_async(wgpu::MapMode::Read, move |r| {
            let _ = sender.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| gpu_error("waiting for the device", e))?;
        receiver
            .recv()
            .map_err(|e| gpu_error("reading results back", e))?
            .map_err(|e| gpu_error("reading results back", e))?;
        // Words, not a cast of the bytes: a byte vector need not be aligned for u32.
        let words = staging
            .slice(..)
            .get_mapped_range()
            .map_err(|e| gpu_error("reading results back", e))?
            .chunks_exact(4)
            .take((bytes / 4) as usize)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        staging.unmap();
        Ok(words)
    }

    /// Renders `gaussians` through `camera`: the same outputs as
    /// [`crate::raster::render`] in f32.
    pub fn render(
        &self,
        gaussians: &Gaussians<f32>,
        camera: &Camera<f32>,
        settings: &Settings<f32>,
    ) -> Result<Render<f32>, SplatError> {
        Ok(self.forward(gaussians, camera, settings)?.render)
    }

    /// Renders and keeps what the backward pass needs on the device.
    pub fn forward(
        &self,
        gaussians: &Gaussians<f32>,
        camera: &Camera<f32>,
        settings: &Settings<f32>,
    ) -> Result<GpuFrame, SplatError> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let result = self.forward_inner(gaussians, camera, settings);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_error("rendering failed", e));
        }
        result
    }

    fn forward_inner(
        &self,
        gaussians: &Gaussians<f32>,
        camera: &Camera<f32>,
        settings: &Settings<f32>,
    ) -> Result<GpuFrame, SplatError> {
        let scene = self.upload(gaussians)?;
        self.forward_scene(&scene, camera, settings, true)
    }

    /// Copies activated Gaussians to the device.
    fn upload(&self, gaussians: &Gaussians<f32>) -> Result<SceneBuffers, SplatError> {
        let (coeffs, per_channel, plain): (Vec<f32>, u32, bool) = match &gaussians.colors {
            Colors::Rgb(c) => (c.iter().flatten().copied().collect(), 1, true),
            Colors::Sh { degree, coeffs } => (
                coeffs.iter().flatten().copied().collect(),
                crate::sh::coefficients(*degree) as u32,
                false,
            ),
        };
        let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
        Ok(SceneBuffers {
            n: gaussians.means.len() as u32,
            per_channel,
            stride: per_channel,
            plain,
            means: self.storage("means", &flat(&gaussians.means)),
            scales: self.storage("scales", &flat(&gaussians.scales)),
            quats: self.storage(
                "quats",
                &gaussians
                    .quats
                    .iter()
                    .flatten()
                    .copied()
                    .collect::<Vec<f32>>(),
            ),
            opacities: self.storage("opacities", &gaussians.opacities),
            coeffs: self.storage("colour coefficients", &coeffs),
        })
    }

    /// The forward pass of Gaussians already on the device.
    /// The forward pass of Gaussians already on the device; the image comes
    /// back to the host only when `read_back` (else `render` has no pixels).
    fn forward_scene(
        &self,
        scene: &SceneBuffers,
        camera: &Camera<f32>,
        settings: &Settings<f32>,
        read_back: bool,
    ) -> Result<GpuFrame, SplatError> {
        let n = scene.n;
        let per_channel = scene.per_channel;
        let (width, height) = (camera.width, camera.height);
        if width == 0 || height == 0 {
            return Err(SplatError::Invalid("cannot render an empty image".into()));
        }
        let (tiles_x, tiles_y) = (width.div_ceil(TILE), height.div_ceil(TILE));
        let tiles = tiles_x * tiles_y;
        let view = ViewGeometry::new(camera);
        if per_channel > 16 || scene.stride < per_channel {
            return Err(SplatError::Invalid(
                "the GPU backend evaluates SH up to degree 3".into(),
            ));
        }
        let background = [
            settings.background[0],
            settings.background[1],
            settings.background[2],
            0.0,
        ];
        let camera_uniform = CameraUniform {
            rot: [0, 1, 2].map(|r| {
                [
                    view.rot[r][0],
                    view.rot[r][1],
                    view.rot[r][2],
                    view.trans[r],
                ]
            }),
            campos: [view.campos[0], view.campos[1], view.campos[2], 0.0],
            intrinsics: [camera.fx, camera.fy, camera.cx, camera.cy],
            limits: [view.lim_x.0, view.lim_x.1, view.lim_y.0, view.lim_y.1],
            size: [width as f32, height as f32, camera.near, camera.far],
            footprint: [
                settings.eps2d,
                if settings.mode == Mode::Antialiased {
                    1.0
                } else {
                    0.0
                },
                if settings.appearance == crate::raster::Appearance::FixedRig {
                    1.0
                } else {
                    0.0
                },
                0.0,
            ],
            background,
            counts: [n, per_channel, u32::from(scene.plain), tiles_x],
            counts2: [tiles_y, scene.stride, 0, 0],
        };
        let camera_buffer = self.uniform("camera", &camera_uniform);
        let SceneBuffers {
            means,
            scales,
            quats,
            opacities,
            coeffs: coeff_buffer,
            ..
        } = scene.clone();
        let projected = self.zeroed("projected", 12 * n as u64);
        let rects = self.zeroed("tile rectangles", 4 * n as u64);
        let counts = self.zeroed("tile counts", n as u64 + 1);

        // Projection; the Gaussians in depth order; their intersections'
        // offsets in that order.
        let mut encoder = self.device.create_command_encoder(&Default::default());
        let group = self.bind(
            &self.project,
            &[
                (0, &camera_buffer),
                (1, &means),
                (2, &scales),
                (3, &quats),
                (4, &opacities),
                (5, &coeff_buffer),
                (6, &projected),
                (7, &rects),
                (8, &counts),
            ],
        );
        Self::dispatch(
            &mut encoder,
            &self.project,
            &group,
            grid((n + 1).div_ceil(GROUP)),
        );
        let gaussian_keys = self.key_sets(n as u64);
        let depth_params = self.uniform(
            "depth key params",
            &self.sort_params(n, 0, n, tiles_x, tiles),
        );
        let group = self.bind(
            &self.depth_keys,
            &[
                (0, &depth_params),
                (1, &projected),
                (30, &counts),
                (31, &gaussian_keys[0][0]),
                (32, &gaussian_keys[0][1]),
                (33, &gaussian_keys[0][2]),
            ],
        );
        Self::dispatch(
            &mut encoder,
            &self.depth_keys,
            &group,
            grid(n.div_ceil(GROUP)),
        );
        let depth_shifts: Vec<u32> = (0..8).map(|p| 4 * p).collect();
        let by_depth = self.record_radix(
            &mut encoder,
            &gaussian_keys,
            n,
            &depth_shifts,
            n,
            tiles_x,
            tiles,
        );
        let depth_order = &gaussian_keys[by_depth][2];
        let offsets = self.zeroed("tile offsets in depth order", n as u64 + 1);
        let group = self.bind(
            &self.gather_counts,
            &[
                (0, &depth_params),
                (30, &counts),
                (34, depth_order),
                (35, &offsets),
            ],
        );
        Self::dispatch(
            &mut encoder,
            &self.gather_counts,
            &group,
            grid((n + 1).div_ceil(GROUP)),
        );
        self.record_scan(&mut encoder, &offsets, n + 1);
        let total = self.submit_and_read_at(encoder, &offsets, n as u64)?[0];

        // Intersections in depth order, then sorted (stably) by tile.
        let mut keys = self.key_sets(total as u64);
        let ranges = self.zeroed("tile ranges", 2 * tiles as u64);
        let output = self.zeroed("image", PIXEL_FLOATS * (width * height) as u64);
        let last_contributor = self.zeroed("last contributors", (width * height) as u64);
        let mut encoder = self.device.create_command_encoder(&Default::default());
        let emit_params = self.uniform(
            "emit params",
            &self.sort_params(total, 0, n, tiles_x, tiles),
        );
        let group = self.bind(
            &self.emit,
            &[
                (0, &emit_params),
                (2, &rects),
                (3, &offsets),
                (4, &keys[0][0]),
                (5, &keys[0][1]),
                (6, &keys[0][2]),
                (34, depth_order),
            ],
        );
        Self::dispatch(&mut encoder, &self.emit, &group, grid(n.div_ceil(GROUP)));
        let tile_bits = 32 - tiles.saturating_sub(1).leading_zeros();
        let tile_shifts: Vec<u32> = (0..tile_bits.div_ceil(4)).map(|p| 32 + 4 * p).collect();
        let current =
            self.record_radix(&mut encoder, &keys, total, &tile_shifts, n, tiles_x, tiles);
        let sorted = &keys[current];
        encoder.clear_buffer(&ranges, 0, None);
        let ranges_params = self.uniform(
            "range params",
            &self.sort_params(total, 0, n, tiles_x, tiles),
        );
        let group = self.bind(
            &self.tile_ranges,
            &[(0, &ranges_params), (20, &sorted[0]), (21, &ranges)],
        );
        Self::dispatch(
            &mut encoder,
            &self.tile_ranges,
            &group,
            grid(total.div_ceil(GROUP)),
        );
        let raster_params = self.uniform(
            "raster params",
            &RasterParams {
                width,
                height,
                tiles_x,
                _pad: 0,
                background,
            },
        );
        let group = self.bind(
            &self.rasterize,
            &[
                (0, &raster_params),
                (1, &projected),
                (2, &sorted[2]),
                (3, &ranges),
                (4, &output),
                (5, &last_contributor),
            ],
        );
        Self::dispatch(&mut encoder, &self.rasterize, &group, (tiles_x, tiles_y));
        let bytes = if read_back {
            self.submit_and_read(encoder, &output, 4 * PIXEL_FLOATS * (width * height) as u64)?
        } else {
            self.queue.submit([encoder.finish()]);
            Vec::new()
        };
        let values: Vec<f32> = bytes.iter().map(|&w| f32::from_bits(w)).collect();
        let pixels = values.len() / PIXEL_FLOATS as usize;
        let mut render = Render {
            width,
            height,
            rgb: Vec::with_capacity(pixels),
            alpha: Vec::with_capacity(pixels),
            depth: Vec::with_capacity(pixels),
            median_depth: Vec::with_capacity(pixels),
            contributors: Vec::with_capacity(pixels),
        };
        for p in values.chunks_exact(PIXEL_FLOATS as usize) {
            render.rgb.push([p[0], p[1], p[2]]);
            render.alpha.push(p[3]);
            render.depth.push(p[4]);
            render.contributors.push(p[5] as u32);
            render.median_depth.push(p[6]);
        }
        let [_, _, sorted_index] = keys.swap_remove(current);
        Ok(GpuFrame {
            render,
            gaussians: n,
            sh_stride: scene.stride,
            camera: camera_buffer,
            inputs: [means, scales, quats, opacities, coeff_buffer],
            projected,
            sorted_index,
            ranges,
            image: output,
            last_contributor,
            raster_params,
            tiles: (tiles_x, tiles_y),
        })
    }

    /// Gradients of the loss with respect to every Gaussian parameter (as
    /// [`crate::backward::backward`] returns them), given dL/d(rgb) and
    /// dL/d(alpha) per pixel of `frame`'s render; and which Gaussians were
    /// visible (the CPU reference's non-zero radii).
    pub fn backward(
        &self,
        frame: &GpuFrame,
        d_rgb: &[[f32; 3]],
        d_alpha: &[f32],
    ) -> Result<(Gradients<f32>, Vec<bool>), SplatError> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let result = self.backward_inner(frame, d_rgb, d_alpha);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_error("the backward pass failed", e));
        }
        result
    }

    /// Records the backward pass of `frame` into a new encoder: the 2D
    /// gradients (10 per Gaussian) and the parameter gradients (means,
    /// quaternions, scales, opacities, colour coefficients).
    pub(crate) fn record_backward(
        &self,
        frame: &GpuFrame,
        d_rgb: &[[f32; 3]],
        d_alpha: &[f32],
    ) -> Result<(wgpu::CommandEncoder, wgpu::Buffer, [wgpu::Buffer; 5]), SplatError> {
        let d_image = self.image_gradients(frame, d_rgb, d_alpha)?;
        let mut encoder = self.device.create_command_encoder(&Default::default());
        let (grads2d, outputs, _) =
            self.record_backward_from(&mut encoder, frame, &d_image, true, false)?;
        Ok((encoder, grads2d, outputs))
    }

    /// dL/d(rgb) and dL/d(alpha) per pixel of `frame`'s render, on the
    /// device as the backward kernels read them (4 floats a pixel).
    fn image_gradients(
        &self,
        frame: &GpuFrame,
        d_rgb: &[[f32; 3]],
        d_alpha: &[f32],
    ) -> Result<wgpu::Buffer, SplatError> {
        let pixels = (frame.render.width * frame.render.height) as usize;
        if d_rgb.len() != pixels || d_alpha.len() != pixels {
            return Err(SplatError::Invalid(format!(
                "backward pass: {} colour and {} alpha gradients for {pixels} pixels",
                d_rgb.len(),
                d_alpha.len()
            )));
        }
        let d_image: Vec<f32> = d_rgb
            .iter()
            .zip(d_alpha)
            .flat_map(|(c, a)| [c[0], c[1], c[2], *a])
            .collect();
        Ok(self.storage("image gradients", &d_image))
    }

    /// The gradient of the loss with respect to a motion of `frame`'s
    /// camera (as [`crate::backward::backward_with_camera`] returns it),
    /// given dL/d(rgb) and dL/d(alpha) per pixel of its render.
    pub fn camera_gradient(
        &self,
        frame: &GpuFrame,
        d_rgb: &[[f32; 3]],
        d_alpha: &[f32],
    ) -> Result<crate::backward::CameraGradient, SplatError> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let d_image = self.image_gradients(frame, d_rgb, d_alpha)?;
        let mut encoder = self.device.create_command_encoder(&Default::default());
        let (_, _, partials) =
            self.record_backward_from(&mut encoder, frame, &d_image, false, true)?;
        let Some(partials) = partials else {
            return Err(SplatError::Invalid(
                "GPU backend: the backward pass recorded no camera gradient".into(),
            ));
        };
        let words = self.submit_and_read(encoder, &partials.buffer, 4 * partials.words)?;
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(gpu_error("the camera gradient failed", e));
        }
        Ok(camera_gradient_of(&words))
    }

    /// Records the backward pass of `frame` given dL/d(rgb, alpha) per pixel
    /// (4 floats) in `d_image`: the 2D gradients (`GRADS2D_FLOATS` per
    /// Gaussian, the absolute sums only if `absolute`), the parameter
    /// gradients (means, quaternions, scales, opacities, colour coefficients)
    /// and, if `camera`, the camera gradient's partial sums.
    pub(crate) fn record_backward_from(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        frame: &GpuFrame,
        d_image: &wgpu::Buffer,
        absolute: bool,
        camera: bool,
    ) -> Result<(wgpu::Buffer, [wgpu::Buffer; 5], Option<CameraPartials>), SplatError> {
        let Some(BackwardKernels {
            raster: raster_backward,
            project: project_backward,
            camera_sum,
        }) = &self.backward
        else {
            return Err(SplatError::Invalid(format!(
                "GPU backend: {} has no subgroup operations, which the backward pass needs; train with --backend cpu",
                self.adapter()
            )));
        };
        let n = frame.gaussians as u64;
        let k = frame.sh_stride as u64;
        let grads2d = self.zeroed("2D gradients", GRADS2D_FLOATS * n);
        let outputs = [
            self.zeroed("mean gradients", 3 * n),
            self.zeroed("quaternion gradients", 4 * n),
            self.zeroed("scale gradients", 3 * n),
            self.zeroed("opacity gradients", n),
            self.zeroed("colour gradients", 3 * k * n),
        ];
        encoder.clear_buffer(&grads2d, 0, None);
        // One float: the kernel leaves the camera gradient alone.
        let d_camera = self.zeroed("camera gradient shares", if camera { 6 * n } else { 1 });
        let options = self.uniform("backward options", &[u32::from(absolute), 0, 0, 0]);
        let group = self.bind(
            raster_backward,
            &[
                (0, &frame.raster_params),
                (8, &options),
                (1, &frame.projected),
                (2, &frame.sorted_index),
                (3, &frame.ranges),
                (4, &frame.image),
                (5, &frame.last_contributor),
                (6, d_image),
                (7, &grads2d),
            ],
        );
        Self::dispatch(encoder, raster_backward, &group, frame.tiles);
        let [means, scales, quats, opacities, coeffs] = &frame.inputs;
        let group = self.bind(
            project_backward,
            &[
                (0, &frame.camera),
                (1, means),
                (2, scales),
                (3, quats),
                (4, opacities),
                (5, coeffs),
                (6, &frame.projected),
                (7, &grads2d),
                (8, &outputs[0]),
                (9, &outputs[1]),
                (10, &outputs[2]),
                (11, &outputs[3]),
                (12, &outputs[4]),
                (13, &d_camera),
            ],
        );
        let groups = grid((n as u32).div_ceil(GROUP));
        Self::dispatch(encoder, project_backward, &group, groups);
        let partials = camera.then(|| {
            let words = 6 * u64::from(groups.0) * u64::from(groups.1);
            let buffer = self.zeroed("camera gradient partial sums", words);
            let count = self.uniform("gaussians", &[n as u32, 0, 0, 0]);
            let group = self.bind(camera_sum, &[(0, &count), (1, &d_camera), (2, &buffer)]);
            Self::dispatch(encoder, camera_sum, &group, groups);
            CameraPartials { buffer, words }
        });
        Ok((grads2d, outputs, partials))
    }

    fn backward_inner(
        &self,
        frame: &GpuFrame,
        d_rgb: &[[f32; 3]],
        d_alpha: &[f32],
    ) -> Result<(Gradients<f32>, Vec<bool>), SplatError> {
        let (mut encoder, grads2d, outputs) = self.record_backward(frame, d_rgb, d_alpha)?;
        let n = frame.gaussians as u64;
        let k = frame.sh_stride as u64;
        // One read-back of everything: the 2D gradients, then each output.
        let sizes = [GRADS2D_FLOATS * n, 3 * n, 4 * n, 3 * n, n, 3 * k * n];
        let total: u64 = sizes.iter().sum();
        let gathered = self.zeroed("gradients", total);
        let mut offset = 0;
        for (buffer, &size) in std::iter::once(&grads2d).chain(outputs.iter()).zip(&sizes) {
            if size > 0 {
                encoder.copy_buffer_to_buffer(buffer, 0, &gathered, 4 * offset, 4 * size);
            }
            offset += size;
        }
        let bytes = self.submit_and_read(encoder, &gathered, 4 * total)?;
        let all: Vec<f32> = bytes.iter().map(|&w| f32::from_bits(w)).collect();
        let (g2, rest) = all.split_at((GRADS2D_FLOATS * n) as usize);
        let (d_means, rest) = rest.split_at((3 * n) as usize);
        let (d_quats, rest) = rest.split_at((4 * n) as usize);
        let (d_scales, rest) = rest.split_at((3 * n) as usize);
        let (d_opacities, d_coeffs) = rest.split_at(n as usize);
        let triples = |v: &[f32]| {
            v.chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect::<Vec<_>>()
        };
        let per_gaussian = || g2.chunks_exact(GRADS2D_FLOATS as usize);
        let visible = per_gaussian().map(|c| c[9] > 0.5).collect();
        let gradients = Gradients {
            means2d: per_gaussian().map(|c| [c[0], c[1]]).collect(),
            means2d_abs: per_gaussian().map(|c| [c[10], c[11]]).collect(),
            conics: per_gaussian().map(|c| [c[2], c[3], c[4]]).collect(),
            opacities_view: per_gaussian().map(|c| c[5]).collect(),
            colors_view: per_gaussian().map(|c| [c[6], c[7], c[8]]).collect(),
            means: triples(d_means),
            quats: d_quats
                .chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect(),
            scales: triples(d_scales),
            opacities: d_opacities.to_vec(),
            colors: triples(d_coeffs),
        };
        Ok((gradients, visible))
    }

    /// Submits `encoder` and reads one word of `source` at word `index`.
    fn submit_and_read_at(
        &self,
        mut encoder: wgpu::CommandEncoder,
        source: &wgpu::Buffer,
        index: u64,
    ) -> Result<Vec<u32>, SplatError> {
        let word = self.zeroed("one word", 1);
        encoder.copy_buffer_to_buffer(source, 4 * index, &word, 0, 4);
        self.submit_and_read(encoder, &word, 4)
    }
}
