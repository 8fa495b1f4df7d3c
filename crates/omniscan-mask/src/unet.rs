//! The paper's learned gripper segmentation ("Gripper Mask Generation": a
//! U-Net trained on labelled images), trained and run in Rust.
//!
//! Architecture: a three-level U-Net (Ronneberger et al. 2015) sized for
//! the CPU: two 3x3 convolutions with ReLU per encoder level (8, 16, 32
//! channels), 2x2 max pooling, nearest-neighbour upsampling with skip
//! concatenation, one 3x3 convolution per decoder level, a 1x1 head and a
//! sigmoid. It sees the image at a fixed working size (160x120 by default),
//! normalised as (rgb/255 − 0.5)/0.25; its probabilities are upsampled
//! bilinearly to the image. Training: binary cross-entropy on the logits
//! against the simulator's gripper masks (area-averaged to the working size,
//! so boundary pixels get soft targets), Adam, seeded He initialisation,
//! seeded mini-batches with horizontal flips and brightness jitter.
//!
//! The forward and backward passes are written here (direct convolution
//! loops, rayon over the images of a batch) because the deep-learning crates
//! that build here are either too slow to build (burn: 24 minutes) or cannot
//! train (tract runs inference only); the network is small enough that
//! plain loops train it in minutes. Gradients are checked against central
//! differences in the tests.
//!
//! File format: safetensors (the Hugging Face format, readable by PyTorch),
//! float32 tensors named `<layer>.weight` (`[out, in, k, k]`) and
//! `<layer>.bias` (`[out]`) for the layers `enc1a enc1b enc2a enc2b mid_a
//! mid_b dec2 dec1 head`, with metadata `format = omniscan-gripper-unet-v1`,
//! `input_width`, `input_height`, `channels` (e.g. `8,16,32`).

use std::collections::HashMap;
use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use omniscan_core::image_io::RgbImage;

use crate::plane::Plane;
use crate::{MaskError, Result};

/// Value of the `format` metadata entry of a saved network.
pub const FORMAT: &str = "omniscan-gripper-unet-v1";
const LAYER_NAMES: [&str; 9] = [
    "enc1a", "enc1b", "enc2a", "enc2b", "mid_a", "mid_b", "dec2", "dec1", "head",
];

/// A channels x height x width activation of one image.
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    pub channels: usize,
    pub height: usize,
    pub width: usize,
    pub data: Vec<f32>,
}

impl Tensor {
    fn zeros(channels: usize, height: usize, width: usize) -> Tensor {
        Tensor {
            channels,
            height,
            width,
            data: vec![0.0; channels * height * width],
        }
    }
    fn plane(&self) -> usize {
        self.height * self.width
    }
}

/// A 2D convolution with "same" zero padding and a bias.
#[derive(Debug, Clone, PartialEq)]
pub struct Conv {
    pub outputs: usize,
    pub inputs: usize,
    pub kernel: usize,
    /// `[outputs][inputs][kernel][kernel]`, row-major.
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
}

/// Gradients of one convolution.
#[derive(Debug, Clone, PartialEq)]
struct ConvGrad {
    weight: Vec<f32>,
    bias: Vec<f32>,
}

/// The overlap of a shifted row/column range with `0..len`: where `i` and
/// `i + shift` are both inside.
#[inline]
fn shifted_range(len: usize, shift: isize) -> std::ops::Range<usize> {
    let lo = (-shift).max(0) as usize;
    let hi = (len as isize - shift.max(0)).max(0) as usize;
    lo.min(hi)..hi
}

impl Conv {
    fn new(inputs: usize, outputs: usize, kernel: usize, rng: &mut ChaCha8Rng) -> Conv {
        // He initialisation for ReLU networks.
        let std = (2.0 / (inputs * kernel * kernel) as f64).sqrt();
        let weight = (0..outputs * inputs * kernel * kernel)
            .map(|_| (standard_normal(rng) * std) as f32)
            .collect();
        Conv {
            outputs,
            inputs,
            kernel,
            weight,
            bias: vec![0.0; outputs],
        }
    }

    #[inline]
    fn w(&self, o: usize, i: usize, ky: usize, kx: usize) -> f32 {
        self.weight[((o * self.inputs + i) * self.kernel + ky) * self.kernel + kx]
    }

    fn forward(&self, input: &Tensor) -> Tensor {
        let (h, w) = (input.height, input.width);
        let hw = h * w;
        let half = (self.kernel / 2) as isize;
        let mut out = Tensor::zeros(self.outputs, h, w);
        for (o, out_plane) in out.data.chunks_mut(hw).enumerate() {
            out_plane.fill(self.bias[o]);
            for i in 0..self.inputs {
                let in_plane = &input.data[i * hw..(i + 1) * hw];
                for ky in 0..self.kernel {
                    let dy = ky as isize - half;
                    let rows = shifted_range(h, dy);
                    for kx in 0..self.kernel {
                        let dx = kx as isize - half;
                        let cols = shifted_range(w, dx);
                        let weight = self.w(o, i, ky, kx);
                        for y in rows.clone() {
                            let src = ((y as isize + dy) as usize) * w;
                            let dst = &mut out_plane[y * w + cols.start..y * w + cols.end];
                            let from = (src as isize + cols.start as isize + dx) as usize;
                            let srow = &in_plane[from..from + cols.len()];
                            for (d, s) in dst.iter_mut().zip(srow) {
                                *d += weight * s;
                            }
                        }
                    }
                }
            }
        }
        out
    }

