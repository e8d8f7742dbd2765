//! JPEG camera images (nuScenes ships JPEG): `read_image` against libjpeg's decoding of the same
//! files (fixtures made by `scripts/make_jpeg_fixture.py`), and PNG/JPEG told apart by content.

use occ_data::image::{read_image, read_png, write_png, RgbImage};
use occ_data::DataError;
use std::path::PathBuf;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests")
        .join("data")
        .join(name)
}

/// Max and mean absolute difference to libjpeg's RGB output.
fn compare(name: &str) -> (u8, f64) {
    let img = read_image(&fixture(&format!("{name}.jpg"))).unwrap();
    assert_eq!((img.width, img.height), (48, 32), "{name}");
    let reference = std::fs::read(fixture(&format!("{name}.rgb"))).unwrap();
    assert_eq!(img.data.len(), reference.len(), "{name}");
    let diffs: Vec<u8> = img
        .data
        .iter()
        .zip(&reference)
        .map(|(&a, &b)| a.abs_diff(b))
        .collect();
    let max = *diffs.iter().max().unwrap();
    let mean = diffs.iter().map(|&d| d as f64).sum::<f64>() / diffs.len() as f64;
    eprintln!("{name}: max |diff| {max}, mean {mean:.3}");
    (max, mean)
}

#[test]
fn jpeg_444_matches_libjpeg() {
    let (max, mean) = compare("pattern_444");
    // Measured: max 2, mean 0.02 (IDCT rounding).
    assert!(max <= 3 && mean <= 0.1, "max {max}, mean {mean}");
}

#[test]
fn jpeg_420_matches_libjpeg() {
    // Chroma upsampling differs slightly between decoders; libjpeg's "fancy" upsampling is the reference.
    let (max, mean) = compare("pattern_420");
    assert!(max <= 24 && mean <= 2.0, "max {max}, mean {mean}");
}

#[test]
fn image_kind_is_read_from_the_content_not_the_name() {
    let dir = std::env::temp_dir().join(format!("occ_jpeg_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // A PNG named .jpg and a JPEG named .png both decode.
    let mut png = RgbImage::new(5, 3);
    png.data[7] = 200;
    let p = dir.join("really_png.jpg");
    write_png(&p, &png).unwrap();
    assert_eq!(read_image(&p).unwrap(), png);
    let j = dir.join("really_jpeg.png");
    std::fs::copy(fixture("pattern_444.jpg"), &j).unwrap();
    assert_eq!(read_image(&j).unwrap().width, 48);
    assert!(read_png(&j).is_err());
    // A truncated JPEG is an error naming the file, not a panic.
    let bytes = std::fs::read(fixture("pattern_420.jpg")).unwrap();
    let t = dir.join("truncated.jpg");
    std::fs::write(&t, &bytes[..bytes.len() / 3]).unwrap();
    match read_image(&t) {
        Err(e @ DataError::Image { .. }) => assert!(e.to_string().contains("truncated.jpg"), "{e}"),
        Ok(img) => {
            // Some decoders fill a truncated scan with grey; the size must still be right.
            assert_eq!((img.width, img.height), (48, 32));
        }
        Err(e) => panic!("unexpected error {e}"),
    }
    let _ = std::fs::remove_dir_all(&dir);
}
