//! Point clouds: positions (metres, or the file's units), optional colours
//! (RGB in [0, 1]) and normals; read and written as PLY (any property order,
//! ASCII or binary), PCD (ASCII, binary, binary_compressed) and XYZ text; and
//! extracted from 3D Gaussian Splat models (centres with their DC colour,
//! filtered by opacity and size, since raw centres carry floaters and
//! oversized background splats).
//!
//! PCD is read by our own parser rather than a crate so that every format
//! error names the file and the problem in the same way as the other readers;
//! it needs only the header, three data layouts and LZF decompression.

use std::path::Path;

use nalgebra::{Point3, Vector3};

use crate::RegisterError;
use omniscan_core::Pose;
use omniscan_core::ply::{Column, Element, Format, PlyFile, Property, ScalarType};

/// A variance along a principal axis and the axis' unit direction.
pub type PrincipalAxis = (f64, nalgebra::Unit<Vector3<f64>>);

/// A point cloud. `colors` and `normals` are empty or one per point.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    pub points: Vec<Point3<f64>>,
    pub colors: Vec<[f32; 3]>,
    pub normals: Vec<Vector3<f64>>,
}

/// The zeroth-order SH basis constant: colour = 0.5 + C0 · f_dc.
const SH_C0: f64 = 0.282_094_791_773_878_14;

impl PointCloud {
    pub fn len(&self) -> usize {
        self.points.len()
    }
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
    pub fn has_colors(&self) -> bool {
        !self.colors.is_empty() && self.colors.len() == self.points.len()
    }
    pub fn has_normals(&self) -> bool {
        !self.normals.is_empty() && self.normals.len() == self.points.len()
    }

    /// Intensity (mean of RGB) of point `i`, as colored ICP uses it.
    pub fn intensity(&self, i: usize) -> f64 {
        let c = self.colors[i];
        (c[0] as f64 + c[1] as f64 + c[2] as f64) / 3.0
    }

    /// Checks sizes and finiteness; `what` names the cloud in errors.
    pub fn validate(&self, what: &str) -> Result<(), RegisterError> {
        if self.points.is_empty() {
            return Err(RegisterError::Invalid(format!(
                "{what}: the point cloud is empty"
            )));
        }
        if let Some(i) = self
            .points
            .iter()
            .position(|p| !p.coords.iter().all(|c| c.is_finite()))
        {
            return Err(RegisterError::Invalid(format!(
                "{what}: point {i} has a NaN or infinite coordinate"
            )));
        }
        if !self.colors.is_empty() && self.colors.len() != self.points.len() {
            return Err(RegisterError::Invalid(format!(
                "{what}: {} colours for {} points",
                self.colors.len(),
                self.points.len()
            )));
        }
        if !self.normals.is_empty() && self.normals.len() != self.points.len() {
            return Err(RegisterError::Invalid(format!(
                "{what}: {} normals for {} points",
                self.normals.len(),
                self.points.len()
            )));
        }
        Ok(())
    }

    /// A copy moved by `pose` (normals rotated).
    pub fn transformed(&self, pose: &Pose) -> PointCloud {
        PointCloud {
            points: self.points.iter().map(|p| pose * p).collect(),
            colors: self.colors.clone(),
            normals: self.normals.iter().map(|n| pose.rotation * n).collect(),
        }
    }

    /// The points at `indices`, with their attributes.
    pub fn select(&self, indices: &[usize]) -> PointCloud {
        PointCloud {
            points: indices.iter().map(|&i| self.points[i]).collect(),
            colors: if self.has_colors() {
                indices.iter().map(|&i| self.colors[i]).collect()
            } else {
                vec![]
            },
            normals: if self.has_normals() {
                indices.iter().map(|&i| self.normals[i]).collect()
            } else {
                vec![]
            },
        }
    }

    /// Appends another cloud; attributes survive only if both have them.
    pub fn extend(&mut self, other: &PointCloud) {
        // An empty cloud adds nothing and takes nothing away: it has no
        // colours only because it has no points (a frame where the object
        // left the view used to strip a whole scan's colours, and with them
        // colored ICP).
        if other.is_empty() {
            return;
        }
        let colors =
            self.has_colors() && other.has_colors() || self.is_empty() && other.has_colors();
        let normals =
            self.has_normals() && other.has_normals() || self.is_empty() && other.has_normals();
        self.points.extend_from_slice(&other.points);
        if colors {
            self.colors.extend_from_slice(&other.colors);
        } else {
            self.colors.clear();
        }
        if normals {
            self.normals.extend_from_slice(&other.normals);
        } else {
            self.normals.clear();
        }
    }

    /// Centroid of the points.
    pub fn centroid(&self) -> Point3<f64> {
        let sum: Vector3<f64> = self.points.iter().map(|p| p.coords).sum();
        Point3::from(sum / self.points.len().max(1) as f64)
    }

