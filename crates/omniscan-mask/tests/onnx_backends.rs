//! The learned (ONNX) backends: real loading and inference through ONNX
//! Runtime, on tiny models these tests write (no weights can be downloaded
//! here). They need ONNX Runtime's library (`ORT_DYLIB_PATH`, see
//! `omniscan_mask::onnx`), so they are ignored by default; `.ci/run`
//! installs the library and runs them.

use std::path::{Path, PathBuf};

use omniscan_core::capture::Capture;
use omniscan_core::image_io::RgbImage;
use omniscan_core::plan::ScanPlanConfig;
use omniscan_mask::depth::{DepthOutput, MonocularDepth};
use omniscan_mask::flow::{FlowEstimator, FlowInputRange, OnnxFlow};
use omniscan_mask::onnx::graph::{Attribute, Dim, ElementType, Graph};
use omniscan_mask::pipeline::{LearnedModels, Masker};
use omniscan_mask::plane::{Plane, iou};
use omniscan_mask::sam::{SamProposer, SamSettings};
use omniscan_mask::segment::CandidateProposer;
use omniscan_mask::unet::{GripperNet, UNet};
use omniscan_mask::{MaskSettings, evaluate_capture, mask_capture};
use omniscan_sim::{SimConfig, Simulation};

fn write(dir: &Path, name: &str, graph: &Graph) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, graph.to_model_bytes(17)).unwrap();
    path
}

fn image(width: u32, height: u32, colour: impl Fn(u32, u32) -> [u8; 3]) -> RgbImage {
    let mut data = Vec::with_capacity((width * height * 3) as usize);
    for y in 0..height {
        for x in 0..width {
            data.extend_from_slice(&colour(x, y));
        }
    }
    RgbImage {
        width,
        height,
        data,
    }
}

fn nchw(channels: i64, height: Dim, width: Dim) -> Vec<Dim> {
    vec![Dim::Fixed(1), Dim::Fixed(channels), height, width]
}

fn open(name: &str) -> Dim {
    Dim::Named(name.into())
}

#[test]
#[ignore = "needs ONNX Runtime (ORT_DYLIB_PATH)"]
fn the_exported_gripper_unet_runs_in_onnx_runtime_as_in_rust() {
    let tmp = tempfile::tempdir().unwrap();
    let mut net = UNet::new(32, 24, [4, 8, 8], 5).unwrap();
    // Fresh networks have zero biases; make every term count.
    for (l, layer) in net.layers.iter_mut().enumerate() {
        for (i, b) in layer.bias.iter_mut().enumerate() {
            *b = 0.05 * ((i + l) % 5) as f32 - 0.1;
        }
    }
    let path = tmp.path().join("gripper.onnx");
    std::fs::write(&path, net.to_onnx()).unwrap();
    let onnx = GripperNet::load(&path, None).unwrap();
    let GripperNet::Onnx(onnx_net) = &onnx else {
        panic!("an .onnx file loads as an ONNX network")
    };
    let picture = image(70, 50, |x, y| {
        [(x * 3 + y) as u8, (y * 5) as u8, ((x * y) % 251) as u8]
    });
    let rust = net.probabilities(&picture);
    let ort = onnx_net.probabilities(&picture).unwrap();
    let worst = rust
        .data
        .iter()
        .zip(&ort.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst < 1e-4, "largest difference {worst}");
    let spread = rust.data.iter().cloned().fold(f32::MIN, f32::max)
        - rust.data.iter().cloned().fold(f32::MAX, f32::min);
    assert!(
        spread > 0.01,
        "the test network's output is not flat ({spread})"
    );
    assert_eq!(onnx.mask(&picture).unwrap(), net.mask(&picture));
}

/// A "depth network" whose output is the red channel after ImageNet
/// normalisation, so red = 255·(0.1 m / z) encodes disparity.
fn red_channel_depth_model(dir: &Path) -> PathBuf {
    let mut g = Graph::new("tiny_depth");
    g.input(
        "pixel_values",
        ElementType::Float,
        nchw(3, open("h"), open("w")),
    )
    .output(
        "predicted_depth",
        ElementType::Float,
        vec![Dim::Fixed(1), open("h"), open("w")],
    )
    .constant("w", &[1, 3, 1, 1], vec![1.0, 0.0, 0.0])
    .constant("b", &[1], vec![0.0])
    .constant_int64("axes", &[1], vec![1])
    .node("Conv", &["pixel_values", "w", "b"], &["red"], vec![])
    .node("Squeeze", &["red", "axes"], &["predicted_depth"], vec![]);
    write(dir, "depth.onnx", &g)
}

