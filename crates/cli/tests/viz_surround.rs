//! `sparseocc viz --nuscenes`: a surround-camera key frame with its LiDAR points and a grid
//! projected into every camera, on generated surround scenes. The projections are checked against
//! the dataset path's cameras (`SurroundDataset::load`) and against the chain built by hand from
//! the JSON tables (with ego motion between the LiDAR and camera timestamps); LiDAR points on a
//! rendered surface land on a pixel of that surface's class colour; custom rigs and bad tables.

use occ_data::formats::nuscenes_occupancy::{NuscenesTables, SampleData, Sensor};
use occ_data::formats::occ3d::{read_labels_npz, FREE};
use occ_data::image::{read_image, read_png};
use occ_data::synthetic::classes::{nearest_class_by_chroma, nuscenes_class};
use occ_data::synthetic::{generate, Preset, SynthConfig, NUSCENES_VERSION};
use occ_geometry::mat::mat4_from_quat_translation;
use occ_geometry::{project_with, Mat4};
use occ_train::dataset::{DatasetFormat, SurroundDataset};
use occ_viz::{project_points, ProjectedPoint};
use std::path::{Path, PathBuf};

const W: usize = 352;
const H: usize = 128;
const NEAR_M: f64 = 0.5;

mod support;
use support::{copy_dir, fails_status_1 as fails, ok, p, run};

/// A temporary folder removed when dropped.
struct TempDir(PathBuf);
impl TempDir {
    fn new(tag: &str) -> Self {
        TempDir(support::tmp("vizsur", tag))
    }
}
impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn synth(root: &Path) {
    let cfg = SynthConfig {
        preset: Preset::Surround,
        seed: 5,
        sequences: vec![("scene-0001".into(), 2)],
        image_size: Some((W, H)),
    };
    generate(root, &cfg, &mut |_, _| {}).unwrap();
}

fn tables(root: &Path) -> NuscenesTables {
    NuscenesTables::load(&root.join(NUSCENES_VERSION)).unwrap()
}

fn rewrite(root: &Path, t: NuscenesTables) {
    let dir = root.join(NUSCENES_VERSION);
    NuscenesTables::new(
        dir.clone(),
        t.sample,
        t.sample_data,
        t.calibrated_sensor,
        t.ego_pose,
        t.sensor,
    )
    .write(&dir)
    .unwrap();
}

fn open(root: &Path) -> SurroundDataset {
    let pipeline = occ_data::image::ImagePipelineConfig {
        out_width: W,
        out_height: H,
        ..occ_data::image::ImagePipelineConfig::semantic_kitti()
    };
    SurroundDataset::open(
        root,
        DatasetFormat::Occ3d,
        &["*".to_string()],
        &[],
        pipeline,
        None,
        None,
    )
    .unwrap()
}

/// Pixels of the points as [`project_points`] puts them, by point index.
fn pixels(pts: &[ProjectedPoint]) -> Vec<(usize, (usize, usize))> {
    pts.iter().map(|q| (q.index, q.pixel())).collect()
}

fn channel_of(t: &NuscenesTables, sd: &SampleData) -> String {
    let cs = t
        .calibrated_sensor
        .iter()
        .find(|c| c.token == sd.calibrated_sensor_token)
        .unwrap();
    t.sensor
        .iter()
        .find(|s| s.token == cs.sensor_token)
        .unwrap()
        .channel
        .clone()
}

// --- the projection chain built by hand from the JSON (no occ-data table code) ------------------

fn json(root: &Path, name: &str) -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(root.join(NUSCENES_VERSION).join(name)).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn find<'a>(rows: &'a [serde_json::Value], token: &str) -> &'a serde_json::Value {
    rows.iter().find(|r| r["token"] == token).unwrap()
}

fn f3(v: &serde_json::Value) -> [f64; 3] {
    [0, 1, 2].map(|i| v[i].as_f64().unwrap())
}

/// Rigid transform from a (w, x, y, z) quaternion and a translation (occ-geometry's formula, which
/// its own tests check against rotation properties).
fn pose(q: &serde_json::Value, t: &serde_json::Value) -> Mat4 {
    let q = [0, 1, 2, 3].map(|i| q[i].as_f64().unwrap());
    mat4_from_quat_translation(q, f3(t)).unwrap()
}

fn apply(m: &Mat4, p: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3])
}