    /// Principal axes through the centroid: the centroid, and the
    /// variances along the axes (largest first) with their unit directions.
    pub fn principal_axes(&self) -> (Point3<f64>, [PrincipalAxis; 3]) {
        let centre = self.centroid();
        let mut covariance = nalgebra::Matrix3::zeros();
        for p in &self.points {
            let d = p - centre;
            covariance += d * d.transpose();
        }
        let eigen = nalgebra::SymmetricEigen::new(covariance / self.points.len().max(1) as f64);
        let mut order = [0, 1, 2];
        order.sort_by(|&a, &b| eigen.eigenvalues[b].total_cmp(&eigen.eigenvalues[a]));
        let axes = order.map(|k| {
            (
                eigen.eigenvalues[k],
                nalgebra::Unit::new_normalize(eigen.eigenvectors.column(k).into_owned()),
            )
        });
        (centre, axes)
    }

    /// Length of the bounding-box diagonal.
    pub fn extent(&self) -> f64 {
        let mut lo = Point3::new(f64::INFINITY, f64::INFINITY, f64::INFINITY);
        let mut hi = -lo;
        for p in &self.points {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        if self.points.is_empty() {
            0.0
        } else {
            (hi - lo).norm()
        }
    }
}

/// How to turn a splat model into points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplatFilter {
    /// Keep splats whose opacity (after the sigmoid) is at least this. Trained
    /// models are mostly faint splats (median opacity about 0.035 in the
    /// shared Omni-Scan models), so the default keeps about a third of them.
    pub min_opacity: f64,
    /// Drop splats whose largest scale exceeds this many times the median largest scale.
    pub max_scale_over_median: f64,
}

impl Default for SplatFilter {
    fn default() -> Self {
        SplatFilter {
            min_opacity: 0.05,
            max_scale_over_median: 6.0,
        }
    }
}

/// Whether a PLY file is a 3D Gaussian Splat model (has opacity and scales).
pub fn is_splat_ply(ply: &PlyFile) -> bool {
    ply.element("vertex")
        .is_some_and(|v| v.scalar("opacity").is_some() && v.scalar("scale_0").is_some())
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// Reads a point cloud file (`.ply`, `.pcd`, `.xyz`, `.xyzn`, `.xyzrgb`).
/// A splat PLY gives its filtered centres.
pub fn read_cloud(path: &Path) -> Result<PointCloud, RegisterError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let cloud = match ext.as_str() {
        "ply" => {
            let ply = omniscan_core::ply::read(path)?;
            if is_splat_ply(&ply) {
                splat_centres(&ply, &SplatFilter::default())
                    .map_err(|e| RegisterError::file(path, e))?
            } else {
                cloud_from_ply(&ply).map_err(|e| RegisterError::file(path, e))?
            }
        }
        "pcd" => read_pcd(path)?,
        "xyz" | "xyzn" | "xyzrgb" | "txt" => read_xyz(path, &ext)?,
        _ => {
            return Err(RegisterError::file(
                path,
                "unsupported point cloud format: use .ply, .pcd, .xyz, .xyzn or .xyzrgb",
            ));
        }
    };
    cloud.validate(&path.display().to_string())?;
    Ok(cloud)
}

/// Points of a PLY `vertex` element: x, y, z; optional colours
/// (red/green/blue as 0-255 integers or 0-1 floats, or splat `f_dc_*`) and
/// normals (nx, ny, nz; all-zero normals, as 3DGS files carry, count as absent).
pub fn cloud_from_ply(ply: &PlyFile) -> Result<PointCloud, String> {
    let v = ply.element("vertex").ok_or("PLY has no `vertex` element")?;
    let (Some(x), Some(y), Some(z)) = (v.scalar("x"), v.scalar("y"), v.scalar("z")) else {
        return Err("PLY vertices need x, y and z".into());
    };
    let mut cloud = PointCloud {
        points: (0..v.count)
            .map(|i| Point3::new(x[i], y[i], z[i]))
            .collect(),
        ..Default::default()
    };
    if let (Some(r), Some(g), Some(b)) = (v.scalar("red"), v.scalar("green"), v.scalar("blue")) {
        let integer = v
            .properties
            .iter()
            .find(|p| p.name == "red")
            .is_some_and(|p| p.scalar != ScalarType::F32 && p.scalar != ScalarType::F64);
        let scale = if integer { 255.0 } else { 1.0 };
        cloud.colors = (0..v.count)
            .map(|i| [r[i], g[i], b[i]].map(|c| (c / scale).clamp(0.0, 1.0) as f32))
            .collect();
    } else if let (Some(r), Some(g), Some(b)) =
        (v.scalar("f_dc_0"), v.scalar("f_dc_1"), v.scalar("f_dc_2"))
    {
        cloud.colors = (0..v.count)
            .map(|i| [r[i], g[i], b[i]].map(|c| (0.5 + SH_C0 * c).clamp(0.0, 1.0) as f32))
            .collect();
    }
    if let (Some(nx), Some(ny), Some(nz)) = (v.scalar("nx"), v.scalar("ny"), v.scalar("nz")) {
        let normals: Vec<Vector3<f64>> = (0..v.count)
            .map(|i| Vector3::new(nx[i], ny[i], nz[i]))
            .collect();
        if normals.iter().any(|n| n.norm_squared() > 0.0) {
            cloud.normals = normals
                .into_iter()
                .map(|n| if n.norm() > 0.0 { n.normalize() } else { n })
                .collect();
        }
    }
    Ok(cloud)
}