    /// Gradients of the weights and bias, and of the input, from the gradient of the output.
    fn backward(&self, input: &Tensor, grad_out: &Tensor) -> (Tensor, ConvGrad) {
        let (h, w) = (input.height, input.width);
        let hw = h * w;
        let half = (self.kernel / 2) as isize;
        let mut grad_in = Tensor::zeros(self.inputs, h, w);
        let mut grad = ConvGrad {
            weight: vec![0.0; self.weight.len()],
            bias: vec![0.0; self.outputs],
        };
        for o in 0..self.outputs {
            let g_plane = &grad_out.data[o * hw..(o + 1) * hw];
            grad.bias[o] = g_plane.iter().sum();
            for i in 0..self.inputs {
                let in_plane = &input.data[i * hw..(i + 1) * hw];
                let gi_plane = &mut grad_in.data[i * hw..(i + 1) * hw];
                for ky in 0..self.kernel {
                    let dy = ky as isize - half;
                    let rows = shifted_range(h, dy);
                    for kx in 0..self.kernel {
                        let dx = kx as isize - half;
                        let cols = shifted_range(w, dx);
                        let weight = self.w(o, i, ky, kx);
                        let mut dw = 0f32;
                        for y in rows.clone() {
                            let g = &g_plane[y * w + cols.start..y * w + cols.end];
                            let from = (((y as isize + dy) as usize * w) as isize
                                + cols.start as isize
                                + dx) as usize;
                            let s = &in_plane[from..from + cols.len()];
                            dw += g.iter().zip(s).map(|(a, b)| a * b).sum::<f32>();
                            let gi = &mut gi_plane[from..from + cols.len()];
                            for (d, a) in gi.iter_mut().zip(g) {
                                *d += weight * a;
                            }
                        }
                        grad.weight
                            [((o * self.inputs + i) * self.kernel + ky) * self.kernel + kx] += dw;
                    }
                }
            }
        }
        (grad_in, grad)
    }
}

fn standard_normal(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-12);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn relu(t: &mut Tensor) {
    t.data.iter_mut().for_each(|v| *v = v.max(0.0));
}

/// Zeroes the gradient where the ReLU's output was zero.
fn relu_backward(grad: &mut Tensor, output: &Tensor) {
    for (g, &o) in grad.data.iter_mut().zip(&output.data) {
        if o <= 0.0 {
            *g = 0.0;
        }
    }
}

fn max_pool(t: &Tensor) -> (Tensor, Vec<u32>) {
    let (h, w) = (t.height / 2, t.width / 2);
    let mut out = Tensor::zeros(t.channels, h, w);
    let mut argmax = vec![0u32; t.channels * h * w];
    for c in 0..t.channels {
        for y in 0..h {
            for x in 0..w {
                let mut best = (f32::NEG_INFINITY, 0usize);
                for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let i = (c * t.height + 2 * y + dy) * t.width + 2 * x + dx;
                    if t.data[i] > best.0 {
                        best = (t.data[i], i);
                    }
                }
                let o = (c * h + y) * w + x;
                out.data[o] = best.0;
                argmax[o] = best.1 as u32;
            }
        }
    }
    (out, argmax)
}

fn max_pool_backward(grad: &Tensor, argmax: &[u32], input_shape: (usize, usize, usize)) -> Tensor {
    let mut out = Tensor::zeros(input_shape.0, input_shape.1, input_shape.2);
    for (g, &i) in grad.data.iter().zip(argmax) {
        out.data[i as usize] += g;
    }
    out
}

/// Adds the gradient arriving through a max pool (`grad`, at the pooled
/// size) to `skip`, the gradient of the pool's input from the skip connection.
fn add_pool_gradient(skip: &mut Tensor, grad: &Tensor, argmax: &[u32]) {
    let pooled = max_pool_backward(grad, argmax, (skip.channels, skip.height, skip.width));
    for (a, b) in skip.data.iter_mut().zip(&pooled.data) {
        *a += b;
    }
}

fn upsample(t: &Tensor) -> Tensor {
    let (h, w) = (t.height * 2, t.width * 2);
    let mut out = Tensor::zeros(t.channels, h, w);
    for c in 0..t.channels {
        for y in 0..h {
            for x in 0..w {
                out.data[(c * h + y) * w + x] = t.data[(c * t.height + y / 2) * t.width + x / 2];
            }
        }
    }
    out
}

fn upsample_backward(grad: &Tensor) -> Tensor {
    let (h, w) = (grad.height / 2, grad.width / 2);
    let mut out = Tensor::zeros(grad.channels, h, w);
    for c in 0..grad.channels {
        for y in 0..grad.height {
            for x in 0..grad.width {
                out.data[(c * h + y / 2) * w + x / 2] +=
                    grad.data[(c * grad.height + y) * grad.width + x];
            }
        }
    }
    out
}

fn concat(a: &Tensor, b: &Tensor) -> Tensor {
    let mut data = a.data.clone();
    data.extend_from_slice(&b.data);
    Tensor {
        channels: a.channels + b.channels,
        height: a.height,
        width: a.width,
        data,
    }
}

fn split(t: &Tensor, first: usize) -> (Tensor, Tensor) {
    let n = first * t.plane();
    (
        Tensor {
            channels: first,
            height: t.height,
            width: t.width,
            data: t.data[..n].to_vec(),
        },
        Tensor {
            channels: t.channels - first,
            height: t.height,
            width: t.width,
            data: t.data[n..].to_vec(),
        },
    )
}

/// The activations of one forward pass, kept for the backward pass.
struct Activations {
    input: Tensor,
    a1: Tensor,
    s1: Tensor,
    p1: Tensor,
    pool1: Vec<u32>,
    a2: Tensor,
    s2: Tensor,
    p2: Tensor,
    pool2: Vec<u32>,
    a3: Tensor,
    s3: Tensor,
    c2: Tensor,
    d2: Tensor,
    c1: Tensor,
    d1: Tensor,
    logits: Tensor,
}

