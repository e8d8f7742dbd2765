//! RGB images (PNG, and baseline/progressive JPEG as nuScenes ships its camera images) and the camera-image pipeline of SparseOcc/OccFormer (docs/formats.md
//! §2.8): resize, crop, flip, rotate in one resampling pass, ImageNet normalisation
//! to CHW float32, and the matching post-augmentation matrix.

use crate::error::DataError;
use crate::formats::io::{read_bytes, write_atomic};
use occ_geometry::{mat3_inverse, ImageAug, Mat3, Mat4};
use rand::Rng;
use std::path::Path;

/// An 8-bit RGB image, row-major, 3 bytes per pixel.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    /// `data[(v·width + u)·3 + c]`.
    pub data: Vec<u8>,
}

impl RgbImage {
    /// A black image.
    pub fn new(width: usize, height: usize) -> Self {
        RgbImage {
            width,
            height,
            data: vec![0; width * height * 3],
        }
    }

    /// Pixel `(u, v)` (column, row); `None` outside the image.
    pub fn pixel(&self, u: usize, v: usize) -> Option<[u8; 3]> {
        if u >= self.width || v >= self.height {
            return None;
        }
        let o = (v * self.width + u) * 3;
        Some([self.data[o], self.data[o + 1], self.data[o + 2]])
    }
}

/// The largest image the readers decode: 8192 x 8192 pixels (a 192 MiB RGB buffer). A header
/// claiming more is an error naming the file, raised before anything is allocated.
pub const MAX_IMAGE_PIXELS: usize = 8192 * 8192;

/// Checks the size an image header claims against [`MAX_IMAGE_PIXELS`].
pub fn check_image_size(path: &Path, width: usize, height: usize) -> Result<(), DataError> {
    if width == 0 || height == 0 {
        return Err(DataError::Image {
            path: path.to_path_buf(),
            detail: format!("the header claims an empty {width}x{height} image"),
        });
    }
    match width.checked_mul(height) {
        Some(n) if n <= MAX_IMAGE_PIXELS => Ok(()),
        _ => Err(DataError::Image {
            path: path.to_path_buf(),
            detail: format!(
                "the header claims {width}x{height} pixels, more than the {MAX_IMAGE_PIXELS} \
                 (8192x8192) this reader decodes"
            ),
        }),
    }
}

/// Checks that a PNG or JPEG file is whole, from its structure alone (nothing decoded): a PNG's
/// chunks, each of the length it declares, up to its `IEND` chunk; a JPEG's segments and
/// entropy-coded scans up to its end-of-image marker (`FFD9`). Bytes after that end are allowed.
///
/// A file cut short (an interrupted download or copy) fails here with an error naming it. This
/// matters most for JPEG: the decoder, like browsers, fills a scan that ends early with grey and
/// reports success, so a truncated camera image would otherwise train or predict silently.
pub fn check_image_complete(bytes: &[u8], path: &Path) -> Result<(), DataError> {
    let (kind, end) = if bytes.starts_with(JPEG_START) {
        ("JPEG", jpeg_end(bytes))
    } else if bytes.starts_with(PNG_SIGNATURE) {
        ("PNG", png_end(bytes))
    } else {
        // Neither: the decoders name what is wrong.
        return Ok(());
    };
    match end {
        Some(_) => Ok(()),
        None => Err(DataError::Image {
            path: path.to_path_buf(),
            detail: format!(
                "truncated: the {kind} file ({} bytes) ends before its end-of-image {}",
                bytes.len(),
                if kind == "PNG" {
                    "chunk (IEND)"
                } else {
                    "marker (FFD9)"
                }
            ),
        }),
    }
}

const PNG_SIGNATURE: &[u8] = &[0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];

/// A JPEG's first bytes: start-of-image and the first marker's `FF` (how the readers tell it from
/// a PNG).
const JPEG_START: &[u8] = &[0xFF, 0xD8, 0xFF];

/// The offset just after a PNG's `IEND` chunk, walking the chunks by their declared lengths;
/// `None` when the file ends first.
fn png_end(bytes: &[u8]) -> Option<usize> {
    let mut at = PNG_SIGNATURE.len();
    loop {
        let len = u32::from_be_bytes(bytes.get(at..at + 4)?.try_into().ok()?) as usize;
        let kind = bytes.get(at + 4..at + 8)?;
        // Length, type, data, CRC.
        let next = at.checked_add(12)?.checked_add(len)?;
        if next > bytes.len() {
            return None;
        }
        if kind == b"IEND" {
            return Some(next);
        }
        at = next;
    }
}