/// Centres of a splat model's Gaussians that pass `filter`, with their DC colour.
pub fn splat_centres(ply: &PlyFile, filter: &SplatFilter) -> Result<PointCloud, String> {
    let v = ply.element("vertex").ok_or("PLY has no `vertex` element")?;
    let cloud = cloud_from_ply(ply)?;
    let opacity = v.scalar("opacity").ok_or("splat PLY has no opacity")?;
    let scales: Vec<&[f64]> = ["scale_0", "scale_1", "scale_2"]
        .iter()
        .map(|n| v.scalar(n).ok_or_else(|| format!("splat PLY has no {n}")))
        .collect::<Result<_, _>>()?;
    let largest: Vec<f64> = (0..v.count)
        .map(|i| {
            scales
                .iter()
                .map(|s| s[i])
                .fold(f64::NEG_INFINITY, f64::max)
                .exp()
        })
        .collect();
    let mut sorted: Vec<f64> = largest.iter().copied().filter(|s| s.is_finite()).collect();
    sorted.sort_by(f64::total_cmp);
    let median = sorted
        .get(sorted.len() / 2)
        .copied()
        .unwrap_or(f64::INFINITY);
    let keep: Vec<usize> = (0..v.count)
        .filter(|&i| {
            let ok_opacity = sigmoid(opacity[i]) >= filter.min_opacity;
            let ok_size =
                largest[i].is_finite() && largest[i] <= filter.max_scale_over_median * median;
            ok_opacity && ok_size && cloud.points[i].coords.iter().all(|c| c.is_finite())
        })
        .collect();
    let mut out = cloud.select(&keep);
    out.normals.clear();
    if out.is_empty() {
        return Err(format!(
            "no splat passes the filter (opacity >= {}, size <= {} x median)",
            filter.min_opacity, filter.max_scale_over_median
        ));
    }
    Ok(out)
}

/// Writes a binary PLY with x, y, z (double), colours (uchar) and normals (float) when present.
pub fn write_ply(path: &Path, cloud: &PointCloud) -> Result<(), RegisterError> {
    let n = cloud.len();
    let mut properties = Vec::new();
    let mut columns = Vec::new();
    let prop = |name: &str, scalar| Property {
        name: name.into(),
        scalar,
        list_count: None,
    };
    for (k, name) in ["x", "y", "z"].iter().enumerate() {
        properties.push(prop(name, ScalarType::F64));
        columns.push(Column::Scalar(cloud.points.iter().map(|p| p[k]).collect()));
    }
    if cloud.has_normals() {
        for (k, name) in ["nx", "ny", "nz"].iter().enumerate() {
            properties.push(prop(name, ScalarType::F32));
            columns.push(Column::Scalar(cloud.normals.iter().map(|v| v[k]).collect()));
        }
    }
    if cloud.has_colors() {
        for (k, name) in ["red", "green", "blue"].iter().enumerate() {
            properties.push(prop(name, ScalarType::U8));
            columns.push(Column::Scalar(
                cloud
                    .colors
                    .iter()
                    .map(|c| (c[k] as f64 * 255.0).round().clamp(0.0, 255.0))
                    .collect(),
            ));
        }
    }
    let file = PlyFile {
        format: Format::BinaryLittleEndian,
        comments: vec!["written by omniscan".into()],
        elements: vec![Element {
            name: "vertex".into(),
            count: n,
            properties,
            columns,
        }],
    };
    omniscan_core::io::write_atomic(path, &omniscan_core::ply::to_binary_le(&file))?;
    Ok(())
}

fn read_xyz(path: &Path, ext: &str) -> Result<PointCloud, RegisterError> {
    let text =
        std::fs::read_to_string(path).map_err(|e| RegisterError::file(path, e.to_string()))?;
    let mut cloud = PointCloud::default();
    for (line_no, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = line
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|_| {
                RegisterError::file(
                    path,
                    format!("line {}: not a list of numbers: `{line}`", line_no + 1),
                )
            })?;
        if v.len() < 3 {
            return Err(RegisterError::file(
                path,
                format!("line {}: needs at least x y z", line_no + 1),
            ));
        }
        cloud.points.push(Point3::new(v[0], v[1], v[2]));
        match ext {
            "xyzn" if v.len() >= 6 => cloud.normals.push(Vector3::new(v[3], v[4], v[5])),
            "xyzrgb" if v.len() >= 6 => cloud.colors.push([v[3], v[4], v[5]].map(|c| c as f32)),
            "xyzn" | "xyzrgb" => {
                return Err(RegisterError::file(
                    path,
                    format!("line {}: needs 6 columns", line_no + 1),
                ));
            }
            _ => {}
        }
    }
    if cloud.colors.iter().any(|c| c.iter().any(|&x| x > 1.0)) {
        for c in &mut cloud.colors {
            *c = c.map(|x| x / 255.0);
        }
    }
    Ok(cloud)
}

