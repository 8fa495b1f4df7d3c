//! Niantic's SPZ, the common compressed splat format (about a tenth of the
//! PLY's size), read in all its versions and written as version 4 (the
//! current one) or 3 and 2 for older readers.
//!
//! Layout, from Niantic's reference library (`nianticlabs/spz`, MIT), which
//! holds the format's only specification: a 16-byte header (magic `NGSP`,
//! version, count, SH degree, fractional bits, flags), then per attribute,
//! all splats at once: positions as 24-bit fixed point (version 1: half
//! floats), opacities after the sigmoid in a byte, DC colours as
//! `dc·0.15·255 + 127.5`, log-scales as `(ln s + 10)·16`, rotations (v2: the
//! `xyz` of the quaternion with `w ≥ 0`, a byte each; v3 and later: the
//! smallest three in 10 bits each and the index of the largest in 2), and
//! the higher SH bands as `128 + 128·c`, coefficient major, channel minor.
//! Versions 1 to 3 gzip the whole stream; version 4 has a 32-byte plain
//! header with a table of contents and one zstd frame per attribute.
//!
//! SPZ is defined in the RUB axes of OpenGL and three.js; a 3DGS PLY is
//! taken to be in COLMAP's RDF axes, as the reference library and
//! PlayCanvas' `splat-transform` take it. The change is a half turn about
//! x: positions and quaternion vectors flip `y` and `z`, and each SH
//! coefficient flips with the parity of its basis function
//! ([`rdf_rub_sh_signs`]). So PLY → SPZ → PLY returns the model where it was,
//! and an SPZ from another tool opens the same way up as its PLY.
//!
//! Written here rather than taken from a crate: the format is a few hundred
//! lines, the Rust ports on crates.io follow older versions, and the
//! conformance test is against the reference library itself (through
//! `splat-transform`, which runs it compiled to WebAssembly).

use std::io::Read;

use crate::Splats;
use crate::sh::{basis, coefficients};

const MAGIC: u32 = 0x5053_474e;
const COLOR_SCALE: f32 = 0.15;
const FLAG_ANTIALIASED: u8 = 0x1;
const FLAG_EXTENSIONS: u8 = 0x2;
/// The reference reader's bound, kept so a corrupt count cannot ask for
/// gigabytes.
const MAX_SPLATS: usize = 10_000_000;
const EXTENSION_SH_QUANTIZATION: u32 = 0xADBE_0001;
const EXTENSION_SAFE_ORBIT: u32 = 0xADBE_0002;

/// The SPZ version to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SpzVersion {
    /// gzip, rotations as three bytes (readers from 2024).
    V2,
    /// gzip, smallest-three rotations (readers from early 2025).
    V3,
    /// zstd per attribute (the reference library's current version).
    V4,
}

impl SpzVersion {
    pub fn number(self) -> u32 {
        match self {
            SpzVersion::V2 => 2,
            SpzVersion::V3 => 3,
            SpzVersion::V4 => 4,
        }
    }
}

/// Header fields shared by every version.
struct Header {
    version: u32,
    count: usize,
    sh_degree: usize,
    fractional_bits: u32,
    flags: u8,
}

/// The attribute arrays as they lie in the file.
#[derive(Default)]
struct Packed {
    positions: Vec<u8>,
    alphas: Vec<u8>,
    colors: Vec<u8>,
    scales: Vec<u8>,
    rotations: Vec<u8>,
    sh: Vec<u8>,
}

/// Per coefficient `k ≥ 1` of the 3DGS basis, the sign it takes under the
/// RDF ↔ RUB change (y → −y, z → −z): the basis function's parity.
pub fn rdf_rub_sh_signs(degree: usize) -> Vec<f32> {
    let d = [0.267f64, 0.534, 0.801];
    let flipped = [d[0], -d[1], -d[2]];
    let (b, f) = (basis(degree, d), basis(degree, flipped));
    b.iter()
        .zip(&f)
        .skip(1)
        .map(|(a, c)| if (a * c) < 0.0 { -1.0 } else { 1.0 })
        .collect()
}