#[test]
#[ignore = "needs ONNX Runtime (ORT_DYLIB_PATH)"]
fn a_relative_depth_network_is_put_in_metres_on_the_gripper_pixels() {
    let tmp = tempfile::tempdir().unwrap();
    let model = MonocularDepth::load(
        &red_channel_depth_model(tmp.path()),
        DepthOutput::Disparity,
        None,
    )
    .unwrap();
    let (w, h) = (64u32, 48u32);
    // A smooth depth ramp 0.25..0.5 m, encoded in red as disparity.
    let depth_at = |x: u32, _y: u32| 0.25 + 0.25 * x as f32 / (w - 1) as f32;
    let picture = image(w, h, |x, y| {
        [(255.0 * 0.1 / depth_at(x, y) * 2.4).min(255.0) as u8, 0, 0]
    });
    // The "gripper" covers the left quarter; its model depth is the truth.
    let anchor = Plane {
        width: w as usize,
        height: h as usize,
        data: (0..w * h)
            .map(|i| {
                if i % w < w / 4 {
                    depth_at(i % w, i / w)
                } else {
                    0.0
                }
            })
            .collect(),
    };
    let capture_free =
        omniscan_mask::depth::disparity_to_metres(&model.raw(&picture).unwrap(), &anchor).unwrap();
    // Red is quantised to bytes, so compare with the depth the bytes encode.
    let mut worst = 0f32;
    for y in 0..h {
        for x in 2..w - 2 {
            let red = picture.data[3 * (y * w + x) as usize] as f32;
            let encoded = 255.0 * 0.1 * 2.4 / red;
            worst = worst.max((capture_free.at(x as usize, y as usize) - encoded).abs() / encoded);
        }
    }
    assert!(worst < 0.02, "largest relative depth error {worst}");
}

/// A "flow network" at half resolution: dx = red of the first image, dy =
/// green of the second, in output pixels.
fn half_resolution_flow_model(dir: &Path) -> PathBuf {
    let mut g = Graph::new("tiny_flow");
    let mut weights = vec![0f32; 2 * 6];
    weights[0] = 1.0; // out 0 <- first image, red
    weights[6 + 4] = 1.0; // out 1 <- second image, green
    g.input("image1", ElementType::Float, nchw(3, open("h"), open("w")))
        .input("image2", ElementType::Float, nchw(3, open("h"), open("w")))
        .output("flow", ElementType::Float, nchw(2, open("h2"), open("w2")))
        .constant("w", &[2, 6, 1, 1], weights)
        .constant("b", &[2], vec![0.0, 0.0])
        .node(
            "Concat",
            &["image1", "image2"],
            &["both"],
            vec![("axis", Attribute::Int(1))],
        )
        .node("Conv", &["both", "w", "b"], &["full"], vec![])
        .node(
            "AveragePool",
            &["full"],
            &["flow"],
            vec![
                ("kernel_shape", Attribute::Ints(vec![2, 2])),
                ("strides", Attribute::Ints(vec![2, 2])),
            ],
        );
    write(dir, "flow.onnx", &g)
}

#[test]
#[ignore = "needs ONNX Runtime (ORT_DYLIB_PATH)"]
fn a_flow_network_is_fed_two_images_and_its_output_rescaled_to_image_pixels() {
    let tmp = tempfile::tempdir().unwrap();
    let flow = OnnxFlow::load(
        &half_resolution_flow_model(tmp.path()),
        FlowInputRange::Bytes,
        None,
    )
    .unwrap();
    // 30x20 is padded to 32x24 for the network, whose output is 16x12.
    let first = image(30, 20, |_, _| [10, 0, 0]);
    let second = image(30, 20, |_, _| [0, 20, 0]);
    let field = flow.flow(&first, &second).unwrap();
    assert_eq!((field.dx.width, field.dx.height), (30, 20));
    for i in 0..field.dx.len() {
        assert!(
            (field.dx.data[i] - 10.0 * 30.0 / 16.0).abs() < 1e-3,
            "dx {}",
            field.dx.data[i]
        );
        assert!(
            (field.dy.data[i] - 20.0 * 20.0 / 12.0).abs() < 1e-3,
            "dy {}",
            field.dy.data[i]
        );
        assert!(field.valid.data[i]);
    }
    // A different value range reaches the network.
    let unit = OnnxFlow::load(&tmp.path().join("flow.onnx"), FlowInputRange::Unit, None).unwrap();
    let field = unit.flow(&first, &second).unwrap();
    assert!((field.dx.data[0] - 10.0 / 255.0 * 30.0 / 16.0).abs() < 1e-4);
    // A file that is not an ONNX model is refused with its name.
    let garbage = tmp.path().join("garbage.onnx");
    std::fs::write(&garbage, b"not a model").unwrap();
    let err = OnnxFlow::load(&garbage, FlowInputRange::Bytes, None).unwrap_err();
    assert!(err.to_string().contains("garbage.onnx"), "{err}");
    // Images of different sizes are an error, not a panic.
    assert!(flow.flow(&first, &image(20, 20, |_, _| [0; 3])).is_err());
}