/// Inverse of a rigid transform.
fn inv(m: &Mat4) -> Mat4 {
    let mut o = [[0.0; 4]; 4];
    for r in 0..3 {
        for c in 0..3 {
            o[r][c] = m[c][r];
        }
        o[r][3] = -(0..3).map(|k| m[k][r] * m[k][3]).sum::<f64>();
    }
    o[3][3] = 1.0;
    o
}

/// `(u, v)` of LiDAR-frame point `p` in the camera of sample_data `cam_sd`, with ego motion:
/// lidar -> ego(t_lidar) -> global -> ego(t_cam) -> camera -> K (or, `ignore_motion`, with the
/// ego pose of the LiDAR for both).
fn hand_project(
    root: &Path,
    lidar_sd: &str,
    cam_sd: &str,
    points: &[[f64; 3]],
    ignore_motion: bool,
) -> Vec<Option<[f64; 2]>> {
    let sd = json(root, "sample_data.json");
    let cs = json(root, "calibrated_sensor.json");
    let ep = json(root, "ego_pose.json");
    let (l, c) = (find(&sd, lidar_sd), find(&sd, cam_sd));
    let lcs = find(&cs, l["calibrated_sensor_token"].as_str().unwrap());
    let ccs = find(&cs, c["calibrated_sensor_token"].as_str().unwrap());
    let lep = find(&ep, l["ego_pose_token"].as_str().unwrap());
    let cep = if ignore_motion {
        lep
    } else {
        find(&ep, c["ego_pose_token"].as_str().unwrap())
    };
    let ego_from_lidar = pose(&lcs["rotation"], &lcs["translation"]);
    let global_from_ego_l = pose(&lep["rotation"], &lep["translation"]);
    let global_from_ego_c = pose(&cep["rotation"], &cep["translation"]);
    let ego_from_cam = pose(&ccs["rotation"], &ccs["translation"]);
    let k = &ccs["camera_intrinsic"];
    let kk = |r: usize, c: usize| k[r][c].as_f64().unwrap();
    points
        .iter()
        .map(|&q| {
            let g = apply(&global_from_ego_l, apply(&ego_from_lidar, q));
            let cam = apply(&inv(&ego_from_cam), apply(&inv(&global_from_ego_c), g));
            (cam[2] > NEAR_M).then(|| {
                [
                    kk(0, 0) * cam[0] / cam[2] + kk(0, 2),
                    kk(1, 1) * cam[1] / cam[2] + kk(1, 2),
                ]
            })
        })
        .collect()
}

fn read_pcd(path: &Path) -> Vec<[f64; 3]> {
    let b = std::fs::read(path).unwrap();
    b.chunks_exact(20)
        .map(|r| {
            [0, 1, 2].map(|i| f32::from_le_bytes(r[4 * i..4 * i + 4].try_into().unwrap()) as f64)
        })
        .collect()
}

/// Moves the ego pose of every camera sample_data of `sample` by a translation and a yaw (as if the
/// car drove between the LiDAR and camera timestamps), each camera 30 ms after the LiDAR.
fn add_ego_motion(root: &Path, sample: &str) {
    let mut t = tables(root);
    let cam_sd: Vec<(String, String)> = t
        .sample_data
        .iter()
        .filter(|sd| sd.sample_token == sample && channel_of(&t, sd).starts_with("CAM_"))
        .map(|sd| (sd.token.clone(), sd.ego_pose_token.clone()))
        .collect();
    assert_eq!(cam_sd.len(), 6);
    let yaw = 3.0f64.to_radians();
    for (n, (sd_tok, ep_tok)) in cam_sd.iter().enumerate() {
        let ep = t.ego_pose.iter_mut().find(|e| &e.token == ep_tok).unwrap();
        ep.translation[0] += 0.9 + 0.1 * n as f64;
        ep.translation[1] -= 0.35;
        ep.rotation = [(yaw / 2.0).cos(), 0.0, 0.0, (yaw / 2.0).sin()];
        ep.timestamp += 30_000;
        let sd = t
            .sample_data
            .iter_mut()
            .find(|s| &s.token == sd_tok)
            .unwrap();
        sd.timestamp += 30_000;
    }
    rewrite(root, t);
}

