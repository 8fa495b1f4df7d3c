//! The formats against an independent implementation: PlayCanvas'
//! `splat-transform` (pinned in `web/package.json`), which reads and writes
//! SPZ through Niantic's reference library compiled to WebAssembly, writes
//! PlayCanvas' compressed PLY and glTF `KHR_gaussian_splatting`. Each file
//! one side writes, the other reads, and the model must come back within
//! the format's quantisation: positions, covariances (quaternion
//! conventions differ between writers, the covariance they give may not),
//! opacities, base colours and every SH coefficient (whose signs carry the
//! axis conventions).

use std::path::{Path, PathBuf};
use std::process::Command;

use omniscan_splat::Splats;
use omniscan_splat::ply::{read_splats, write_splats};
use omniscan_splat::sh::coefficients;
use omniscan_splat::spz::{SpzVersion, to_spz};

fn web() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../web")
}

/// `splat-transform IN OUT [flags]`.
fn splat_transform(input: &Path, output: &Path, flags: &[&str]) {
    let tool = web().join("node_modules/.bin/splat-transform");
    let out = Command::new(&tool)
        .arg("-w")
        .arg(input)
        .args(flags)
        .arg(output)
        .current_dir(web())
        .output()
        .unwrap_or_else(|e| panic!("{}: {e}", tool.display()));
    assert!(
        out.status.success(),
        "splat-transform {} {}: {}{}",
        input.display(),
        output.display(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A model of degree 3 with no structure to hide a convention mistake.
fn model() -> Splats {
    let mut state = 12345u64;
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 33) as f64 / (1u64 << 31) as f64) as f32
    };
    let mut s = Splats {
        sh_degree: 3,
        ..Default::default()
    };
    for _ in 0..2000 {
        s.means.push([0, 1, 2].map(|_| (next() - 0.5) * 0.1));
        s.log_scales.push([0, 1, 2].map(|_| -7.0 + 3.0 * next()));
        let q = [0, 1, 2, 3].map(|_| next() - 0.5);
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        s.quats.push(q.map(|v| v / norm));
        s.opacity_logits.push(5.0 * next() - 2.0);
        for k in 0..16 {
            let spread = if k == 0 { 2.0 } else { 0.6 };
            s.sh.push([0, 1, 2].map(|_| (next() - 0.5) * spread));
        }
    }
    s
}

fn covariance(s: &Splats, i: usize) -> nalgebra::Matrix3<f64> {
    let [w, x, y, z] = s.quats[i].map(f64::from);
    let r = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z))
        .to_rotation_matrix()
        .into_inner();
    let d = nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::from(
        s.log_scales[i].map(|l| (2.0 * f64::from(l)).exp()),
    ));
    r * d * r.transpose()
}

/// Tolerances of one comparison: position (model units), relative
/// covariance, opacity, DC coefficient, higher SH coefficient.
struct Tolerance {
    position: f32,
    covariance: f64,
    opacity: f32,
    dc: f32,
    sh: f32,
}

/// `back` is `original` within `t`, splats matched by nearest position
/// (some writers reorder them).
fn assert_close(original: &Splats, back: &Splats, t: &Tolerance, what: &str) {
    assert_eq!(back.len(), original.len(), "{what}: splat count");
    let nearest = |p: &[f32; 3]| {
        (0..original.len())
            .min_by(|&a, &b| {
                let d = |i: usize| {
                    (0..3)
                        .map(|k| (original.means[i][k] - p[k]).powi(2))
                        .sum::<f32>()
                };
                d(a).total_cmp(&d(b))
            })
            .unwrap()
    };
    let k = original.sh_coefficients();
    let kb = back.sh_coefficients();
    let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
    for j in 0..back.len() {
        let i = nearest(&back.means[j]);
        for a in 0..3 {
            assert!(
                (back.means[j][a] - original.means[i][a]).abs() <= t.position,
                "{what}: position of {i}"
            );
        }
        let (ca, cb) = (covariance(original, i), covariance(back, j));
        let relative = (ca - cb).norm() / ca.norm();
        assert!(
            relative <= t.covariance,
            "{what}: covariance of {i} off by {relative:.4}"
        );
        let opacity = (sigmoid(back.opacity_logits[j]) - sigmoid(original.opacity_logits[i])).abs();
        assert!(
            opacity <= t.opacity,
            "{what}: opacity of {i} off by {opacity}"
        );
        for c in 0..kb {
            for ch in 0..3 {
                let error = (back.sh[j * kb + c][ch] - original.sh[i * k + c][ch]).abs();
                let bound = if c == 0 { t.dc } else { t.sh };
                assert!(error <= bound, "{what}: SH {c} of {i} off by {error}");
            }
        }
    }
}