/// The model as an SPZ file. Models whose SH depend on the splat's normal
/// (the fixed-rig appearance) keep their base colour only: other viewers
/// would read their bands as view-dependent colour.
pub fn to_spz(s: &Splats, version: SpzVersion) -> Vec<u8> {
    let degree = if s.appearance == crate::raster::Appearance::ViewDirection {
        s.sh_degree
    } else {
        0
    };
    let fractional_bits = fractional_bits_for(s);
    let packed = pack(s, degree, fractional_bits, version);
    let flags = if s.antialiased { FLAG_ANTIALIASED } else { 0 };
    let mut head = Vec::with_capacity(32);
    head.extend(MAGIC.to_le_bytes());
    head.extend(version.number().to_le_bytes());
    head.extend((s.len() as u32).to_le_bytes());
    head.extend([degree as u8, fractional_bits as u8, flags]);
    let streams = [
        &packed.positions,
        &packed.alphas,
        &packed.colors,
        &packed.scales,
        &packed.rotations,
        &packed.sh,
    ];
    if version != SpzVersion::V4 {
        head.push(0);
        let mut raw = head;
        for stream in streams {
            raw.extend_from_slice(stream);
        }
        return gzip(&raw);
    }
    // The reference writer leaves the SH stream out at degree 0.
    let streams = if degree == 0 {
        &streams[..5]
    } else {
        &streams[..]
    };
    head.push(streams.len() as u8);
    head.extend(32u32.to_le_bytes());
    head.resize(32, 0);
    let frames: Vec<Vec<u8>> = streams.iter().map(|s| zstd_frame(s)).collect();
    for (frame, stream) in frames.iter().zip(streams) {
        head.extend((frame.len() as u64).to_le_bytes());
        head.extend((stream.len() as u64).to_le_bytes());
    }
    for frame in frames {
        head.extend(frame);
    }
    head
}

/// The fractional bits of the positions: the reference's 12 (0.24 mm
/// steps in metres) unless the splats are small enough that a step would
/// show, then enough for a step of a sixteenth of the median splat's size;
/// never more than keeps every coordinate within the 24-bit range.
fn fractional_bits_for(s: &Splats) -> u32 {
    let extent = s
        .means
        .iter()
        .flatten()
        .fold(0f64, |m, v| m.max(f64::from(v.abs())));
    let range_bits = 23 - (extent + 1.0).log2().ceil().max(0.0) as i64;
    let mut sizes: Vec<f32> = s
        .log_scales
        .iter()
        .map(|l| (l.iter().sum::<f32>() / 3.0).exp())
        .collect();
    let median = if sizes.is_empty() {
        1.0
    } else {
        let middle = sizes.len() / 2;
        *sizes.select_nth_unstable_by(middle, f32::total_cmp).1
    };
    let wanted = (16.0 / f64::from(median).max(1e-9)).log2().ceil() as i64;
    wanted.clamp(12, 20).min(range_bits).max(0) as u32
}

fn pack(s: &Splats, degree: usize, fractional_bits: u32, version: SpzVersion) -> Packed {
    let n = s.len();
    let k = s.sh_coefficients();
    let signs = rdf_rub_sh_signs(degree);
    let flip = [1.0f32, -1.0, -1.0];
    let step = (1u32 << fractional_bits) as f32;
    let mut p = Packed::default();
    for i in 0..n {
        for a in 0..3 {
            let fixed = (flip[a] * s.means[i][a] * step).round() as i32;
            p.positions.extend(&fixed.to_le_bytes()[..3]);
            p.colors
                .push(to_byte(s.sh[i * k][a] * COLOR_SCALE * 255.0 + 127.5));
            p.scales.push(to_byte((s.log_scales[i][a] + 10.0) * 16.0));
        }
        p.alphas.push(to_byte(sigmoid(s.opacity_logits[i]) * 255.0));
        let [w, x, y, z] = s.quats[i];
        let xyzw = [x, -y, -z, w];
        match version {
            SpzVersion::V2 => p.rotations.extend(pack_first_three(xyzw)),
            _ => p.rotations.extend(pack_smallest_three(xyzw)),
        }
        for kk in 1..coefficients(degree) {
            for ch in 0..3 {
                let bucket = if kk < 4 { 8 } else { 16 };
                let v = signs[kk - 1] * s.sh[i * k + kk][ch];
                let q = (v * 128.0).round() as i32 + 128;
                let q = (q + bucket / 2) / bucket * bucket;
                p.sh.push(q.clamp(0, 255) as u8);
            }
        }
    }
    p
}