#[test]
fn viz_projections_agree_with_the_dataset_path_and_the_tables_with_ego_motion() {
    let t = TempDir::new("agree");
    synth(&t.0);
    let ds0 = open(&t.0);
    let sample = ds0.frames()[1].frame.clone();
    add_ego_motion(&t.0, &sample);
    let mut ds = open(&t.0);
    ds.load_points = true;
    assert_eq!(ds.frames()[1].frame, sample);
    let views = ds.frame_views(1).unwrap();
    let points = views.read_points().unwrap();
    let s = ds.load::<rand_chacha::ChaCha8Rng>(1, None).unwrap();
    assert_eq!(
        s.size,
        (W, H),
        "the test-time image transform must be the identity"
    );
    assert_eq!(s.points.as_ref().unwrap(), &points);
    let raw = read_pcd(&views.lidar);
    assert_eq!(raw.len(), points.len());
    let tabs = tables(&t.0);
    let lidar_sd = tabs
        .sample_data
        .iter()
        .find(|sd| sd.sample_token == sample && channel_of(&tabs, sd) == "LIDAR_TOP")
        .unwrap()
        .token
        .clone();
    let (mut total, mut moved) = (0usize, 0usize);
    for (c, cam) in views.cameras.iter().enumerate() {
        let k = cam.view.camera;
        assert_eq!((k.width, k.height), (W, H));
        let viz = project_points(&points, &cam.view.img_from_lidar(), W, H, NEAR_M);
        assert!(viz.len() > 300, "{}: {} points", cam.channel, viz.len());
        // The dataset path's camera (what the network sees) puts every point on the same pixel.
        let m = s.cameras[c].img_from_lidar;
        let from_ds: Vec<(usize, (usize, usize))> = points
            .iter()
            .enumerate()
            .filter_map(|(i, q)| {
                let [u, v, d] = project_with(&m, q.map(f64::from))?;
                (d > NEAR_M && u >= -0.5 && v >= -0.5 && u < W as f64 - 0.5 && v < H as f64 - 0.5)
                    .then(|| (i, (u.round() as usize, v.round() as usize)))
            })
            .collect();
        assert_eq!(pixels(&viz), from_ds, "{}", cam.channel);
        // The chain from the JSON tables by hand agrees to well under a pixel.
        let hand = hand_project(&t.0, &lidar_sd, &cam.sample_data_token, &raw, false);
        let still = hand_project(&t.0, &lidar_sd, &cam.sample_data_token, &raw, true);
        for q in &viz {
            let h = hand[q.index].expect("in front of the camera");
            assert!(
                (h[0] - q.u).abs() < 1e-3 && (h[1] - q.v).abs() < 1e-3,
                "{} point {}: viz ({}, {}) vs tables ({}, {})",
                cam.channel,
                q.index,
                q.u,
                q.v,
                h[0],
                h[1]
            );
            total += 1;
            // Without the ego motion most points would land elsewhere.
            if still[q.index].is_none_or(|s| (s[0] - q.u).hypot(s[1] - q.v) > 2.0) {
                moved += 1;
            }
        }
    }
    assert!(
        moved * 10 > total * 8,
        "ego motion moves only {moved} of {total} points by > 2 px"
    );

    // The binary reports the same number of points in each camera.
    let out = t.0.join("out/frame.png");
    let text = ok(&[
        "viz",
        "--nuscenes",
        p(&t.0),
        "--sample",
        &sample,
        "--out",
        p(&out),
    ]);
    for cam in &views.cameras {
        let n = project_points(&points, &cam.view.img_from_lidar(), W, H, NEAR_M).len();
        assert!(
            text.contains(&format!("{} {n},", cam.channel))
                || text.contains(&format!("{} {n}\n", cam.channel)),
            "{}: {n} points; {text}",
            cam.channel
        );
    }
    assert!(text.contains("6 cameras"), "{text}");
    let img = read_png(&out).unwrap();
    assert!(
        img.width > 3 * 800 && img.height > 2 * 225,
        "{}x{}",
        img.width,
        img.height
    );
}

