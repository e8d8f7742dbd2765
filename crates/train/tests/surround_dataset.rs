//! The six-camera nuScenes-layout datasets of the trainer (Occ3D and nuScenes-Occupancy ground
//! truth) on built-in synthetic scenes: frames, cameras in the label grid's frame, class ids,
//! LiDAR points, the `"*"` scene selection, predictions written in each layout and scored with the
//! official protocol.

use burn::backend::NdArray;
use occ_data::formats::nuscenes_occupancy::{self as nocc, NuscenesTables};
use occ_data::formats::occ3d::{self, FREE};
use occ_data::synthetic::{generate, read_synthetic_meta, Preset, SynthConfig};
use occ_geometry::{mat4_inverse, mat4_mul, transform_point, Mat4, VoxelGrid};
use occ_train::dataset::{collate, occ3d_training_labels, Dataset, DatasetFormat};
use occ_train::RunConfig;
use std::path::Path;

use occ_testdata::TempDir;

const W: usize = 176;
const H: usize = 64;

fn synth(root: &Path) {
    let cfg = SynthConfig {
        preset: Preset::Surround,
        seed: 3,
        sequences: vec![("a".into(), 2), ("b".into(), 1)],
        image_size: Some((W, H)),
    };
    generate(root, &cfg, &mut |_, _| {}).unwrap();
}

/// A run config for the layout (network input = the synthetic image size, so the test-time image
/// transform is the identity).
fn config(format: DatasetFormat, classes: usize, dims: [usize; 3]) -> RunConfig {
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/synthetic_surround_tiny.toml"),
    )
    .unwrap();
    let mut cfg = RunConfig::from_toml(&text, "synthetic_surround_tiny.toml").unwrap();
    cfg.data.format = format;
    cfg.data.image_width = W;
    cfg.data.image_height = H;
    cfg.model.num_classes = classes;
    cfg.model.full_dims = dims;
    cfg.validate().unwrap();
    cfg
}

fn close(a: &Mat4, b: &Mat4) -> bool {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .all(|(x, y)| (x - y).abs() < 1e-9)
}

