//! Running learned models from ONNX files: the masking stage's Depth
//! Anything V2, SAM and RAFT roles and our exported gripper U-Net, and the
//! evaluation's LPIPS network.
//!
//! Runtime choice: **ONNX Runtime through the `ort` crate, loaded at run
//! time** (`ort` 2.0.0-rc.15 with `default-features = false` and
//! `load-dynamic`). Measured for this project (`../shared/notes/masking.md`):
//! it is the fastest CPU runtime available here (a 1024² ISNet segmentation
//! net in 1.18 s, where tract gave no result after 15 minutes and burn took
//! 10.9 s), it covers every operator the DAv2/SAM/RAFT exports use, and with
//! `load-dynamic` it builds in seconds with nothing downloaded or linked at
//! build time. tract is the pure-Rust alternative the issue mentions; it builds
//! offline too (8 minutes here) but is 5-8x slower on small convnets and
//! unusable on the real models' sizes, so it would make the learned backends a
//! formality. The price of ONNX Runtime is a shared library the user supplies
//! at run time: the CPU library is inside the PyPI `onnxruntime` wheel
//! (`pip install onnxruntime`, file `onnxruntime/capi/libonnxruntime.so.*`),
//! version 1.24 or newer. It is found, in order: the path the caller passes
//! (`--onnx-runtime` in the CLI), `$ORT_DYLIB_PATH`, then the `onnxruntime`
//! package of `python3` if one is installed. Without it, only the learned
//! backends fail, with an error that says how to get it; everything
//! weight-free runs as before.
//!
//! [`graph`] writes ONNX files (the U-Net export, the tests' tiny models).

pub mod graph;

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use ort::session::Session;
use ort::value::Tensor as OrtTensor;

/// Errors of loading and running ONNX models.
#[derive(Debug, thiserror::Error)]
pub enum OnnxError {
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
    #[error("{0}")]
    Invalid(String),
}

impl OnnxError {
    pub fn file(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        OnnxError::File {
            path: path.into(),
            message: message.into(),
        }
    }
}

pub type Result<T, E = OnnxError> = std::result::Result<T, E>;

/// Environment variable naming the ONNX Runtime library.
pub const RUNTIME_VARIABLE: &str = "ORT_DYLIB_PATH";

const HOW_TO_GET: &str = "ONNX models (learned masking backends, LPIPS) need ONNX Runtime's shared library, version 1.24 or newer: \
`pip install onnxruntime`, then pass its `onnxruntime/capi/libonnxruntime.so.*` with --onnx-runtime or set ORT_DYLIB_PATH";

/// The process's ONNX Runtime environment, once one has started (a failed
/// attempt is not remembered, so a later call may name another library).
static ENVIRONMENT: Mutex<Option<ort::environment::Environment>> = Mutex::new(None);

/// The ONNX Runtime library to load: `explicit`, else `$ORT_DYLIB_PATH`,
/// else the library inside `python3`'s `onnxruntime` package.
pub fn find_runtime(explicit: Option<&Path>) -> Result<PathBuf> {
    if let Some(path) = explicit {
        return existing(path, "--onnx-runtime");
    }
    if let Some(path) = std::env::var_os(RUNTIME_VARIABLE).filter(|p| !p.is_empty()) {
        return existing(Path::new(&path), RUNTIME_VARIABLE);
    }
    if let Some(path) = python_runtime() {
        return Ok(path);
    }
    Err(OnnxError::Invalid(format!(
        "no ONNX Runtime library found. {HOW_TO_GET}"
    )))
}

fn existing(path: &Path, what: &str) -> Result<PathBuf> {
    if path.is_file() {
        Ok(path.to_path_buf())
    } else {
        Err(OnnxError::file(
            path,
            format!("no such file (the ONNX Runtime library, from {what}). {HOW_TO_GET}"),
        ))
    }
}

/// The library shipped in the `onnxruntime` wheel of `python3`, if installed.
fn python_runtime() -> Option<PathBuf> {
    let out = std::process::Command::new("python3")
        .args([
            "-c",
            "import onnxruntime, os; print(os.path.dirname(onnxruntime.__file__))",
        ])
        .stderr(std::process::Stdio::null())
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    let capi = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim()).join("capi");
    let mut candidates: Vec<PathBuf> = std::fs::read_dir(&capi)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("libonnxruntime.so"))
        })
        .collect();
    candidates.sort();
    candidates.pop()
}

