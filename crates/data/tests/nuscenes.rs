//! nuScenes-Occupancy sparse ground truth and nuScenes v1.0 camera tables, on small files
//! written by the test in the public schema.

mod common;

use occ_data::formats::npy::write_npy;
use occ_data::formats::nuscenes_occupancy::*;
use occ_data::DataError;
use occ_geometry::{transform_point, VoxelGrid};
use occ_testdata::TempDir;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::json;

#[test]
fn sparse_occupancy_to_dense_grid() {
    let tmp = TempDir::new("occ-data-test", "nuocc");
    let p = tmp.path().join("lidar_token.npy");
    // rows [z, y, x, cls]: a car voxel, a noise voxel, a voxel listed twice with a vote
    let rows: Vec<i64> = vec![
        3, 100, 200, 4, 0, 0, 0, 0, 39, 511, 511, 11, 39, 511, 511, 11, 39, 511, 511, 16,
    ];
    write_npy(&p, &[5, 4], &rows).unwrap();
    let dense = read_sparse_occupancy(&p).unwrap();
    let g = VoxelGrid::nuscenes_occupancy();
    assert_eq!(dense.len(), g.num_voxels());
    assert_eq!(dense[g.linear_index([200, 100, 3])], 4);
    assert_eq!(dense[g.linear_index([0, 0, 0])], 255, "noise -> 255");
    assert_eq!(dense[g.linear_index([511, 511, 39])], 11, "majority vote");
    assert_eq!(
        dense.iter().filter(|&&c| c != 0).count(),
        3,
        "unlisted voxels are empty (0)"
    );
    // 7-column variant with velocities, int32
    let rows7: Vec<i32> = vec![3, 100, 200, 9, 9, 9, 10];
    write_npy(&p, &[1, 7], &rows7).unwrap();
    assert_eq!(
        read_sparse_occupancy(&p).unwrap()[g.linear_index([200, 100, 3])],
        10
    );
    // round trip through the writer
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut grid = vec![0u8; g.num_voxels()];
    for _ in 0..5000 {
        let n = rng.random_range(0..grid.len());
        grid[n] = if rng.random_bool(0.1) {
            255
        } else {
            rng.random_range(1..17)
        };
    }
    write_sparse_occupancy(&p, &grid).unwrap();
    assert_eq!(read_sparse_occupancy(&p).unwrap(), grid);
    // bad inputs name the file
    write_npy(&p, &[1, 4], &[40i64, 0, 0, 1]).unwrap();
    let e = read_sparse_occupancy(&p).unwrap_err();
    assert!(
        e.to_string().contains("lidar_token.npy") && e.to_string().contains("outside"),
        "{e}"
    );
    write_npy(&p, &[1, 4], &[0i64, 0, 0, 17]).unwrap();
    assert!(read_sparse_occupancy(&p)
        .unwrap_err()
        .to_string()
        .contains("unknown class"));
    write_npy(&p, &[2, 3], &[0i64; 6]).unwrap();
    assert!(matches!(
        read_sparse_occupancy(&p),
        Err(DataError::Format { .. })
    ));
    // the class list
    assert_eq!(CLASS_NAMES.len(), NUM_CLASSES);
    assert_eq!(CLASS_NAMES[0], "empty");
    assert_eq!(training_class(0), Some(255));
}

// ---- quaternion helpers written independently of occ_geometry (Hamilton product) ----
fn qmul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}
fn qrot(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let r = qmul(
        qmul(q, [0.0, v[0], v[1], v[2]]),
        [q[0], -q[1], -q[2], -q[3]],
    );
    [r[1], r[2], r[3]]
}
fn qinv_apply(q: [f64; 4], t: [f64; 3], p: [f64; 3]) -> [f64; 3] {
    // inverse of p -> R(q) p + t
    qrot(
        [q[0], -q[1], -q[2], -q[3]],
        [p[0] - t[0], p[1] - t[1], p[2] - t[2]],
    )
}
fn rand_quat(rng: &mut ChaCha8Rng) -> [f64; 4] {
    let q: [f64; 4] = [
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    ];
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
}
fn rand_t(rng: &mut ChaCha8Rng, s: f64) -> [f64; 3] {
    [
        rng.random_range(-s..s),
        rng.random_range(-s..s),
        rng.random_range(-s..s),
    ]
}

/// channel, calibration (q, t), ego pose at the camera time (q, t), intrinsics (fx, fy, cx, cy)
type CamSpec = (String, [f64; 4], [f64; 3], [f64; 4], [f64; 3], [f64; 4]);

struct Scene {
    ego_lidar: ([f64; 4], [f64; 3]),
    lidar_cal: ([f64; 4], [f64; 3]),
    cams: Vec<CamSpec>,
}