fn to_byte(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

fn normalized(q: [f32; 4]) -> [f32; 4] {
    let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
    q.map(|v| v / norm)
}

fn pack_first_three(xyzw: [f32; 4]) -> [u8; 3] {
    let q = normalized(xyzw);
    let sign = if q[3] < 0.0 { -1.0 } else { 1.0 };
    [0, 1, 2].map(|a| to_byte(sign * q[a] * 127.5 + 127.5))
}

fn pack_smallest_three(xyzw: [f32; 4]) -> [u8; 4] {
    let q = normalized(xyzw);
    let largest = (0..4)
        .max_by(|&a, &b| q[a].abs().total_cmp(&q[b].abs()).then(b.cmp(&a)))
        .unwrap_or(3);
    let negate = q[largest] < 0.0;
    let mut word = largest as u32;
    for (a, v) in q.iter().enumerate() {
        if a != largest {
            let sign = u32::from((*v < 0.0) ^ negate);
            let magnitude = (511.0 * v.abs() * std::f32::consts::SQRT_2 + 0.5).min(511.0) as u32;
            word = (word << 10) | (sign << 9) | magnitude;
        }
    }
    word.to_le_bytes()
}

fn unpack_first_three(b: &[u8]) -> [f32; 4] {
    let xyz = [b[0], b[1], b[2]].map(|v| f32::from(v) / 127.5 - 1.0);
    let w = (1.0 - xyz.iter().map(|v| v * v).sum::<f32>())
        .max(0.0)
        .sqrt();
    [xyz[0], xyz[1], xyz[2], w]
}

fn unpack_smallest_three(b: &[u8]) -> [f32; 4] {
    let mut word = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    let largest = (word >> 30) as usize;
    let mut q = [0f32; 4];
    let mut sum = 0.0;
    for a in (0..4).rev() {
        if a != largest {
            let magnitude = (word & 511) as f32 / 511.0 * std::f32::consts::FRAC_1_SQRT_2;
            let negative = (word >> 9) & 1 == 1;
            q[a] = if negative { -magnitude } else { magnitude };
            sum += q[a] * q[a];
            word >>= 10;
        }
    }
    q[largest] = (1.0 - sum).max(0.0).sqrt();
    q
}

fn gzip(raw: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut encoder = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::new(6));
    encoder
        .write_all(raw)
        .expect("writing to a Vec cannot fail");
    encoder.finish().expect("writing to a Vec cannot fail")
}

/// Level 12, as the reference writer's: the streams are small enough that
/// the time is tens of milliseconds for a million splats' attributes.
fn zstd_frame(raw: &[u8]) -> Vec<u8> {
    zstd::bulk::compress(raw, 12).expect("compressing a buffer in memory cannot fail")
}

/// Reads an SPZ file of any version (1 to 4), back into the PLY's axes.
pub fn from_spz(bytes: &[u8]) -> Result<Splats, String> {
    let (header, extensions, packed) = if bytes.starts_with(&[0x1f, 0x8b]) {
        read_gzipped(bytes)?
    } else if bytes.starts_with(&MAGIC.to_le_bytes()) {
        read_v4(bytes)?
    } else {
        return Err("not an SPZ file: neither gzip data nor an `NGSP` header".into());
    };
    unpack(&header, &extensions, &packed)
}

/// The SH range of the SH-quantization extension, when the file has one.
#[derive(Default)]
struct Extensions {
    sh_range: Option<(f32, f32)>,
}

fn parse_header(raw: &[u8]) -> Result<Header, String> {
    if raw.len() < 16 {
        return Err(format!(
            "truncated SPZ: the header needs 16 bytes, the file has {}",
            raw.len()
        ));
    }
    let u32_at = |i: usize| u32::from_le_bytes(raw[i..i + 4].try_into().unwrap());
    if u32_at(0) != MAGIC {
        return Err("not an SPZ file: the data does not start with `NGSP`".into());
    }
    let header = Header {
        version: u32_at(4),
        count: u32_at(8) as usize,
        sh_degree: usize::from(raw[12]),
        fractional_bits: u32::from(raw[13]),
        flags: raw[14],
    };
    if !(1..=4).contains(&header.version) {
        return Err(format!(
            "SPZ version {} is not one omniscan reads (1 to 4)",
            header.version
        ));
    }
    if header.count == 0 {
        return Err("the model has no splats (an SPZ with 0 points)".into());
    }
    if header.count > MAX_SPLATS {
        return Err(format!(
            "{} splats is more than SPZ allows ({MAX_SPLATS})",
            header.count
        ));
    }
    if header.sh_degree > 4 {
        return Err(format!(
            "SH degree {} is not an SPZ degree (0 to 4)",
            header.sh_degree
        ));
    }
    if header.fractional_bits > 23 {
        return Err(format!(
            "{} fractional bits do not fit a 24-bit coordinate",
            header.fractional_bits
        ));
    }
    Ok(header)
}

