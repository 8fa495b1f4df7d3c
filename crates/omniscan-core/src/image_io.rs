//! Image files of a capture: RGB images (PNG or JPEG), 8-bit masks (255 = in),
//! 16-bit depth PNGs in millimetres (0 = no measurement). Readers check the
//! pixel format and name the file in every error.

use std::path::Path;

pub use image::ColorType;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder, ImageReader};

use crate::error::{CoreError, Result};

/// Depth unit of depth PNGs: one count is one millimetre.
pub const DEPTH_METRES_PER_UNIT: f64 = 0.001;

/// An 8-bit RGB image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

/// A binary mask, row-major, one byte per pixel: 0 = out, 255 = in.
#[derive(Debug, Clone, PartialEq)]
pub struct Mask {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl Mask {
    pub fn new(width: u32, height: u32) -> Self {
        Mask {
            width,
            height,
            data: vec![0; (width * height) as usize],
        }
    }
    pub fn get(&self, x: u32, y: u32) -> bool {
        self.data[(y * self.width + x) as usize] >= 128
    }
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&v| v >= 128).count()
    }
}

/// A depth map in millimetres, 0 = no measurement.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMm {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u16>,
}

impl DepthMm {
    /// Depth in metres at a pixel, `None` where there is no measurement.
    pub fn metres(&self, x: u32, y: u32) -> Option<f64> {
        let v = self.data[(y * self.width + x) as usize];
        (v != 0).then_some(v as f64 * DEPTH_METRES_PER_UNIT)
    }
}

/// Width, height and colour type of an image file, read from its header only.
pub fn probe(path: &Path) -> Result<(u32, u32, ColorType)> {
    let reader = ImageReader::open(path)
        .map_err(|e| CoreError::io(path, e))?
        .with_guessed_format()
        .map_err(|e| CoreError::io(path, e))?;
    use image::ImageDecoder;
    let decoder = reader
        .into_decoder()
        .map_err(|e| CoreError::image(path, format!("cannot decode image: {e}")))?;
    let (w, h) = decoder.dimensions();
    Ok((w, h, decoder.color_type()))
}

/// Decodes the whole image and drops it: what a header [`probe`] cannot
/// tell, a truncated file or a damaged chunk (PNG's CRCs are checked).
pub fn check_decodes(path: &Path) -> Result<()> {
    open(path).map(drop)
}

fn open(path: &Path) -> Result<image::DynamicImage> {
    ImageReader::open(path)
        .map_err(|e| CoreError::io(path, e))?
        .with_guessed_format()
        .map_err(|e| CoreError::io(path, e))?
        .decode()
        .map_err(|e| CoreError::image(path, format!("cannot decode image: {e}")))
}

/// Reads an RGB image (alpha, if any, is dropped; grey is expanded).
pub fn read_rgb(path: &Path) -> Result<RgbImage> {
    let img = open(path)?.into_rgb8();
    Ok(RgbImage {
        width: img.width(),
        height: img.height(),
        data: img.into_raw(),
    })
}

/// Reads an image as [`read_rgb`] does and, when it has an alpha channel,
/// that channel as a mask (8-bit; values >= 128 count as in, as in
/// [`read_mask`]): Blender's NeRF sets keep the object's mask there.
pub fn read_rgb_and_alpha(path: &Path) -> Result<(RgbImage, Option<Mask>)> {
    let img = open(path)?;
    let alpha = img.color().has_alpha().then(|| {
        let rgba = img.to_rgba8();
        Mask {
            width: rgba.width(),
            height: rgba.height(),
            data: rgba.pixels().map(|p| p[3]).collect(),
        }
    });
    let rgb = img.into_rgb8();
    Ok((
        RgbImage {
            width: rgb.width(),
            height: rgb.height(),
            data: rgb.into_raw(),
        },
        alpha,
    ))
}

/// Reads an 8-bit single-channel mask; values >= 128 count as in.
pub fn read_mask(path: &Path) -> Result<Mask> {
    let img = open(path)?;
    if img.color() != ColorType::L8 {
        return Err(CoreError::image(
            path,
            format!(
                "a mask must be an 8-bit greyscale PNG, found {:?}",
                img.color()
            ),
        ));
    }
    let img = img.into_luma8();
    Ok(Mask {
        width: img.width(),
        height: img.height(),
        data: img.into_raw(),
    })
}