/// Write the five tables as raw JSON in the public nuScenes schema (not through our writer).
fn write_scene(dir: &std::path::Path, rng: &mut ChaCha8Rng) -> Scene {
    let ego_lidar = (rand_quat(rng), rand_t(rng, 500.0));
    let lidar_cal = (rand_quat(rng), rand_t(rng, 2.0));
    let mut sensors =
        vec![json!({"token": "s_lidar", "channel": "LIDAR_TOP", "modality": "lidar"})];
    let mut calibs = vec![
        json!({"token": "c_lidar", "sensor_token": "s_lidar", "translation": lidar_cal.1,
        "rotation": lidar_cal.0, "camera_intrinsic": []}),
    ];
    let mut poses = vec![
        json!({"token": "e_lidar", "timestamp": 1_000_000i64, "rotation": ego_lidar.0, "translation": ego_lidar.1}),
    ];
    let mut sds = vec![
        json!({"token": "sd_lidar", "sample_token": "sample0", "ego_pose_token": "e_lidar", "calibrated_sensor_token": "c_lidar",
            "timestamp": 1_000_000i64, "fileformat": "pcd", "is_key_frame": true, "height": 0, "width": 0,
            "filename": "samples/LIDAR_TOP/x.pcd.bin", "prev": "", "next": ""}),
        // a sweep of the same sample: must be ignored
        json!({"token": "sd_lidar_sweep", "sample_token": "sample0", "ego_pose_token": "e_lidar", "calibrated_sensor_token": "c_lidar",
            "timestamp": 1_050_000i64, "fileformat": "pcd", "is_key_frame": false, "height": 0, "width": 0,
            "filename": "sweeps/LIDAR_TOP/y.pcd.bin", "prev": "sd_lidar", "next": ""}),
    ];
    let mut cams = Vec::new();
    for (i, ch) in CAMERA_CHANNELS.iter().enumerate() {
        let cal = (rand_quat(rng), rand_t(rng, 2.0));
        let ego = (
            rand_quat(rng),
            [
                ego_lidar.1[0] + rng.random_range(-0.5..0.5),
                ego_lidar.1[1],
                ego_lidar.1[2],
            ],
        );
        let k = [
            rng.random_range(800.0..1300.0),
            rng.random_range(800.0..1300.0),
            rng.random_range(780.0..820.0),
            rng.random_range(430.0..470.0),
        ];
        sensors.push(json!({"token": format!("s{i}"), "channel": ch, "modality": "camera"}));
        calibs.push(json!({"token": format!("c{i}"), "sensor_token": format!("s{i}"), "translation": cal.1, "rotation": cal.0,
            "camera_intrinsic": [[k[0], 0.0, k[2]], [0.0, k[1], k[3]], [0.0, 0.0, 1.0]]}));
        poses.push(json!({"token": format!("e{i}"), "timestamp": 1_000_000i64 + 5000 * i as i64, "rotation": ego.0, "translation": ego.1}));
        sds.push(json!({"token": format!("sd{i}"), "sample_token": "sample0", "ego_pose_token": format!("e{i}"),
            "calibrated_sensor_token": format!("c{i}"), "timestamp": 1_000_000i64 + 5000 * i as i64, "fileformat": "jpg",
            "is_key_frame": true, "height": 900, "width": 1600, "filename": format!("samples/{ch}/{i}.jpg"), "prev": "", "next": ""}));
        cams.push((ch.to_string(), cal.0, cal.1, ego.0, ego.1, k));
    }
    let samples = json!([{"token": "sample0", "timestamp": 1_000_000i64, "prev": "", "next": "", "scene_token": "scene0"}]);
    std::fs::create_dir_all(dir).unwrap();
    for (name, v) in [
        ("sample.json", samples),
        ("sample_data.json", json!(sds)),
        ("calibrated_sensor.json", json!(calibs)),
        ("ego_pose.json", json!(poses)),
        ("sensor.json", json!(sensors)),
    ] {
        std::fs::write(dir.join(name), serde_json::to_string_pretty(&v).unwrap()).unwrap();
    }
    Scene {
        ego_lidar,
        lidar_cal,
        cams,
    }
}