/// A Segment Anything pair for `width`x`height` images with a 64-pixel
/// encoder: the embedding is (red − blue) of the normalised image, and the
/// decoder returns it, cropped to the image and scaled, as the mask logits
/// for any prompt.
fn red_object_sam(dir: &Path, width: i64, height: i64) -> (PathBuf, PathBuf) {
    let mut encoder = Graph::new("tiny_sam_encoder");
    encoder
        .input(
            "image",
            ElementType::Float,
            nchw(3, Dim::Fixed(64), Dim::Fixed(64)),
        )
        .output(
            "image_embeddings",
            ElementType::Float,
            nchw(1, Dim::Fixed(64), Dim::Fixed(64)),
        )
        .constant("w", &[1, 3, 1, 1], vec![1.0, 0.0, -1.0])
        .constant("b", &[1], vec![0.0])
        .node("Conv", &["image", "w", "b"], &["image_embeddings"], vec![]);
    let mut decoder = Graph::new("tiny_sam_decoder");
    let rows = height * 64 / width.max(height);
    let cols = width * 64 / width.max(height);
    decoder
        .input(
            "image_embeddings",
            ElementType::Float,
            nchw(1, Dim::Fixed(64), Dim::Fixed(64)),
        )
        .input(
            "point_coords",
            ElementType::Float,
            vec![Dim::Fixed(1), open("n"), Dim::Fixed(2)],
        )
        .input(
            "point_labels",
            ElementType::Float,
            vec![Dim::Fixed(1), open("n")],
        )
        .input(
            "mask_input",
            ElementType::Float,
            nchw(1, Dim::Fixed(256), Dim::Fixed(256)),
        )
        .input("has_mask_input", ElementType::Float, vec![Dim::Fixed(1)])
        .input("orig_im_size", ElementType::Float, vec![Dim::Fixed(2)])
        .output(
            "masks",
            ElementType::Float,
            nchw(1, Dim::Fixed(height), Dim::Fixed(width)),
        )
        .output(
            "iou_predictions",
            ElementType::Float,
            vec![Dim::Fixed(1), Dim::Fixed(1)],
        )
        .constant_int64("starts", &[2], vec![0, 0])
        .constant_int64("ends", &[2], vec![rows, cols])
        .constant_int64("axes", &[2], vec![2, 3])
        .constant(
            "scales",
            &[4],
            vec![
                1.0,
                1.0,
                height as f32 / rows as f32,
                width as f32 / cols as f32,
            ],
        )
        .constant("gain", &[], vec![4.0])
        .constant("iou", &[1, 1], vec![0.95])
        .node(
            "Slice",
            &["image_embeddings", "starts", "ends", "axes"],
            &["valid"],
            vec![],
        )
        .node(
            "Resize",
            &["valid", "", "scales"],
            &["resized"],
            vec![("mode", Attribute::Text("nearest".into()))],
        )
        .node("Mul", &["resized", "gain"], &["masks"], vec![])
        .node("Identity", &["iou"], &["iou_predictions"], vec![]);
    (
        write(dir, "sam_encoder.onnx", &encoder),
        write(dir, "sam_decoder.onnx", &decoder),
    )
}

