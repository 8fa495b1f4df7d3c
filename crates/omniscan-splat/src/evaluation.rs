//! A model's figures against views (paper, "Results"): PSNR and SSIM over
//! the whole image and over the object's pixels the model covers, the
//! gripper's left out, and LPIPS from a user-supplied network; mean and per
//! view, typed.

use rayon::prelude::*;

use crate::SplatError;
use crate::Splats;
use crate::backend::Renderer;
use crate::metrics::{ImageView, psnr};
use crate::view::{TrainingView, View};

/// A model's figures over a set of views: means over the views where a
/// figure exists (a view whose object the model never covers has no
/// masked figures), and each view's own.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Evaluation {
    pub views: usize,
    /// dB.
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    /// Over the object's pixels the model covers, the gripper's left out, dB.
    pub psnr_masked: Option<f64>,
    pub ssim_masked: Option<f64>,
    pub lpips: Option<f64>,
    pub lpips_masked: Option<f64>,
    pub per_view: Vec<ViewFigures>,
    /// Why there is no LPIPS, when there is none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips_note: Option<String>,
}

/// One view's figures.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ViewFigures {
    /// The view's index in the set it was scored in.
    pub view: usize,
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    pub psnr_masked: Option<f64>,
    pub ssim_masked: Option<f64>,
}

/// PSNR and SSIM over whole images (on black) and masked by object ∩
/// accumulation minus gripper (the paper's evaluation), averaged over views.
pub fn evaluate(
    model: &Splats,
    views: &[impl TrainingView],
    lpips: Option<&crate::lpips::Lpips>,
) -> Result<Evaluation, SplatError> {
    evaluate_views(
        model,
        &Renderer::Cpu,
        views.len(),
        |i| Ok(views[i].pixels()),
        lpips,
        |_, _, _| Ok(()),
    )
}

/// [`evaluate`] over `count` views that `view(i)` gives (a view read from
/// disk is dropped once compared), rendered by `renderer`: views on all
/// threads on the CPU, one after another on a GPU, which serves one view at
/// a time; `rendered(i, view, rgb)` is handed each render. The figures do
/// not depend on the threads: each view's are its own, and the means add
/// them in view order. A GPU's figures agree with the CPU reference's to
/// its rendering tolerance (1e-4 relative), not to the digit.
pub fn evaluate_views<'a>(
    model: &Splats,
    renderer: &Renderer,
    count: usize,
    view: impl Fn(usize) -> Result<std::borrow::Cow<'a, View>, SplatError> + Sync,
    lpips: Option<&crate::lpips::Lpips>,
    rendered: impl Fn(usize, &View, &[[f32; 3]]) -> Result<(), SplatError> + Sync,
) -> Result<Evaluation, SplatError> {
    use crate::metrics::ssim_whole_and_masked;
    let g = model.gaussians::<f32>();
    let settings = model.render_settings([0.0; 3]);
    // psnr, ssim, psnr_masked, ssim_masked, lpips, lpips_masked.
    let one = |i: usize| -> Result<[Option<f64>; 6], SplatError> {
        let v = view(i)?;
        let r = renderer.render(&g, &v.camera, &settings)?;
        if !r.rgb.iter().flatten().all(|c| c.is_finite()) {
            return Err(SplatError::Invalid(format!(
                "view {i}: the model renders NaN or infinite pixels, so no figure can be given for it"
            )));
        }
        rendered(i, &v, &r.rgb)?;
        let (w, h) = (v.camera.width as usize, v.camera.height as usize);
        let target: Vec<[f32; 3]> = v
            .image
            .iter()
            .zip(&v.object)
            .map(|(c, m)| c.map(|x| x * m))
            .collect();
        let a = ImageView {
            width: w,
            height: h,
            pixels: &r.rgb,
        };
        let b = ImageView {
            width: w,
            height: h,
            pixels: &target,
        };
        let mask: Vec<bool> = (0..w * h)
            .map(|i| v.object[i] >= 0.5 && r.alpha[i] >= 0.5 && v.excluded[i] < 0.5)
            .collect();
        let (mut l_all, mut l_mask) = (None, None);
        if let Some(net) = lpips {
            l_all = Some(net.distance(&r.rgb, &target, w, h, None)?);
            if mask.iter().any(|&m| m) {
                l_mask = Some(net.distance(&r.rgb, &target, w, h, Some(&mask))?);
            }
        }
        let (ssim_whole, ssim_masked) = ssim_whole_and_masked(&a, &b, &mask);
        Ok([
            psnr(&a, &b, None),
            ssim_whole,
            psnr(&a, &b, Some(&mask)),
            ssim_masked,
            l_all,
            l_mask,
        ])
    };
    let figures: Vec<[Option<f64>; 6]> = if renderer.is_gpu() {
        (0..count).map(one).collect::<Result<_, _>>()?
    } else {
        (0..count)
            .into_par_iter()
            .map(one)
            .collect::<Vec<Result<_, SplatError>>>()
            .into_iter()
            .collect::<Result<_, _>>()?
    };
    // Each view's own figures, so a user can see which views pull the mean down.
    let per_view = figures
        .iter()
        .enumerate()
        .map(|(view, f)| ViewFigures {
            view,
            psnr: f[0],
            ssim: f[1],
            psnr_masked: f[2],
            ssim_masked: f[3],
        })
        .collect();
    let mean = |k: usize| {
        let known: Vec<f64> = figures.iter().filter_map(|f| f[k]).collect();
        (!known.is_empty()).then(|| known.iter().sum::<f64>() / known.len() as f64)
    };
    Ok(Evaluation {
        views: count,
        psnr: mean(0),
        ssim: mean(1),
        psnr_masked: mean(2),
        ssim_masked: mean(3),
        lpips: mean(4),
        lpips_masked: mean(5),
        per_view,
        lpips_note: lpips
            .is_none()
            .then(|| "LPIPS not computed: no network was given (--lpips FILE.onnx)".into()),
    })
}