/// Loads ONNX Runtime once per process (its environment is process-wide);
/// later calls reuse it whatever path they name.
fn environment(explicit: Option<&Path>) -> Result<ort::environment::Environment> {
    let mut slot = ENVIRONMENT
        .lock()
        .map_err(|_| OnnxError::Invalid("ONNX Runtime: an earlier start panicked".into()))?;
    if let Some(env) = slot.as_ref() {
        return Ok(env.clone());
    }
    let path = find_runtime(explicit)?;
    let builder = ort::init_from(&path).map_err(|e| {
        OnnxError::file(
            &path,
            format!("could not load ONNX Runtime: {e}. {HOW_TO_GET}"),
        )
    })?;
    let env = builder
        .with_name("omniscan")
        .build()
        .map_err(|e| OnnxError::file(&path, format!("ONNX Runtime did not start: {e}")))?;
    *slot = Some(env.clone());
    Ok(env)
}

/// One input or output of a model: its name and dimensions (`-1` where the
/// model leaves a dimension open).
#[derive(Debug, Clone, PartialEq)]
pub struct TensorInfo {
    pub name: String,
    pub dims: Vec<i64>,
}

/// A tensor passed to a model.
#[derive(Debug, Clone, PartialEq)]
pub enum Input {
    Float { dims: Vec<i64>, data: Vec<f32> },
    Int64 { dims: Vec<i64>, data: Vec<i64> },
}

impl Input {
    pub fn float(dims: &[i64], data: Vec<f32>) -> Input {
        Input::Float {
            dims: dims.to_vec(),
            data,
        }
    }
}

/// A float tensor a model returned.
#[derive(Debug, Clone, PartialEq)]
pub struct Output {
    pub name: String,
    pub dims: Vec<i64>,
    pub data: Vec<f32>,
}

/// A loaded ONNX model. Runs are serialised (ONNX Runtime parallelises
/// inside each run).
pub struct OnnxModel {
    pub path: PathBuf,
    pub inputs: Vec<TensorInfo>,
    pub outputs: Vec<TensorInfo>,
    session: Mutex<Session>,
}

impl std::fmt::Debug for OnnxModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnnxModel")
            .field("path", &self.path)
            .field("inputs", &self.inputs)
            .field("outputs", &self.outputs)
            .finish()
    }
}

fn infos(outlets: &[ort::value::Outlet]) -> Vec<TensorInfo> {
    outlets
        .iter()
        .map(|o| TensorInfo {
            name: o.name().to_string(),
            dims: o
                .dtype()
                .tensor_shape()
                .map(|s| s.to_vec())
                .unwrap_or_default(),
        })
        .collect()
}

impl OnnxModel {
    /// Loads `path` with the ONNX Runtime library found by [`find_runtime`].
    pub fn load(path: &Path, runtime: Option<&Path>) -> Result<OnnxModel> {
        if !path.is_file() {
            return Err(OnnxError::file(path, "no such ONNX model file"));
        }
        let env = environment(runtime)?;
        let fail = |e: String| OnnxError::file(path, format!("not a usable ONNX model: {e}"));
        let session = Session::builder(&env)
            .map_err(|e| fail(e.to_string()))?
            .commit_from_file(path)
            .map_err(|e| fail(e.to_string()))?;
        Ok(OnnxModel {
            path: path.to_path_buf(),
            inputs: infos(session.inputs()),
            outputs: infos(session.outputs()),
            session: Mutex::new(session),
        })
    }

    /// The input called `name`.
    pub fn input(&self, name: &str) -> Option<&TensorInfo> {
        self.inputs.iter().find(|i| i.name == name)
    }

    /// Runs the model; returns every output, converted to f32.
    pub fn run(&self, inputs: Vec<(String, Input)>) -> Result<Vec<Output>> {
        let fail = |e: String| OnnxError::file(&self.path, format!("inference failed: {e}"));
        let mut values: Vec<(
            std::borrow::Cow<'static, str>,
            ort::session::SessionInputValue,
        )> = Vec::with_capacity(inputs.len());
        for (name, input) in inputs {
            let value = match input {
                Input::Float { dims, data } => OrtTensor::from_array((dims, data))
                    .map_err(|e| fail(e.to_string()))?
                    .into_dyn(),
                Input::Int64 { dims, data } => OrtTensor::from_array((dims, data))
                    .map_err(|e| fail(e.to_string()))?
                    .into_dyn(),
            };
            values.push((name.into(), value.into()));
        }
        let mut session = self
            .session
            .lock()
            .map_err(|_| fail("an earlier run panicked".into()))?;
        let outputs = session.run(values).map_err(|e| fail(e.to_string()))?;
        let mut result = Vec::with_capacity(outputs.len());
        for (name, value) in outputs.iter() {
            let (shape, data) = value
                .try_extract_tensor::<f32>()
                .map_err(|e| fail(format!("output `{name}` is not a float tensor: {e}")))?;
            result.push(Output {
                name: name.to_string(),
                dims: shape.to_vec(),
                data: data.to_vec(),
            });
        }
        Ok(result)
    }
}