/// Bytes per splat of each attribute, in file order.
fn stream_sizes(header: &Header) -> [usize; 6] {
    let position = if header.version == 1 { 6 } else { 9 };
    let rotation = if header.version >= 3 { 4 } else { 3 };
    let sh = 3 * (coefficients(header.sh_degree) - 1);
    [position, 1, 3, 3, rotation, sh].map(|b| b * header.count)
}

fn read_gzipped(bytes: &[u8]) -> Result<(Header, Extensions, Packed), String> {
    let mut decoder = flate2::read::GzDecoder::new(bytes);
    let mut head = [0u8; 16];
    decoder
        .read_exact(&mut head)
        .map_err(|e| format!("truncated or damaged SPZ (gzip): {e}"))?;
    let header = parse_header(&head)?;
    if header.version == 4 {
        return Err("SPZ version 4 is not gzipped: the file is damaged".into());
    }
    // The rest is bounded by the header's count, plus a few bytes of
    // extensions: a gzip bomb stops there.
    let expected: usize = stream_sizes(&header).iter().sum();
    // Grown as data arrives: a header's count alone allocates nothing.
    let mut rest = Vec::with_capacity(expected.min(16 * bytes.len()));
    decoder
        .take((expected + 64) as u64)
        .read_to_end(&mut rest)
        .map_err(|e| format!("truncated or damaged SPZ (gzip): {e}"))?;
    let mut at = 0;
    let mut extensions = Extensions::default();
    if header.flags & FLAG_EXTENSIONS != 0 {
        at = read_legacy_extensions(&rest, &mut extensions);
    }
    let packed = split_streams(&header, &rest[at..])?;
    Ok((header, extensions, packed))
}

/// The extensions of versions 2 and 3: records of known types one after
/// another, the first unknown type ending them (the reference reader's
/// rule). Returns the bytes they took.
fn read_legacy_extensions(raw: &[u8], extensions: &mut Extensions) -> usize {
    let mut at = 0;
    while raw.len() >= at + 4 {
        let kind = u32::from_le_bytes(raw[at..at + 4].try_into().unwrap());
        let body = &raw[at + 4..];
        match kind {
            EXTENSION_SH_QUANTIZATION if body.len() >= 10 => {
                extensions.sh_range = Some(sh_range(&body[2..10]));
                at += 14;
            }
            EXTENSION_SAFE_ORBIT if body.len() >= 12 => at += 16,
            _ => break,
        }
    }
    at
}

fn sh_range(b: &[u8]) -> (f32, f32) {
    let f = |i: usize| f32::from_le_bytes(b[i..i + 4].try_into().unwrap());
    (f(0), f(4))
}

fn split_streams(header: &Header, raw: &[u8]) -> Result<Packed, String> {
    let sizes = stream_sizes(header);
    let expected: usize = sizes.iter().sum();
    if raw.len() < expected {
        return Err(format!(
            "truncated SPZ: {} splats need {expected} bytes of data, the file holds {}",
            header.count,
            raw.len()
        ));
    }
    if raw.len() > expected {
        return Err(format!(
            "{} bytes after the last splat's data: the header's count or degree is wrong",
            raw.len() - expected
        ));
    }
    let mut streams = Vec::with_capacity(6);
    let mut at = 0;
    for size in sizes {
        streams.push(raw[at..at + size].to_vec());
        at += size;
    }
    let mut it = streams.into_iter();
    let mut next = || it.next().unwrap_or_default();
    Ok(Packed {
        positions: next(),
        alphas: next(),
        colors: next(),
        scales: next(),
        rotations: next(),
        sh: next(),
    })
}