/// LZF decompression (the `binary_compressed` PCD body).
fn lzf_decompress(input: &[u8], out_len: usize) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(out_len);
    let mut i = 0;
    while i < input.len() {
        let ctrl = input[i] as usize;
        i += 1;
        if ctrl < 32 {
            let n = ctrl + 1;
            if i + n > input.len() {
                return Err("compressed data ends inside a literal run".into());
            }
            out.extend_from_slice(&input[i..i + n]);
            i += n;
        } else {
            let mut len = ctrl >> 5;
            if len == 7 {
                len += *input
                    .get(i)
                    .ok_or("compressed data ends inside a back-reference")?
                    as usize;
                i += 1;
            }
            let low = *input
                .get(i)
                .ok_or("compressed data ends inside a back-reference")?
                as usize;
            i += 1;
            let back = ((ctrl & 0x1f) << 8) + low + 1;
            if back > out.len() {
                return Err("back-reference before the start of the data".into());
            }
            let start = out.len() - back;
            for k in 0..len + 2 {
                out.push(out[start + k]);
            }
        }
    }
    if out.len() != out_len {
        return Err(format!(
            "decompressed {} bytes, header says {out_len}",
            out.len()
        ));
    }
    Ok(out)
}

/// A PCD header (PCL's format, v0.7): the fields, their layout, and where
/// the body starts.
struct PcdHeader {
    fields: Vec<String>,
    sizes: Vec<usize>,
    types: Vec<char>,
    counts: Vec<usize>,
    /// POINTS.
    n: usize,
    /// `ascii`, `binary` or `binary_compressed`.
    data_kind: String,
    /// The first byte after the DATA line.
    body_start: usize,
}

impl PcdHeader {
    /// Bytes per point in a binary body.
    fn stride(&self) -> Option<usize> {
        self.sizes
            .iter()
            .zip(&self.counts)
            .try_fold(0usize, |s, (&a, &c)| a.checked_mul(c)?.checked_add(s))
    }

    /// Values per point: one per (field, element).
    fn width(&self) -> usize {
        self.counts.iter().sum()
    }

    /// Where each field's first value sits among a point's values.
    fn offsets(&self) -> Vec<usize> {
        self.counts
            .iter()
            .scan(0, |s, c| {
                let o = *s;
                *s += c;
                Some(o)
            })
            .collect()
    }
}

/// Reads and checks a PCD header: every per-field line the same length,
/// no field of size or count 0, types PCL writes (F 4/8, I and U 1/2/4),
/// and POINTS = WIDTH × HEIGHT (HEIGHT 1 for an unorganised cloud, never 0).
fn read_pcd_header(
    bytes: &[u8],
    err: &dyn Fn(String) -> RegisterError,
) -> Result<PcdHeader, RegisterError> {
    let (mut fields, mut sizes, mut types, mut counts) = (vec![], vec![], vec![], vec![]);
    let (mut points, mut width, mut height) = (None, None, None);
    let mut at = 0;
    let data_kind = loop {
        let end = bytes[at..]
            .iter()
            .position(|&b| b == b'\n')
            .map(|e| at + e)
            .ok_or_else(|| err("PCD header has no DATA line".into()))?;
        let line = String::from_utf8_lossy(&bytes[at..end]).trim().to_string();
        at = end + 1;
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut words = line.split_whitespace();
        let key = words.next().unwrap_or("").to_ascii_uppercase();
        let rest: Vec<String> = words.map(String::from).collect();
        let nums = |rest: &[String]| -> Result<Vec<usize>, RegisterError> {
            rest.iter()
                .map(|w| {
                    w.parse::<usize>().map_err(|_| {
                        err(format!("bad number `{w}` in `{line}` (a count, 0 or more)"))
                    })
                })
                .collect()
        };
        let one = |rest: &[String]| -> Result<usize, RegisterError> {
            match nums(rest)?.as_slice() {
                [v] => Ok(*v),
                _ => Err(err(format!("`{line}` must hold one number"))),
            }
        };
        match key.as_str() {
            "FIELDS" => fields = rest,
            "SIZE" => sizes = nums(&rest)?,
            "TYPE" => {
                types = rest
                    .iter()
                    .map(|t| t.chars().next().unwrap_or('?'))
                    .collect()
            }
            "COUNT" => counts = nums(&rest)?,
            "WIDTH" => width = Some(one(&rest)?),
            "HEIGHT" => height = Some(one(&rest)?),
            "POINTS" => points = Some(one(&rest)?),
            "DATA" => break rest.first().cloned().unwrap_or_default(),
            _ => {}
        }
    };
    let n = points.ok_or_else(|| err("PCD header has no POINTS line".into()))?;
    if height == Some(0) {
        return Err(err(
            "PCD header: HEIGHT 0 (an unorganised cloud has HEIGHT 1)".into(),
        ));
    }
    if let (Some(w), Some(h)) = (width, height)
        && w.checked_mul(h) != Some(n)
    {
        return Err(err(format!(
            "PCD header: POINTS {n} is not WIDTH {w} × HEIGHT {h}"
        )));
    }
    if counts.is_empty() {
        counts = vec![1; fields.len()];
    }
    if sizes.len() != fields.len() || types.len() != fields.len() || counts.len() != fields.len() {
        return Err(err(
            "PCD header: FIELDS, SIZE, TYPE and COUNT differ in length".into(),
        ));
    }
    if sizes.contains(&0) || counts.contains(&0) {
        return Err(err("PCD header: a field of SIZE or COUNT 0".into()));
    }
    for ((field, &t), &size) in fields.iter().zip(&types).zip(&sizes) {
        if !matches!((t, size), ('F', 4 | 8) | ('I' | 'U', 1 | 2 | 4)) {
            return Err(err(format!(
                "PCD header: field `{field}` has TYPE {t} SIZE {size}, which no reader decodes (F 4 or 8, I or U 1, 2 or 4)"
            )));
        }
    }
    Ok(PcdHeader {
        fields,
        sizes,
        types,
        counts,
        n,
        data_kind,
        body_start: at,
    })
}

