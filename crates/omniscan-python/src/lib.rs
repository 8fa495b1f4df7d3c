//! omniscan's Python bindings: the native half of the `omniscan` package
//! (`python/omniscan/`), built by maturin.
//!
//! The bindings are thin on purpose. A stage's keyword arguments arrive as
//! JSON, are laid over the settings struct's `Default` (the library's, so a
//! default is written once, there) and deserialised into it; the stage runs
//! with the GIL released; its serde report goes back as JSON, which the
//! Python side wraps for attribute access. Splat models and point clouds
//! cross as numpy arrays. Errors become the Python exceptions of
//! `omniscan.errors`, chosen by the library error's type, with the message
//! the command line prints.

use std::path::PathBuf;

use anyhow::{Result, bail};
use pyo3::prelude::*;
use serde::Serialize;
use serde::de::DeserializeOwned;

use omniscan_pipeline::Progress;

mod arrays;

/// A Python object as the stages' [`Progress`]: each event calls the method
/// of that name when the object has one. Errors it raises are reported as
/// unraisable (printed) and the work goes on.
struct PyProgress(Py<PyAny>);

impl PyProgress {
    fn call<A>(&self, name: &str, args: A)
    where
        A: for<'py> pyo3::call::PyCallArgs<'py>,
    {
        Python::attach(|py| {
            let object = self.0.bind(py);
            if let Ok(method) = object.getattr(name)
                && let Err(e) = method.call1(args)
            {
                e.write_unraisable(py, Some(object));
            }
        });
    }
}

impl Progress for PyProgress {
    fn start(&self, label: &str, total: u64, unit: &str) {
        self.call("start", (label, total, unit));
    }
    fn set(&self, done: u64) {
        self.call("set", (done,));
    }
    fn advance(&self) {
        self.call("advance", ());
    }
    fn message(&self, text: &str) {
        self.call("message", (text,));
    }
    fn finish(&self) {
        self.call("finish", ());
    }
    fn note(&self, line: &str) {
        self.call("note", (line,));
    }
}

/// The stages the bindings run, by the Python function's name.
const STAGES: [&str; 14] = [
    "simulate",
    "mask",
    "train",
    "align",
    "twin",
    "evaluate",
    "render",
    "inspect",
    "make_copy",
    "convert",
    "view",
    "mesh",
    "asset",
    "import_ros2",
];

/// A keyword argument the stage's settings cannot take.
#[derive(Debug)]
struct BadSetting(String);

impl std::fmt::Display for BadSetting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for BadSetting {}

/// `T`'s `Default` with the keys of `given` (a JSON object) laid over it.
fn settings<T: Serialize + DeserializeOwned + Default>(given: serde_json::Value) -> Result<T> {
    let bad = |message: String| anyhow::Error::new(BadSetting(message));
    let mut value = serde_json::to_value(T::default())?;
    let (Some(object), serde_json::Value::Object(given)) = (value.as_object_mut(), given) else {
        return Err(bad("settings must be keyword arguments".into()));
    };
    for (key, v) in given {
        if !object.contains_key(&key) {
            return Err(bad(format!("unknown setting `{key}`")));
        }
        object.insert(key, v);
    }
    serde_path_to_error::deserialize(value)
        .map_err(|e| bad(format!("setting `{}`: {}", e.path(), e.inner())))
}

fn default_json(stage: &str) -> Result<serde_json::Value> {
    use omniscan_pipeline::*;
    fn json<T: Serialize + Default>() -> Result<serde_json::Value> {
        Ok(serde_json::to_value(T::default())?)
    }
    match stage {
        "simulate" => json::<simulate::SimulateSettings>(),
        "mask" => json::<mask::MaskingSettings>(),
        "train" => json::<train::TrainSettings>(),
        "align" => json::<align::AlignSettings>(),
        "twin" => json::<twin::TwinSettings>(),
        "evaluate" => json::<evaluate::EvalSettings>(),
        "render" => json::<render::RenderSettings>(),
        "inspect" => json::<inspect::InspectionSettings>(),
        "make_copy" => json::<inspect::MakeCopySettings>(),
        "convert" => json::<share::ConvertSettings>(),
        "view" => json::<share::ViewSettings>(),
        "mesh" => json::<geometry::MeshSettings>(),
        "asset" => json::<geometry::AssetSettings>(),
        "import_ros2" => json::<omniscan_pipeline::import::ImportSettings>(),
        other => bail!("no stage `{other}`: the stages are {}", STAGES.join(", ")),
    }
}