/// The gripper U-Net.
#[derive(Debug, Clone, PartialEq)]
pub struct UNet {
    /// Working size the image is resized to; both multiples of 4.
    pub input_width: usize,
    pub input_height: usize,
    /// Channels of the three levels.
    pub channels: [usize; 3],
    /// In the order of the module doc's layer names.
    pub layers: Vec<Conv>,
}

/// Bounds on a U-Net's working size (pixels a side) and channel counts,
/// far above any use (the default works at 160x120 with 8, 16, 32 channels).
const MAX_SIDE: usize = 4096;
const MAX_CHANNELS: usize = 1024;

impl UNet {
    /// A freshly initialised network (seeded).
    pub fn new(
        input_width: usize,
        input_height: usize,
        channels: [usize; 3],
        seed: u64,
    ) -> Result<UNet> {
        if !input_width.is_multiple_of(4)
            || !input_height.is_multiple_of(4)
            || input_width < 8
            || input_height < 8
        {
            return Err(MaskError::Invalid(format!(
                "the U-Net's working size must be multiples of 4 and at least 8, got {input_width}x{input_height}"
            )));
        }
        // Sizes come from a network file's metadata too: a damaged one
        // (input_height 2⁴⁰) made the first image's buffers abort the
        // process on a failed allocation.
        if input_width > MAX_SIDE || input_height > MAX_SIDE {
            return Err(MaskError::Invalid(format!(
                "the U-Net's working size is at most {MAX_SIDE} pixels a side, got {input_width}x{input_height}"
            )));
        }
        if channels.iter().any(|&c| c == 0 || c > MAX_CHANNELS) {
            return Err(MaskError::Invalid(format!(
                "the U-Net's channel counts must be at least 1 and at most {MAX_CHANNELS}, got {channels:?}"
            )));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let [c1, c2, c3] = channels;
        let shapes = [
            (3, c1, 3),
            (c1, c1, 3),
            (c1, c2, 3),
            (c2, c2, 3),
            (c2, c3, 3),
            (c3, c3, 3),
            (c3 + c2, c2, 3),
            (c2 + c1, c1, 3),
            (c1, 1, 1),
        ];
        let layers = shapes
            .iter()
            .map(|&(i, o, k)| Conv::new(i, o, k, &mut rng))
            .collect();
        Ok(UNet {
            input_width,
            input_height,
            channels,
            layers,
        })
    }

    /// Network input from an image: resized to the working size by area
    /// averaging, normalised.
    pub fn input(&self, image: &RgbImage) -> Tensor {
        let mut t = area_resized(image, self.input_width, self.input_height);
        t.data
            .iter_mut()
            .for_each(|v| *v = (*v / 255.0 - 0.5) / 0.25);
        t
    }

    fn forward(&self, input: Tensor) -> Activations {
        let l = &self.layers;
        let mut a1 = l[0].forward(&input);
        relu(&mut a1);
        let mut s1 = l[1].forward(&a1);
        relu(&mut s1);
        let (p1, pool1) = max_pool(&s1);
        let mut a2 = l[2].forward(&p1);
        relu(&mut a2);
        let mut s2 = l[3].forward(&a2);
        relu(&mut s2);
        let (p2, pool2) = max_pool(&s2);
        let mut a3 = l[4].forward(&p2);
        relu(&mut a3);
        let mut s3 = l[5].forward(&a3);
        relu(&mut s3);
        let c2 = concat(&upsample(&s3), &s2);
        let mut d2 = l[6].forward(&c2);
        relu(&mut d2);
        let c1 = concat(&upsample(&d2), &s1);
        let mut d1 = l[7].forward(&c1);
        relu(&mut d1);
        let logits = l[8].forward(&d1);
        Activations {
            input,
            a1,
            s1,
            p1,
            pool1,
            a2,
            s2,
            p2,
            pool2,
            a3,
            s3,
            c2,
            d2,
            c1,
            d1,
            logits,
        }
    }

    /// Logits at the working size.
    pub fn logits(&self, input: Tensor) -> Tensor {
        self.forward(input).logits
    }

    /// Gripper probability per pixel of `image`, at the image's size.
    pub fn probabilities(&self, image: &RgbImage) -> Plane<f32> {
        let logits = self.logits(self.input(image));
        let small = Plane {
            width: logits.width,
            height: logits.height,
            data: logits.data.iter().map(|&z| sigmoid(z)).collect(),
        };
        to_image_size(&small, image)
    }

    /// The gripper mask of `image` (probability ≥ 0.5).
    pub fn mask(&self, image: &RgbImage) -> Plane<bool> {
        threshold(&self.probabilities(image))
    }

    /// Mean binary cross-entropy of the logits against `target` (0..1 per
    /// working-size pixel), and the gradient of every layer.
    fn loss_and_gradients(&self, input: Tensor, target: &[f32]) -> (f64, Vec<ConvGrad>) {
        let act = self.forward(input);
        let n = target.len() as f32;
        let mut loss = 0f64;
        let mut grad = Tensor::zeros(1, act.logits.height, act.logits.width);
        for ((g, &z), &y) in grad.data.iter_mut().zip(&act.logits.data).zip(target) {
            loss += (z.max(0.0) - z * y + (-z.abs()).exp().ln_1p()) as f64;
            *g = (sigmoid(z) - y) / n;
        }
        let l = &self.layers;
        let mut grads: Vec<Option<ConvGrad>> = vec![None; 9];
        let (mut g, gw) = l[8].backward(&act.d1, &grad);
        grads[8] = Some(gw);
        relu_backward(&mut g, &act.d1);
        let (g_c1, gw) = l[7].backward(&act.c1, &g);
        grads[7] = Some(gw);
        let (g_up1, mut g_s1) = split(&g_c1, act.d2.channels);
        let mut g = upsample_backward(&g_up1);
        relu_backward(&mut g, &act.d2);
        let (g_c2, gw) = l[6].backward(&act.c2, &g);
        grads[6] = Some(gw);
        let (g_up2, mut g_s2) = split(&g_c2, act.s3.channels);
        let mut g = upsample_backward(&g_up2);
        relu_backward(&mut g, &act.s3);
        let (mut g, gw) = l[5].backward(&act.a3, &g);
        grads[5] = Some(gw);
        relu_backward(&mut g, &act.a3);
        let (g_p2, gw) = l[4].backward(&act.p2, &g);
        grads[4] = Some(gw);
        add_pool_gradient(&mut g_s2, &g_p2, &act.pool2);
        relu_backward(&mut g_s2, &act.s2);
        let (mut g, gw) = l[3].backward(&act.a2, &g_s2);
        grads[3] = Some(gw);
        relu_backward(&mut g, &act.a2);
        let (g_p1, gw) = l[2].backward(&act.p1, &g);
        grads[2] = Some(gw);
        add_pool_gradient(&mut g_s1, &g_p1, &act.pool1);
        relu_backward(&mut g_s1, &act.s1);
        let (mut g, gw) = l[1].backward(&act.a1, &g_s1);
        grads[1] = Some(gw);
        relu_backward(&mut g, &act.a1);
        let (_, gw) = l[0].backward(&act.input, &g);
        grads[0] = Some(gw);
        (
            loss / n as f64,
            grads.into_iter().map(|g| g.expect("every layer")).collect(),
        )
    }

    /// Writes the network as safetensors (see the module doc), atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut bytes: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
        for (name, layer) in LAYER_NAMES.iter().zip(&self.layers) {
            let to_bytes = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
            bytes.push((
                format!("{name}.weight"),
                vec![layer.outputs, layer.inputs, layer.kernel, layer.kernel],
                to_bytes(&layer.weight),
            ));
            bytes.push((
                format!("{name}.bias"),
                vec![layer.outputs],
                to_bytes(&layer.bias),
            ));
        }
        let views = bytes
            .iter()
            .map(|(name, shape, data)| {
                safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape.clone(), data)
                    .map(|v| (name.clone(), v))
            })
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|e| MaskError::file(path, format!("cannot encode the network: {e}")))?;
        let metadata = HashMap::from([
            ("format".to_string(), FORMAT.to_string()),
            ("input_width".to_string(), self.input_width.to_string()),
            ("input_height".to_string(), self.input_height.to_string()),
            (
                "channels".to_string(),
                self.channels.map(|c| c.to_string()).join(","),
            ),
        ]);
        let encoded = safetensors::serialize(views, Some(metadata))
            .map_err(|e| MaskError::file(path, format!("cannot encode the network: {e}")))?;
        omniscan_core::io::write_atomic(path, &encoded)?;
        Ok(())
    }

    /// Reads a network written by [`UNet::save`], checking every shape.
    pub fn load(path: &Path) -> Result<UNet> {
        let bytes = std::fs::read(path).map_err(|e| omniscan_core::CoreError::io(path, e))?;
        let bad = |message: String| MaskError::file(path, message);
        let (_, metadata) = safetensors::SafeTensors::read_metadata(&bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let info = metadata.metadata().clone().unwrap_or_default();
        if info.get("format").map(String::as_str) != Some(FORMAT) {
            return Err(bad(format!(
                "not an omniscan gripper U-Net (metadata `format` is {:?}, expected {FORMAT:?})",
                info.get("format")
            )));
        }
        let number = |key: &str| -> Result<usize> {
            info.get(key)
                .and_then(|v| v.parse().ok())
                .ok_or_else(|| bad(format!("metadata `{key}` is missing or not a number")))
        };
        let (input_width, input_height) = (number("input_width")?, number("input_height")?);
        let channels: Vec<usize> = info
            .get("channels")
            .map(|c| c.split(',').filter_map(|v| v.trim().parse().ok()).collect())
            .unwrap_or_default();
        let channels: [usize; 3] = channels
            .try_into()
            .map_err(|_| bad("metadata `channels` must be three numbers, e.g. 8,16,32".into()))?;
        let mut net =
            UNet::new(input_width, input_height, channels, 0).map_err(|e| bad(e.to_string()))?;
        let tensors = safetensors::SafeTensors::deserialize(&bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        for (name, layer) in LAYER_NAMES.iter().zip(net.layers.iter_mut()) {
            let read = |key: String, shape: Vec<usize>| -> Result<Vec<f32>> {
                let view = tensors
                    .tensor(&key)
                    .map_err(|_| bad(format!("tensor `{key}` is missing")))?;
                if view.dtype() != safetensors::Dtype::F32 || view.shape() != shape.as_slice() {
                    return Err(bad(format!(
                        "tensor `{key}` is {:?} {:?}, expected F32 {shape:?}",
                        view.dtype(),
                        view.shape()
                    )));
                }
                let values: Vec<f32> = view
                    .data()
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect();
                if values.iter().any(|v| !v.is_finite()) {
                    return Err(bad(format!("tensor `{key}` holds NaN or infinite values")));
                }
                Ok(values)
            };
            layer.weight = read(
                format!("{name}.weight"),
                vec![layer.outputs, layer.inputs, layer.kernel, layer.kernel],
            )?;
            layer.bias = read(format!("{name}.bias"), vec![layer.outputs])?;
        }
        Ok(net)
    }
}

impl UNet {
    /// The network as an ONNX model (operator set 17), so that other tools
    /// (Python onnxruntime, and [`OnnxGripperNet`] here) can run it. Input
    /// `rgb`: `[1, 3, input_height, input_width]`, float, 0..255, the image
    /// area-averaged to the working size (the normalisation is inside the
    /// graph). Outputs `logits` and `probability`, `[1, 1, input_height,
    /// input_width]`. Metadata as in the safetensors file.
    pub fn to_onnx(&self) -> Vec<u8> {
        use crate::onnx::graph::{Attribute, Dim, ElementType, Graph};
        let (w, h) = (self.input_width as i64, self.input_height as i64);
        let shape = |c: i64| vec![Dim::Fixed(1), Dim::Fixed(c), Dim::Fixed(h), Dim::Fixed(w)];
        let mut g = Graph::new("omniscan_gripper_unet");
        g.input("rgb", ElementType::Float, shape(3))
            .output("logits", ElementType::Float, shape(1))
            .output("probability", ElementType::Float, shape(1))
            .metadata("format", FORMAT)
            .metadata("input_width", &self.input_width.to_string())
            .metadata("input_height", &self.input_height.to_string())
            .metadata("channels", &self.channels.map(|c| c.to_string()).join(","))
            // (rgb/255 - 0.5)/0.25 = rgb/63.75 - 2
            .constant("norm_scale", &[], vec![1.0 / 63.75])
            .constant("norm_shift", &[], vec![2.0])
            .constant("upsample_scales", &[4], vec![1.0, 1.0, 2.0, 2.0])
            .node("Mul", &["rgb", "norm_scale"], &["rgb_scaled"], vec![])
            .node("Sub", &["rgb_scaled", "norm_shift"], &["input"], vec![]);
        for (name, layer) in LAYER_NAMES.iter().zip(&self.layers) {
            let k = layer.kernel as i64;
            g.constant(
                &format!("{name}.weight"),
                &[layer.outputs as i64, layer.inputs as i64, k, k],
                layer.weight.clone(),
            )
            .constant(
                &format!("{name}.bias"),
                &[layer.outputs as i64],
                layer.bias.clone(),
            );
        }
        let conv = |g: &mut Graph, layer: &str, from: &str, to: &str, relu: bool| {
            let k = self.layers[LAYER_NAMES.iter().position(|n| *n == layer).unwrap_or(0)].kernel
                as i64;
            let pad = k / 2;
            let conv_out = if relu {
                format!("{to}_pre")
            } else {
                to.to_string()
            };
            g.node(
                "Conv",
                &[from, &format!("{layer}.weight"), &format!("{layer}.bias")],
                &[&conv_out],
                vec![
                    ("kernel_shape", Attribute::Ints(vec![k, k])),
                    ("pads", Attribute::Ints(vec![pad; 4])),
                ],
            );
            if relu {
                g.node("Relu", &[&conv_out], &[to], vec![]);
            }
        };
        let pool = |g: &mut Graph, from: &str, to: &str| {
            g.node(
                "MaxPool",
                &[from],
                &[to],
                vec![
                    ("kernel_shape", Attribute::Ints(vec![2, 2])),
                    ("strides", Attribute::Ints(vec![2, 2])),
                ],
            );
        };
        // Nearest-neighbour doubling with output pixel y taking input y/2.
        let up_concat = |g: &mut Graph, from: &str, skip: &str, to: &str| {
            let up = format!("{from}_up");
            g.node(
                "Resize",
                &[from, "", "upsample_scales"],
                &[&up],
                vec![
                    ("mode", Attribute::Text("nearest".into())),
                    (
                        "coordinate_transformation_mode",
                        Attribute::Text("asymmetric".into()),
                    ),
                    ("nearest_mode", Attribute::Text("floor".into())),
                ],
            )
            .node(
                "Concat",
                &[&up, skip],
                &[to],
                vec![("axis", Attribute::Int(1))],
            );
        };
        conv(&mut g, "enc1a", "input", "a1", true);
        conv(&mut g, "enc1b", "a1", "s1", true);
        pool(&mut g, "s1", "p1");
        conv(&mut g, "enc2a", "p1", "a2", true);
        conv(&mut g, "enc2b", "a2", "s2", true);
        pool(&mut g, "s2", "p2");
        conv(&mut g, "mid_a", "p2", "a3", true);
        conv(&mut g, "mid_b", "a3", "s3", true);
        up_concat(&mut g, "s3", "s2", "c2");
        conv(&mut g, "dec2", "c2", "d2", true);
        up_concat(&mut g, "d2", "s1", "c1");
        conv(&mut g, "dec1", "c1", "d1", true);
        conv(&mut g, "head", "d1", "logits", false);
        g.node("Sigmoid", &["logits"], &["probability"], vec![]);
        g.to_model_bytes(17)
    }
}

/// A gripper network exported by [`UNet::to_onnx`] (or any model with the
/// same input and output), run by ONNX Runtime.
#[derive(Debug)]
pub struct OnnxGripperNet {
    pub model: crate::onnx::OnnxModel,
    pub input_width: usize,
    pub input_height: usize,
}

impl OnnxGripperNet {
    pub fn load(path: &Path, runtime: Option<&Path>) -> Result<OnnxGripperNet> {
        let model = crate::onnx::OnnxModel::load(path, runtime)?;
        let dims = model
            .input("rgb")
            .map(|i| i.dims.clone())
            .unwrap_or_default();
        let (input_height, input_width) = match dims.as_slice() {
            [1, 3, h, w] if *h > 0 && *w > 0 => (*h as usize, *w as usize),
            _ => {
                return Err(MaskError::file(
                    path,
                    format!(
                        "a gripper network needs an input `rgb` of fixed shape [1, 3, H, W]; this model's inputs are {:?}",
                        model.inputs
                    ),
                ));
            }
        };
        if !model.outputs.iter().any(|o| o.name == "probability") {
            return Err(MaskError::file(
                path,
                "a gripper network needs an output `probability`",
            ));
        }
        Ok(OnnxGripperNet {
            model,
            input_width,
            input_height,
        })
    }

    /// Gripper probability per pixel of `image`, at the image's size.
    pub fn probabilities(&self, image: &RgbImage) -> Result<Plane<f32>> {
        let (w, h) = (self.input_width, self.input_height);
        let input = area_resized(image, w, h);
        let outputs = self.model.run(vec![(
            "rgb".into(),
            crate::onnx::Input::float(&[1, 3, h as i64, w as i64], input.data),
        )])?;
        let probability = crate::onnx::pick_output(&outputs, &["probability"], 0)
            .filter(|o| o.data.len() == w * h)
            .ok_or_else(|| {
                MaskError::file(
                    &self.model.path,
                    format!("output `probability` is not [1, 1, {h}, {w}]"),
                )
            })?;
        let small = Plane {
            width: w,
            height: h,
            data: probability.data.clone(),
        };
        Ok(to_image_size(&small, image))
    }
}

/// A gripper segmentation network: ours run in Rust, or an ONNX file.
#[derive(Debug)]
pub enum GripperNet {
    Native(UNet),
    Onnx(OnnxGripperNet),
}

impl GripperNet {
    /// Reads `path`: an ONNX model when it ends in `.onnx`, else our
    /// safetensors file.
    pub fn load(path: &Path, runtime: Option<&Path>) -> Result<GripperNet> {
        if path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("onnx"))
        {
            Ok(GripperNet::Onnx(OnnxGripperNet::load(path, runtime)?))
        } else {
            Ok(GripperNet::Native(UNet::load(path)?))
        }
    }

    /// The gripper mask of `image` (probability ≥ 0.5).
    pub fn mask(&self, image: &RgbImage) -> Result<Plane<bool>> {
        match self {
            GripperNet::Native(net) => Ok(net.mask(image)),
            GripperNet::Onnx(net) => Ok(threshold(&net.probabilities(image)?)),
        }
    }
}

