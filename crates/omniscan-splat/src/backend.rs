//! Choosing where rendering runs: the rayon CPU reference or the wgpu GPU
//! backend (`crate::gpu`), as `--backend auto|cpu|gpu` says. `auto` takes a
//! real GPU when there is one and the CPU otherwise: a software Vulkan
//! device (lavapipe) is slower than the CPU reference, so only `gpu` uses it.

use crate::SplatError;
use crate::gpu::{DeviceChoice, GpuRenderer};
use crate::raster::{Camera, Gaussians, Render, Settings};

/// The user's choice of backend.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    #[default]
    Auto,
    Cpu,
    Gpu,
}

impl std::str::FromStr for Backend {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "auto" => Ok(Backend::Auto),
            "cpu" => Ok(Backend::Cpu),
            "gpu" => Ok(Backend::Gpu),
            other => Err(format!("unknown backend `{other}` (auto, cpu or gpu)")),
        }
    }
}

/// A ready renderer.
#[derive(Debug)]
pub enum Renderer {
    Cpu,
    Gpu(Box<GpuRenderer>),
}

impl Renderer {
    /// The renderer `backend` asks for; `gpu` without a usable device is an error.
    pub fn new(backend: Backend) -> Result<Renderer, SplatError> {
        match backend {
            Backend::Cpu => Ok(Renderer::Cpu),
            Backend::Gpu => Ok(Renderer::Gpu(Box::new(GpuRenderer::new(
                DeviceChoice::AllowSoftware,
            )?))),
            Backend::Auto => match GpuRenderer::new(DeviceChoice::Hardware) {
                Ok(gpu) => Ok(Renderer::Gpu(Box::new(gpu))),
                Err(e) => {
                    tracing::info!("rendering on the CPU: {e}");
                    Ok(Renderer::Cpu)
                }
            },
        }
    }

    /// "cpu", or "gpu: ADAPTER".
    pub fn describe(&self) -> String {
        match self {
            Renderer::Cpu => "cpu".into(),
            Renderer::Gpu(gpu) => format!("gpu: {}", gpu.adapter()),
        }
    }

    pub fn is_gpu(&self) -> bool {
        matches!(self, Renderer::Gpu(_))
    }

    /// Renders one view (colour with background, alpha, depth sum, median
    /// depth, contributors).
    pub fn render(
        &self,
        gaussians: &Gaussians<f32>,
        camera: &Camera<f32>,
        settings: &Settings<f32>,
    ) -> Result<Render<f32>, SplatError> {
        match self {
            Renderer::Cpu => Ok(crate::raster::render(gaussians, camera, settings).1),
            Renderer::Gpu(gpu) => gpu.render(gaussians, camera, settings),
        }
    }
}
