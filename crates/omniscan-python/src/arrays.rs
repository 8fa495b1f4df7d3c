//! Splat models and point clouds as numpy arrays. The Python classes
//! (`omniscan.Splats`, `omniscan.PointCloud`) own the arrays; these
//! functions read and write files through the library's readers and
//! writers, so a model read here is the one the command line reads.

use std::path::PathBuf;

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use omniscan_register::PointCloud;
use omniscan_splat::Splats;
use omniscan_splat::raster::Appearance;

/// `rows` flattened into an `(N, W)` array.
fn matrix<'py, T: numpy::Element + Copy, const W: usize>(
    py: Python<'py>,
    rows: &[[T; W]],
) -> PyResult<Bound<'py, PyAny>> {
    let flat: Vec<T> = rows.iter().flatten().copied().collect();
    Ok(PyArray1::from_vec(py, flat)
        .reshape([rows.len(), W])?
        .into_any())
}

/// The rows of an `(N, W)` array.
fn rows<T: numpy::Element + Copy, const W: usize>(
    name: &str,
    array: &PyReadonlyArray2<'_, T>,
) -> PyResult<Vec<[T; W]>> {
    let view = array.as_array();
    if view.ncols() != W {
        return Err(pyo3::exceptions::PyValueError::new_err(format!(
            "`{name}` must have shape (N, {W}), got {:?}",
            view.shape()
        )));
    }
    Ok(view
        .rows()
        .into_iter()
        .map(|row| std::array::from_fn(|i| row[i]))
        .collect())
}

fn input_error(py: Python<'_>, error: impl Into<anyhow::Error>) -> PyErr {
    crate::to_py_err(py, error.into())
}

/// Reads a 3DGS PLY: `(means (N,3), log_scales (N,3), quats (N,4) wxyz,
/// opacity_logits (N,), sh (N,K,3), sh_degree, antialiased, appearance)`.
#[pyfunction]
fn read_splats_arrays(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, PyTuple>> {
    let s = py
        .detach(|| omniscan_splat::ply::read_splats(&path))
        .map_err(|e| input_error(py, e))?;
    let k = s.sh_coefficients();
    let sh_flat: Vec<f32> = s.sh.iter().flatten().copied().collect();
    let sh = PyArray1::from_vec(py, sh_flat).reshape([s.len(), k, 3])?;
    (
        matrix(py, &s.means)?,
        matrix(py, &s.log_scales)?,
        matrix(py, &s.quats)?,
        PyArray1::from_vec(py, s.opacity_logits.clone()),
        sh,
        s.sh_degree,
        s.antialiased,
        s.appearance.name(),
    )
        .into_pyobject(py)
}

/// Writes a 3DGS PLY from arrays shaped as [`read_splats_arrays`] returns
/// them (float32, C order); the model is validated first.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn write_splats_arrays(
    py: Python<'_>,
    path: PathBuf,
    means: PyReadonlyArray2<'_, f32>,
    log_scales: PyReadonlyArray2<'_, f32>,
    quats: PyReadonlyArray2<'_, f32>,
    opacity_logits: PyReadonlyArray1<'_, f32>,
    sh: PyReadonlyArray3<'_, f32>,
    antialiased: bool,
    appearance: &str,
) -> PyResult<()> {
    let sh = sh.as_array();
    let k = sh.shape()[1];
    let degree = (0..=3).find(|d| (d + 1) * (d + 1) == k).ok_or_else(|| {
        pyo3::exceptions::PyValueError::new_err(format!(
            "`sh` must have shape (N, K, 3) with K = 1, 4, 9 or 16 (SH degree 0-3), got {:?}",
            sh.shape()
        ))
    })?;
    if sh.shape()[2] != 3 {
        return Err(pyo3::exceptions::PyValueError::new_err(format!(
            "`sh` must have shape (N, K, 3), got {:?}",
            sh.shape()
        )));
    }
    let splats = Splats {
        means: rows("means", &means)?,
        log_scales: rows("scales", &log_scales)?,
        quats: rows("quats", &quats)?,
        opacity_logits: opacity_logits.as_array().to_vec(),
        sh_degree: degree,
        sh: sh.rows().into_iter().map(|c| [c[0], c[1], c[2]]).collect(),
        antialiased,
        appearance: Appearance::from_name(appearance).ok_or_else(|| {
            pyo3::exceptions::PyValueError::new_err(format!("unknown appearance `{appearance}`"))
        })?,
    };
    py.detach(|| {
        splats.validate()?;
        omniscan_splat::ply::write_splats(&path, &splats)
    })
    .map_err(|e| input_error(py, e))
}

/// Reads a point cloud (PLY, PCD, XYZ; a splat model's centres):
/// `(points (N,3) float64, colors (N,3) float32 or None, normals (N,3)
/// float64 or None)`.
#[pyfunction]
fn read_cloud_arrays(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, PyTuple>> {
    let cloud = py
        .detach(|| omniscan_register::cloud::read_cloud(&path))
        .map_err(|e| input_error(py, e))?;
    let points: Vec<[f64; 3]> = cloud.points.iter().map(|p| [p.x, p.y, p.z]).collect();
    let normals: Vec<[f64; 3]> = cloud.normals.iter().map(|n| [n.x, n.y, n.z]).collect();
    let colors = match cloud.has_colors() {
        true => Some(matrix(py, &cloud.colors)?),
        false => None,
    };
    let normals = match cloud.has_normals() {
        true => Some(matrix(py, &normals)?),
        false => None,
    };
    (matrix(py, &points)?, colors, normals).into_pyobject(py)
}

/// Writes a point cloud as binary PLY (colours and normals when given).
#[pyfunction]
#[pyo3(signature = (path, points, colors=None, normals=None))]
fn write_cloud_arrays(
    py: Python<'_>,
    path: PathBuf,
    points: PyReadonlyArray2<'_, f64>,
    colors: Option<PyReadonlyArray2<'_, f32>>,
    normals: Option<PyReadonlyArray2<'_, f64>>,
) -> PyResult<()> {
    let cloud = PointCloud {
        points: rows::<f64, 3>("points", &points)?
            .into_iter()
            .map(Into::into)
            .collect(),
        colors: match &colors {
            Some(c) => rows("colors", c)?,
            None => Vec::new(),
        },
        normals: match &normals {
            Some(n) => rows::<f64, 3>("normals", n)?
                .into_iter()
                .map(Into::into)
                .collect(),
            None => Vec::new(),
        },
    };
    py.detach(|| {
        cloud.validate(&path.display().to_string())?;
        omniscan_register::cloud::write_ply(&path, &cloud)
    })
    .map_err(|e| input_error(py, e))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(read_splats_arrays, m)?)?;
    m.add_function(wrap_pyfunction!(write_splats_arrays, m)?)?;
    m.add_function(wrap_pyfunction!(read_cloud_arrays, m)?)?;
    m.add_function(wrap_pyfunction!(write_cloud_arrays, m)?)?;
    Ok(())
}