fn read_pcd(path: &Path) -> Result<PointCloud, RegisterError> {
    let bytes = std::fs::read(path).map_err(|e| RegisterError::file(path, e.to_string()))?;
    let err = |m: String| RegisterError::file(path, m);
    let header = read_pcd_header(&bytes, &err)?;
    let values = read_pcd_body(&header, &bytes[header.body_start..], &err)?;
    let (width, offsets, fields) = (header.width(), header.offsets(), &header.fields);
    let col = |name: &str| fields.iter().position(|f| f == name).map(|f| offsets[f]);
    let (Some(x), Some(y), Some(z)) = (col("x"), col("y"), col("z")) else {
        return Err(err("PCD needs x, y and z fields".into()));
    };
    let mut cloud = PointCloud::default();
    // Organised clouds mark missing points with NaN: skip them.
    for r in values.chunks_exact(width) {
        if ![r[x], r[y], r[z]].iter().all(|v| v.is_finite()) {
            continue;
        }
        cloud.points.push(Point3::new(r[x], r[y], r[z]));
        if let Some(c) = col("rgb").or(col("rgba")) {
            let packed = r[c] as u32;
            cloud.colors.push(
                [(packed >> 16) & 255, (packed >> 8) & 255, packed & 255].map(|v| v as f32 / 255.0),
            );
        }
        if let (Some(a), Some(b), Some(c)) = (col("normal_x"), col("normal_y"), col("normal_z")) {
            cloud.normals.push(Vector3::new(r[a], r[b], r[c]));
        }
    }
    Ok(cloud)
}