/// The offset just after a JPEG's end-of-image marker: marker segments are skipped by their
/// declared lengths, and the entropy-coded data after each start-of-scan up to the next marker (an
/// `FF` followed by anything but a stuffed `00`, a restart marker `D0`-`D7` or another fill `FF`).
/// Stray bytes between segments are skipped, as decoders do. `None` when the file ends first.
fn jpeg_end(bytes: &[u8]) -> Option<usize> {
    let mut at = 2;
    loop {
        // Find the next marker: `FF` (any number of fill `FF`s) then the marker code.
        at += next_ff(bytes.get(at..)?)?;
        while *bytes.get(at)? == 0xFF {
            at += 1;
        }
        let code = *bytes.get(at)?;
        at += 1;
        match code {
            0xD9 => return Some(at),
            // Standalone markers: restart, TEM, a stray SOI.
            0xD0..=0xD8 | 0x01 => {}
            // A stuffed 00 outside a scan: not a marker.
            0x00 => {}
            _ => {
                let len = u16::from_be_bytes([*bytes.get(at)?, *bytes.get(at + 1)?]) as usize;
                at = at.checked_add(len)?;
                if at > bytes.len() {
                    return None;
                }
                if code == 0xDA {
                    // Entropy-coded data up to the next real marker.
                    loop {
                        at += next_ff(bytes.get(at..)?)?;
                        match *bytes.get(at + 1)? {
                            0x00 | 0xD0..=0xD7 | 0xFF => at += 1,
                            _ => break,
                        }
                    }
                }
            }
        }
    }
}

/// The position of the first `FF` byte.
fn next_ff(bytes: &[u8]) -> Option<usize> {
    bytes.iter().position(|&b| b == 0xFF)
}

/// The size (width, height) of a PNG or JPEG from its header alone (nothing decoded), checked
/// against [`MAX_IMAGE_PIXELS`], and the file checked whole ([`check_image_complete`]), so that a
/// dataset check finds a truncated image before training starts.
pub fn read_image_size(path: &Path) -> Result<(usize, usize), DataError> {
    let bytes = read_bytes(path)?;
    let (w, h) = if bytes.starts_with(JPEG_START) {
        let mut dec = zune_jpeg::JpegDecoder::new(std::io::Cursor::new(&bytes));
        dec.decode_headers().map_err(|e| DataError::Image {
            path: path.to_path_buf(),
            detail: format!("not a decodable JPEG: {e:?}"),
        })?;
        dec.dimensions().ok_or_else(|| DataError::Image {
            path: path.to_path_buf(),
            detail: "JPEG without a frame header".into(),
        })?
    } else {
        let mut decoder = png::Decoder::new(bytes.as_slice());
        let info = decoder.read_header_info().map_err(|e| DataError::Image {
            path: path.to_path_buf(),
            detail: e.to_string(),
        })?;
        (info.width as usize, info.height as usize)
    };
    check_image_size(path, w, h)?;
    check_image_complete(&bytes, path)?;
    Ok((w, h))
}

/// Read a camera image, PNG or JPEG (told apart by the file's magic bytes, not its name), as RGB8.
/// A missing file gives [`DataError::NotFound`] naming it; a header claiming more than
/// [`MAX_IMAGE_PIXELS`] is an error before any pixel buffer is allocated, and so is a file cut
/// short ([`check_image_complete`]).
pub fn read_image(path: &Path) -> Result<RgbImage, DataError> {
    let bytes = read_bytes(path)?;
    if bytes.starts_with(JPEG_START) {
        decode_jpeg(&bytes, path)
    } else {
        decode_png(&bytes, path)
    }
}

/// Decode JPEG bytes (grey, YCbCr or CMYK) into RGB8 (`path` is used in error messages).
pub fn decode_jpeg(bytes: &[u8], path: &Path) -> Result<RgbImage, DataError> {
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    let err = |detail: String| DataError::Image {
        path: path.to_path_buf(),
        detail,
    };
    // The decoder fills a scan cut short with grey and succeeds: refuse a truncated file first.
    check_image_complete(bytes, path)?;
    let opts = DecoderOptions::default().jpeg_set_out_colorspace(ColorSpace::RGB);
    let mut dec = zune_jpeg::JpegDecoder::new_with_options(std::io::Cursor::new(bytes), opts);
    dec.decode_headers()
        .map_err(|e| err(format!("not a decodable JPEG: {e:?}")))?;
    let (hw, hh) = dec
        .dimensions()
        .ok_or_else(|| err("JPEG without a frame header".into()))?;
    check_image_size(path, hw, hh)?;
    let data = dec
        .decode()
        .map_err(|e| err(format!("not a decodable JPEG: {e:?}")))?;
    let (width, height) = dec
        .dimensions()
        .ok_or_else(|| err("JPEG without a frame header".into()))?;
    if data.len() != width * height * 3 {
        return Err(err(format!(
            "JPEG decoded to {} bytes, expected {width}x{height}x3",
            data.len()
        )));
    }
    Ok(RgbImage {
        width,
        height,
        data,
    })
}