/// Reads a 16-bit depth PNG in millimetres.
pub fn read_depth(path: &Path) -> Result<DepthMm> {
    let img = open(path)?;
    if img.color() != ColorType::L16 {
        return Err(CoreError::image(
            path,
            format!(
                "a depth map must be a 16-bit greyscale PNG in millimetres, found {:?}",
                img.color()
            ),
        ));
    }
    let img = img.into_luma16();
    Ok(DepthMm {
        width: img.width(),
        height: img.height(),
        data: img.into_raw(),
    })
}

fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    bytes: &[u8],
    color: ExtendedColorType,
) -> Result<()> {
    crate::io::write_atomic_with(path, |file| {
        let encoder =
            PngEncoder::new_with_quality(file, CompressionType::Fast, FilterType::Adaptive);
        encoder
            .write_image(bytes, width, height, color)
            .map_err(std::io::Error::other)
    })
}

/// An RGB image as PNG bytes (for pages that carry their pictures inside).
pub fn rgb_png_bytes(image: &RgbImage) -> Vec<u8> {
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Adaptive)
        .write_image(
            &image.data,
            image.width,
            image.height,
            ExtendedColorType::Rgb8,
        )
        .expect("encoding a well-formed RGB image to memory cannot fail");
    out
}

/// Writes an RGB PNG atomically.
pub fn write_rgb(path: &Path, image: &RgbImage) -> Result<()> {
    write_png(
        path,
        image.width,
        image.height,
        &image.data,
        ExtendedColorType::Rgb8,
    )
}

/// Writes an 8-bit mask PNG atomically.
pub fn write_mask(path: &Path, mask: &Mask) -> Result<()> {
    write_png(
        path,
        mask.width,
        mask.height,
        &mask.data,
        ExtendedColorType::L8,
    )
}

/// Writes a 16-bit depth PNG (millimetres) atomically.
pub fn write_depth(path: &Path, depth: &DepthMm) -> Result<()> {
    // The encoder takes native-endian samples and writes PNG big-endian itself.
    let bytes: Vec<u8> = depth.data.iter().flat_map(|v| v.to_ne_bytes()).collect();
    write_png(
        path,
        depth.width,
        depth.height,
        &bytes,
        ExtendedColorType::L16,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_format_checks() {
        let dir = tempfile::tempdir().unwrap();
        let rgb = RgbImage {
            width: 3,
            height: 2,
            data: (0..18).collect(),
        };
        let mask = Mask {
            width: 3,
            height: 2,
            data: vec![0, 255, 0, 255, 255, 0],
        };
        let depth = DepthMm {
            width: 3,
            height: 2,
            data: vec![0, 1, 500, 1000, 65535, 300],
        };
        write_rgb(&dir.path().join("a.png"), &rgb).unwrap();
        write_mask(&dir.path().join("m.png"), &mask).unwrap();
        write_depth(&dir.path().join("d.png"), &depth).unwrap();
        assert_eq!(read_rgb(&dir.path().join("a.png")).unwrap(), rgb);
        assert_eq!(read_mask(&dir.path().join("m.png")).unwrap(), mask);
        assert_eq!(read_depth(&dir.path().join("d.png")).unwrap(), depth);
        assert_eq!(
            probe(&dir.path().join("d.png")).unwrap(),
            (3, 2, ColorType::L16)
        );
        // Wrong formats are refused with the file named.
        let err = read_depth(&dir.path().join("m.png"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("m.png") && err.contains("16-bit"), "{err}");
        let err = read_mask(&dir.path().join("a.png"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("8-bit"), "{err}");
        std::fs::write(dir.path().join("bad.png"), b"not a png").unwrap();
        assert!(
            read_rgb(&dir.path().join("bad.png"))
                .unwrap_err()
                .to_string()
                .contains("bad.png")
        );
        assert!(
            read_rgb(&dir.path().join("missing.png"))
                .unwrap_err()
                .to_string()
                .contains("missing.png")
        );
    }
}
