//! JPEG camera images (nuScenes ships JPEG): `read_image` against libjpeg's decoding of the same
//! files (fixtures made by `scripts/make_jpeg_fixture.py`), and PNG/JPEG told apart by content.

use occ_data::image::{read_image, read_image_size, read_png, write_png, RgbImage};
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
fn progressive_jpeg_matches_libjpeg() {
    // Several scans with tables between them; same chroma upsampling difference as 4:2:0 above.
    let (max, mean) = compare("pattern_420_progressive");
    assert!(max <= 24 && mean <= 2.0, "max {max}, mean {mean}");
}

/// A JPEG or PNG cut short anywhere (an interrupted download or copy) is an error naming the file,
/// from the full read and from the header-only size check a dataset check runs; bytes after the
/// end-of-image are allowed. The JPEG decoder alone would fill the missing part with grey.
#[test]
fn truncated_images_are_errors_naming_the_file() {
    let dir = occ_testdata::TempDir::new("occ-data", "truncated-images");
    let png = occ_data::image::encode_png(&RgbImage {
        width: 9,
        height: 7,
        data: (0..9 * 7 * 3).map(|i| (i * 37 % 256) as u8).collect(),
    })
    .unwrap();
    let mut files = vec![("png", png)];
    for name in ["pattern_444", "pattern_420", "pattern_420_progressive"] {
        files.push((
            name,
            std::fs::read(fixture(&format!("{name}.jpg"))).unwrap(),
        ));
    }
    for (name, bytes) in &files {
        let whole = dir.path().join(format!("{name}_whole"));
        let mut trailing = bytes.clone();
        trailing.extend_from_slice(b"\0\0trailer");
        std::fs::write(&whole, &trailing).unwrap();
        let img = read_image(&whole).unwrap_or_else(|e| panic!("{name} with a trailer: {e}"));
        assert_eq!(read_image_size(&whole).unwrap(), (img.width, img.height));
        // Every cut: the end marker alone, one byte, a few bytes, halfway, just after the header.
        let n = bytes.len();
        for keep in [n - 2, n - 1, n - 5, n / 2, n / 3, 40] {
            let p = dir.path().join(format!("{name}_cut_{keep}"));
            std::fs::write(&p, &bytes[..keep]).unwrap();
            for result in [read_image(&p).map(|_| ()), read_image_size(&p).map(|_| ())] {
                let e = result.expect_err(&format!("{name} cut to {keep} of {n} bytes"));
                assert!(matches!(e, DataError::Image { .. }), "{name} {keep}: {e}");
                assert!(e.to_string().contains(&format!("{name}_cut_{keep}")), "{e}");
            }
        }
    }
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
    let _ = std::fs::remove_dir_all(&dir);
}

/// A valid small PNG whose IHDR (with a correct CRC) claims `w` x `h` pixels.
fn png_claiming(w: u32, h: u32) -> Vec<u8> {
    let img = RgbImage {
        width: 4,
        height: 4,
        data: vec![7; 48],
    };
    occ_testdata::png_claiming_size(&occ_data::image::encode_png(&img).unwrap(), w, h)
}

/// The 48x32 JPEG fixture with its frame header patched to claim `w` x `h` pixels.
fn jpeg_claiming(w: u16, h: u16) -> Vec<u8> {
    let mut b = std::fs::read(fixture("pattern_444.jpg")).unwrap();
    let sof = (0..b.len() - 1)
        .find(|&i| b[i] == 0xFF && (b[i + 1] == 0xC0 || b[i + 1] == 0xC2))
        .expect("a frame header");
    // FFCx, length (2), precision (1), height (2), width (2).
    b[sof + 5..sof + 7].copy_from_slice(&h.to_be_bytes());
    b[sof + 7..sof + 9].copy_from_slice(&w.to_be_bytes());
    b
}

/// Headers claiming huge images are errors naming the file and the size, raised before the pixel
/// buffer is allocated (a 100000x100000 PNG used to abort the process on a 30 GB allocation).
#[test]
fn images_claiming_huge_sizes_are_errors_not_aborts() {
    let dir = std::env::temp_dir().join(format!("occ-data-huge-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        ("huge.png", png_claiming(100_000, 100_000), "100000x100000"),
        ("wide.png", png_claiming(2_000_000_000, 1), "2000000000x1"),
        ("huge.jpg", jpeg_claiming(16_000, 16_000), "16000x16000"),
        (
            "huge_jpeg_named.png",
            jpeg_claiming(16_384, 5_000),
            "16384x5000",
        ),
    ];
    for (name, bytes, size) in &cases {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        for e in [
            read_image(&p).unwrap_err(),
            occ_data::image::read_image_size(&p).unwrap_err(),
        ] {
            assert!(matches!(e, DataError::Image { .. }), "{name}: {e}");
            let e = e.to_string();
            assert!(e.contains(name) && e.contains(size), "{name}: {e}");
        }
    }
    // A PNG claiming an empty image.
    let p = dir.join("empty.png");
    std::fs::write(&p, png_claiming(0, 5)).unwrap();
    assert!(read_image(&p).is_err());
    // The unpatched sizes read fine, from the header alone too.
    let ok = dir.join("ok.png");
    std::fs::write(&ok, png_claiming(4, 4)).unwrap();
    assert_eq!(occ_data::image::read_image_size(&ok).unwrap(), (4, 4));
    assert_eq!(read_image(&ok).unwrap().width, 4);
    assert_eq!(
        occ_data::image::read_image_size(&fixture("pattern_444.jpg")).unwrap(),
        (48, 32)
    );
    let _ = std::fs::remove_dir_all(&dir);
}