/// Runs `stage` on `paths` (in the order the Python function documents).
fn run(
    stage: &str,
    paths: &[PathBuf],
    mut given: serde_json::Value,
    progress: &dyn Progress,
) -> Result<serde_json::Value> {
    use omniscan_pipeline::*;
    let wanted = match stage {
        "simulate" | "mask" => 1,
        "align" => 3,
        _ => 2,
    };
    let any_number = matches!(stage, "inspect" | "view");
    if paths.len() < wanted || (!any_number && paths.len() != wanted) {
        bail!("{stage} takes {wanted} paths, got {}", paths.len());
    }
    let p = |i: usize| paths[i].as_path();
    match stage {
        "simulate" => to_json(simulate::simulate(&settings(given)?, p(0), progress)?),
        "mask" => {
            let evaluate = given
                .as_object_mut()
                .and_then(|o| o.remove("evaluate"))
                .and_then(|v| v.as_bool())
                .unwrap_or(false);
            to_json(mask::mask(p(0), &settings(given)?, evaluate, progress)?)
        }
        "train" => to_json(train::train(p(0), p(1), &settings(given)?, progress)?),
        "align" => to_json(align::align(p(0), p(1), p(2), &settings(given)?)?),
        "twin" => to_json(twin::twin(p(0), p(1), &settings(given)?, progress)?),
        "evaluate" => to_json(evaluate::evaluate(p(0), p(1), &settings(given)?, progress)?),
        "render" => to_json(render::render(p(0), p(1), &settings(given)?, progress)?),
        "inspect" => to_json(inspect::inspect(
            &paths[1..],
            p(0),
            &settings(given)?,
            progress,
        )?),
        "make_copy" => to_json(inspect::make_copy(p(0), p(1), &settings(given)?)?),
        "convert" => to_json(share::convert(p(0), p(1), &settings(given)?)?),
        "view" => to_json(share::view(&paths[1..], p(0), &settings(given)?)?),
        "mesh" => to_json(geometry::mesh(p(0), p(1), &settings(given)?, progress)?),
        "asset" => to_json(geometry::asset(p(0), p(1), &settings(given)?, progress)?),
        "import_ros2" => to_json(omniscan_pipeline::import::import_ros2(
            p(0),
            p(1),
            &settings(given)?,
            progress,
        )?),
        other => bail!("no stage `{other}`: the stages are {}", STAGES.join(", ")),
    }
}

fn to_json(report: impl Serialize) -> Result<serde_json::Value> {
    Ok(serde_json::to_value(report)?)
}

/// The name of the `omniscan.errors` class for `error`.
fn error_class(error: &anyhow::Error) -> &'static str {
    use omniscan_pipeline::failure::Failure;
    if error
        .chain()
        .any(|c| c.downcast_ref::<BadSetting>().is_some())
    {
        return "InputError";
    }
    match Failure::of(error) {
        Failure::Input => "InputError",
        Failure::File => "FileError",
        Failure::Busy => "OutputInUse",
        Failure::Other => "OmniscanError",
    }
}

/// `error` as the `omniscan.errors` exception for it, with the message the
/// command line prints (`{:#}`: the context chain).
fn to_py_err(py: Python<'_>, error: anyhow::Error) -> PyErr {
    let message = format!("{error:#}");
    let class = error_class(&error);
    match py
        .import("omniscan.errors")
        .and_then(|errors| errors.getattr(class))
        .and_then(|class| class.call1((message.clone(),)))
    {
        Ok(exception) => PyErr::from_value(exception),
        Err(_) => pyo3::exceptions::PyRuntimeError::new_err(message),
    }
}

/// Runs a stage; returns its report as JSON. The GIL is released while
/// the stage runs.
#[pyfunction]
#[pyo3(signature = (stage, paths, settings_json, progress=None))]
fn run_stage(
    py: Python<'_>,
    stage: &str,
    paths: Vec<PathBuf>,
    settings_json: &str,
    progress: Option<Py<PyAny>>,
) -> PyResult<String> {
    let given: serde_json::Value = serde_json::from_str(settings_json)
        .map_err(|e| to_py_err(py, anyhow::Error::from(e).context("settings")))?;
    let progress: Box<dyn Progress + Send> = match progress {
        Some(object) if !object.is_none(py) => Box::new(PyProgress(object)),
        _ => Box::new(omniscan_pipeline::Silent),
    };
    let result = py.detach(|| {
        run(stage, &paths, given, progress.as_ref())
            .and_then(|report| Ok(serde_json::to_string(&report)?))
    });
    result.map_err(|e| to_py_err(py, e))
}

/// The default settings of `stage`, as JSON.
#[pyfunction]
fn default_settings(py: Python<'_>, stage: &str) -> PyResult<String> {
    default_json(stage)
        .map(|v| v.to_string())
        .map_err(|e| to_py_err(py, e))
}

/// Lets captures and photo sets name files outside their folder (the
/// command line's `--allow-outside-paths`), for the whole process.
#[pyfunction]
fn allow_outside_paths(allow: bool) {
    omniscan_core::paths::set_allow_outside(allow);
}

/// Every GPU this process opens from now on is the one `selector` names:
/// an index among the hardware adapters or a PCI bus id (the command
/// line's `--gpu`); `None`: wgpu's high-performance adapter.
#[pyfunction]
#[pyo3(signature = (selector=None))]
fn use_gpu(py: Python<'_>, selector: Option<String>) -> PyResult<()> {
    use omniscan_splat::gpu::select::{GpuSelector, select_gpu};
    let selector = match selector {
        None => GpuSelector::Preferred,
        Some(s) => s
            .parse()
            .map_err(|e: String| to_py_err(py, anyhow::Error::new(BadSetting(e))))?,
    };
    select_gpu(selector);
    Ok(())
}

/// Runs the command line with `argv` (its first item the program's name)
/// in this process; returns its exit status.
#[pyfunction]
fn run_cli(py: Python<'_>, argv: Vec<String>) -> i32 {
    py.detach(|| omniscan::run_from(argv))
}

#[pymodule]
fn _omniscan(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(run_stage, m)?)?;
    m.add_function(wrap_pyfunction!(default_settings, m)?)?;
    m.add_function(wrap_pyfunction!(allow_outside_paths, m)?)?;
    m.add_function(wrap_pyfunction!(run_cli, m)?)?;
    m.add_function(wrap_pyfunction!(use_gpu, m)?)?;
    arrays::register(m)?;
    Ok(())
}