/// The source pixels `lo..hi` that output pixel `i` of `out` averages when
/// `src` pixels are resized to `out` (at least one).
fn source_span(i: usize, out: usize, src: usize) -> (usize, usize) {
    let lo = i * src / out;
    (lo, ((i + 1) * src / out).max(lo + 1))
}

/// The image at `w`x`h` by area averaging, channels first, values 0..255.
fn area_resized(image: &RgbImage, w: usize, h: usize) -> Tensor {
    let mut t = Tensor::zeros(3, h, w);
    let (iw, ih) = (image.width as usize, image.height as usize);
    for y in 0..h {
        let (y0, y1) = source_span(y, h, ih);
        for x in 0..w {
            let (x0, x1) = source_span(x, w, iw);
            let mut sum = [0f32; 3];
            for sy in y0..y1 {
                for sx in x0..x1 {
                    let p = 3 * (sy * iw + sx);
                    for c in 0..3 {
                        sum[c] += image.data[p + c] as f32;
                    }
                }
            }
            let n = ((y1 - y0) * (x1 - x0)) as f32;
            for c in 0..3 {
                t.data[(c * h + y) * w + x] = sum[c] / n;
            }
        }
    }
    t
}

/// Working-size probabilities resampled bilinearly to `image`'s size.
fn to_image_size(small: &Plane<f32>, image: &RgbImage) -> Plane<f32> {
    crate::onnx::resampled(
        &small.data,
        small.width,
        small.height,
        image.width as usize,
        image.height as usize,
    )
}