#[test]
fn occ3d_frames_cameras_targets_points_and_scoring() {
    let t = TempDir::new("occ_train", "occ3d");
    synth(&t.0);
    let cfg = config(DatasetFormat::Occ3d, 18, [200, 200, 16]);
    let tables = NuscenesTables::load(&t.0.join("v1.0-trainval")).unwrap();

    // Scene selection: "*" = every scene not excluded; names are scene names; unknown names fail.
    let all = Dataset::open(&t.0, &cfg.data, &["*".into()], &["scene-b".into()]).unwrap();
    assert_eq!(all.len(), 2);
    assert!(all.frames().iter().all(|f| f.sequence == "scene-a"));
    let b = Dataset::open(&t.0, &cfg.data, &["scene-b".into()], &[]).unwrap();
    assert_eq!(b.len(), 1);
    let err = Dataset::open(&t.0, &cfg.data, &["scene-zz".into()], &[]).unwrap_err();
    assert!(err.to_string().contains("scene-zz"), "{err}");

    let mut ds = Dataset::open(&t.0, &cfg.data, &["*".into()], &[]).unwrap();
    assert_eq!(ds.len(), 3);
    assert_eq!(ds.grid(), VoxelGrid::occ3d_nuscenes());
    assert!(ds.is_labelled().unwrap());
    ds.set_load_points(true);
    let grid = ds.grid();
    let mut samples = Vec::new();
    for i in 0..ds.len() {
        let f = ds.frames()[i].clone();
        let s = ds.load::<rand_chacha::ChaCha8Rng>(i, None).unwrap();
        let cams = tables.sample_cameras(&f.frame).unwrap();
        assert_eq!(s.cameras.len(), 6);
        assert_eq!(s.size, (W, H));
        assert_eq!(s.chw.len(), 6 * 3 * W * H);
        for (c, cam) in s.cameras.iter().zip(&cams.cameras) {
            // The Occ3D grid lives in the ego frame at the LiDAR time.
            assert!(close(&c.cam_from_lidar, &cam.cam_from_ego_lidar));
            let k = cam.view.camera;
            let kmat: Mat4 = [
                [k.fx, 0.0, k.cx, 0.0],
                [0.0, k.fy, k.cy, 0.0],
                [0.0, 0.0, 1.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
            ];
            assert!(close(
                &c.img_from_lidar,
                &mat4_mul(&kmat, &cam.cam_from_ego_lidar)
            ));
        }
        // Targets: free -> 0, class c -> c + 1, outside mask_camera -> 255.
        let gt = occ3d::read_labels_npz(
            &t.0.join("gts")
                .join(&f.sequence)
                .join(&f.frame)
                .join("labels.npz"),
        )
        .unwrap();
        let target = s.target.clone().unwrap();
        assert_eq!(target, occ3d_training_labels(&gt));
        for ((&tv, &sem), &m) in target.iter().zip(&gt.semantics).zip(&gt.mask_camera) {
            match (m, sem) {
                (0, _) => assert_eq!(tv, 255),
                (_, FREE) => assert_eq!(tv, 0),
                (_, c) => assert_eq!(tv, c + 1),
            }
        }
        // LiDAR points come in the grid (ego) frame: every return inside the grid is in an
        // occupied voxel.
        let pts = s.points.clone().unwrap();
        let mut inside = 0;
        for p in &pts {
            if let Some(ijk) = grid.voxel_of_point_m(p.map(f64::from)) {
                assert_ne!(gt.semantics[grid.linear_index(ijk)], FREE, "{p:?}");
                inside += 1;
            }
        }
        assert!(inside > 1000, "{inside} points in the grid");
        samples.push(s);
    }
    let batch = collate::<NdArray<f32>>(&samples[..2], grid, &Default::default()).unwrap();
    assert_eq!(batch.images.dims(), [2, 6, 3, H, W]);
    assert_eq!(batch.cameras.len(), 2);
    assert!(batch.cameras.iter().all(|c| c.len() == 6));

    // Predictions in the Occ3D layout, scored with the official protocol: the ground truth itself
    // scores 1, and the in-process score equals the folder scorer over the same frames.
    let pred = t.0.join("pred");
    for (i, s) in samples.iter().enumerate() {
        let p = ds
            .write_prediction(&pred, i, s.target.as_ref().unwrap())
            .unwrap();
        let f = &ds.frames()[i];
        assert_eq!(p, pred.join(&f.sequence).join(&f.frame).join("labels.npz"));
    }
    let r = ds.score(&pred).unwrap();
    assert_eq!(r.frames, 3);
    assert!((r.iou - 1.0).abs() < 1e-12, "{}", r.iou);
    let folder =
        occ_eval::score_occ3d_folder(&t.0, &pred, &occ_eval::FolderOptions::default()).unwrap();
    assert_eq!(folder.evaluated_voxels, r.evaluated_voxels);
    assert_eq!(folder.miou.to_bits(), r.miou.to_bits());
    // An all-free prediction: IoU 0, every class 0.
    let empty = vec![0u8; grid.num_voxels()];
    for i in 0..ds.len() {
        ds.write_prediction(&pred, i, &empty).unwrap();
    }
    let r0 = ds.score(&pred).unwrap();
    assert_eq!(r0.iou, 0.0);
}

#[test]
fn nuscenes_occupancy_frames_use_the_lidar_frame() {
    let t = TempDir::new("occ_train", "nocc");
    synth(&t.0);
    let tables = NuscenesTables::load(&t.0.join("v1.0-trainval")).unwrap();
    let meta = read_synthetic_meta(&t.0).unwrap().unwrap();
    let occ_grid = VoxelGrid::nuscenes_occupancy();
    // nuScenes-Occupancy ground truth for the synthetic samples: the Occ3D voxel centres moved to
    // the LiDAR frame (raw class 0 "others" is nuScenes-Occupancy noise -> 255 in training ids).
    let mut expected = Vec::new();
    for s in &tables.sample {
        let cams = tables.sample_cameras(&s.token).unwrap();
        let scene = meta
            .sequences
            .iter()
            .find(|q| q.scene_token.as_deref() == Some(&s.scene_token))
            .unwrap();
        let l = occ3d::read_labels_npz(
            &t.0.join("gts")
                .join(format!("scene-{}", scene.name))
                .join(&s.token)
                .join("labels.npz"),
        )
        .unwrap();
        let lidar_from_ego = mat4_inverse(&cams.ego_from_lidar).unwrap();
        let mut dense = vec![0u8; occ_grid.num_voxels()];
        for (i, &c) in l.semantics.iter().enumerate() {
            if c == FREE {
                continue;
            }
            let p = transform_point(
                &lidar_from_ego,
                meta.grid.voxel_center_m(meta.grid.ijk_of(i)),
            );
            if let Some(ijk) = occ_grid.voxel_of_point_m(p) {
                dense[occ_grid.linear_index(ijk)] = if c == 0 { 255 } else { c };
            }
        }
        let path = tables.occupancy_path(&t.0.join("nuScenes-Occupancy"), &cams);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        nocc::write_sparse_occupancy(&path, &dense).unwrap();
        expected.push((s.token.clone(), dense));
    }
    let cfg = config(DatasetFormat::NuscenesOccupancy, 17, [512, 512, 40]);
    let mut ds = Dataset::open(&t.0, &cfg.data, &["scene-a".into()], &[]).unwrap();
    assert_eq!(ds.grid(), occ_grid);
    ds.set_load_points(true);
    let pred = t.0.join("pred");
    for i in 0..ds.len() {
        let f = ds.frames()[i].clone();
        let s = ds.load::<rand_chacha::ChaCha8Rng>(i, None).unwrap();
        let cams = tables.sample_cameras(&f.frame).unwrap();
        for (c, cam) in s.cameras.iter().zip(&cams.cameras) {
            assert!(close(&c.cam_from_lidar, &cam.view.cam_from_lidar));
        }
        let target = s.target.clone().unwrap();
        let want = &expected.iter().find(|e| e.0 == f.frame).unwrap().1;
        assert!(target == *want);
        // Points stay in the LiDAR frame.
        let raw = nocc::read_lidar_pcd_bin(&t.0.join(&cams.lidar_filename)).unwrap();
        assert_eq!(s.points.clone().unwrap(), raw);
        let p = ds.write_prediction(&pred, i, &target).unwrap();
        assert_eq!(p, tables.occupancy_path(&pred, &cams));
    }
    let r = ds.score(&pred).unwrap();
    assert!((r.iou - 1.0).abs() < 1e-12, "{}", r.iou);
    let folder =
        occ_eval::score_nuscenes_occupancy_folder(&t.0, &pred, &occ_eval::FolderOptions::default());
    // The folder scorer sees every scene's ground truth; scene-b has no prediction here.
    assert!(folder.is_err());
}

#[test]
fn config_classes_must_match_the_layout() {
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/synthetic_surround_tiny.toml"),
    )
    .unwrap();
    let bad = text.replace("num_classes = 18", "num_classes = 20");
    let err = RunConfig::from_toml(&bad, "x.toml")
        .unwrap_err()
        .to_string();
    assert!(err.contains("occ3d") && err.contains("18"), "{err}");
}