const SPZ: Tolerance = Tolerance {
    position: 2.5e-4,
    covariance: 0.15,
    opacity: 0.5 / 255.0 + 1e-4,
    dc: 0.5 / (0.15 * 255.0) + 1e-4,
    // Degree 1 in 5 bits, the others in 4, of ±1 in 8-bit steps.
    sh: 8.5 / 128.0 + 1e-4,
};

/// Two decodings of the same bytes.
const SAME: Tolerance = Tolerance {
    position: 1e-6,
    covariance: 1e-3,
    opacity: 1e-5,
    dc: 1e-5,
    sh: 1e-5,
};

#[test]
#[ignore = "needs web/node_modules (npm ci in web/; .ci/run does it)"]
fn our_spz_reads_in_the_reference_library_in_every_version() {
    let tmp = tempfile::tempdir().unwrap();
    let original = model();
    for version in [SpzVersion::V2, SpzVersion::V3, SpzVersion::V4] {
        let bytes = to_spz(&original, version);
        let spz = tmp.path().join(format!("ours{}.spz", version.number()));
        omniscan_core::io::write_atomic(&spz, &bytes).unwrap();
        let ply = tmp.path().join(format!("theirs{}.ply", version.number()));
        splat_transform(&spz, &ply, &[]);
        let theirs = read_splats(&ply).unwrap();
        let what = format!("ours v{} → reference", version.number());
        // The reference decodes our file as we do, to rounding.
        let ours = omniscan_splat::spz::from_spz(&bytes).unwrap();
        assert_close(&ours, &theirs, &SAME, &what);
        // Version 2's 8-bit rotations are coarse (up to ~7° where w is
        // small); 3 and 4 keep 10 bits of the smallest three.
        let loose = Tolerance {
            covariance: if version == SpzVersion::V2 {
                0.4
            } else {
                SPZ.covariance
            },
            ..SPZ
        };
        assert_close(&original, &theirs, &loose, &what);
    }
}

#[test]
#[ignore = "needs web/node_modules (npm ci in web/; .ci/run does it)"]
fn we_read_what_splat_transform_writes() {
    let tmp = tempfile::tempdir().unwrap();
    let original = model();
    let ply = tmp.path().join("model.ply");
    write_splats(&ply, &original).unwrap();
    let cases: [(&str, &[&str], Tolerance); 4] = [
        ("v4.spz", &[], SPZ),
        ("v3.spz", &["--spz-version", "3"], SPZ),
        (
            "model.compressed.ply",
            &[],
            // 11/10/11 bits of each 256-splat chunk's range; 8-bit colour
            // and SH over ±4.
            Tolerance {
                position: 1e-4,
                covariance: 0.2,
                opacity: 0.5 / 255.0 + 1e-4,
                dc: 0.5 / (255.0 * 0.2821) * 2.0 + 0.01,
                sh: 8.0 / 256.0 + 1e-4,
            },
        ),
        (
            "model.glb",
            &[],
            Tolerance {
                position: 1e-6,
                covariance: 1e-4,
                opacity: 1e-6,
                dc: 1e-6,
                sh: 1e-6,
            },
        ),
    ];
    for (name, flags, tolerance) in cases {
        let file = tmp.path().join(name);
        splat_transform(&ply, &file, flags);
        let back = read_splats(&file).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(back.sh_degree, 3, "{name}");
        assert_close(&original, &back, &tolerance, name);
    }
    // And coefficient count is what the degree says.
    assert_eq!(coefficients(3), 16);
}