fn threshold(p: &Plane<f32>) -> Plane<bool> {
    Plane {
        width: p.width,
        height: p.height,
        data: p.data.iter().map(|&v| v >= 0.5).collect(),
    }
}

#[inline]
fn sigmoid(z: f32) -> f32 {
    1.0 / (1.0 + (-z).exp())
}

/// One labelled example at the network's working size.
#[derive(Debug, Clone)]
pub struct Example {
    pub input: Tensor,
    /// Gripper share of each working-size pixel, 0..1.
    pub target: Vec<f32>,
}

impl Example {
    /// From an image and its gripper mask (both at image size).
    pub fn new(net: &UNet, image: &RgbImage, mask: &Plane<bool>) -> Example {
        let (w, h) = (net.input_width, net.input_height);
        let (iw, ih) = (mask.width, mask.height);
        let mut target = vec![0f32; w * h];
        for y in 0..h {
            let (y0, y1) = source_span(y, h, ih);
            for x in 0..w {
                let (x0, x1) = source_span(x, w, iw);
                let mut set = 0;
                for sy in y0..y1 {
                    for sx in x0..x1 {
                        set += mask.at(sx, sy) as usize;
                    }
                }
                target[y * w + x] = set as f32 / ((y1 - y0) * (x1 - x0)) as f32;
            }
        }
        Example {
            input: net.input(image),
            target,
        }
    }

