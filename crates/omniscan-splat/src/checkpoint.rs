//! Training checkpoints: a [`TrainState`] in one safetensors file, written
//! atomically, so an interrupted `omniscan train` continues where it stopped
//! and ends with the model an uninterrupted run would have given.
//!
//! Tensors: `means` `[N,3]`, `log_scales` `[N,3]`, `quats` `[N,4]`,
//! `opacity_logits` `[N]`, `sh` `[N·K,3]` (float32); `adam.<g>.m`,
//! `adam.<g>.v` for the five parameter groups (float32); `grad2d_sum`
//! (float32), `grad2d_count` (uint32), `order` (uint32); with pose
//! refinement, `pose.views` `[V,18]` and `pose.groups` `[G,18]` (float64:
//! each correction's six parameters and their two Adam moments) and
//! `pose.views.steps`, `pose.groups.steps` (uint32). Metadata: `format`
//! = `omniscan-train-state-v2`, `step`, `extent`, `rng_word_pos`,
//! `sh_degree`, `antialiased`, `appearance`, `fingerprint`, and `checksum`:
//! an FNV-1a digest of every tensor (name, type, shape, bytes) and every
//! other metadata entry, so a flipped byte or an edited number is found
//! before training resumes from it (version 1 had none, and 7 of 42
//! damaged checkpoints resumed to another model).

use std::collections::HashMap;
use std::path::Path;

use safetensors::{Dtype, SafeTensors, tensor::TensorView};

use crate::pose::{Learned, PoseState};
use crate::train::TrainState;
use crate::{SplatError, Splats};

pub const FORMAT: &str = "omniscan-train-state-v2";

/// The digest stored as the `checksum` metadata: tensors in name order,
/// then the other metadata in key order.
fn checksum<'a>(
    tensors: impl IntoIterator<Item = (&'a str, Dtype, &'a [usize], &'a [u8])>,
    metadata: &HashMap<String, String>,
) -> String {
    let mut tensors: Vec<_> = tensors.into_iter().collect();
    tensors.sort_by_key(|t| t.0);
    let mut digest = omniscan_core::digest::Digest::default();
    for (name, dtype, shape, data) in tensors {
        digest.add(format!("{name}\0{dtype:?}\0{shape:?}\0{}\0", data.len()).as_bytes());
        digest.add(data);
    }
    let mut entries: Vec<_> = metadata.iter().filter(|(k, _)| *k != "checksum").collect();
    entries.sort();
    for (key, value) in entries {
        digest.add(format!("{key}\0{value}\0").as_bytes());
    }
    digest.hex()
}

