//! omniscan's web pages: a splat viewer that lives in one HTML file (it
//! opens from `file://`, with no server and no network), and the pieces the
//! twin and inspection reports are made of.
//!
//! The viewer is Spark (`@sparkjsdev/spark`, MIT), a maintained WebGL2
//! splat renderer on three.js (MIT), bundled with esbuild into
//! `assets/viewer-lib.js.gz` by `scripts/refresh-viewer` from the versions
//! pinned in `web/package.json`; their licences are in
//! `assets/THIRD-PARTY-LICENSES.md` and travel inside every page. Our own
//! part, `assets/viewer.js`, is the orbit camera, the buttons, the markers
//! and `window.omniscanViewer`, the interface the browser tests drive.
//! Models travel inside the page as SPZ version 3 ([`omniscan_splat::spz`]),
//! the newest version Spark reads, in base64.

pub mod browser;

use std::path::Path;

use base64::Engine;
use omniscan_splat::Splats;
use omniscan_splat::orbit::{HALF_FOV_DEG, orbit_eye, robust_bounds};
use serde::Serialize;

/// The vendored viewer library (three.js + Spark), gzipped.
const LIBRARY_GZ: &[u8] = include_bytes!("../assets/viewer-lib.js.gz");
/// The licences of what the library bundles.
pub const THIRD_PARTY_LICENSES: &str = include_str!("../assets/THIRD-PARTY-LICENSES.md");
const GLUE: &str = include_str!("../assets/viewer.js");
const STYLE: &str = include_str!("../assets/viewer.css");

#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error(transparent)]
    Core(#[from] omniscan_core::CoreError),
    #[error(transparent)]
    Splat(#[from] omniscan_splat::SplatError),
    #[error("{0}")]
    Invalid(String),
}

/// A place to point at in a model, in the model's frame and units: an
/// inspection's defect region.
#[derive(Debug, Clone, Serialize)]
pub struct Marker {
    pub label: String,
    pub position: [f32; 3],
    /// The sphere drawn around it, in model units.
    pub radius: f32,
    /// sRGB, 0-255.
    pub colour: [u8; 3],
}

/// One model of a page, with its name (shown on its button) and markers.
pub struct ViewerModel<'a> {
    pub name: String,
    pub splats: &'a Splats,
    pub markers: Vec<Marker>,
}

/// The camera as the viewer and the CPU renderer's orbit share it.
#[derive(Debug, Clone, Serialize)]
struct ViewCamera {
    eye: [f64; 3],
    target: [f64; 3],
    up: [f64; 3],
    horizontal_fov_deg: f64,
}

#[derive(Serialize)]
struct ModelInfo<'a> {
    name: &'a str,
    splats: usize,
    data_id: String,
    centre: [f64; 3],
    radius: f64,
    camera: ViewCamera,
    markers: &'a [Marker],
}

#[derive(Serialize)]
struct Config<'a> {
    models: Vec<ModelInfo<'a>>,
    up: [f64; 3],
    background: [f32; 3],
}

/// The page background, also the canvas's (a dark grey that reads well
/// behind bright and dark parts alike).
pub const BACKGROUND: [f32; 3] = [0.12, 0.12, 0.13];

