//! The LPIPS metric's real loading and inference path, on a tiny network
//! with LPIPS's structure (features, channel normalisation, squared
//! difference, learned 1x1 weights, spatial mean) that this test writes as
//! ONNX and also evaluates independently. Needs ONNX Runtime's library
//! (`ORT_DYLIB_PATH`); `.ci/run` provides it.

use omniscan_onnx::graph::{Attribute, Dim, ElementType, Graph};
use omniscan_splat::lpips::Lpips;

const W1: [[f32; 3]; 4] = [
    [0.5, -0.2, 0.1],
    [-0.3, 0.8, 0.2],
    [0.1, 0.1, 0.9],
    [0.7, 0.3, -0.4],
];
const B1: [f32; 4] = [0.1, 0.2, -0.05, 0.3];
const LIN: [f32; 4] = [0.4, 0.3, 0.2, 0.6];

fn tiny_lpips(path: &std::path::Path) {
    let image = |name: &str| {
        (
            name.to_string(),
            vec![
                Dim::Fixed(1),
                Dim::Fixed(3),
                Dim::Named("h".into()),
                Dim::Named("w".into()),
            ],
        )
    };
    let mut g = Graph::new("tiny_lpips");
    for (name, dims) in [image("in0"), image("in1")] {
        g.input(&name, ElementType::Float, dims);
    }
    g.output("distance", ElementType::Float, vec![Dim::Fixed(1); 4])
        .constant("w1", &[4, 3, 1, 1], W1.iter().flatten().copied().collect())
        .constant("b1", &[4], B1.to_vec())
        .constant("lin", &[1, 4, 1, 1], LIN.to_vec())
        .constant("eps", &[], vec![1e-10]);
    for i in 0..2 {
        let x = format!("in{i}");
        let pre = format!("pre{i}");
        let feat = format!("feat{i}");
        let sq = format!("sq{i}");
        let norm = format!("norm{i}");
        let normeps = format!("normeps{i}");
        let unit = format!("unit{i}");
        g.node("Conv", &[&x, "w1", "b1"], &[&pre], vec![])
            .node("Relu", &[&pre], &[&feat], vec![])
            .node(
                "ReduceSumSquare",
                &[&feat],
                &[&sq],
                vec![
                    ("axes", Attribute::Ints(vec![1])),
                    ("keepdims", Attribute::Int(1)),
                ],
            )
            .node("Sqrt", &[&sq], &[&norm], vec![])
            .node("Add", &[&norm, "eps"], &[&normeps], vec![])
            .node("Div", &[&feat, &normeps], &[&unit], vec![]);
    }
    g.node("Sub", &["unit0", "unit1"], &["diff"], vec![])
        .node("Mul", &["diff", "diff"], &["diff2"], vec![])
        .node("Conv", &["diff2", "lin"], &["weighted"], vec![])
        .node(
            "ReduceMean",
            &["weighted"],
            &["distance"],
            vec![
                ("axes", Attribute::Ints(vec![2, 3])),
                ("keepdims", Attribute::Int(1)),
            ],
        );
    std::fs::write(path, g.to_model_bytes(17)).unwrap();
}

/// The same network in plain Rust.
fn reference(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let unit = |p: [f32; 3]| {
        let x = p.map(|v| v * 2.0 - 1.0);
        let f: Vec<f64> = (0..4)
            .map(|c| {
                ((W1[c][0] * x[0] + W1[c][1] * x[1] + W1[c][2] * x[2] + B1[c]) as f64).max(0.0)
            })
            .collect();
        let norm = f.iter().map(|v| v * v).sum::<f64>().sqrt() + 1e-10;
        f.iter().map(|v| v / norm).collect::<Vec<f64>>()
    };
    let total: f64 = a
        .iter()
        .zip(b)
        .map(|(p, q)| {
            let (u, v) = (unit(*p), unit(*q));
            (0..4)
                .map(|c| LIN[c] as f64 * (u[c] - v[c]).powi(2))
                .sum::<f64>()
        })
        .sum();
    total / a.len() as f64
}

#[test]
#[ignore = "needs ONNX Runtime (ORT_DYLIB_PATH)"]
fn lpips_runs_the_users_network_on_whole_and_masked_images() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("lpips.onnx");
    tiny_lpips(&path);
    let net = Lpips::load(&path, None).unwrap();
    let (w, h) = (20, 15);
    let a: Vec<[f32; 3]> = (0..w * h)
        .map(|i| [(i % w) as f32 / w as f32, (i / w) as f32 / h as f32, 0.3])
        .collect();
    // `b` differs from `a` in the left half only.
    let b: Vec<[f32; 3]> = a
        .iter()
        .enumerate()
        .map(|(i, p)| {
            if i % w < w / 2 {
                [p[2], p[0], p[1]]
            } else {
                *p
            }
        })
        .collect();
    assert!(net.distance(&a, &a, w, h, None).unwrap().abs() < 1e-7);
    let d = net.distance(&a, &b, w, h, None).unwrap();
    let expected = reference(&a, &b);
    assert!(d > 1e-3, "different images are apart ({d})");
    assert!(
        (d - expected).abs() < 1e-5 * expected.max(1e-3),
        "{d} vs {expected}"
    );
    // Masking out the differing half leaves nothing to tell them apart.
    let right: Vec<bool> = (0..w * h).map(|i| i % w >= w / 2).collect();
    assert!(net.distance(&a, &b, w, h, Some(&right)).unwrap().abs() < 1e-7);
    // A file that is not an LPIPS network is refused with its name.
    let garbage = tmp.path().join("garbage.onnx");
    std::fs::write(&garbage, b"no").unwrap();
    let err = Lpips::load(&garbage, None).unwrap_err();
    assert!(err.to_string().contains("garbage.onnx"), "{err}");
}