/// Finds an output by name, else the one at `fallback`.
pub fn pick_output<'a>(
    outputs: &'a [Output],
    names: &[&str],
    fallback: usize,
) -> Option<&'a Output> {
    names
        .iter()
        .find_map(|n| outputs.iter().find(|o| o.name == *n))
        .or_else(|| outputs.get(fallback))
}

/// `image` resampled bilinearly (pixel centres aligned) to `width`x`height`,
/// channels first, each value `normalise(channel, value 0..255)`.
pub fn image_tensor(
    image: &omniscan_core::image_io::RgbImage,
    width: usize,
    height: usize,
    normalise: impl Fn(usize, f32) -> f32,
) -> Vec<f32> {
    let (iw, ih) = (image.width as usize, image.height as usize);
    let mut out = vec![0f32; 3 * width * height];
    if iw == 0 || ih == 0 {
        return out;
    }
    let (sx, sy) = (iw as f32 / width as f32, ih as f32 / height as f32);
    let px = |x: usize, y: usize, c: usize| image.data[3 * (y * iw + x) + c] as f32;
    for y in 0..height {
        let fy = ((y as f32 + 0.5) * sy - 0.5).clamp(0.0, (ih - 1) as f32);
        let (y0, ty) = (fy.floor() as usize, fy - fy.floor());
        let y1 = (y0 + 1).min(ih - 1);
        for x in 0..width {
            let fx = ((x as f32 + 0.5) * sx - 0.5).clamp(0.0, (iw - 1) as f32);
            let (x0, tx) = (fx.floor() as usize, fx - fx.floor());
            let x1 = (x0 + 1).min(iw - 1);
            for c in 0..3 {
                let top = px(x0, y0, c) * (1.0 - tx) + px(x1, y0, c) * tx;
                let bottom = px(x0, y1, c) * (1.0 - tx) + px(x1, y1, c) * tx;
                out[(c * height + y) * width + x] = normalise(c, top * (1.0 - ty) + bottom * ty);
            }
        }
    }
    out
}

/// ImageNet normalisation of a 0..255 value (the preprocessing of Depth
/// Anything V2, SAM and most torchvision models).
pub fn imagenet(channel: usize, value: f32) -> f32 {
    const MEAN: [f32; 3] = [0.485, 0.456, 0.406];
    const STD: [f32; 3] = [0.229, 0.224, 0.225];
    (value / 255.0 - MEAN[channel]) / STD[channel]
}

/// The last two dimensions of `output` as (height, width), when its data
/// holds exactly one plane of that size times `planes`.
pub fn output_plane_size(output: &Output, planes: usize) -> Option<(usize, usize)> {
    let n = output.dims.len();
    if n < 2 {
        return None;
    }
    let (h, w) = (output.dims[n - 2], output.dims[n - 1]);
    (h > 0 && w > 0 && output.data.len() == planes * (h * w) as usize)
        .then_some((h as usize, w as usize))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_runtime_or_model_is_a_clear_error() {
        let missing = Path::new("/nonexistent/libonnxruntime.so.1.31.1");
        let err = find_runtime(Some(missing)).unwrap_err().to_string();
        assert!(err.contains("/nonexistent/libonnxruntime.so"), "{err}");
        assert!(err.contains("pip install onnxruntime"), "{err}");
        // The model file is checked before any runtime is loaded.
        let err = OnnxModel::load(Path::new("/nonexistent/depth.onnx"), Some(missing))
            .unwrap_err()
            .to_string();
        assert!(err.contains("/nonexistent/depth.onnx"), "{err}");
    }

    #[test]
    fn images_are_resampled_with_pixel_centres_aligned() {
        let image = omniscan_core::image_io::RgbImage {
            width: 4,
            height: 2,
            data: (0..24).map(|i| (i * 10) as u8).collect(),
        };
        // Same size: the identity, channels first.
        let same = image_tensor(&image, 4, 2, |_, v| v);
        assert_eq!(same[0], 0.0);
        assert_eq!(same[1], 30.0);
        assert_eq!(same[8], 10.0);
        // Halving averages pixel pairs (x 0.5 between source centres 0 and 1).
        let half = image_tensor(&image, 2, 1, |_, v| v);
        assert!((half[0] - 0.25 * (0.0 + 30.0 + 120.0 + 150.0)).abs() < 1e-4);
    }
}
