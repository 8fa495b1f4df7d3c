//! Sharing a twin: [`convert`] between the model formats people use
//! ([`omniscan_splat::ply::ModelFormat`]: 3DGS PLY, SPZ, glTF
//! `KHR_gaussian_splatting`, `.splat`; PlayCanvas' compressed PLY read) and
//! [`view`], one HTML file that shows models in 3D in any browser, offline
//! ([`omniscan_view`]).

use std::path::{Path, PathBuf};

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use omniscan_splat::ply::{ModelFormat, read_splats, write_splats_as};
use omniscan_splat::spz::SpzVersion;

use crate::settings::default_from_flags;

/// Everything `convert` can be told besides the two files.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ConvertSettings {
    /// The SPZ version to write: 4 (current, zstd), 3 or 2 (gzip; for readers from before 2026, Spark 2.2 among them).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(2..=4))]
    pub spz_version: u32,
}

default_from_flags!(ConvertSettings);

/// What [`convert`] wrote.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ConvertReport {
    pub input: PathBuf,
    pub output: PathBuf,
    /// The written format's name.
    pub format: String,
    pub splats: usize,
    pub bytes: u64,
}

/// Reads `input` and writes it to `output`, each in the format its
/// extension names. An unknown output extension is refused before the
/// input is read.
pub fn convert(input: &Path, output: &Path, settings: &ConvertSettings) -> Result<ConvertReport> {
    let version = match settings.spz_version {
        2 => SpzVersion::V2,
        3 => SpzVersion::V3,
        4 => SpzVersion::V4,
        other => bail!("spz_version {other}: omniscan writes SPZ versions 2, 3 and 4"),
    };
    let format = ModelFormat::writable(output)?;
    let model = read_splats(input)?;
    write_splats_as(output, &model, version)?;
    Ok(ConvertReport {
        input: input.to_path_buf(),
        output: output.to_path_buf(),
        format: format.name().into(),
        splats: model.len(),
        bytes: std::fs::metadata(output)?.len(),
    })
}

/// Everything `view` can be told besides the models and the page.
#[derive(clap::Args, Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ViewSettings {
    /// A name per model for its button (default: the file names).
    #[arg(long = "name")]
    pub names: Vec<String>,
    /// The page's title (default: "omniscan: " and the names).
    #[arg(long)]
    pub title: Option<String>,
}

/// What [`view`] wrote.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewReport {
    pub out: PathBuf,
    pub models: usize,
    pub splats: usize,
    pub bytes: u64,
}

/// Writes `out`, an HTML page that shows `models` (any format
/// [`read_splats`] reads) in 3D.
pub fn view(models: &[PathBuf], out: &Path, settings: &ViewSettings) -> Result<ViewReport> {
    if models.is_empty() {
        bail!("no model to show");
    }
    if !settings.names.is_empty() && settings.names.len() != models.len() {
        bail!(
            "{} names for {} models: give one per model, or none",
            settings.names.len(),
            models.len()
        );
    }
    if out
        .extension()
        .is_none_or(|e| !e.eq_ignore_ascii_case("html"))
    {
        bail!(
            "{}: the viewer is an HTML page; name it *.html",
            out.display()
        );
    }
    let loaded: Vec<omniscan_splat::Splats> = models
        .iter()
        .map(|m| read_splats(m))
        .collect::<Result<_, _>>()?;
    let names: Vec<String> = models
        .iter()
        .enumerate()
        .map(|(i, path)| {
            settings.names.get(i).cloned().unwrap_or_else(|| {
                path.file_name().map_or_else(
                    || path.display().to_string(),
                    |n| n.to_string_lossy().into_owned(),
                )
            })
        })
        .collect();
    let viewer_models: Vec<omniscan_view::ViewerModel> = loaded
        .iter()
        .zip(&names)
        .map(|(splats, name)| omniscan_view::ViewerModel {
            name: name.clone(),
            splats,
            markers: Vec::new(),
        })
        .collect();
    let title = settings
        .title
        .clone()
        .unwrap_or_else(|| format!("omniscan: {}", names.join(", ")));
    omniscan_view::write_view(out, &title, &viewer_models)?;
    Ok(ViewReport {
        out: out.to_path_buf(),
        models: loaded.len(),
        splats: loaded.iter().map(|m| m.len()).sum(),
        bytes: std::fs::metadata(out)?.len(),
    })
}