    /// Mirrored left-right, brightness scaled (augmentation).
    fn augmented(&self, flip: bool, gain: f32) -> Example {
        let (c, h, w) = (self.input.channels, self.input.height, self.input.width);
        let mut input = self.input.clone();
        let mut target = self.target.clone();
        for ch in 0..c {
            for y in 0..h {
                for x in 0..w {
                    let src = if flip { w - 1 - x } else { x };
                    // Normalised value of gain · rgb.
                    let v = self.input.data[(ch * h + y) * w + src];
                    input.data[(ch * h + y) * w + x] = ((v * 0.25 + 0.5) * gain - 0.5) / 0.25;
                }
            }
        }
        if flip {
            for y in 0..h {
                for x in 0..w {
                    target[y * w + x] = self.target[y * w + w - 1 - x];
                }
            }
        }
        Example { input, target }
    }
}

/// Training settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct TrainSettings {
    pub steps: usize,
    pub batch: usize,
    pub learning_rate: f32,
    pub seed: u64,
}

impl Default for TrainSettings {
    fn default() -> Self {
        TrainSettings {
            steps: 800,
            batch: 8,
            learning_rate: 3e-3,
            seed: 0,
        }
    }
}

/// Adam state for every layer.
struct Adam {
    m: Vec<(Vec<f32>, Vec<f32>)>,
    v: Vec<(Vec<f32>, Vec<f32>)>,
    t: i32,
}