fn read_v4(bytes: &[u8]) -> Result<(Header, Extensions, Packed), String> {
    let header = parse_header(bytes)?;
    if header.version != 4 {
        return Err(format!(
            "an uncompressed SPZ header says version {}: only version 4 is stored so",
            header.version
        ));
    }
    if bytes.len() < 32 {
        return Err("truncated SPZ: a version 4 header needs 32 bytes".into());
    }
    let streams = usize::from(bytes[15]);
    let toc = u32::from_le_bytes(bytes[16..20].try_into().unwrap()) as usize;
    if !(5..=6).contains(&streams) || toc < 32 || toc > bytes.len() {
        return Err(format!(
            "damaged SPZ header: {streams} streams with the table at byte {toc}"
        ));
    }
    let mut extensions = Extensions::default();
    if header.flags & FLAG_EXTENSIONS != 0 {
        read_v4_extensions(&bytes[32..toc], &mut extensions)?;
    }
    let sizes = stream_sizes(&header);
    let table_end = toc + 16 * streams;
    if bytes.len() < table_end {
        return Err("truncated SPZ: the table of streams is cut off".into());
    }
    let mut at = table_end;
    let mut raw = Vec::with_capacity(sizes.iter().sum::<usize>().min(16 * bytes.len()));
    for (index, expected) in sizes.iter().enumerate() {
        if index >= streams {
            if *expected != 0 {
                return Err("the SPZ has no SH stream but its header names SH bands".into());
            }
            break;
        }
        let entry = toc + 16 * index;
        let u64_at = |i: usize| u64::from_le_bytes(bytes[i..i + 8].try_into().unwrap());
        let (compressed, size) = (u64_at(entry) as usize, u64_at(entry + 8) as usize);
        if size != *expected {
            return Err(format!(
                "SPZ stream {index} holds {size} bytes where {} splats need {expected}",
                header.count
            ));
        }
        let frame = bytes
            .get(at..at.saturating_add(compressed))
            .ok_or("truncated SPZ: a compressed stream is cut off")?;
        raw.extend(unzstd(frame, size).map_err(|e| format!("SPZ stream {index}: {e}"))?);
        at += compressed;
    }
    if at != bytes.len() {
        return Err(format!(
            "{} bytes after the last SPZ stream",
            bytes.len().saturating_sub(at)
        ));
    }
    let packed = split_streams(&header, &raw)?;
    Ok((header, extensions, packed))
}

/// Version 4's extensions: records of type, length and body, so unknown
/// ones are skipped.
fn read_v4_extensions(mut raw: &[u8], extensions: &mut Extensions) -> Result<(), String> {
    while !raw.is_empty() {
        if raw.len() < 8 {
            return Err("damaged SPZ extension record".into());
        }
        let kind = u32::from_le_bytes(raw[0..4].try_into().unwrap());
        let length = u32::from_le_bytes(raw[4..8].try_into().unwrap()) as usize;
        let body = raw
            .get(8..8 + length)
            .ok_or("truncated SPZ extension record")?;
        if kind == EXTENSION_SH_QUANTIZATION && body.len() >= 10 {
            extensions.sh_range = Some(sh_range(&body[2..10]));
        }
        raw = &raw[8 + length..];
    }
    Ok(())
}

fn unzstd(frame: &[u8], size: usize) -> Result<Vec<u8>, String> {
    // Streamed, so memory follows the data rather than the table's claim;
    // one byte more than the table says, so a longer stream shows.
    let decoder = zstd::stream::read::Decoder::with_buffer(frame)
        .map_err(|e| format!("not a zstd frame: {e}"))?;
    let mut out = Vec::with_capacity(size.min(16 * frame.len()));
    decoder
        .take(size as u64 + 1)
        .read_to_end(&mut out)
        .map_err(|e| format!("damaged or truncated zstd data: {e}"))?;
    if out.len() != size {
        return Err(format!(
            "decompressed to {} bytes where the table says {size}",
            out.len()
        ));
    }
    Ok(out)
}