/// Text made safe inside HTML elements and attribute values.
pub fn escape_html(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// JSON made safe inside a `<script>` element: `<` is written as `\u003c`,
/// so no string in it can close the element.
fn script_json(value: &impl Serialize) -> String {
    serde_json::to_string(value)
        .expect("the viewer's configuration serialises")
        .replace('<', "\\u003c")
}

/// The library as the page carries it: the gzip file in base64, which the
/// page unpacks with the browser's `DecompressionStream` (1.4 MB rather
/// than 3.3).
fn library_base64() -> String {
    base64::engine::general_purpose::STANDARD.encode(LIBRARY_GZ)
}

/// The viewer as an HTML fragment: its box, buttons, the models' data, the
/// library and our script. One per page.
pub fn viewer_html(models: &[ViewerModel]) -> Result<String, ViewError> {
    if models.is_empty() {
        return Err(ViewError::Invalid("the viewer has no model to show".into()));
    }
    let mut infos = Vec::new();
    let mut data = String::new();
    for (index, model) in models.iter().enumerate() {
        model.splats.validate()?;
        let (centre, radius) = robust_bounds(model.splats);
        let (eye, target) = orbit_eye(model.splats, 0.0);
        let data_id = format!("omniscan-model-{index}");
        let spz = omniscan_splat::spz::to_spz(model.splats, omniscan_splat::spz::SpzVersion::V3);
        data.push_str(&format!(
            "<script type=\"application/octet-stream\" id=\"{data_id}\">{}</script>\n",
            base64::engine::general_purpose::STANDARD.encode(spz)
        ));
        infos.push(ModelInfo {
            name: &model.name,
            splats: model.splats.len(),
            data_id,
            centre: centre.coords.into(),
            radius,
            camera: ViewCamera {
                eye: eye.coords.into(),
                target: target.coords.into(),
                up: [0.0, 0.0, 1.0],
                horizontal_fov_deg: 2.0 * HALF_FOV_DEG,
            },
            markers: &model.markers,
        });
    }
    let config = Config {
        models: infos,
        up: [0.0, 0.0, 1.0],
        background: BACKGROUND,
    };
    let mut buttons = String::new();
    if models.len() > 1 {
        for (index, model) in models.iter().enumerate() {
            buttons.push_str(&format!(
                "<button type=\"button\" data-show=\"{index}\">{}</button>",
                escape_html(&model.name)
            ));
        }
        let all: Vec<String> = (0..models.len()).map(|i| i.to_string()).collect();
        buttons.push_str(&format!(
            "<button type=\"button\" data-show=\"{}\">all, side by side</button>",
            all.join(",")
        ));
    }
    let marker_toggle = if models.iter().any(|m| !m.markers.is_empty()) {
        "<label><input type=\"checkbox\" class=\"ov-markers\" checked> markers</label>"
    } else {
        ""
    };
    Ok(format!(
        "<style>{STYLE}</style>\n\
         <div id=\"omniscan-viewer\"><div class=\"ov-canvas\"><div class=\"ov-status\">Loading the viewer…</div></div>\
         <div class=\"ov-buttons\">{buttons}<button type=\"button\" class=\"ov-reset\">reset view</button>{marker_toggle}\
         <span class=\"ov-help\">drag: orbit · right-drag: pan · wheel: zoom</span></div></div>\n\
         <script type=\"application/json\" id=\"omniscan-viewer-config\">{}</script>\n{data}\
         <script type=\"application/octet-stream\" id=\"omniscan-viewer-lib\">{}</script>\n<script>{GLUE}</script>\n\
         <!-- Third-party software in this page:\n{}\n-->\n",
        script_json(&config),
        library_base64(),
        THIRD_PARTY_LICENSES.replace("--", "- -")
    ))
}

/// A page with nothing but the viewer (what `omniscan view` writes).
pub fn view_page(title: &str, models: &[ViewerModel]) -> Result<String, ViewError> {
    Ok(format!(
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width,initial-scale=1\">\
         <title>{}</title><style>html,body{{margin:0;height:100%;background:#1f1f21;color:#ddd;font-family:sans-serif}}\
         #omniscan-viewer{{height:100vh}}</style></head><body>{}</body></html>\n",
        escape_html(title),
        viewer_html(models)?
    ))
}

/// Writes [`view_page`] atomically to `path`.
pub fn write_view(path: &Path, title: &str, models: &[ViewerModel]) -> Result<(), ViewError> {
    let page = view_page(title, models)?;
    omniscan_core::io::write_atomic(path, page.as_bytes())?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;

    fn model() -> Splats {
        Splats {
            means: vec![[0.0; 3], [0.01, 0.0, 0.0]],
            log_scales: vec![[-5.0; 3]; 2],
            quats: vec![[1.0, 0.0, 0.0, 0.0]; 2],
            opacity_logits: vec![2.0; 2],
            sh: vec![[0.1; 3]; 2],
            ..Default::default()
        }
    }

    #[test]
    fn user_strings_cannot_break_out_of_the_page() {
        let s = model();
        let hostile = "</script><img src=x onerror=alert(1)>\"'&";
        let page = view_page(
            hostile,
            &[
                ViewerModel {
                    name: hostile.into(),
                    splats: &s,
                    markers: vec![Marker {
                        label: hostile.into(),
                        position: [0.0; 3],
                        radius: 0.01,
                        colour: [255, 0, 0],
                    }],
                },
                ViewerModel {
                    name: "b".into(),
                    splats: &s,
                    markers: vec![],
                },
            ],
        )
        .unwrap();
        assert!(!page.contains("<img src=x"), "raw markup from a name");
        // The only closing script tags are the page's own five.
        assert_eq!(page.matches("</script>").count(), 5);
        assert!(page.contains("&lt;/script&gt;&lt;img src=x onerror=alert(1)&gt;&quot;&#39;&amp;"));
    }

    #[test]
    fn the_page_holds_everything_it_needs() {
        let s = model();
        let page = view_page(
            "m",
            &[ViewerModel {
                name: "m".into(),
                splats: &s,
                markers: vec![],
            }],
        )
        .unwrap();
        // No script, style or image from elsewhere.
        for needle in ["src=\"http", "href=\"http", "src=\"//", "@import", "<link"] {
            assert!(!page.contains(needle), "{needle}");
        }
        let config_start = page.find("omniscan-viewer-config\">").unwrap() + 24;
        let config_end = config_start + page[config_start..].find("</script>").unwrap();
        let config: serde_json::Value =
            serde_json::from_str(&page[config_start..config_end]).unwrap();
        assert_eq!(config["models"][0]["splats"], 2);
        // The model inside decodes to the model.
        let id = config["models"][0]["data_id"].as_str().unwrap();
        let at = page.find(&format!("id=\"{id}\">")).unwrap() + id.len() + 6;
        let end = at + page[at..].find("</script>").unwrap();
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(&page[at..end])
            .unwrap();
        let back = omniscan_splat::spz::from_spz(&bytes).unwrap();
        assert_eq!(back.len(), 2);
        assert!((back.means[1][0] - 0.01).abs() < 1e-5);
        // The library unpacks to three.js and Spark.
        let needle = "id=\"omniscan-viewer-lib\">";
        let lib_at = page.find(needle).unwrap() + needle.len();
        let lib_end = lib_at + page[lib_at..].find("</script>").unwrap();
        let gz = base64::engine::general_purpose::STANDARD
            .decode(&page[lib_at..lib_end])
            .unwrap();
        let mut text = String::new();
        flate2::read::GzDecoder::new(&gz[..])
            .read_to_string(&mut text)
            .unwrap();
        assert!(text.contains("OmniscanViewerLib") && text.contains("SplatMesh"));
        assert!(page.contains("three"));
    }

    #[test]
    fn an_empty_viewer_is_refused() {
        assert!(viewer_html(&[]).is_err());
    }
}