impl Adam {
    fn new(net: &UNet) -> Adam {
        let zeros = || {
            net.layers
                .iter()
                .map(|l| (vec![0.0; l.weight.len()], vec![0.0; l.bias.len()]))
                .collect()
        };
        Adam {
            m: zeros(),
            v: zeros(),
            t: 0,
        }
    }

    fn step(&mut self, net: &mut UNet, grads: &[ConvGrad], lr: f32) {
        const B1: f32 = 0.9;
        const B2: f32 = 0.999;
        self.t += 1;
        let c1 = 1.0 - B1.powi(self.t);
        let c2 = 1.0 - B2.powi(self.t);
        let update = |p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]| {
            for i in 0..p.len() {
                m[i] = B1 * m[i] + (1.0 - B1) * g[i];
                v[i] = B2 * v[i] + (1.0 - B2) * g[i] * g[i];
                p[i] -= lr * (m[i] / c1) / ((v[i] / c2).sqrt() + 1e-8);
            }
        };
        for (k, layer) in net.layers.iter_mut().enumerate() {
            let (mw, mb) = &mut self.m[k];
            let (vw, vb) = &mut self.v[k];
            update(&mut layer.weight, &grads[k].weight, mw, vw);
            update(&mut layer.bias, &grads[k].bias, mb, vb);
        }
    }
}