fn unpack(header: &Header, extensions: &Extensions, p: &Packed) -> Result<Splats, String> {
    let n = header.count;
    let degree = header.sh_degree.min(3);
    if header.sh_degree > 3 {
        tracing::warn!("the SPZ has SH degree 4; omniscan keeps bands 0-3");
    }
    let file_coefficients = coefficients(header.sh_degree) - 1;
    let signs = rdf_rub_sh_signs(degree);
    let step = 1.0 / (1u32 << header.fractional_bits) as f32;
    let flip = [1.0f32, -1.0, -1.0];
    let (sh_min, sh_max) = extensions.sh_range.unwrap_or((-1.0, 1.0));
    let mut s = Splats {
        sh_degree: degree,
        antialiased: header.flags & FLAG_ANTIALIASED != 0,
        ..Default::default()
    };
    for i in 0..n {
        let position = |a: usize| -> f32 {
            if header.version == 1 {
                let at = 6 * i + 2 * a;
                half_to_f32(u16::from_le_bytes([p.positions[at], p.positions[at + 1]]))
            } else {
                let at = 9 * i + 3 * a;
                let b = &p.positions[at..at + 3];
                let fixed = i32::from_le_bytes([b[0], b[1], b[2], 0]) << 8 >> 8;
                fixed as f32 * step
            }
        };
        s.means.push([0, 1, 2].map(|a| flip[a] * position(a)));
        s.log_scales
            .push([0, 1, 2].map(|a| f32::from(p.scales[3 * i + a]) / 16.0 - 10.0));
        let xyzw = if header.version >= 3 {
            unpack_smallest_three(&p.rotations[4 * i..4 * i + 4])
        } else {
            unpack_first_three(&p.rotations[3 * i..3 * i + 3])
        };
        s.quats.push([xyzw[3], xyzw[0], -xyzw[1], -xyzw[2]]);
        // A byte of 0 or 255 is an opacity of exactly 0 or 1, whose logit is
        // infinite; the half-step keeps it finite.
        let alpha = (f32::from(p.alphas[i]) / 255.0).clamp(0.5 / 255.0, 254.5 / 255.0);
        s.opacity_logits.push((alpha / (1.0 - alpha)).ln());
        s.sh.push([0, 1, 2].map(|a| (f32::from(p.colors[3 * i + a]) / 255.0 - 0.5) / COLOR_SCALE));
        for kk in 1..coefficients(degree) {
            let at = 3 * (i * file_coefficients + kk - 1);
            s.sh.push([0, 1, 2].map(|ch| {
                let byte = p.sh[at + ch];
                let v = if extensions.sh_range.is_some() {
                    sh_min + f32::from(byte) / 255.0 * (sh_max - sh_min)
                } else {
                    (f32::from(byte) - 128.0) / 128.0
                };
                signs[kk - 1] * v
            }));
        }
    }
    s.validate().map_err(|e| e.to_string())?;
    Ok(s)
}

