//! The synthetic Occ3D-nuScenes-layout generator (`surround`), checked through the real readers.

mod common;

use common::traverse;
use occ_data::formats::nuscenes_occupancy::{NuscenesTables, CAMERA_CHANNELS};
use occ_data::formats::occ3d::{read_labels_npz, FREE};
use occ_data::image::read_png;
use occ_data::synthetic::classes::{nearest_class_by_chroma, nuscenes_class};
use occ_data::synthetic::{generate, read_synthetic_meta, Preset, SynthConfig, NUSCENES_VERSION};
use occ_geometry::{mat4_inverse, transform_point, Mat4, PinholeCamera, VoxelGrid};
use occ_testdata::TempDir;

fn pixel_ray(ego_from_cam: &Mat4, cam: &PinholeCamera, u: usize, v: usize) -> ([f64; 3], [f64; 3]) {
    let o = transform_point(ego_from_cam, [0.0, 0.0, 0.0]);
    let p = transform_point(
        ego_from_cam,
        [
            (u as f64 - cam.cx) / cam.fx,
            (v as f64 - cam.cy) / cam.fy,
            1.0,
        ],
    );
    let dv = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
    let n = (dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]).sqrt();
    (o, dv.map(|x| x / n))
}

/// How many entries of `dir` have names starting with `prefix`.
fn files_starting_with(dir: &std::path::Path, prefix: &str) -> usize {
    std::fs::read_dir(dir)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with(prefix)
        })
        .count()
}

#[test]
fn surround_scene_reads_back_and_is_consistent() {
    let t = TempDir::new("sparseocc-synth", "surround");
    let (w, h) = (176, 64);
    let cfg = SynthConfig {
        preset: Preset::Surround,
        seed: 4,
        sequences: vec![("0001".into(), 2)],
        image_size: Some((w, h)),
    };
    let summary = generate(&t.0, &cfg, &mut |_, _| {}).unwrap();
    assert_eq!(summary.frames, 2);
    let meta = read_synthetic_meta(&t.0).unwrap().unwrap();
    assert!(meta.complete);
    assert_eq!(meta.grid, VoxelGrid::occ3d_nuscenes());
    assert_eq!(meta.num_cameras, 6);
    let tables = NuscenesTables::load(&t.0.join(NUSCENES_VERSION)).unwrap();
    let tokens: Vec<String> = tables
        .sample_tokens()
        .iter()
        .map(|s| s.to_string())
        .collect();
    assert_eq!(tokens.len(), 2);
    let grid = meta.grid;
    let candidates: Vec<u8> = (1..=24).collect();
    let mut seen_classes = [0u64; 18];
    let (mut n_app, mut ok_app) = (0usize, 0usize);
    let mut checked_cam = 0usize;
    for tok in &tokens {
        let cams = tables.sample_cameras(tok).unwrap();
        assert_eq!(cams.cameras.len(), 6);
        assert_eq!(
            cams.scene_token,
            meta.sequences[0].scene_token.clone().unwrap()
        );
        let labels = read_labels_npz(
            &t.0.join("gts")
                .join("scene-0001")
                .join(tok)
                .join("labels.npz"),
        )
        .unwrap();
        assert_eq!(labels.dims, [200, 200, 16]);
        for &c in &labels.semantics {
            assert!(c <= FREE);
            seen_classes[c as usize] += 1;
        }
        let occupied = |i: usize| labels.semantics[i] != FREE;
        // LiDAR returns, moved to the ego frame, are occupied and LiDAR-observed voxels
        let pts = std::fs::read(t.0.join(&cams.lidar_filename)).unwrap();
        assert_eq!(pts.len() % 20, 0);
        let mut n_in = 0;
        for c in pts.chunks_exact(20) {
            let f = |k: usize| {
                f32::from_le_bytes([c[4 * k], c[4 * k + 1], c[4 * k + 2], c[4 * k + 3]]) as f64
            };
            let p = transform_point(&cams.ego_from_lidar, [f(0), f(1), f(2)]);
            if let Some(ijk) = grid.voxel_of_point_m(p) {
                let i = grid.linear_index(ijk);
                assert!(occupied(i), "LiDAR return in a free voxel {ijk:?}");
                assert_eq!(labels.mask_lidar[i], 1);
                n_in += 1;
            }
        }
        assert!(n_in > 5000, "{n_in} LiDAR returns in the grid");
        for (ci, cam) in cams.cameras.iter().enumerate() {
            assert_eq!(cam.channel, CAMERA_CHANNELS[ci]);
            let img = read_png(&t.0.join(&cam.filename)).unwrap();
            assert_eq!((img.width, img.height), (w, h));
            let ego_from_cam = mat4_inverse(&cam.cam_from_ego_lidar).unwrap();
            let k = cam.view.camera;
            let mut first = vec![None; w * h];
            for v in 0..h {
                for u in 0..w {
                    let (o, d) = pixel_ray(&ego_from_cam, &k, u, v);
                    let (visited, hit) = traverse(&grid, &occupied, o, d, 150.0);
                    for i in visited {
                        assert_eq!(
                            labels.mask_camera[i],
                            1,
                            "{}: voxel {:?} on the ray of pixel ({u},{v}) not in mask_camera",
                            cam.channel,
                            grid.ijk_of(i)
                        );
                        checked_cam += 1;
                    }
                    first[v * w + u] = hit;
                }
            }
            // appearance of the voxel each pixel shows
            for v in 0..h {
                for u in 0..w {
                    if let Some(i) = first[v * w + u] {
                        let rgb = img.pixel(u, v).unwrap();
                        let got = nearest_class_by_chroma(rgb, &candidates).map(nuscenes_class);
                        n_app += 1;
                        ok_app += usize::from(got == Some(labels.semantics[i]));
                    }
                }
            }
        }
        let cam_frac = labels.mask_camera.iter().filter(|&&m| m == 1).count() as f64
            / labels.mask_camera.len() as f64;
        assert!(
            cam_frac > 0.05 && cam_frac < 0.95,
            "mask_camera fraction {cam_frac}"
        );
    }
    let frac = ok_app as f64 / n_app as f64;
    eprintln!("surround appearance (pixel shows voxel): {ok_app}/{n_app} = {frac:.4}");
    assert!(frac >= 0.95, "{frac}");
    assert!(checked_cam > 50_000);
    for c in 1..=16 {
        assert!(
            seen_classes[c] > 0,
            "nuScenes class {c} never occurs: {seen_classes:?}"
        );
    }
    assert!(seen_classes[FREE as usize] > seen_classes[1..17].iter().sum::<u64>());
}