/// Trains `net` on `examples`; `progress(step, loss)` after every step.
/// Returns the mean loss of the last tenth of the steps.
pub fn train(
    net: &mut UNet,
    examples: &[Example],
    settings: &TrainSettings,
    progress: &(dyn Fn(usize, f64) + Sync),
) -> Result<f64> {
    if examples.is_empty() {
        return Err(MaskError::Invalid("no training examples".into()));
    }
    for e in examples {
        if (e.input.width, e.input.height) != (net.input_width, net.input_height) {
            return Err(MaskError::Invalid(format!(
                "a training example is {}x{} but the network works at {}x{}",
                e.input.width, e.input.height, net.input_width, net.input_height
            )));
        }
    }
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed ^ 0x0b5e55ed);
    let mut adam = Adam::new(net);
    let mut recent = Vec::new();
    for step in 0..settings.steps {
        let batch: Vec<(usize, bool, f32)> = (0..settings.batch.max(1))
            .map(|_| {
                (
                    rng.random_range(0..examples.len()),
                    rng.random::<bool>(),
                    rng.random_range(0.75f32..1.25),
                )
            })
            .collect();
        let results: Vec<(f64, Vec<ConvGrad>)> = batch
            .par_iter()
            .map(|&(i, flip, gain)| {
                let e = examples[i].augmented(flip, gain);
                net.loss_and_gradients(e.input, &e.target)
            })
            .collect();
        let n = results.len() as f32;
        let mut total = results[0].1.clone();
        for (_, g) in &results[1..] {
            for (t, l) in total.iter_mut().zip(g) {
                t.weight
                    .iter_mut()
                    .zip(&l.weight)
                    .for_each(|(a, b)| *a += b);
                t.bias.iter_mut().zip(&l.bias).for_each(|(a, b)| *a += b);
            }
        }
        for t in &mut total {
            t.weight.iter_mut().for_each(|a| *a /= n);
            t.bias.iter_mut().for_each(|a| *a /= n);
        }
        // Cosine decay to a tenth keeps the last steps from bouncing.
        let progress_share = step as f32 / settings.steps.max(1) as f32;
        let lr =
            settings.learning_rate * (0.55 + 0.45 * (std::f32::consts::PI * progress_share).cos());
        adam.step(net, &total, lr);
        let loss = results.iter().map(|r| r.0).sum::<f64>() / n as f64;
        if step * 10 >= settings.steps * 9 {
            recent.push(loss);
        }
        progress(step + 1, loss);
    }
    Ok(recent.iter().sum::<f64>() / recent.len().max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny_image(w: usize, h: usize, seed: u64) -> (RgbImage, Plane<bool>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (cx, cy) = (
            rng.random_range(0.3..0.7) * w as f32,
            rng.random_range(0.3..0.7) * h as f32,
        );
        let mut data = Vec::with_capacity(w * h * 3);
        let mut mask = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let inside = (x as f32 - cx).abs() < w as f32 * 0.2
                    && (y as f32 - cy).abs() < h as f32 * 0.25;
                let noise: u8 = rng.random_range(0..40);
                let px = if inside {
                    [30 + noise, 30 + noise, 35 + noise]
                } else {
                    [150 + noise, 140, 110 + noise]
                };
                data.extend_from_slice(&px);
                mask.push(inside);
            }
        }
        (
            RgbImage {
                width: w as u32,
                height: h as u32,
                data,
            },
            Plane {
                width: w,
                height: h,
                data: mask,
            },
        )
    }

    /// Central differences in f32. A step can cross a ReLU or max-pool
    /// switch (then the difference quotient is off by ~10%), so several steps
    /// are tried and one must agree to 1%; a wrong gradient agrees with none.
    #[test]
    fn gradients_match_central_differences() {
        let net = UNet::new(8, 8, [2, 3, 4], 7).unwrap();
        let image = RgbImage {
            width: 8,
            height: 8,
            data: (0..192).map(|i| ((i * 37) % 200) as u8).collect(),
        };
        let mask = Plane {
            width: 8,
            height: 8,
            data: (0..64).map(|i| i % 8 < 4).collect(),
        };
        let example = Example::new(&net, &image, &mask);
        let (_, grads) = net.loss_and_gradients(example.input.clone(), &example.target);
        let loss_with = |net: &UNet| {
            net.loss_and_gradients(example.input.clone(), &example.target)
                .0
        };
        let agrees = |perturb: &dyn Fn(&mut UNet, f32), analytic: f64| -> bool {
            [3e-3f32, 1e-3, 3e-4, 1e-4].iter().any(|&eps| {
                let mut plus = net.clone();
                perturb(&mut plus, eps);
                let mut minus = net.clone();
                perturb(&mut minus, -eps);
                let numeric = (loss_with(&plus) - loss_with(&minus)) / (2.0 * eps as f64);
                (numeric - analytic).abs() <= 1e-2 * numeric.abs().max(analytic.abs()) + 2e-5
            })
        };
        let mut checked = 0;
        for (k, layer) in net.layers.iter().enumerate() {
            for index in [0, layer.weight.len() / 2, layer.weight.len() - 1] {
                let analytic = grads[k].weight[index] as f64;
                assert!(
                    agrees(&|n, e| n.layers[k].weight[index] += e, analytic),
                    "layer {k} weight {index}: analytic {analytic}"
                );
                checked += 1;
            }
            let analytic = grads[k].bias[0] as f64;
            assert!(
                agrees(&|n, e| n.layers[k].bias[0] += e, analytic),
                "layer {k} bias: analytic {analytic}"
            );
            checked += 1;
        }
        assert_eq!(checked, 36);
        // A deliberately wrong gradient is caught.
        let wrong = grads[4].weight[0] as f64 * 1.1 + 1e-3;
        assert!(!agrees(&|n, e| n.layers[4].weight[0] += e, wrong));
    }

    #[test]
    fn learns_a_dark_block_and_round_trips_through_its_file() {
        let mut net = UNet::new(32, 24, [4, 8, 8], 3).unwrap();
        let examples: Vec<Example> = (0..12)
            .map(|s| {
                let (img, mask) = tiny_image(64, 48, s);
                Example::new(&net, &img, &mask)
            })
            .collect();
        let before = examples
            .iter()
            .map(|e| net.loss_and_gradients(e.input.clone(), &e.target).0)
            .sum::<f64>();
        let settings = TrainSettings {
            steps: 150,
            batch: 4,
            learning_rate: 1e-2,
            seed: 1,
        };
        let final_loss = train(&mut net, &examples, &settings, &|_, _| {}).unwrap();
        let after = examples
            .iter()
            .map(|e| net.loss_and_gradients(e.input.clone(), &e.target).0)
            .sum::<f64>();
        assert!(
            after < 0.3 * before,
            "loss {before} -> {after} (last steps {final_loss})"
        );
        let (img, truth) = tiny_image(64, 48, 99);
        let iou = crate::plane::iou(&net.mask(&img), &truth);
        assert!(iou > 0.8, "held-out IoU {iou}");

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("unet.safetensors");
        net.save(&path).unwrap();
        let loaded = UNet::load(&path).unwrap();
        assert_eq!(loaded, net);
        // Same seed, same network.
        let mut again = UNet::new(32, 24, [4, 8, 8], 3).unwrap();
        train(&mut again, &examples, &settings, &|_, _| {}).unwrap();
        assert_eq!(again, net);

        // Broken files are errors naming the file.
        std::fs::write(&path, b"not a network").unwrap();
        let e = UNet::load(&path).unwrap_err().to_string();
        assert!(
            e.contains("unet.safetensors") && e.contains("safetensors"),
            "{e}"
        );
        let other = safetensors::serialize(
            Vec::<(String, safetensors::tensor::TensorView)>::new(),
            None,
        )
        .unwrap();
        std::fs::write(&path, other).unwrap();
        let e = UNet::load(&path).unwrap_err().to_string();
        assert!(e.contains("not an omniscan gripper U-Net"), "{e}");
        // Damaged sizes in the metadata: errors, before the first image's
        // buffers (2⁴⁰ rows aborted the process on a failed allocation).
        for (height, channels) in [("1099511627776", "4,8,8"), ("24", "4,8,100000000")] {
            let metadata = [
                ("format", FORMAT),
                ("input_width", "32"),
                ("input_height", height),
                ("channels", channels),
            ]
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .into_iter()
            .collect();
            let file = safetensors::serialize(
                Vec::<(String, safetensors::tensor::TensorView)>::new(),
                Some(metadata),
            )
            .unwrap();
            std::fs::write(&path, file).unwrap();
            let e = UNet::load(&path).unwrap_err().to_string();
            assert!(
                e.contains("unet.safetensors") && e.contains("at most"),
                "{e}"
            );
        }
        assert!(UNet::new(32, 24, [4, 0, 8], 0).is_err());
    }
}