/// IEEE half to single precision (version 1's positions).
fn half_to_f32(h: u16) -> f32 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exponent = i32::from((h >> 10) & 0x1f);
    let mantissa = f32::from(h & 0x3ff);
    match exponent {
        0 => sign * mantissa * 2f32.powi(-24),
        31 => sign * f32::INFINITY,
        e => sign * (1.0 + mantissa / 1024.0) * 2f32.powi(e - 15),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(degree: usize, n: usize) -> Splats {
        crate::test_support::random_model(7, degree, n, 0.1)
    }

    /// Rotation matrices of two quaternions agree (q and −q are one rotation).
    fn same_rotation(a: [f32; 4], b: [f32; 4], tolerance: f32) -> bool {
        let (a, b) = (normalized(a), normalized(b));
        let dot: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        1.0 - dot.abs() < tolerance
    }

    #[test]
    fn round_trips_every_version_within_its_quantisation() {
        let s = model(3, 200);
        for version in [SpzVersion::V2, SpzVersion::V3, SpzVersion::V4] {
            let back = from_spz(&to_spz(&s, version)).unwrap();
            assert_eq!(back.len(), s.len());
            assert_eq!(back.sh_degree, 3);
            for i in 0..s.len() {
                for a in 0..3 {
                    // 12 fractional bits for these millimetre splats.
                    assert!((back.means[i][a] - s.means[i][a]).abs() <= 0.5 / 4096.0 + 1e-7);
                    assert!(
                        (back.log_scales[i][a] - s.log_scales[i][a]).abs() <= 1.0 / 32.0 + 1e-6
                    );
                    let dc = (back.sh[i * 16][a] - s.sh[i * 16][a]).abs();
                    assert!(dc <= 0.5 / (255.0 * COLOR_SCALE) + 1e-5, "{dc}");
                }
                let tolerance = if version == SpzVersion::V2 {
                    2e-3
                } else {
                    2e-5
                };
                assert!(
                    same_rotation(back.quats[i], s.quats[i], tolerance),
                    "{version:?}"
                );
                let alpha = |l: f32| sigmoid(l);
                assert!(
                    (alpha(back.opacity_logits[i]) - alpha(s.opacity_logits[i])).abs()
                        < 0.5 / 255.0 + 1e-5
                );
                for kk in 1..16 {
                    for ch in 0..3 {
                        let bucket = if kk < 4 { 8.0 } else { 16.0 };
                        let error = (back.sh[i * 16 + kk][ch] - s.sh[i * 16 + kk][ch]).abs();
                        assert!(
                            error <= (bucket / 2.0 + 0.5) / 128.0 + 1e-5,
                            "k {kk}: {error}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn the_file_is_in_rub_axes() {
        let mut s = model(1, 1);
        s.means[0] = [0.01, 0.02, 0.03];
        let bytes = to_spz(&s, SpzVersion::V3);
        let mut raw = Vec::new();
        flate2::read::GzDecoder::new(&bytes[..])
            .read_to_end(&mut raw)
            .unwrap();
        let step = (1u32 << raw[13]) as f32;
        let at = |a: usize| {
            i32::from_le_bytes([raw[16 + 3 * a], raw[17 + 3 * a], raw[18 + 3 * a], 0]) << 8 >> 8
        };
        assert_eq!(at(0), (0.01 * step).round() as i32);
        assert_eq!(at(1), (-0.02 * step).round() as i32);
        assert_eq!(at(2), (-0.03 * step).round() as i32);
    }

    #[test]
    fn small_splats_get_finer_positions_within_the_24_bit_range() {
        let mut s = model(0, 50);
        assert_eq!(fractional_bits_for(&s), 12);
        for l in &mut s.log_scales {
            *l = [(20e-6f32).ln(); 3];
        }
        // A step of at most a sixteenth of a 20 µm splat.
        let bits = fractional_bits_for(&s);
        assert!(0.5f32.powi(bits as i32) <= 20e-6 / 16.0, "{bits}");
        s.means[0] = [3000.0, 0.0, 0.0];
        let bits = fractional_bits_for(&s);
        assert!(3000.0 * 2f32.powi(bits as i32) < 2f32.powi(23), "{bits}");
        let back = from_spz(&to_spz(&s, SpzVersion::V4)).unwrap();
        assert!((back.means[0][0] - 3000.0).abs() < 1.0);
    }

    #[test]
    fn sh_signs_are_the_parities_of_the_basis_under_a_half_turn_about_x() {
        // Degree 1 is (y, z, x): y and z flip. Degree 2: xy, yz, 3z²−1, xz,
        // x²−y²; degree 3 by hand from the 3DGS basis.
        let signs = rdf_rub_sh_signs(3);
        let expected = [
            -1., -1., 1., //
            -1., 1., 1., -1., 1., //
            -1., 1., -1., -1., 1., -1., 1.,
        ];
        assert_eq!(signs, expected);
    }

    #[test]
    fn fixed_rig_models_keep_their_base_colour_only() {
        let mut s = model(2, 10);
        s.appearance = crate::raster::Appearance::FixedRig;
        let back = from_spz(&to_spz(&s, SpzVersion::V4)).unwrap();
        assert_eq!(back.sh_degree, 0);
        assert_eq!(back.sh.len(), 10);
    }

    #[test]
    fn bad_files_are_refused_with_the_reason() {
        let s = model(1, 20);
        let v4 = to_spz(&s, SpzVersion::V4);
        let v3 = to_spz(&s, SpzVersion::V3);
        let error = |b: &[u8]| from_spz(b).unwrap_err();
        assert!(
            error(&v4[..v4.len() - 3]).contains("truncated"),
            "{}",
            error(&v4[..v4.len() - 3])
        );
        assert!(error(&v3[..v3.len() / 2]).contains("truncated"));
        assert!(error(b"ply\nformat").contains("not an SPZ"));
        let mut unknown = v4.clone();
        unknown[4] = 9;
        assert!(error(&unknown).contains("version 9"), "{}", error(&unknown));
        let mut longer = v4.clone();
        longer.extend([0, 0]);
        assert!(error(&longer).contains("after the last"));
    }

    #[test]
    fn half_floats_decode() {
        assert_eq!(half_to_f32(0x3c00), 1.0);
        assert_eq!(half_to_f32(0xc000), -2.0);
        assert_eq!(half_to_f32(0x3555), 0.333_251_95);
        assert_eq!(half_to_f32(0x0001), 2f32.powi(-24));
    }
}