/// Decode a PNG (8/16-bit, grey, grey+alpha, RGB, RGBA or palette) into RGB8.
/// A missing file gives [`DataError::NotFound`] naming it.
pub fn read_png(path: &Path) -> Result<RgbImage, DataError> {
    let bytes = read_bytes(path)?;
    decode_png(&bytes, path)
}

/// Decode PNG bytes (`path` is used in error messages).
pub fn decode_png(bytes: &[u8], path: &Path) -> Result<RgbImage, DataError> {
    let err = |e: png::DecodingError| DataError::Image {
        path: path.to_path_buf(),
        detail: e.to_string(),
    };
    check_image_complete(bytes, path)?;
    let mut decoder = png::Decoder::new(bytes);
    {
        let info = decoder.read_header_info().map_err(err)?;
        check_image_size(path, info.width as usize, info.height as usize)?;
    }
    // The decoder's own allocations (rows, palette expansion, 16-bit input) stay within a few
    // times the largest RGBA image.
    decoder.set_limits(png::Limits {
        bytes: MAX_IMAGE_PIXELS * 8 + (1 << 20),
    });
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().map_err(err)?;
    let mut buf = vec![0u8; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(err)?;
    let (w, h) = (info.width as usize, info.height as usize);
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => {
            return Err(DataError::Image {
                path: path.to_path_buf(),
                detail: "palette image was not expanded".into(),
            })
        }
    };
    if info.bit_depth != png::BitDepth::Eight {
        return Err(DataError::Image {
            path: path.to_path_buf(),
            detail: format!("unsupported bit depth {:?}", info.bit_depth),
        });
    }
    let stride = info.line_size;
    if stride < w * channels || buf.len() < stride * h {
        return Err(DataError::Image {
            path: path.to_path_buf(),
            detail: "decoded buffer smaller than the image".into(),
        });
    }
    let mut data = Vec::with_capacity(w * h * 3);
    for row in 0..h {
        let line = &buf[row * stride..row * stride + w * channels];
        for px in line.chunks_exact(channels) {
            match channels {
                1 | 2 => data.extend_from_slice(&[px[0], px[0], px[0]]),
                _ => data.extend_from_slice(&px[..3]),
            }
        }
    }
    Ok(RgbImage {
        width: w,
        height: h,
        data,
    })
}

/// Encode RGB8 as PNG bytes.
pub fn encode_png(img: &RgbImage) -> Result<Vec<u8>, DataError> {
    if img.data.len() != img.width * img.height * 3 {
        return Err(DataError::InvalidArgument(format!(
            "image {}x{} needs {} bytes, has {}",
            img.width,
            img.height,
            img.width * img.height * 3,
            img.data.len()
        )));
    }
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, img.width as u32, img.height as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let e =
            |e: png::EncodingError| DataError::InvalidArgument(format!("PNG encoding failed: {e}"));
        let mut w = enc.write_header().map_err(e)?;
        w.write_image_data(&img.data).map_err(e)?;
        w.finish().map_err(e)?;
    }
    Ok(out)
}

/// Write an RGB8 PNG, atomically.
pub fn write_png(path: &Path, img: &RgbImage) -> Result<(), DataError> {
    let bytes = encode_png(img).map_err(|e| match e {
        DataError::InvalidArgument(d) => DataError::Image {
            path: path.to_path_buf(),
            detail: d,
        },
        other => other,
    })?;
    write_atomic(path, &bytes)
}

/// ImageNet mean (RGB, 0..255) used by mmdet3d/SparseOcc normalisation.
pub const IMAGENET_MEAN: [f32; 3] = [123.675, 116.28, 103.53];
/// ImageNet standard deviation (RGB, 0..255).
pub const IMAGENET_STD: [f32; 3] = [58.395, 57.12, 57.375];

