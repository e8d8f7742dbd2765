//! Occ3D-nuScenes `labels.npz`: the real sample(s) in `$SPARSEOCC_REALDATA/occ3d` (external; the
//! tests print a skip line without it), round trips and bad input.

mod common;

use occ_data::formats::occ3d::*;
use occ_data::DataError;
use occ_testdata::TempDir;
use std::io::Read;
use std::path::PathBuf;

/// The real `*/labels.npz` samples, or `None` (skip reported) without the real-data folder.
fn samples() -> Option<Vec<PathBuf>> {
    let dir = occ_testdata::realdata()?.join("occ3d");
    let mut out = Vec::new();
    for e in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let p = e.unwrap().path().join("labels.npz");
        if p.is_file() {
            out.push(p);
        }
    }
    assert!(!out.is_empty(), "no */labels.npz under {}", dir.display());
    Some(out)
}

fn median_z(l: &Occ3dLabels, class: u8) -> Option<usize> {
    let mut zs: Vec<usize> = l
        .semantics
        .iter()
        .enumerate()
        .filter(|(_, &c)| c == class)
        .map(|(n, _)| n % l.dims[2])
        .collect();
    zs.sort();
    zs.get(zs.len() / 2).copied()
}

#[test]
fn real_samples_read_and_round_trip() {
    let Some(samples) = samples() else { return };
    for path in samples {
        let bytes = std::fs::read(&path).unwrap();
        // the real sample is DEFLATE-compressed
        let mut z = zip::ZipArchive::new(std::io::Cursor::new(&bytes)).unwrap();
        assert_eq!(
            z.by_index(0).unwrap().compression(),
            zip::CompressionMethod::Deflated
        );
        let l = read_labels_npz(&path).unwrap();
        assert_eq!(l.dims, DIMS);
        assert_eq!(l.semantics.len(), 640_000);
        let free = l.semantics.iter().filter(|&&c| c == FREE).count();
        let cam = l.mask_camera.iter().filter(|&&m| m == 1).count();
        let lidar = l.mask_lidar.iter().filter(|&&m| m == 1).count();
        let mut hist = [0usize; 18];
        for &c in &l.semantics {
            hist[c as usize] += 1;
        }
        println!(
            "{}: free {free}, mask_camera {cam}, mask_lidar {lidar}, class histogram {hist:?}",
            path.display()
        );
        assert!(free > 500_000 && free < 640_000);
        assert!(cam > 1000 && lidar > 1000);
        // [x][y][z] order: the road is at the bottom, buildings and vegetation above it
        let road = median_z(&l, 11).expect("sample has driveable_surface");
        assert!(road <= 2, "driveable_surface median z index {road}");
        for c in [15u8, 16] {
            if let Some(zc) = median_z(&l, c) {
                assert!(
                    zc > road,
                    "{} median z {zc} not above the road",
                    CLASS_NAMES[c as usize]
                );
            }
        }
        // round trip
        let tmp = TempDir::new("occ-data-test", "occ3d");
        let out = tmp.path().join("labels.npz");
        write_labels_npz(&out, &l).unwrap();
        assert_eq!(read_labels_npz(&out).unwrap(), l);
        let written = std::fs::read(&out).unwrap();
        let mut zw = zip::ZipArchive::new(std::io::Cursor::new(&written)).unwrap();
        let mut names = Vec::new();
        for i in 0..zw.len() {
            let mut f = zw.by_index(i).unwrap();
            assert_eq!(f.compression(), zip::CompressionMethod::Deflated);
            names.push(f.name().to_string());
            let mut b = Vec::new();
            f.read_to_end(&mut b).unwrap();
            assert!(b.starts_with(b"\x93NUMPY"));
        }
        names.sort();
        assert_eq!(
            names,
            vec!["mask_camera.npy", "mask_lidar.npy", "semantics.npy"]
        );
        assert!(written.len() < 200_000, "compressed size {}", written.len());
    }
}

#[test]
fn bad_npz_inputs() {
    let Some(samples) = samples() else { return };
    let tmp = TempDir::new("occ-data-test", "occ3d-bad");
    let d = tmp.path();
    let real = std::fs::read(&samples[0]).unwrap();
    let p = d.join("labels.npz");
    std::fs::write(&p, &real[..real.len() / 2]).unwrap();
    let e = read_labels_npz(&p).unwrap_err();
    assert!(e.to_string().contains("labels.npz"), "{e}");
    // a zip without mask_camera
    let mut l = read_labels_npz(&samples[0]).unwrap();
    {
        use std::io::Write;
        let mut zw = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        let o = zip::write::SimpleFileOptions::default();
        for name in ["semantics", "mask_lidar"] {
            zw.start_file(format!("{name}.npy"), o).unwrap();
            zw.write_all(&occ_data::formats::npy::npy_bytes(&DIMS, &l.semantics).unwrap())
                .unwrap();
        }
        std::fs::write(&p, zw.finish().unwrap().into_inner()).unwrap();
    }
    assert!(
        matches!(read_labels_npz(&p), Err(DataError::MissingKey { ref key, .. }) if key == "mask_camera")
    );
    // out-of-range class
    l.semantics[5] = 18;
    std::fs::write(&p, labels_npz_bytes(&l).unwrap()).unwrap();
    assert!(read_labels_npz(&p).unwrap_err().to_string().contains("18"));
    // inconsistent lengths are rejected on writing
    l.semantics.pop();
    assert!(write_labels_npz(&p, &l).is_err());
    assert!(matches!(
        read_labels_npz(&d.join("missing.npz")),
        Err(DataError::NotFound { .. })
    ));
}