#[test]
fn rerun_replaces_previous_output_and_foreign_data_is_protected() {
    let t = TempDir::new("sparseocc-synth", "rerun");
    let mut cfg = SynthConfig {
        preset: Preset::Surround,
        seed: 1,
        sequences: vec![("a".into(), 2)],
        image_size: Some((32, 16)),
    };
    generate(&t.0, &cfg, &mut |_, _| {}).unwrap();
    cfg.sequences = vec![("b".into(), 1)];
    generate(&t.0, &cfg, &mut |_, _| {}).unwrap();
    assert!(!t.0.join("gts/scene-a").exists());
    assert_eq!(
        files_starting_with(&t.0.join("samples/CAM_FRONT"), "scene-a__"),
        0
    );
    let tables = NuscenesTables::load(&t.0.join(NUSCENES_VERSION)).unwrap();
    assert_eq!(tables.sample_tokens().len(), 1);
    // a folder that holds a dataset without synthetic.json is never overwritten
    let foreign = TempDir::new("sparseocc-synth", "foreign");
    std::fs::create_dir_all(foreign.0.join("sequences/00")).unwrap();
    std::fs::write(foreign.0.join("sequences/00/calib.txt"), b"x").unwrap();
    let k = SynthConfig {
        preset: Preset::KittiSmall,
        seed: 1,
        sequences: vec![("00".into(), 1)],
        image_size: Some((32, 16)),
    };
    let e = generate(&foreign.0, &k, &mut |_, _| {}).unwrap_err();
    assert!(e.to_string().contains("refusing"), "{e}");
    assert_eq!(
        std::fs::read(foreign.0.join("sequences/00/calib.txt")).unwrap(),
        b"x"
    );
}

#[test]
fn scene_names_are_prefixed_once_and_rerun_cleans_prefixed_scenes() {
    assert_eq!(occ_data::synthetic::scene_name_of("0001"), "scene-0001");
    assert_eq!(
        occ_data::synthetic::scene_name_of("scene-0001"),
        "scene-0001"
    );
    let t = TempDir::new("sparseocc-synth", "prefix");
    let mut cfg = SynthConfig {
        preset: Preset::Surround,
        seed: 2,
        sequences: vec![("scene-0001".into(), 1), ("0002".into(), 1)],
        image_size: Some((32, 16)),
    };
    generate(&t.0, &cfg, &mut |_, _| {}).unwrap();
    let scenes =
        occ_data::formats::nuscenes_occupancy::read_scenes(&t.0.join(NUSCENES_VERSION)).unwrap();
    let names: Vec<&str> = scenes.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(names, ["scene-0001", "scene-0002"]);
    assert!(t.0.join("gts/scene-0001").is_dir());
    assert!(!t.0.join("gts/scene-scene-0001").exists());
    let prefixed = |dir: &str, prefix: &str| files_starting_with(&t.0.join(dir), prefix);
    assert_eq!(prefixed("samples/CAM_FRONT", "scene-0001__"), 1);
    assert_eq!(prefixed("samples/CAM_FRONT", "scene-scene-"), 0);
    // A rerun without the prefixed sequence removes its files (found under the same name).
    cfg.sequences = vec![("0002".into(), 1)];
    generate(&t.0, &cfg, &mut |_, _| {}).unwrap();
    assert!(!t.0.join("gts/scene-0001").exists());
    assert_eq!(prefixed("samples/CAM_FRONT", "scene-0001__"), 0);
}