#[test]
#[ignore = "needs ONNX Runtime (ORT_DYLIB_PATH)"]
fn sam_masks_become_non_overlapping_candidates_split_at_the_gripper_edge() {
    let tmp = tempfile::tempdir().unwrap();
    let (w, h) = (64u32, 48u32);
    let (encoder, decoder) = red_object_sam(tmp.path(), w as i64, h as i64);
    let sam = SamProposer::load(&encoder, &decoder, SamSettings::default(), None).unwrap();
    // Blue background, a red object, a green patch.
    let red = |x: u32, y: u32| (12..32).contains(&x) && (8..40).contains(&y);
    let green = |x: u32, y: u32| (40..56).contains(&x) && (16..32).contains(&y);
    let picture = image(w, h, |x, y| {
        if red(x, y) {
            [230, 20, 20]
        } else if green(x, y) {
            [20, 200, 20]
        } else {
            [20, 20, 230]
        }
    });
    let n = (w * h) as usize;
    let plane = |f: &dyn Fn(u32, u32) -> bool| Plane {
        width: w as usize,
        height: h as usize,
        data: (0..n as u32).map(|i| f(i % w, i / w)).collect(),
    };
    let region = plane(&|x, _| x >= 4);
    // The "gripper" covers the lower part of the red object.
    let barrier = plane(&|_, y| y >= 30);
    let depth = Plane::filled(w as usize, h as usize, 0.4f32);
    let segmentation = sam.propose(&picture, &depth, &region, &barrier).unwrap();
    let labels = &segmentation.labels;
    // Every region pixel has a segment, nothing outside does.
    for i in 0..n {
        assert_eq!(labels.data[i] != u32::MAX, region.data[i], "pixel {i}");
    }
    // Sizes agree with the labels, and no segment crosses the barrier's edge.
    let mut counted = vec![0usize; segmentation.sizes.len()];
    let mut side = vec![None; segmentation.sizes.len()];
    for i in 0..n {
        if labels.data[i] == u32::MAX {
            continue;
        }
        let s = labels.data[i] as usize;
        counted[s] += 1;
        assert!(*side[s].get_or_insert(barrier.data[i]) == barrier.data[i]);
    }
    assert_eq!(counted, segmentation.sizes);
    // The red object above the gripper is one segment, from SAM's mask.
    let above = plane(&|x, y| red(x, y) && y < 30);
    let label = labels.data[(20 * w + 20) as usize];
    let segment = Plane {
        width: w as usize,
        height: h as usize,
        data: labels.data.iter().map(|&l| l == label).collect(),
    };
    assert!(
        iou(&segment, &above) > 0.95,
        "IoU {}",
        iou(&segment, &above)
    );
    // A decoder without SAM's inputs is refused with their names.
    let err = SamProposer::load(&encoder, &encoder, SamSettings::default(), None).unwrap_err();
    assert!(err.to_string().contains("point_coords"), "{err}");
}

#[test]
#[ignore = "needs ONNX Runtime (ORT_DYLIB_PATH)"]
fn a_capture_masks_with_learned_flow_and_candidates_and_records_them() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("capture");
    let config = SimConfig {
        object: "builtin:remote".into(),
        width: 160,
        height: 120,
        seed: 3,
        supersample: 2,
        plan: ScanPlanConfig {
            wrist_angles: 4,
            latitudes: 1,
            ..ScanPlanConfig::default()
        },
        ..SimConfig::default()
    };
    Simulation::new(config)
        .unwrap()
        .run(&dir, &|_, _| {})
        .unwrap();
    let mut capture = Capture::load(&dir).unwrap();
    let (encoder, decoder) = red_object_sam(tmp.path(), 160, 120);
    let models = LearnedModels {
        flow: Some(half_resolution_flow_model(tmp.path())),
        sam_encoder: Some(encoder),
        sam_decoder: Some(decoder),
        ..LearnedModels::default()
    };
    let masker = Masker::new(&capture, None, MaskSettings::default())
        .unwrap()
        .with_learned(&models)
        .unwrap();
    assert!(masker.settings.backends.contains("flow=onnx-flow"));
    assert!(masker.settings.backends.contains("candidates=sam"));
    mask_capture(&mut capture, &masker, &|_, _| {}).unwrap();
    let evaluation = evaluate_capture(&capture).unwrap();
    // The toy flow calls everything moving and the toy SAM sees only red, so
    // the scores do the work; the masks must still be the object's.
    assert!(
        evaluation.object_miou.left.unwrap() > 0.8,
        "{:?}",
        evaluation.object_miou
    );
    let recorded = std::fs::read_to_string(dir.join("masks/settings.json")).unwrap();
    assert!(recorded.contains("onnx-flow"), "{recorded}");
}