#[test]
fn camera_tables_give_lidar_to_camera_projections() {
    let tmp = TempDir::new("occ-data-test", "nusc");
    let dir = tmp.path().join("v1.0-mini");
    let mut rng = ChaCha8Rng::seed_from_u64(33);
    let scene = write_scene(&dir, &mut rng);
    let tables = NuscenesTables::load(&dir).unwrap();
    let sc = tables.sample_cameras("sample0").unwrap();
    assert_eq!(sc.lidar_token, "sd_lidar");
    assert_eq!(sc.cameras.len(), 6);
    assert_eq!(
        tables.occupancy_path(std::path::Path::new("/occ"), &sc),
        std::path::PathBuf::from("/occ/scene_scene0/occupancy/sd_lidar.npy")
    );
    for (cam, (ch, cq, ct, eq, et, k)) in sc.cameras.iter().zip(&scene.cams) {
        assert_eq!(&cam.channel, ch);
        assert_eq!((cam.view.camera.width, cam.view.camera.height), (1600, 900));
        for _ in 0..20 {
            // a point in the global frame, expressed in the LiDAR and camera frames independently
            let pg = [
                scene.ego_lidar.1[0] + rng.random_range(-30.0..30.0),
                scene.ego_lidar.1[1] + rng.random_range(-30.0..30.0),
                rng.random_range(-3.0..3.0),
            ];
            let p_lidar = qinv_apply(
                scene.lidar_cal.0,
                scene.lidar_cal.1,
                qinv_apply(scene.ego_lidar.0, scene.ego_lidar.1, pg),
            );
            let p_cam = qinv_apply(*cq, *ct, qinv_apply(*eq, *et, pg));
            let got = transform_point(&cam.view.cam_from_lidar, p_lidar);
            for a in 0..3 {
                assert!(
                    (got[a] - p_cam[a]).abs() < 1e-6,
                    "{ch}: {got:?} vs {p_cam:?}"
                );
            }
            let p_ego = qinv_apply(scene.ego_lidar.0, scene.ego_lidar.1, pg);
            let got_e = transform_point(&cam.cam_from_ego_lidar, p_ego);
            assert!((got_e[2] - p_cam[2]).abs() < 1e-6);
            if p_cam[2] > 0.1 {
                let uvd = cam.view.project_point(p_lidar).unwrap();
                assert!((uvd[0] - (k[0] * p_cam[0] / p_cam[2] + k[2])).abs() < 1e-5);
                assert!((uvd[1] - (k[1] * p_cam[1] / p_cam[2] + k[3])).abs() < 1e-5);
            } else {
                assert!(cam
                    .view
                    .project_point(p_lidar)
                    .is_none_or(|u| u[2] <= 0.1 + 1e-9));
            }
        }
    }
    // writer -> reader round trip, with the exact nuScenes field names
    let out = tmp.path().join("copy");
    tables.write(&out).unwrap();
    let again = NuscenesTables::load(&out).unwrap();
    assert_eq!(
        again.sample_cameras("sample0").unwrap(),
        NuscenesTables::load(&dir)
            .unwrap()
            .sample_cameras("sample0")
            .unwrap()
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("sample_data.json")).unwrap())
            .unwrap();
    let keys: Vec<&str> = v[0]
        .as_object()
        .unwrap()
        .keys()
        .map(|k| k.as_str())
        .collect();
    for k in [
        "token",
        "sample_token",
        "ego_pose_token",
        "calibrated_sensor_token",
        "timestamp",
        "fileformat",
        "is_key_frame",
        "height",
        "width",
        "filename",
        "prev",
        "next",
    ] {
        assert!(keys.contains(&k), "sample_data.json lacks {k}");
    }
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("calibrated_sensor.json")).unwrap())
            .unwrap();
    assert!(v[1]["camera_intrinsic"].as_array().unwrap().len() == 3);
}

#[test]
fn camera_table_errors_name_the_file() {
    let tmp = TempDir::new("occ-data-test", "nusc-bad");
    let dir = tmp.path().join("v1.0-mini");
    let mut rng = ChaCha8Rng::seed_from_u64(34);
    write_scene(&dir, &mut rng);
    // a sample without CAM_BACK
    let sd: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("sample_data.json")).unwrap())
            .unwrap();
    let kept: Vec<serde_json::Value> = sd
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["token"] != "sd3")
        .cloned()
        .collect();
    std::fs::write(
        dir.join("sample_data.json"),
        serde_json::to_string(&kept).unwrap(),
    )
    .unwrap();
    let t = NuscenesTables::load(&dir).unwrap();
    let e = t.sample_cameras("sample0").unwrap_err();
    assert!(
        e.to_string().contains("sample_data.json") && e.to_string().contains("CAM_BACK"),
        "{e}"
    );
    assert!(t
        .sample_cameras("nope")
        .unwrap_err()
        .to_string()
        .contains("sample.json"));
    // malformed JSON / missing field
    std::fs::write(
        dir.join("ego_pose.json"),
        "[{\"token\": \"e\", \"timestamp\": 1, \"rotation\": [1,0,0,0]}]",
    )
    .unwrap();
    let e = NuscenesTables::load(&dir).unwrap_err();
    assert!(
        matches!(e, DataError::Parse { .. })
            && e.to_string().contains("ego_pose.json")
            && e.to_string().contains("translation"),
        "{e}"
    );
    std::fs::remove_file(dir.join("sensor.json")).unwrap();
    std::fs::write(dir.join("ego_pose.json"), "[]").unwrap();
    assert!(matches!(
        NuscenesTables::load(&dir),
        Err(DataError::NotFound { .. })
    ));
}
