//! Export to nerfstudio's `transforms.json` (OpenGL camera axes), which
//! nerfstudio, gsplat's examples and Brush read. Images and masks are linked
//! (or copied) into the output directory so that it stands on its own.
//!
//! The mask is the object mask: nerfstudio ignores pixels where it is 0, so
//! the background and the gripper (never part of the object mask) take no
//! part in training. The gripper mask goes beside it under omniscan's own
//! key, `gripper_mask_path`, so that omniscan reading the set back leaves the
//! gripper out of its losses as it does in the capture.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::camera::opencv_to_opengl;
use crate::capture::Capture;
use crate::error::{CoreError, Result};
use crate::poses::{ViewSet, camera_views};

#[derive(Debug, Serialize)]
struct TransformsFile {
    camera_model: &'static str,
    fl_x: f64,
    fl_y: f64,
    cx: f64,
    cy: f64,
    w: u32,
    h: u32,
    k1: f64,
    k2: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    k3: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    k4: Option<f64>,
    p1: f64,
    p2: f64,
    frames: Vec<TransformsFrame>,
}

#[derive(Debug, Serialize)]
struct TransformsFrame {
    file_path: String,
    transform_matrix: [[f64; 4]; 4],
    #[serde(skip_serializing_if = "Option::is_none")]
    mask_path: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    depth_file_path: Option<String>,
    /// omniscan's own key (nerfstudio ignores it): the pixels the gripper
    /// covers, which a capture leaves out of every loss; without it, a set
    /// read back would train them as background.
    #[serde(skip_serializing_if = "Option::is_none")]
    gripper_mask_path: Option<String>,
}

/// Options of [`export_nerfstudio`].
#[derive(Debug, Clone, Copy)]
pub struct ExportOptions {
    pub views: ViewSet,
    /// Write `mask_path` entries (object masks); frames without one are an error.
    pub masks: bool,
}

/// What an export wrote.
#[derive(Debug, Clone, Serialize)]
pub struct ExportSummary {
    pub transforms: PathBuf,
    pub frames: usize,
    pub masks: bool,
}

/// Hard-links `from` (the file itself, its links followed) into the export
/// when it lies inside the capture's folder, and copies it otherwise: an
/// export must not share an inode with a file outside the capture, which
/// `--allow-outside-paths` may have let in.
fn link_or_copy(capture_dir: &Path, from: &Path, to: &Path) -> Result<()> {
    if let Some(parent) = to.parent() {
        std::fs::create_dir_all(parent).map_err(|e| CoreError::io(parent, e))?;
    }
    if to.exists() {
        std::fs::remove_file(to).map_err(|e| CoreError::io(to, e))?;
    }
    let real = from.canonicalize().map_err(|e| CoreError::io(from, e))?;
    let inside = crate::paths::canonical_folder(capture_dir).is_ok_and(|dir| real.starts_with(dir));
    if inside && std::fs::hard_link(&real, to).is_ok() {
        return Ok(());
    }
    let bytes = std::fs::read(from).map_err(|e| CoreError::io(from, e))?;
    crate::io::write_atomic(to, &bytes)
}

fn extension(path: &str) -> &str {
    Path::new(path)
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("png")
}

/// Writes `out/transforms.json` with `out/images`, `out/masks`,
/// `out/grippers` (gripper masks) and `out/depth`.
pub fn export_nerfstudio(
    capture: &Capture,
    out: &Path,
    options: ExportOptions,
) -> Result<ExportSummary> {
    let views = camera_views(capture, options.views);
    if views.is_empty() {
        return Err(CoreError::Invalid(format!(
            "{}: no frames for the requested arm",
            capture.dir.join(crate::capture::CAPTURE_FILE).display()
        )));
    }
    let k = capture.intrinsics();
    let mut frames = Vec::with_capacity(views.len());
    for (n, view) in views.iter().enumerate() {
        let frame = &capture.file.frames[view.frame_index];
        let name = format!("{:04}_{}", n, frame.arm);
        let image = format!("images/{name}.{}", extension(&frame.file_path));
        link_or_copy(
            &capture.dir,
            &capture.resolve(&frame.file_path),
            &out.join(&image),
        )?;
        let mask_path = if options.masks {
            let source = frame
                .object_mask_path
                .as_ref()
                .or_else(|| frame.gt.as_ref().and_then(|g| g.object_mask_path.as_ref()))
                .ok_or_else(|| {
                    CoreError::Invalid(format!(
                        "frames[{}] ({}) has no object mask: run `omniscan mask` first or export without masks",
                        view.frame_index, frame.file_path
                    ))
                })?;
            let mask = format!("masks/{name}.png");
            link_or_copy(&capture.dir, &capture.resolve(source), &out.join(&mask))?;
            Some(mask)
        } else {
            None
        };
        let gripper_source = frame
            .gripper_mask_path
            .as_ref()
            .or_else(|| frame.gt.as_ref().and_then(|g| g.gripper_mask_path.as_ref()));
        let gripper_mask_path = match gripper_source {
            Some(source) if options.masks => {
                let mask = format!("grippers/{name}.png");
                link_or_copy(&capture.dir, &capture.resolve(source), &out.join(&mask))?;
                Some(mask)
            }
            _ => None,
        };
        let depth_file_path = match &frame.depth_path {
            Some(d) => {
                let depth = format!("depth/{name}.png");
                link_or_copy(&capture.dir, &capture.resolve(d), &out.join(&depth))?;
                Some(depth)
            }
            None => None,
        };
        let gl = opencv_to_opengl(&view.camera_to_object);
        let mut matrix = [[0.0; 4]; 4];
        for (r, row) in matrix.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = gl[(r, c)];
            }
        }
        frames.push(TransformsFrame {
            file_path: image,
            transform_matrix: matrix,
            mask_path,
            depth_file_path,
            gripper_mask_path,
        });
    }
    // nerfstudio's names for the capture's lens (its OPENCV camera has k3
    // too; OPENCV_FISHEYE has k1-k4 and no p1, p2).
    use crate::lens::Distortion;
    let (camera_model, [k1, k2, k3, k4, p1, p2]) = match capture.distortion() {
        None => ("OPENCV", [0.0; 6]),
        Some(&Distortion::RadialTangential { k1, k2, k3, p1, p2 }) => {
            ("OPENCV", [k1, k2, k3, 0.0, p1, p2])
        }
        Some(&Distortion::Fisheye { k1, k2, k3, k4 }) => {
            ("OPENCV_FISHEYE", [k1, k2, k3, k4, 0.0, 0.0])
        }
    };
    let file = TransformsFile {
        camera_model,
        fl_x: k.fx,
        fl_y: k.fy,
        cx: k.cx,
        cy: k.cy,
        w: k.width,
        h: k.height,
        k1,
        k2,
        k3: (k3 != 0.0).then_some(k3),
        k4: (camera_model == "OPENCV_FISHEYE").then_some(k4),
        p1,
        p2,
        frames,
    };
    let transforms = out.join("transforms.json");
    crate::io::write_json_atomic(&transforms, &file)?;
    Ok(ExportSummary {
        transforms,
        frames: views.len(),
        masks: options.masks,
    })
}