/// Decodes a PCD body into `POINTS × width` values, point-major, and
/// checks that it holds exactly what the header says (a final line break
/// aside): a lowered POINTS must not drop the rest silently.
fn read_pcd_body(
    h: &PcdHeader,
    body: &[u8],
    err: &dyn Fn(String) -> RegisterError,
) -> Result<Vec<f64>, RegisterError> {
    let n = h.n;
    let overflow = || err("PCD header: SIZE, COUNT or POINTS too large".into());
    let stride = h.stride().ok_or_else(overflow)?;
    let width = h.width();
    // What the body can hold bounds the header's point count before
    // anything is allocated for it (a damaged POINTS line asked for
    // terabytes). Binary points take `stride` bytes each (every value at
    // least one); an ASCII value at least a digit and a separator; LZF
    // expands at most 264 bytes out of every 3 in.
    let needed = n.checked_mul(stride).ok_or_else(overflow)?;
    let holds = match h.data_kind.as_str() {
        "ascii" => body.len() / 2 + 1 >= n.saturating_mul(width),
        "binary" => body.len() >= needed,
        _ => body.len().saturating_mul(88) >= needed,
    };
    if !holds {
        return Err(err(format!(
            "file is truncated: {} bytes of {} data cannot hold the {n} points its header gives",
            body.len(),
            h.data_kind
        )));
    }
    let left_over = |rest: &[u8]| -> Result<(), RegisterError> {
        if rest.len() <= 2 && rest.iter().all(|b| matches!(b, b'\n' | b'\r')) {
            return Ok(());
        }
        Err(err(format!(
            "{} bytes follow the {n} points the header gives (is POINTS right?)",
            rest.len()
        )))
    };
    let mut values = vec![0f64; n * width];
    let offsets = h.offsets();
    let (fields, types, sizes, counts) = (&h.fields, &h.types, &h.sizes, &h.counts);
    match h.data_kind.as_str() {
        "ascii" => {
            let text =
                std::str::from_utf8(body).map_err(|_| err("ASCII PCD body is not text".into()))?;
            let mut tokens = text.split_whitespace();
            for (k, v) in values.iter_mut().enumerate() {
                let t = tokens.next().ok_or_else(|| {
                    err(format!(
                        "file ends early: point {} of {n}",
                        k / width.max(1)
                    ))
                })?;
                *v = t.parse().map_err(|_| err(format!("bad number `{t}`")))?;
            }
            if let Some(t) = tokens.next() {
                return Err(err(format!(
                    "values follow the {n} points the header gives (from `{t}` on; is POINTS right?)"
                )));
            }
            // Packed rgb in ASCII files is the float reinterpretation of the integer.
            if let Some(f) = fields.iter().position(|f| f == "rgb" || f == "rgba")
                && types[f] == 'F'
            {
                for i in 0..n {
                    let v = &mut values[i * width + offsets[f]];
                    *v = (*v as f32).to_bits() as f64;
                }
            }
        }
        "binary" => {
            left_over(&body[needed..])?;
            for i in 0..n {
                let mut o = i * stride;
                for f in 0..fields.len() {
                    for c in 0..counts[f] {
                        values[i * width + offsets[f] + c] =
                            raw_or_value(&body[o..], types[f], sizes[f], &fields[f]);
                        o += sizes[f];
                    }
                }
            }
        }
        "binary_compressed" => {
            if body.len() < 8 {
                return Err(err("compressed PCD body is truncated".into()));
            }
            let compressed = u32::from_le_bytes(body[0..4].try_into().unwrap()) as usize;
            let raw = u32::from_le_bytes(body[4..8].try_into().unwrap()) as usize;
            if raw != needed {
                return Err(err(format!(
                    "compressed PCD body unpacks to {raw} bytes, its {n} points need {needed}"
                )));
            }
            let data = body
                .get(8..8 + compressed)
                .ok_or_else(|| err("compressed PCD body is truncated".into()))?;
            left_over(&body[8 + compressed..])?;
            let data = lzf_decompress(data, raw).map_err(err)?;
            // Column-major: all of field 0, then all of field 1...
            let mut o = 0;
            for f in 0..fields.len() {
                for i in 0..n {
                    for c in 0..counts[f] {
                        let b = data
                            .get(o..o + sizes[f])
                            .ok_or_else(|| err("decompressed data too short".into()))?;
                        values[i * width + offsets[f] + c] =
                            raw_or_value(b, types[f], sizes[f], &fields[f]);
                        o += sizes[f];
                    }
                }
            }
        }
        other => return Err(err(format!("unknown PCD DATA kind `{other}`"))),
    }
    Ok(values)
}

/// One binary value of a type the header check allows.
fn decode_pcd_value(b: &[u8], t: char, size: usize) -> f64 {
    match (t, size) {
        ('F', 4) => f32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
        ('F', 8) => f64::from_le_bytes(b[..8].try_into().unwrap()),
        ('U', 1) => b[0] as f64,
        ('I', 1) => b[0] as i8 as f64,
        ('U', 2) => u16::from_le_bytes(b[..2].try_into().unwrap()) as f64,
        ('I', 2) => i16::from_le_bytes(b[..2].try_into().unwrap()) as f64,
        ('U', 4) => u32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
        ('I', 4) => i32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
        _ => unreachable!("read_pcd_header refuses TYPE {t} SIZE {size}"),
    }
}