fn bytes_f32(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn bytes_u32(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

type Tensor = (String, Dtype, Vec<usize>, Vec<u8>);

/// A pose refinement's corrections as two tensors each for the views and
/// the groups.
fn pose_tensors(poses: &PoseState) -> Vec<Tensor> {
    let mut tensors = Vec::new();
    for (name, learned) in [("pose.views", &poses.views), ("pose.groups", &poses.groups)] {
        let values: Vec<u8> = learned
            .iter()
            .flat_map(|l| l.params.iter().chain(&l.m).chain(&l.v))
            .flat_map(|x| x.to_le_bytes())
            .collect();
        tensors.push((name.into(), Dtype::F64, vec![learned.len(), 18], values));
        let steps: Vec<u32> = learned.iter().map(|l| l.steps).collect();
        tensors.push((
            format!("{name}.steps"),
            Dtype::U32,
            vec![learned.len()],
            bytes_u32(&steps),
        ));
    }
    tensors
}

/// The corrections [`pose_tensors`] wrote, if the checkpoint has them.
fn read_poses(tensors: &SafeTensors, path: &Path) -> Result<Option<PoseState>, SplatError> {
    let bad = |m: String| SplatError::file(path, m);
    if tensors.tensor("pose.views").is_err() {
        return Ok(None);
    }
    let read = |name: &str| -> Result<Vec<Learned>, SplatError> {
        let values = tensors
            .tensor(name)
            .map_err(|_| bad(format!("tensor `{name}` is missing")))?;
        let steps = tensors
            .tensor(&format!("{name}.steps"))
            .map_err(|_| bad(format!("tensor `{name}.steps` is missing")))?;
        let count = steps.shape().first().copied().unwrap_or(0);
        if values.dtype() != Dtype::F64
            || values.shape() != [count, 18]
            || steps.dtype() != Dtype::U32
            || steps.shape().len() != 1
        {
            return Err(bad(format!(
                "tensors `{name}` ({:?} {:?}) and `{name}.steps` ({:?} {:?}) do not hold pose corrections",
                values.dtype(),
                values.shape(),
                steps.dtype(),
                steps.shape()
            )));
        }
        let numbers: Vec<f64> = values
            .data()
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
            .collect();
        let counts = steps
            .data()
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")));
        Ok(numbers
            .chunks_exact(18)
            .zip(counts)
            .map(|(n, steps)| Learned {
                params: std::array::from_fn(|k| n[k]),
                m: std::array::from_fn(|k| n[6 + k]),
                v: std::array::from_fn(|k| n[12 + k]),
                steps,
            })
            .collect())
    };
    let poses = PoseState {
        views: read("pose.views")?,
        groups: read("pose.groups")?,
    };
    poses.validate().map_err(|e| bad(e.to_string()))?;
    Ok(Some(poses))
}

/// Writes `state` to `path` atomically.
pub fn save(state: &TrainState, path: &Path) -> Result<(), SplatError> {
    let s = &state.splats;
    let n = s.len();
    let flat3 = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    let mut tensors: Vec<Tensor> = vec![
        (
            "means".into(),
            Dtype::F32,
            vec![n, 3],
            bytes_f32(&flat3(&s.means)),
        ),
        (
            "log_scales".into(),
            Dtype::F32,
            vec![n, 3],
            bytes_f32(&flat3(&s.log_scales)),
        ),
        (
            "quats".into(),
            Dtype::F32,
            vec![n, 4],
            bytes_f32(&s.quats.iter().flatten().copied().collect::<Vec<_>>()),
        ),
        (
            "opacity_logits".into(),
            Dtype::F32,
            vec![n],
            bytes_f32(&s.opacity_logits),
        ),
        (
            "sh".into(),
            Dtype::F32,
            vec![s.sh.len(), 3],
            bytes_f32(&flat3(&s.sh)),
        ),
        (
            "grad2d_sum".into(),
            Dtype::F32,
            vec![state.grad2d_sum.len()],
            bytes_f32(&state.grad2d_sum),
        ),
        (
            "grad2d_count".into(),
            Dtype::U32,
            vec![state.grad2d_count.len()],
            bytes_u32(&state.grad2d_count),
        ),
        (
            "order".into(),
            Dtype::U32,
            vec![state.order.len()],
            bytes_u32(&state.order.iter().map(|&i| i as u32).collect::<Vec<_>>()),
        ),
    ];
    if let Some(poses) = &state.poses {
        tensors.extend(pose_tensors(poses));
    }
    for (g, (m, v)) in state.moments.iter().enumerate() {
        tensors.push((
            format!("adam.{g}.m"),
            Dtype::F32,
            vec![m.len()],
            bytes_f32(m),
        ));
        tensors.push((
            format!("adam.{g}.v"),
            Dtype::F32,
            vec![v.len()],
            bytes_f32(v),
        ));
    }
    let views = tensors
        .iter()
        .map(|(name, dtype, shape, data)| {
            TensorView::new(*dtype, shape.clone(), data).map(|v| (name.clone(), v))
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| SplatError::file(path, format!("cannot encode the checkpoint: {e}")))?;
    let mut metadata = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("step".to_string(), state.step.to_string()),
        ("extent".to_string(), state.extent.to_string()),
        ("rng_word_pos".to_string(), state.rng_word_pos.to_string()),
        ("sh_degree".to_string(), s.sh_degree.to_string()),
        ("antialiased".to_string(), s.antialiased.to_string()),
        ("appearance".to_string(), s.appearance.name().to_string()),
        ("fingerprint".to_string(), state.fingerprint.clone()),
    ]);
    let sum = checksum(
        tensors
            .iter()
            .map(|(name, dtype, shape, data)| (name.as_str(), *dtype, &shape[..], &data[..])),
        &metadata,
    );
    metadata.insert("checksum".into(), sum);
    let encoded = safetensors::serialize(views, Some(metadata))
        .map_err(|e| SplatError::file(path, format!("cannot encode the checkpoint: {e}")))?;
    omniscan_core::io::write_atomic(path, &encoded)?;
    Ok(())
}

/// Reads a checkpoint written by [`save`], checking every shape.
pub fn load(path: &Path) -> Result<TrainState, SplatError> {
    let bytes = std::fs::read(path).map_err(|e| SplatError::file(path, e.to_string()))?;
    let bad = |m: String| SplatError::file(path, m);
    let (_, header) = SafeTensors::read_metadata(&bytes)
        .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
    let info = header.metadata().clone().unwrap_or_default();
    match info.get("format").map(String::as_str) {
        Some(FORMAT) => {}
        Some("omniscan-train-state-v1") => {
            return Err(bad(
                "a checkpoint of an older omniscan, without a checksum to check it by: delete it to train from the start".into(),
            ));
        }
        other => {
            return Err(bad(format!(
                "not an omniscan training checkpoint (format {other:?})"
            )));
        }
    }
    let meta = |key: &str| -> Result<&String, SplatError> {
        info.get(key)
            .ok_or_else(|| bad(format!("metadata `{key}` is missing")))
    };
    let number = |key: &str| -> Result<u128, SplatError> {
        meta(key)?
            .parse()
            .map_err(|_| bad(format!("metadata `{key}` is not a number")))
    };
    let tensors = SafeTensors::deserialize(&bytes)
        .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
    let listed = tensors.tensors();
    let found = checksum(
        listed
            .iter()
            .map(|(name, view)| (name.as_str(), view.dtype(), view.shape(), view.data())),
        &info,
    );
    if meta("checksum")? != &found {
        return Err(bad(
            "the checkpoint's checksum does not match its contents (damaged or edited): delete it to train from the start".into(),
        ));
    }
    let read = |name: &str, dtype: Dtype, width: usize| -> Result<Vec<[u8; 4]>, SplatError> {
        let view = tensors
            .tensor(name)
            .map_err(|_| bad(format!("tensor `{name}` is missing")))?;
        let shape = view.shape();
        let ok_shape = match width {
            1 => shape.len() == 1,
            w => shape.len() == 2 && shape[1] == w,
        };
        if view.dtype() != dtype || !ok_shape {
            return Err(bad(format!(
                "tensor `{name}` is {:?} {shape:?}",
                view.dtype()
            )));
        }
        Ok(view
            .data()
            .chunks_exact(4)
            .map(|b| [b[0], b[1], b[2], b[3]])
            .collect())
    };
    let floats = |name: &str, width: usize| -> Result<Vec<f32>, SplatError> {
        let v: Vec<f32> = read(name, Dtype::F32, width)?
            .into_iter()
            .map(f32::from_le_bytes)
            .collect();
        if v.iter().any(|x| !x.is_finite()) {
            return Err(bad(format!("tensor `{name}` holds NaN or infinite values")));
        }
        Ok(v)
    };
    let words = |name: &str| -> Result<Vec<u32>, SplatError> {
        Ok(read(name, Dtype::U32, 1)?
            .into_iter()
            .map(u32::from_le_bytes)
            .collect())
    };
    let triples = |v: Vec<f32>| {
        v.chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect::<Vec<_>>()
    };
    let splats = Splats {
        means: triples(floats("means", 3)?),
        log_scales: triples(floats("log_scales", 3)?),
        quats: floats("quats", 4)?
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect(),
        opacity_logits: floats("opacity_logits", 1)?,
        sh_degree: number("sh_degree")? as usize,
        sh: triples(floats("sh", 3)?),
        antialiased: meta("antialiased")? == "true",
        // Checkpoints from before the setting have none: view direction.
        appearance: match info.get("appearance") {
            None => crate::raster::Appearance::ViewDirection,
            Some(name) => crate::raster::Appearance::from_name(name)
                .ok_or_else(|| bad(format!("metadata `appearance` is `{name}`")))?,
        },
    };
    splats.validate().map_err(|e| bad(e.to_string()))?;
    let n = splats.len();
    let k = splats.sh_coefficients();
    let sizes = [3 * n, 3 * n, 4 * n, n, 3 * k * n];
    let mut moments: [(Vec<f32>, Vec<f32>); 5] = Default::default();
    for (g, size) in sizes.into_iter().enumerate() {
        let m = floats(&format!("adam.{g}.m"), 1)?;
        let v = floats(&format!("adam.{g}.v"), 1)?;
        if m.len() != size || v.len() != size {
            return Err(bad(format!(
                "Adam moments of group {g} do not match {n} splats"
            )));
        }
        moments[g] = (m, v);
    }
    let grad2d_sum = floats("grad2d_sum", 1)?;
    let grad2d_count = words("grad2d_count")?;
    if grad2d_sum.len() != n || grad2d_count.len() != n {
        return Err(bad(format!(
            "densification statistics do not match {n} splats"
        )));
    }
    let extent: f32 = meta("extent")?
        .parse()
        .map_err(|_| bad("metadata `extent` is not a number".into()))?;
    Ok(TrainState {
        step: number("step")? as usize,
        splats,
        extent,
        moments,
        grad2d_sum,
        grad2d_count,
        order: words("order")?.into_iter().map(|i| i as usize).collect(),
        rng_word_pos: number("rng_word_pos")?,
        fingerprint: meta("fingerprint")?.clone(),
        poses: read_poses(&tensors, path)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state() -> TrainState {
        let splats = Splats {
            means: vec![[0.1, 0.2, 0.3], [-0.4, 0.5, 0.6]],
            log_scales: vec![[-3.0; 3], [-2.5; 3]],
            quats: vec![[1.0, 0.0, 0.0, 0.0]; 2],
            opacity_logits: vec![0.5, -0.5],
            sh_degree: 0,
            sh: vec![[0.2, 0.3, 0.4], [0.5, 0.6, 0.7]],
            ..Default::default()
        };
        let moments =
            crate::strategy::moment_strides(1).map(|s| (vec![0.25; 2 * s], vec![1e-4; 2 * s]));
        TrainState {
            step: 7,
            splats,
            extent: 1.5,
            moments,
            grad2d_sum: vec![0.0; 2],
            grad2d_count: vec![0; 2],
            order: vec![1, 0],
            rng_word_pos: 42,
            fingerprint: "test".into(),
            poses: Some(PoseState {
                views: vec![
                    Learned {
                        params: [1e-3, -2e-3, 3e-3, 4e-4, 5e-4, -6e-4],
                        m: [1e-5; 6],
                        v: [1e-9; 6],
                        steps: 3,
                    };
                    2
                ],
                groups: vec![Learned::default()],
            }),
        }
    }

    /// Every flipped byte of the data and every edited metadata value is
    /// found, where before the checksum a third of such files resumed.
    #[test]
    fn a_damaged_or_edited_checkpoint_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state.safetensors");
        save(&state(), &path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let back = load(&path).unwrap();
        assert_eq!(
            (back.step, back.extent, back.splats, back.poses),
            (7, 1.5, state().splats, state().poses)
        );
        let header = 8 + u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        for at in (header..bytes.len()).step_by(7) {
            let mut damaged = bytes.clone();
            damaged[at] ^= 0x10;
            std::fs::write(&path, &damaged).unwrap();
            let message = load(&path).unwrap_err().to_string();
            assert!(message.contains("checksum"), "byte {at}: {message}");
        }
        // The JSON header after its 8-byte length (which is not UTF-8).
        let text = String::from_utf8_lossy(&bytes[8..header]).into_owned();
        for (from, to) in [("\"1.5\"", "\"2.5\""), ("\"step\":\"7\"", "\"step\":\"9\"")] {
            assert!(text.contains(from), "{from} not in {text}");
            // Same length, so the header's size stays right.
            let edited = [
                &bytes[..8],
                text.replacen(from, to, 1).as_bytes(),
                &bytes[header..],
            ]
            .concat();
            std::fs::write(&path, &edited).unwrap();
            let message = load(&path).unwrap_err().to_string();
            assert!(message.contains("checksum"), "{to}: {message}");
        }
    }
}