#[test]
fn lidar_points_land_on_their_surface_class_colour_in_every_camera() {
    let t = TempDir::new("colour");
    synth(&t.0);
    let ds = open(&t.0);
    let grid = ds.grid();
    let candidates: Vec<u8> = (1..=24).collect();
    let (mut n, mut agree) = (0usize, 0usize);
    // A negative control: the same check with every camera turned by 4 degrees about its
    // vertical axis (a calibration error) must agree much less often.
    let (mut n_bad, mut agree_bad) = (0usize, 0usize);
    let (sn, cs) = 4.0f64.to_radians().sin_cos();
    let turn: Mat4 = [
        [cs, 0.0, sn, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [-sn, 0.0, cs, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let mut seen_by = std::collections::HashMap::<usize, usize>::new();
    for i in 0..ds.frames().len() {
        let f = &ds.frames()[i];
        let labels = read_labels_npz(
            &t.0.join("gts")
                .join(&f.sequence)
                .join(&f.frame)
                .join("labels.npz"),
        )
        .unwrap();
        let views = ds.frame_views(i).unwrap();
        let points = views.read_points().unwrap();
        for cam in &views.cameras {
            let img = read_image(&cam.image).unwrap();
            let mut wrong = cam.view;
            wrong.cam_from_lidar = occ_geometry::mat4_mul(&turn, &cam.view.cam_from_lidar);
            let (mut cn, mut ca) = (0usize, 0usize);
            for (control, q) in project_points(&points, &wrong.img_from_lidar(), W, H, NEAR_M)
                .into_iter()
                .map(|q| (true, q))
                .chain(
                    project_points(&points, &cam.view.img_from_lidar(), W, H, NEAR_M)
                        .into_iter()
                        .map(|q| (false, q)),
                )
            {
                let pt = points[q.index].map(f64::from);
                let Some(ijk) = grid.voxel_of_point_m(pt) else {
                    continue;
                };
                let class = labels.semantics[grid.linear_index(ijk)];
                assert_ne!(class, FREE, "LiDAR return in a free voxel");
                let (x, y) = q.pixel();
                // The pixel, or one of its 8 neighbours (a point on an edge), shows the class.
                let hit = (-1i64..=1).any(|dy| {
                    (-1i64..=1).any(|dx| {
                        let (xx, yy) = (x as i64 + dx, y as i64 + dy);
                        xx >= 0
                            && yy >= 0
                            && img.pixel(xx as usize, yy as usize).is_some_and(|rgb| {
                                nearest_class_by_chroma(rgb, &candidates).map(nuscenes_class)
                                    == Some(class)
                            })
                    })
                });
                if control {
                    n_bad += 1;
                    agree_bad += usize::from(hit);
                    continue;
                }
                cn += 1;
                ca += usize::from(hit);
                if i == 0 {
                    *seen_by.entry(q.index).or_default() += 1;
                }
            }
            assert!(cn > 300, "{}: {cn} points on surfaces", cam.channel);
            let rate = ca as f64 / cn as f64;
            eprintln!("frame {i} {}: {ca}/{cn} = {rate:.3}", cam.channel);
            assert!(
                rate > 0.85,
                "{}: {ca}/{cn} points on their class colour",
                cam.channel
            );
            n += cn;
            agree += ca;
        }
    }
    let rate = agree as f64 / n as f64;
    eprintln!("points on their surface's class colour: {agree}/{n} = {rate:.4}");
    assert!(rate > 0.93, "{agree}/{n}");
    let bad = agree_bad as f64 / n_bad as f64;
    eprintln!("with a 4 degree calibration error: {agree_bad}/{n_bad} = {bad:.4}");
    assert!(
        bad < rate - 0.1,
        "the check does not see a 4 degree error: {bad} vs {rate}"
    );
    // Neighbouring cameras overlap: some points are checked in two cameras.
    assert!(seen_by.values().filter(|&&c| c >= 2).count() > 20);
}

#[test]
fn custom_rigs_and_bad_tables_are_handled() {
    let t = TempDir::new("rig");
    let base = t.0.join("base");
    synth(&base);
    let ds = open(&base);
    let (scene, s0, s1) = (
        ds.frames()[0].sequence.clone(),
        ds.frames()[0].frame.clone(),
        ds.frames()[1].frame.clone(),
    );
    assert_eq!(scene, "scene-0001");
    let labels = base.join("gts").join(&scene).join(&s1).join("labels.npz");

    // The frame by scene and index is the frame by token; a grid over it changes the picture.
    let a = t.0.join("a.png");
    let b = t.0.join("b.png");
    let c = t.0.join("c.png");
    ok(&[
        "viz",
        "--nuscenes",
        p(&base),
        "--scene",
        &scene,
        "--index",
        "1",
        "--out",
        p(&a),
    ]);
    ok(&[
        "viz",
        "--nuscenes",
        p(&base),
        "--sample",
        &s1,
        "--out",
        p(&b),
    ]);
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    let text = ok(&[
        "viz",
        "--nuscenes",
        p(&base),
        "--sample",
        &s1,
        "--labels",
        p(&labels),
        "--out",
        p(&c),
    ]);
    assert!(text.contains("6 cameras"), "{text}");
    assert_ne!(std::fs::read(&a).unwrap(), std::fs::read(&c).unwrap());
    // --scene alone is index 0.
    let d = t.0.join("d.png");
    ok(&[
        "viz",
        "--nuscenes",
        p(&base),
        "--scene",
        &scene,
        "--out",
        p(&d),
    ]);
    let e = t.0.join("e.png");
    ok(&[
        "viz",
        "--nuscenes",
        p(&base),
        "--sample",
        &s0,
        "--out",
        p(&e),
    ]);
    assert_eq!(std::fs::read(&d).unwrap(), std::fs::read(&e).unwrap());

    // A custom rig: four cameras, one under a new channel name.
    let rig = t.0.join("rig");
    copy_dir(&base, &rig);
    let mut tb = tables(&rig);
    let drop: Vec<String> = tb
        .sensor
        .iter()
        .filter(|s| s.channel == "CAM_BACK_LEFT" || s.channel == "CAM_BACK_RIGHT")
        .map(|s| s.token.clone())
        .collect();
    let calib_dropped: Vec<String> = tb
        .calibrated_sensor
        .iter()
        .filter(|c| drop.contains(&c.sensor_token))
        .map(|c| c.token.clone())
        .collect();
    tb.sample_data
        .retain(|sd| !calib_dropped.contains(&sd.calibrated_sensor_token));
    tb.sensor.retain(|s| !drop.contains(&s.token));
    for s in tb.sensor.iter_mut() {
        if s.channel == "CAM_BACK" {
            s.channel = "CAM_REAR_WIDE".into();
        }
    }
    assert_eq!(
        tb.sensor.iter().filter(|s| s.modality == "camera").count(),
        4
    );
    rewrite(&rig, tb);
    let mut rds = open(&rig);
    assert_eq!(
        rds.tables().camera_channels(),
        [
            "CAM_FRONT",
            "CAM_FRONT_RIGHT",
            "CAM_FRONT_LEFT",
            "CAM_REAR_WIDE"
        ]
    );
    // The dataset path's six default cameras are no longer there: a clear error.
    let err = rds
        .load::<rand_chacha::ChaCha8Rng>(0, None)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("CAM_BACK") && err.contains("sample_data.json"),
        "{err}"
    );
    rds.set_cameras(rds.tables().camera_channels()).unwrap();
    let s = rds.load::<rand_chacha::ChaCha8Rng>(0, None).unwrap();
    assert_eq!(s.cameras.len(), 4);
    let r4 = t.0.join("rig4.png");
    let text = ok(&[
        "viz",
        "--nuscenes",
        p(&rig),
        "--sample",
        &s0,
        "--out",
        p(&r4),
    ]);
    assert!(
        text.contains("4 cameras") && text.contains("CAM_REAR_WIDE"),
        "{text}"
    );
    let r2 = t.0.join("rig2.png");
    let text = ok(&[
        "viz",
        "--nuscenes",
        p(&rig),
        "--sample",
        &s0,
        "--cameras",
        "CAM_REAR_WIDE,CAM_FRONT",
        "--out",
        p(&r2),
    ]);
    assert!(text.contains("2 cameras"), "{text}");
    // 2x2 for four cameras, 2x1 for two: the same height per row, so the four-camera picture is
    // taller.
    let (i4, i2) = (read_png(&r4).unwrap(), read_png(&r2).unwrap());
    assert!(
        i4.height > i2.height + 200,
        "{} vs {}",
        i4.height,
        i2.height
    );
    let err = fails(&[
        "viz",
        "--nuscenes",
        p(&rig),
        "--sample",
        &s0,
        "--cameras",
        "CAM_BACK",
        "--out",
        p(&r2),
    ]);
    assert!(
        err.contains("sensor.json") && err.contains("CAM_BACK"),
        "{err}"
    );

    // Bad tables: each a clear error naming the file and the key, and no picture.
    let case = |name: &str, edit: &dyn Fn(&mut NuscenesTables)| -> PathBuf {
        let d = t.0.join(name);
        copy_dir(&base, &d);
        let mut tb = tables(&d);
        edit(&mut tb);
        rewrite(&d, tb);
        d
    };
    let out = t.0.join("bad.png");
    // `viz --nuscenes ROOT ARGS --out OUT` fails with status 1 and an error naming each of `want`.
    let viz_fails = |root: &Path, args: &[&str], want: &[&str]| {
        let err = fails(&[&["viz", "--nuscenes", p(root)], args, &["--out", p(&out)]].concat());
        for w in want {
            assert!(err.contains(w), "{err}");
        }
    };
    let no_cam = case("no_cam_row", &|tb| {
        let drop: Vec<String> = tb
            .sample_data
            .iter()
            .filter(|sd| sd.sample_token == s1 && channel_of(tb, sd) == "CAM_BACK")
            .map(|sd| sd.token.clone())
            .collect();
        tb.sample_data.retain(|sd| !drop.contains(&sd.token));
    });
    viz_fails(
        &no_cam,
        &["--sample", &s1],
        &["sample_data.json", "CAM_BACK", &s1],
    );
    // The other frame of that scene is still fine.
    ok(&[
        "viz",
        "--nuscenes",
        p(&no_cam),
        "--sample",
        &s0,
        "--out",
        p(&out),
    ]);
    std::fs::remove_file(&out).unwrap();
    let no_lidar = case("no_lidar_row", &|tb| {
        let keep: Vec<SampleData> = tb
            .sample_data
            .iter()
            .filter(|sd| !(sd.sample_token == s1 && channel_of(tb, sd) == "LIDAR_TOP"))
            .cloned()
            .collect();
        tb.sample_data = keep;
    });
    viz_fails(
        &no_lidar,
        &["--sample", &s1],
        &["sample_data.json", "LIDAR_TOP"],
    );
    let no_sensor = case("no_sensor", &|tb| {
        let keep: Vec<Sensor> = tb
            .sensor
            .iter()
            .filter(|s| s.channel != "CAM_FRONT")
            .cloned()
            .collect();
        tb.sensor = keep;
    });
    viz_fails(&no_sensor, &["--sample", &s0], &["sensor.json"]);
    let no_calib = case("no_calib", &|tb| {
        let cam = tb
            .sensor
            .iter()
            .find(|s| s.channel == "CAM_FRONT_LEFT")
            .unwrap()
            .token
            .clone();
        tb.calibrated_sensor.retain(|c| c.sensor_token != cam);
    });
    viz_fails(&no_calib, &["--sample", &s0], &["calibrated_sensor.json"]);
    // A table that is not JSON, an image that is missing, a LiDAR sweep that is cut short.
    let broken = t.0.join("broken");
    copy_dir(&base, &broken);
    let sd_json = broken.join(NUSCENES_VERSION).join("sample_data.json");
    let text = std::fs::read(&sd_json).unwrap();
    std::fs::write(&sd_json, &text[..text.len() / 2]).unwrap();
    viz_fails(&broken, &["--sample", &s0], &["sample_data.json"]);
    std::fs::write(&sd_json, &text).unwrap();
    let views = open(&broken).frame_views(0).unwrap();
    std::fs::remove_file(&views.cameras[3].image).unwrap();
    let img_name = views.cameras[3]
        .image
        .file_name()
        .unwrap()
        .to_str()
        .unwrap();
    viz_fails(&broken, &["--sample", &s0], &[img_name]);
    let pcd = std::fs::read(&views.lidar).unwrap();
    std::fs::write(&views.lidar, &pcd[..pcd.len() - 7]).unwrap();
    viz_fails(
        &broken,
        &["--sample", &s0, "--cameras", "CAM_FRONT"],
        &[".pcd.bin", "20 bytes"],
    );
    // Frame selection and grid files.
    viz_fails(
        &base,
        &["--sample", "feedbeef"],
        &["sample.json", "feedbeef"],
    );
    viz_fails(
        &base,
        &["--scene", &scene, "--index", "7"],
        &["out of range", "has 2"],
    );
    viz_fails(&base, &["--scene", "scene-9"], &["scene.json", "scene-9"]);
    viz_fails(&base, &[], &["--sample", "--scene"]);
    viz_fails(
        &base,
        &[
            "--sample",
            &s1,
            "--labels",
            p(&labels),
            "--pred",
            p(&labels),
        ],
        &["not both"],
    );
    let txt = t.0.join("grid.txt");
    std::fs::write(&txt, b"x").unwrap();
    viz_fails(
        &base,
        &["--sample", &s1, "--labels", p(&txt)],
        &["grid.txt", "labels.npz"],
    );
    assert!(!out.exists(), "no picture is written on an error");
    // --index without --scene, --image with --nuscenes: usage errors (clap, status 2).
    let o = run(&[
        "viz",
        "--nuscenes",
        p(&base),
        "--index",
        "1",
        "--out",
        p(&out),
    ]);
    assert_eq!(o.status.code(), Some(2));
    let o = run(&[
        "viz",
        "--nuscenes",
        p(&base),
        "--sample",
        &s0,
        "--image",
        p(&a),
        "--calib",
        p(&a),
        "--out",
        p(&out),
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(!out.exists());
}
