//! SCF ground truth (Algorithm 2) and propagation (Algorithm 1) against the PyTorch reference
//! fixtures in `$SPARSEOCC_FIXTURES/reference` (an external folder, found by `occ_testdata`; without it
//! these tests print a skip line). Files are found through `reference/manifest.json` by their role
//! (prefix), never by a hard-coded list of cases.

use occ_geometry::scf::{
    propagate, propagation_to_dense, scf_ground_truth, scf_planar, scf_vertical, ScfConfig,
};
use occ_testdata::read_npy;
use std::path::{Path, PathBuf};

/// `$SPARSEOCC_FIXTURES/reference`, or `None` (skip reported) without the fixtures folder.
fn reference_dir() -> Option<PathBuf> {
    let dir = occ_testdata::fixtures()?.join("reference");
    assert!(
        dir.join("manifest.json").is_file(),
        "{} has no manifest.json",
        dir.display()
    );
    Some(dir)
}

/// Manifest entries: file name -> (shape, dtype, description).
fn manifest(dir: &Path) -> Vec<(String, Vec<usize>, String, String)> {
    let text = std::fs::read_to_string(dir.join("manifest.json")).expect("read manifest.json");
    let v: serde_json::Value = serde_json::from_str(&text).expect("parse manifest.json");
    let files = v["files"]
        .as_object()
        .expect("manifest has no 'files' object");
    files
        .iter()
        .map(|(name, e)| {
            let shape = e["shape"]
                .as_array()
                .expect("shape")
                .iter()
                .map(|d| d.as_u64().expect("dim") as usize)
                .collect();
            let dtype = e["dtype"].as_str().unwrap_or_default().to_string();
            let what = e["what"].as_str().unwrap_or_default().to_string();
            (name.clone(), shape, dtype, what)
        })
        .collect()
}

/// The single manifest file whose name starts with `prefix`, its shape, and its description.
fn find(dir: &Path, prefix: &str) -> (PathBuf, Vec<usize>, String) {
    let hits: Vec<_> = manifest(dir)
        .into_iter()
        .filter(|(n, ..)| n.starts_with(prefix))
        .collect();
    assert_eq!(
        hits.len(),
        1,
        "expected one manifest entry starting with {prefix}, found {}",
        hits.len()
    );
    let (name, shape, _, what) = hits.into_iter().next().unwrap();
    (dir.join(name), shape, what)
}

/// The "s_max N" written in a manifest description.
fn s_max_from(what: &str) -> u32 {
    let i = what.find("s_max").expect("description names s_max");
    what[i + 5..]
        .split(|c: char| !c.is_ascii_digit())
        .find(|t| !t.is_empty())
        .and_then(|t| t.parse().ok())
        .expect("s_max value")
}

fn dims3(shape: &[usize]) -> [usize; 3] {
    assert_eq!(shape.len(), 3, "expected a 3D grid, got shape {shape:?}");
    [shape[0], shape[1], shape[2]]
}

#[test]
fn scf_ground_truth_matches_reference_exactly() {
    let Some(dir) = reference_dir() else { return };
    let (occ_path, _, _) = find(&dir, "scf_occupancy");
    let (occ, shape) = read_npy::<u8>(&occ_path);
    let dims = dims3(&shape);
    let (planar_path, _, planar_what) = find(&dir, "scf_gt_planar");
    let (vertical_path, _, vertical_what) = find(&dir, "scf_gt_vertical");
    let (want_planar, ps) = read_npy::<i8>(&planar_path);
    let (want_vertical, vs) = read_npy::<i8>(&vertical_path);
    assert_eq!(dims3(&ps), dims);
    assert_eq!(dims3(&vs), dims);
    let cfg = ScfConfig {
        s_max_planar: s_max_from(&planar_what),
        s_max_vertical: s_max_from(&vertical_what),
    };
    assert_eq!(
        cfg,
        ScfConfig::default(),
        "manifest s_max differs from the default (10, 3)"
    );
    let gt = scf_ground_truth(&occ, dims, &cfg).unwrap();
    for (name, got, want) in [
        ("planar", &gt.planar, &want_planar),
        ("vertical", &gt.vertical, &want_vertical),
    ] {
        let bad: Vec<usize> = (0..want.len()).filter(|&i| got[i] != want[i]).collect();
        assert!(
            bad.is_empty(),
            "{name}: {} of {} voxels differ, first at flat {} (got {}, want {})",
            bad.len(),
            want.len(),
            bad[0],
            got[bad[0]],
            want[bad[0]]
        );
    }
    // The separate entry points agree with the combined one.
    assert_eq!(
        scf_planar(&occ, dims, cfg.s_max_planar).unwrap(),
        want_planar
    );
    assert_eq!(
        scf_vertical(&occ, dims, cfg.s_max_vertical).unwrap(),
        want_vertical
    );
    // The fixture exercises every sign (guards against a vacuous comparison).
    for v in [&want_planar, &want_vertical] {
        assert!(v.iter().any(|&s| s < 0) && v.iter().any(|&s| s > 0) && v.contains(&0));
    }
}

#[test]
fn propagation_matches_reference_exactly() {
    let Some(dir) = reference_dir() else { return };
    let (anchor_path, _, _) = find(&dir, "prop_anchors");
    let (flat, ashape) = read_npy::<i32>(&anchor_path);
    assert_eq!(ashape.len(), 2);
    assert_eq!(ashape[1], 3);
    let anchors: Vec<[i32; 3]> = flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let (sp, _) = read_npy::<i32>(&find(&dir, "prop_s_planar").0);
    let (sv, _) = read_npy::<i32>(&find(&dir, "prop_s_vertical").0);
    let (want, rshape) = read_npy::<u8>(&find(&dir, "prop_result").0);
    let dims = dims3(&rshape);
    let prop = propagate(&anchors, &sp, &sv, dims).unwrap();
    // New voxels are sorted, unique and disjoint from the anchors.
    assert!(prop.new_voxels.windows(2).all(|w| w[0] < w[1]));
    let anchor_set: std::collections::HashSet<[i32; 3]> = anchors.iter().copied().collect();
    assert!(prop.new_voxels.iter().all(|v| !anchor_set.contains(v)));
    let got = propagation_to_dense(&anchors, &prop, dims).unwrap();
    let bad = (0..want.len()).filter(|&i| got[i] != want[i]).count();
    assert_eq!(bad, 0, "{bad} voxels differ from the reference propagation");
    let occupied = want.iter().filter(|&&v| v != 0).count();
    assert_eq!(anchor_set.len() + prop.new_voxels.len(), occupied);
    assert!(
        prop.new_voxels.len() > anchor_set.len(),
        "fixture should add many voxels"
    );
}