/// Resample `img` through the pixel affine of `aug` (raw pixel -> output pixel): each output
/// pixel `(i, j)` takes the bilinear interpolation of the raw image at `A⁻¹·(i, j)`, with zero
/// outside the raw image (as PIL's crop/rotate padding). Image and [`ImageAug::matrix3`] agree
/// exactly by construction.
pub fn warp_image(img: &RgbImage, aug: &ImageAug) -> Result<RgbImage, DataError> {
    let m = aug.matrix3();
    let inv = mat3_inverse(&m).ok_or_else(|| {
        DataError::InvalidArgument(format!("image augmentation {aug:?} is not invertible"))
    })?;
    let (ow, oh) = (aug.out_width, aug.out_height);
    let mut out = RgbImage::new(ow, oh);
    let (w, h) = (img.width as i64, img.height as i64);
    let fetch = |x: i64, y: i64, c: usize| -> f64 {
        if x < 0 || y < 0 || x >= w || y >= h {
            0.0
        } else {
            img.data[((y * w + x) * 3) as usize + c] as f64
        }
    };
    for j in 0..oh {
        for i in 0..ow {
            let (fi, fj) = (i as f64, j as f64);
            let sx = inv[0][0] * fi + inv[0][1] * fj + inv[0][2];
            let sy = inv[1][0] * fi + inv[1][1] * fj + inv[1][2];
            if !(sx > -1.0 && sy > -1.0 && sx < w as f64 && sy < h as f64) {
                continue;
            }
            let x0 = sx.floor() as i64;
            let y0 = sy.floor() as i64;
            let ax = sx - x0 as f64;
            let ay = sy - y0 as f64;
            let o = (j * ow + i) * 3;
            for c in 0..3 {
                let v = fetch(x0, y0, c) * (1.0 - ax) * (1.0 - ay)
                    + fetch(x0 + 1, y0, c) * ax * (1.0 - ay)
                    + fetch(x0, y0 + 1, c) * (1.0 - ax) * ay
                    + fetch(x0 + 1, y0 + 1, c) * ax * ay;
                out.data[o + c] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    Ok(out)
}

/// `(x - mean) / std` per RGB channel, as a CHW float32 vector of length `3·H·W`.
pub fn normalize_chw(img: &RgbImage) -> Vec<f32> {
    let hw = img.width * img.height;
    let mut out = vec![0f32; 3 * hw];
    for (p, px) in img.data.chunks_exact(3).enumerate() {
        for c in 0..3 {
            out[c * hw + p] = (px[c] as f32 - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
        }
    }
    out
}

/// Settings of the camera-image pipeline (SparseOcc KITTI `data_config`, docs/formats.md §2.8).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImagePipelineConfig {
    /// Network input width (1280 for KITTI).
    pub out_width: usize,
    /// Network input height (384 for KITTI).
    pub out_height: usize,
    /// Training: extra resize offset range added to `out_width / W` (KITTI (-0.06, 0.11)).
    pub resize_lim: (f64, f64),
    /// Training: horizontal flip probability (0.5).
    pub flip_prob: f64,
    /// Training: rotation range in degrees (±5.4).
    pub rot_lim_deg: (f64, f64),
}

impl ImagePipelineConfig {
    /// SparseOcc / OccFormer SemanticKITTI settings.
    pub fn semantic_kitti() -> Self {
        ImagePipelineConfig {
            out_width: 1280,
            out_height: 384,
            resize_lim: (-0.06, 0.11),
            flip_prob: 0.5,
            rot_lim_deg: (-5.4, 5.4),
        }
    }

    /// Test-time transform for a `W x H` raw image: `r = out_w/W`, bottom crop (docs/formats.md §2.8).
    pub fn test_aug(&self, src_width: usize, src_height: usize) -> ImageAug {
        ImageAug::kitti_test(src_width, src_height, self.out_width, self.out_height)
    }

    /// Random training transform: `r = out_w/W + U(resize_lim)`, resized `(int(W·r), int(H·r))`,
    /// bottom-aligned crop `y0 = newH - out_h` (negative = zero padding on top),
    /// `x0 = int(U(0, max(0, newW - out_w)))`, flip with `flip_prob`, rotation `U(rot_lim)`.
    pub fn sample_train_aug<R: Rng + ?Sized>(
        &self,
        src_width: usize,
        src_height: usize,
        rng: &mut R,
    ) -> ImageAug {
        let base = self.out_width as f64 / src_width.max(1) as f64;
        let r = base + sample_uniform(rng, self.resize_lim);
        let new_w = (src_width as f64 * r) as i64;
        let new_h = (src_height as f64 * r) as i64;
        let crop_y0 = (new_h - self.out_height as i64) as f64;
        let max_x = (new_w - self.out_width as i64).max(0) as f64;
        let crop_x0 = sample_uniform(rng, (0.0, max_x)).floor();
        let flip = rng.random::<f64>() < self.flip_prob;
        let rotate_deg = sample_uniform(rng, self.rot_lim_deg);
        ImageAug {
            resize: r,
            crop_x0,
            crop_y0,
            out_width: self.out_width,
            out_height: self.out_height,
            flip,
            rotate_deg,
        }
    }
}

fn sample_uniform<R: Rng + ?Sized>(rng: &mut R, (lo, hi): (f64, f64)) -> f64 {
    if hi > lo {
        lo + (hi - lo) * rng.random::<f64>()
    } else {
        lo
    }
}

/// A network-ready image and its augmentation.
#[derive(Clone, Debug, PartialEq)]
pub struct ProcessedImage {
    /// Normalised CHW float32, `3·height·width` values.
    pub chw: Vec<f32>,
    pub width: usize,
    pub height: usize,
    /// The augmentation that produced it.
    pub aug: ImageAug,
    /// Post-augmentation 3x3 pixel affine (raw pixel -> network pixel).
    pub img_aug3: Mat3,
    /// The same as a 4x4 for [`occ_geometry::CameraView::img_aug`].
    pub img_aug: Mat4,
}

/// Apply `aug` to `img`, normalise, and return the image with its matrices.
pub fn process_image(img: &RgbImage, aug: &ImageAug) -> Result<ProcessedImage, DataError> {
    let warped = warp_image(img, aug)?;
    Ok(ProcessedImage {
        chw: normalize_chw(&warped),
        width: warped.width,
        height: warped.height,
        aug: *aug,
        img_aug3: aug.matrix3(),
        img_aug: aug.matrix4(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use occ_geometry::apply_aug3;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn pattern(w: usize, h: usize) -> RgbImage {
        let mut img = RgbImage::new(w, h);
        for v in 0..h {
            for u in 0..w {
                let o = (v * w + u) * 3;
                img.data[o] = (u * 7 % 256) as u8;
                img.data[o + 1] = (v * 13 % 256) as u8;
                img.data[o + 2] = ((u + v) % 256) as u8;
            }
        }
        img
    }

    /// A JPEG's structure by hand: an APP1 segment holding a whole thumbnail (its own FFD8 ..
    /// FFD9, as EXIF does), a scan whose data has a stuffed `FF 00`, a restart marker and fill
    /// bytes, then EOI. Only the outer EOI ends the file; every cut before it is refused.
    #[test]
    fn the_jpeg_walk_finds_the_outer_end_of_image() {
        let mut b = vec![0xFF, 0xD8];
        let thumbnail = [0xFF, 0xD8, 0xFF, 0xDA, 0x00, 0x02, 0x11, 0xFF, 0xD9];
        b.extend_from_slice(&[0xFF, 0xE1, 0x00, 2 + thumbnail.len() as u8]);
        b.extend_from_slice(&thumbnail);
        b.extend_from_slice(&[0xFF, 0xDA, 0x00, 0x04, 0x01, 0x00]);
        b.extend_from_slice(&[0x12, 0xFF, 0x00, 0x34, 0xFF, 0xD0, 0x56, 0xFF, 0xFF, 0xD9]);
        assert_eq!(jpeg_end(&b), Some(b.len()));
        let mut trailer = b.clone();
        trailer.extend_from_slice(&[0, 0, 0xFF]);
        assert_eq!(jpeg_end(&trailer), Some(b.len()));
        for keep in 0..b.len() {
            assert_eq!(jpeg_end(&b[..keep]), None, "cut to {keep} of {}", b.len());
        }
        let path = Path::new("cut.jpg");
        let e = check_image_complete(&b[..b.len() - 1], path).unwrap_err();
        assert!(e.to_string().contains("cut.jpg") && e.to_string().contains("truncated"));
        assert!(check_image_complete(&b, path).is_ok());
    }

    /// PNG chunks walked by their lengths up to IEND; a length pointing past the end is a cut.
    #[test]
    fn the_png_walk_needs_every_chunk_up_to_iend() {
        let b = encode_png(&pattern(5, 4)).unwrap();
        assert_eq!(png_end(&b), Some(b.len()));
        for keep in 0..b.len() {
            assert_eq!(png_end(&b[..keep]), None, "cut to {keep} of {}", b.len());
        }
        let mut huge = b.clone();
        // The IHDR chunk's length field, claiming 4 GiB.
        huge[8..12].copy_from_slice(&[0xFF; 4]);
        assert_eq!(png_end(&huge), None);
    }

    #[test]
    fn png_round_trip_and_errors() {
        let img = pattern(17, 9);
        let bytes = encode_png(&img).unwrap();
        assert_eq!(decode_png(&bytes, Path::new("x.png")).unwrap(), img);
        let e = decode_png(&bytes[..bytes.len() / 2], Path::new("half.png")).unwrap_err();
        assert!(e.to_string().contains("half.png"), "{e}");
        let e = read_png(Path::new("/nonexistent/dir/000000.png")).unwrap_err();
        assert!(matches!(e, DataError::NotFound { .. }));
        assert!(e.to_string().contains("000000.png"));
    }

    #[test]
    fn warp_identity_crop_and_flip_are_exact() {
        let img = pattern(40, 30);
        let id = warp_image(&img, &ImageAug::identity(40, 30)).unwrap();
        assert_eq!(id, img);
        let aug = ImageAug {
            resize: 1.0,
            crop_x0: 5.0,
            crop_y0: 3.0,
            out_width: 20,
            out_height: 10,
            flip: true,
            rotate_deg: 0.0,
        };
        let out = warp_image(&img, &aug).unwrap();
        for j in 0..10 {
            for i in 0..20 {
                assert_eq!(out.pixel(i, j), img.pixel(5 + 19 - i, 3 + j));
            }
        }
        // crop beyond the image pads with zeros
        let pad = ImageAug {
            resize: 1.0,
            crop_x0: 30.0,
            crop_y0: -2.0,
            out_width: 20,
            out_height: 10,
            flip: false,
            rotate_deg: 0.0,
        };
        let out = warp_image(&img, &pad).unwrap();
        assert_eq!(out.pixel(0, 0), Some([0, 0, 0]));
        assert_eq!(out.pixel(15, 5), Some([0, 0, 0]));
        assert_eq!(out.pixel(2, 5), img.pixel(32, 3));
    }

    #[test]
    fn warped_image_follows_matrix() {
        // a single bright pixel must land where the matrix sends it
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let cfg = ImagePipelineConfig::semantic_kitti();
        for _ in 0..10 {
            let mut img = RgbImage::new(1241, 376);
            let (pu, pv) = (
                rng.random_range(300..900usize),
                rng.random_range(150..350usize),
            );
            for dv in 0..3 {
                for du in 0..3 {
                    let o = ((pv + dv) * 1241 + pu + du) * 3;
                    img.data[o..o + 3].copy_from_slice(&[255, 255, 255]);
                }
            }
            let aug = cfg.sample_train_aug(1241, 376, &mut rng);
            let out = warp_image(&img, &aug).unwrap();
            let q = apply_aug3(&aug.matrix3(), [pu as f64 + 1.0, pv as f64 + 1.0]);
            let (qu, qv) = (q[0].round() as usize, q[1].round() as usize);
            if qu < 1280 && qv < 384 {
                assert!(out.pixel(qu, qv).unwrap()[0] > 200, "aug {aug:?}");
            }
        }
    }

    #[test]
    fn train_aug_ranges() {
        let cfg = ImagePipelineConfig::semantic_kitti();
        let mut rng = ChaCha8Rng::seed_from_u64(10);
        let mut flips = 0;
        for _ in 0..500 {
            let a = cfg.sample_train_aug(1226, 370, &mut rng);
            let base = 1280.0 / 1226.0;
            assert!(a.resize >= base - 0.06 && a.resize <= base + 0.11);
            let (nw, nh) = a.resized_dims(1226, 370);
            assert_eq!(a.crop_y0, nh as f64 - 384.0);
            assert!(a.crop_x0 >= 0.0 && a.crop_x0 <= (nw as f64 - 1280.0).max(0.0));
            assert!(a.rotate_deg.abs() <= 5.4);
            flips += a.flip as usize;
        }
        assert!((180..320).contains(&flips));
    }

    #[test]
    fn normalisation_values() {
        let img = RgbImage {
            width: 1,
            height: 1,
            data: vec![123, 116, 104],
        };
        let n = normalize_chw(&img);
        assert!((n[0] - (123.0 - 123.675) / 58.395).abs() < 1e-6);
        assert!((n[2] - (104.0 - 103.53) / 57.375).abs() < 1e-6);
    }
}