/// Packed colour fields keep their bit pattern (as an integer); others decode.
fn raw_or_value(b: &[u8], t: char, size: usize, field: &str) -> f64 {
    if (field == "rgb" || field == "rgba") && size == 4 {
        u32::from_le_bytes(b[..4].try_into().unwrap()) as f64
    } else {
        decode_pcd_value(b, t, size)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> PointCloud {
        PointCloud {
            points: vec![Point3::new(0.0, 1.0, 2.0), Point3::new(-1.5, 0.25, 3.0)],
            colors: vec![[1.0, 0.0, 0.5019608], [0.0, 1.0, 0.0]],
            normals: vec![Vector3::new(0.0, 0.0, 1.0), Vector3::new(1.0, 0.0, 0.0)],
        }
    }

    #[test]
    fn extending_keeps_colours_and_normals_only_where_both_have_them() {
        let mut joined = sample();
        joined.extend(&PointCloud::default());
        assert_eq!(joined, sample(), "an empty cloud changes nothing");
        let mut from_empty = PointCloud::default();
        from_empty.extend(&sample());
        assert_eq!(from_empty, sample());
        joined.extend(&sample());
        assert_eq!(
            (joined.len(), joined.colors.len(), joined.normals.len()),
            (4, 4, 4)
        );
        let bare = PointCloud {
            points: vec![Point3::origin()],
            ..PointCloud::default()
        };
        joined.extend(&bare);
        assert!(!joined.has_colors() && !joined.has_normals() && joined.len() == 5);
    }

    #[test]
    fn ply_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.ply");
        write_ply(&path, &sample()).unwrap();
        let back = read_cloud(&path).unwrap();
        assert_eq!(back.points, sample().points);
        assert_eq!(back.normals, sample().normals);
        for (a, b) in back.colors.iter().zip(&sample().colors) {
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() < 1.0 / 255.0);
            }
        }
    }

    #[test]
    fn pcd_ascii_binary_and_compressed() {
        let dir = tempfile::tempdir().unwrap();
        let header = |data: &str| {
            format!(
                "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA {data}\n"
            )
        };
        let ascii = header("ascii") + "1 2 3 16711680\n4 5 6 255\n";
        std::fs::write(dir.path().join("a.pcd"), &ascii).unwrap();
        let a = read_cloud(&dir.path().join("a.pcd")).unwrap();
        assert_eq!(a.points[1], Point3::new(4.0, 5.0, 6.0));
        assert_eq!(a.colors[0], [1.0, 0.0, 0.0]);
        assert_eq!(a.colors[1], [0.0, 0.0, 1.0]);
        let mut bin = header("binary").into_bytes();
        for (p, c) in [([1f32, 2.0, 3.0], 0xff0000u32), ([4.0, 5.0, 6.0], 0x0000ff)] {
            for v in p {
                bin.extend(v.to_le_bytes());
            }
            bin.extend(c.to_le_bytes());
        }
        std::fs::write(dir.path().join("b.pcd"), &bin).unwrap();
        let b = read_cloud(&dir.path().join("b.pcd")).unwrap();
        assert_eq!(a, b);
        // binary_compressed with an all-literal LZF stream (column-major data).
        let mut raw = Vec::new();
        // x column, y column, z column, rgb column.
        for v in [1f32, 4.0] {
            raw.extend(v.to_le_bytes());
        }
        for v in [2f32, 5.0] {
            raw.extend(v.to_le_bytes());
        }
        for v in [3f32, 6.0] {
            raw.extend(v.to_le_bytes());
        }
        for c in [0xff0000u32, 0x0000ff] {
            raw.extend(c.to_le_bytes());
        }
        let mut lzf = vec![(raw.len() - 1) as u8];
        lzf.extend_from_slice(&raw);
        let mut cb = header("binary_compressed").into_bytes();
        cb.extend((lzf.len() as u32).to_le_bytes());
        cb.extend((raw.len() as u32).to_le_bytes());
        cb.extend(&lzf);
        std::fs::write(dir.path().join("c.pcd"), &cb).unwrap();
        assert_eq!(read_cloud(&dir.path().join("c.pcd")).unwrap(), a);
        // Truncated binary.
        std::fs::write(dir.path().join("t.pcd"), &bin[..bin.len() - 3]).unwrap();
        assert!(
            read_cloud(&dir.path().join("t.pcd"))
                .unwrap_err()
                .to_string()
                .contains("truncated")
        );
        // A damaged POINTS line: the reader reserved a value for each point
        // it claims (50 TB here) before reading any, and the allocation
        // failure aborted the process. Every encoding now checks the body
        // can hold them first.
        for (kind, body) in [
            ("ascii", &ascii.as_bytes()[header("ascii").len()..]),
            ("binary", &bin[header("binary").len()..]),
            (
                "binary_compressed",
                &cb[header("binary_compressed").len()..],
            ),
        ] {
            let mut file = header(kind)
                .replace("WIDTH 2", "WIDTH 1562500000000")
                .replace("POINTS 2", "POINTS 1562500000000")
                .into_bytes();
            file.extend_from_slice(body);
            std::fs::write(dir.path().join("p.pcd"), &file).unwrap();
            let message = read_cloud(&dir.path().join("p.pcd"))
                .unwrap_err()
                .to_string();
            assert!(message.contains("cannot hold"), "{kind}: {message}");
        }
        // Header numbers whose product overflows, or a field of no bytes.
        for (from, to) in [
            ("SIZE 4 4 4 4", "SIZE 4 4 4 9223372036854775807"),
            ("SIZE 4 4 4 4", "SIZE 4 4 4 0"),
        ] {
            let mut file = header("binary").replace(from, to).into_bytes();
            file.extend_from_slice(&bin[header("binary").len()..]);
            std::fs::write(dir.path().join("s.pcd"), &file).unwrap();
            assert!(read_cloud(&dir.path().join("s.pcd")).is_err(), "{to}");
        }
        // A lowered POINTS (and WIDTH with it) leaves points unread: an
        // error, not a shorter cloud.
        for (kind, file) in [("ascii", ascii.as_bytes()), ("binary", &bin[..])] {
            let body = &file[header(kind).len()..];
            let mut lowered = header(kind)
                .replace("WIDTH 2", "WIDTH 1")
                .replace("POINTS 2", "POINTS 1")
                .into_bytes();
            lowered.extend_from_slice(body);
            std::fs::write(dir.path().join("l.pcd"), &lowered).unwrap();
            let message = read_cloud(&dir.path().join("l.pcd"))
                .unwrap_err()
                .to_string();
            assert!(message.contains("follow the 1 points"), "{kind}: {message}");
        }
        // Header lines that contradict each other or name no decodable type.
        for (from, to, says) in [
            ("POINTS 2", "POINTS 1", "is not WIDTH 2 × HEIGHT 1"),
            ("HEIGHT 1", "HEIGHT 0", "HEIGHT 0"),
            ("HEIGHT 1", "HEIGHT -1", "bad number `-1`"),
            ("SIZE 4 4 4 4", "SIZE 2 4 4 4", "TYPE F SIZE 2"),
        ] {
            let mut file = header("binary").replace(from, to).into_bytes();
            file.extend_from_slice(&bin[header("binary").len()..]);
            std::fs::write(dir.path().join("h.pcd"), &file).unwrap();
            let message = read_cloud(&dir.path().join("h.pcd"))
                .unwrap_err()
                .to_string();
            assert!(message.contains(says), "{to}: {message}");
        }
        // A compressed body whose stated unpacked size is not its points'.
        let mut wrong = cb.clone();
        let at = header("binary_compressed").len() + 4;
        wrong[at..at + 4].copy_from_slice(&(raw.len() as u32 + 4).to_le_bytes());
        std::fs::write(dir.path().join("w.pcd"), &wrong).unwrap();
        let message = read_cloud(&dir.path().join("w.pcd"))
            .unwrap_err()
            .to_string();
        assert!(message.contains("unpacks to"), "{message}");
    }

    #[test]
    fn lzf_back_references() {
        // "abcabcabc": literal "abc", then a back-reference of length 6 at distance 3.
        let compressed = [2u8, b'a', b'b', b'c', (4 << 5), 2];
        assert_eq!(lzf_decompress(&compressed, 9).unwrap(), b"abcabcabc");
        assert!(lzf_decompress(&compressed, 10).is_err());
    }

    #[test]
    fn xyz_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("p.xyz"), "0 0 0\n1 2 3\n").unwrap();
        assert_eq!(read_cloud(&dir.path().join("p.xyz")).unwrap().len(), 2);
        std::fs::write(dir.path().join("e.xyz"), "").unwrap();
        assert!(
            read_cloud(&dir.path().join("e.xyz"))
                .unwrap_err()
                .to_string()
                .contains("empty")
        );
        std::fs::write(dir.path().join("n.xyz"), "0 0 nan\n").unwrap();
        assert!(
            read_cloud(&dir.path().join("n.xyz"))
                .unwrap_err()
                .to_string()
                .contains("NaN")
        );
        std::fs::write(dir.path().join("b.xyz"), "0 0 x\n").unwrap();
        assert!(
            read_cloud(&dir.path().join("b.xyz"))
                .unwrap_err()
                .to_string()
                .contains("b.xyz")
        );
    }

    #[test]
    fn splat_filter_drops_transparent_and_huge_splats() {
        let names = [
            "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        ];
        let rows = [
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, -5.0, -5.0, -5.0],
            [1.0, 0.0, 0.0, 1.0, 0.0, 0.0, -4.0, -5.0, -5.0, -5.0],
            [2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, 0.0, -5.0, -5.0],
            [3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, -5.2, -5.0, -4.9],
        ];
        let element = Element {
            name: "vertex".into(),
            count: rows.len(),
            properties: names
                .iter()
                .map(|n| Property {
                    name: n.to_string(),
                    scalar: ScalarType::F32,
                    list_count: None,
                })
                .collect(),
            columns: (0..names.len())
                .map(|k| Column::Scalar(rows.iter().map(|r| r[k]).collect()))
                .collect(),
        };
        let ply = PlyFile {
            format: Format::BinaryLittleEndian,
            comments: vec![],
            elements: vec![element],
        };
        assert!(is_splat_ply(&ply));
        let cloud = splat_centres(&ply, &SplatFilter::default()).unwrap();
        let xs: Vec<f64> = cloud.points.iter().map(|p| p.x).collect();
        assert_eq!(xs, vec![0.0, 3.0]);
        assert!((cloud.colors[0][0] - 0.5).abs() < 1e-6);
    }
}
