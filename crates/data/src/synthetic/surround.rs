//! Writer of the Occ3D-nuScenes layout with six surround cameras (`surround`).

use super::classes::nuscenes_class;
use super::layout::Style;
use super::render::{render, scan, CamRig};
use super::scene::{SequenceScene, CAMERA_T_MAX_M};
use super::util::{derive_seed, mix64};
use super::vis::{Marker, VisBox};
use super::{Stats, SynthConfig, SynthSequence, NUSCENES_VERSION};
use crate::error::DataError;
use crate::formats::io::{create_dir_all, write_atomic};
use crate::formats::nuscenes_occupancy::{
    CalibratedSensor, EgoPose, NuscenesTables, Sample, SampleData, Sensor, CAMERA_CHANNELS,
    LIDAR_CHANNEL,
};
use crate::formats::occ3d::{write_labels_npz, Occ3dLabels};
use crate::image::{write_png, RgbImage};
use occ_geometry::{mat4_identity, mat4_mul, quat_from_mat4, Mat4, PinholeCamera};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Height of the ego frame origin above the road (m): with the Occ3D grid from z = −1 the road
/// surface (ego z = −0.2) is a voxel boundary.
pub(crate) const EGO_HEIGHT_M: f64 = 0.2;
/// `LIDAR_TOP` position in the ego frame (axes parallel to the ego's).
pub(crate) const LIDAR_IN_EGO_M: [f64; 3] = [0.94, 0.0, 1.84];
/// nuScenes camera intrinsics at 1600×900.
const NUSC_F: f64 = 1266.4;
const NUSC_CX: f64 = 816.3;
const NUSC_CY: f64 = 491.5;
const NUSC_IMAGE: (usize, usize) = (1600, 900);
/// Microseconds between key frames (2 Hz).
const KEYFRAME_DT_US: i64 = 500_000;
const BASE_TIMESTAMP_US: i64 = 1_600_000_000_000_000;

/// The six cameras: channel (in [`CAMERA_CHANNELS`] order), yaw (deg, 0 = forward, positive to
/// the left) and position in the ego frame, laid out like nuScenes.
pub(crate) const CAMERA_MOUNTS: [(&str, f64, [f64; 3]); 6] = [
    ("CAM_FRONT", 0.0, [1.70, 0.0, 1.51]),
    ("CAM_FRONT_RIGHT", -55.0, [1.55, -0.49, 1.50]),
    ("CAM_FRONT_LEFT", 55.0, [1.52, 0.49, 1.51]),
    ("CAM_BACK", 180.0, [0.03, 0.0, 1.57]),
    ("CAM_BACK_LEFT", 110.0, [1.04, 0.48, 1.56]),
    ("CAM_BACK_RIGHT", -110.0, [1.04, -0.48, 1.56]),
];

/// Intrinsics for an image of `width × height`: nuScenes' scaled by `s = width/1600`, the scaled
/// frame (height `round(900·s)`) cut to `height` rows from the bottom (BEVDet-style crop of the
/// sky), so `cy = 491.5·s − (round(900·s) − height)`.
pub(crate) fn surround_camera(width: usize, height: usize) -> PinholeCamera {
    let s = width as f64 / NUSC_IMAGE.0 as f64;
    let scaled_h = (NUSC_IMAGE.1 as f64 * s).round();
    PinholeCamera {
        fx: NUSC_F * s,
        fy: NUSC_F * s,
        cx: NUSC_CX * s,
        cy: NUSC_CY * s - (scaled_h - height as f64),
        width,
        height,
    }
}

/// `ego_from_cam` of a camera with the given yaw and position (camera axes: x right, y down,
/// z forward; horizontal optical axis).
pub(crate) fn ego_from_cam(yaw_deg: f64, t: [f64; 3]) -> Mat4 {
    let (s, c) = yaw_deg.to_radians().sin_cos();
    [
        [s, 0.0, c, t[0]],
        [-c, 0.0, s, t[1]],
        [0.0, -1.0, 0.0, t[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

fn translation(t: [f64; 3]) -> Mat4 {
    let mut m = mat4_identity();
    for a in 0..3 {
        m[a][3] = t[a];
    }
    m
}

/// The nuScenes scene name of a synthetic sequence: `scene-<name>`, unless `name` already starts
/// with `scene-` (`--sequences scene-0001:2` names the scene `scene-0001`, not `scene-scene-0001`).
pub fn scene_name_of(name: &str) -> String {
    if name.starts_with("scene-") {
        name.to_string()
    } else {
        format!("scene-{name}")
    }
}

/// `scene.json` record (nuScenes v1.0 schema).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct SceneRecord {
    pub token: String,
    pub log_token: String,
    pub nbr_samples: usize,
    pub first_sample_token: String,
    pub last_sample_token: String,
    pub name: String,
    pub description: String,
}

/// nuScenes tables accumulated over scenes.
#[derive(Default)]
pub(super) struct Tables {
    sample: Vec<Sample>,
    sample_data: Vec<SampleData>,
    calibrated_sensor: Vec<CalibratedSensor>,
    ego_pose: Vec<EgoPose>,
    sensor: Vec<Sensor>,
    scene: Vec<SceneRecord>,
}

impl Tables {
    pub(super) fn write(self, out: &Path, stats: &mut Stats) -> Result<(), DataError> {
        let dir = out.join(NUSCENES_VERSION);
        let scene = self.scene;
        let t = NuscenesTables::new(
            dir.clone(),
            self.sample,
            self.sample_data,
            self.calibrated_sensor,
            self.ego_pose,
            self.sensor,
        );
        t.write(&dir)?;
        for name in [
            "sample.json",
            "sample_data.json",
            "calibrated_sensor.json",
            "ego_pose.json",
            "sensor.json",
        ] {
            stats.wrote(&dir.join(name));
        }
        let p = dir.join("scene.json");
        let bytes =
            serde_json::to_vec_pretty(&scene).map_err(|e| DataError::format(&p, e.to_string()))?;
        write_atomic(&p, &bytes)?;
        stats.wrote(&p);
        Ok(())
    }
}

/// A 32-hex-digit token derived from the seed and a label.
fn token(seed: u64, label: &str) -> String {
    let a = derive_seed(seed, label);
    format!("{a:016x}{:016x}", mix64(a ^ 0x5eed_70ce))
}

pub(super) fn write_scene(
    out: &Path,
    cfg: &SynthConfig,
    name: &str,
    frames: usize,
    stats: &mut Stats,
    tables: &mut Tables,
    tick: &mut dyn FnMut(),
) -> Result<SynthSequence, DataError> {
    let grid = cfg.preset.grid();
    let dims = grid.dims;
    let n_vox = grid.num_voxels();
    let scene = SequenceScene::new(
        cfg.seed,
        name,
        frames,
        Style::Nuscenes,
        grid,
        EGO_HEIGHT_M,
        &[3.2, 4.0, 4.8],
    );
    let (w, h) = cfg.image_size();
    let cam = surround_camera(w, h);
    let lidar = cfg.preset.lidar();
    let scene_name = scene_name_of(name);
    let seed = cfg.seed;
    let scene_token = token(seed, &format!("scene:{name}"));
    if stats.class_voxels.len() < 18 {
        stats.class_voxels = vec![0; 18];
    }
    // sensors are shared by all scenes
    if tables.sensor.is_empty() {
        for ch in CAMERA_CHANNELS {
            tables.sensor.push(Sensor {
                token: token(0, &format!("sensor:{ch}")),
                channel: ch.into(),
                modality: "camera".into(),
            });
        }
        tables.sensor.push(Sensor {
            token: token(0, &format!("sensor:{LIDAR_CHANNEL}")),
            channel: LIDAR_CHANNEL.into(),
            modality: "lidar".into(),
        });
    }
    let k = vec![
        vec![cam.fx, 0.0, cam.cx],
        vec![0.0, cam.fy, cam.cy],
        vec![0.0, 0.0, 1.0],
    ];
    let mut calib_tokens = Vec::new();
    for (ch, yaw, t) in CAMERA_MOUNTS {
        let m = ego_from_cam(yaw, t);
        let tok = token(seed, &format!("calibrated_sensor:{name}:{ch}"));
        tables.calibrated_sensor.push(CalibratedSensor {
            token: tok.clone(),
            sensor_token: token(0, &format!("sensor:{ch}")),
            translation: t,
            rotation: quat_from_mat4(&m),
            camera_intrinsic: k.clone(),
        });
        calib_tokens.push(tok);
    }
    let lidar_calib = token(seed, &format!("calibrated_sensor:{name}:{LIDAR_CHANNEL}"));
    tables.calibrated_sensor.push(CalibratedSensor {
        token: lidar_calib.clone(),
        sensor_token: token(0, &format!("sensor:{LIDAR_CHANNEL}")),
        translation: LIDAR_IN_EGO_M,
        rotation: [1.0, 0.0, 0.0, 0.0],
        camera_intrinsic: Vec::new(),
    });
    let scene_index = tables.scene.len() as i64;
    let ts = |i: usize| BASE_TIMESTAMP_US + scene_index * 1_000_000_000 + i as i64 * KEYFRAME_DT_US;
    let sample_tok = |i: usize| token(seed, &format!("sample:{name}:{i}"));
    let sd_tok = |ch: &str, i: usize| token(seed, &format!("sample_data:{name}:{ch}:{i}"));
    let file_of =
        |ch: &str, i: usize, ext: &str| format!("samples/{ch}/{scene_name}__{ch}__{}.{ext}", ts(i));
    for ch in CAMERA_CHANNELS
        .iter()
        .chain(std::iter::once(&LIDAR_CHANNEL))
    {
        create_dir_all(&out.join("samples").join(ch))?;
    }
    for group in scene.frame_groups() {
        let world = scene.build_window(group.clone());
        for i in group {
            let off = scene.frame_off(i);
            let ego = scene.sensor_pos[i];
            let world_from_ego = translation(ego);
            let cam_vis = VisBox::new(off, dims);
            let lidar_vis = VisBox::new(off, dims);
            let stoken = sample_tok(i);
            let prev_next = |j: Option<usize>, f: &dyn Fn(usize) -> String| {
                j.filter(|&j| j < frames).map(f).unwrap_or_default()
            };
            tables.sample.push(Sample {
                token: stoken.clone(),
                timestamp: ts(i),
                prev: prev_next(i.checked_sub(1), &sample_tok),
                next: prev_next(Some(i + 1), &sample_tok),
                scene_token: scene_token.clone(),
            });
            // A sensor's key-frame record: its ego pose and its `sample_data` row.
            let key_frame_record = |tables: &mut Tables,
                                    ch: &str,
                                    calib: &str,
                                    fileformat: &str,
                                    [height, width]: [u32; 2],
                                    filename: String| {
                let ep = token(seed, &format!("ego_pose:{name}:{ch}:{i}"));
                tables.ego_pose.push(EgoPose {
                    token: ep.clone(),
                    timestamp: ts(i),
                    rotation: [1.0, 0.0, 0.0, 0.0],
                    translation: ego,
                });
                tables.sample_data.push(SampleData {
                    token: sd_tok(ch, i),
                    sample_token: stoken.clone(),
                    ego_pose_token: ep,
                    calibrated_sensor_token: calib.to_string(),
                    timestamp: ts(i),
                    fileformat: fileformat.into(),
                    is_key_frame: true,
                    height,
                    width,
                    filename,
                    prev: prev_next(i.checked_sub(1), &|j| sd_tok(ch, j)),
                    next: prev_next(Some(i + 1), &|j| sd_tok(ch, j)),
                });
            };
            let frame_seed = derive_seed(scene.seed, &format!("frame:{i}"));
            for (ci, (ch, yaw, t)) in CAMERA_MOUNTS.iter().enumerate() {
                let rig = CamRig {
                    cam,
                    world_from_cam: mat4_mul(&world_from_ego, &ego_from_cam(*yaw, *t)),
                };
                let boxes = [&cam_vis];
                let img = render(
                    &world,
                    &rig,
                    CAMERA_T_MAX_M,
                    scene.seed,
                    frame_seed ^ ci as u64,
                    Some(Marker { boxes: &boxes }),
                );
                let rel = file_of(ch, i, "png");
                let p = out.join(&rel);
                write_png(
                    &p,
                    &RgbImage {
                        width: w,
                        height: h,
                        data: img,
                    },
                )?;
                stats.wrote(&p);
                let hw = [h as u32, w as u32];
                key_frame_record(tables, ch, &calib_tokens[ci], "png", hw, rel);
            }
            let lidar_origin = [0, 1, 2].map(|a| ego[a] + LIDAR_IN_EGO_M[a]);
            let boxes = [&lidar_vis];
            let s = scan(&world, &lidar, lidar_origin, Some(Marker { boxes: &boxes }));
            let mut bytes = Vec::with_capacity(s.points.len() * 20);
            for (p, r) in s.points.iter().zip(&s.rings) {
                for v in [p[0], p[1], p[2], p[3] * 255.0, *r as f32] {
                    bytes.extend_from_slice(&v.to_le_bytes());
                }
            }
            let rel = file_of(LIDAR_CHANNEL, i, "pcd.bin");
            let p = out.join(&rel);
            write_atomic(&p, &bytes)?;
            stats.wrote(&p);
            stats.lidar_points += s.points.len();
            key_frame_record(tables, LIDAR_CHANNEL, &lidar_calib, "pcd", [0, 0], rel);

            let semantics: Vec<u8> = scene
                .frame_classes(&world, i)
                .into_iter()
                .map(nuscenes_class)
                .collect();
            for &c in &semantics {
                if (c as usize) < stats.class_voxels.len() {
                    stats.class_voxels[c as usize] += 1;
                }
            }
            let mask_camera = cam_vis.extract(off, dims);
            stats.unobserved +=
                mask_camera.iter().filter(|&&v| v == 0).count() as f64 / n_vox as f64;
            let labels = Occ3dLabels {
                semantics,
                mask_lidar: lidar_vis.extract(off, dims),
                mask_camera,
                dims,
            };
            let dir = out.join("gts").join(&scene_name).join(&stoken);
            create_dir_all(&dir)?;
            let p = dir.join("labels.npz");
            write_labels_npz(&p, &labels)?;
            stats.wrote(&p);
            stats.frames += 1;
            tick();
        }
    }
    tables.scene.push(SceneRecord {
        token: scene_token.clone(),
        log_token: token(seed, &format!("log:{name}")),
        nbr_samples: frames,
        first_sample_token: sample_tok(0),
        last_sample_token: sample_tok(frames - 1),
        name: scene_name,
        description: format!("sparseocc synthetic scene {name} (seed {seed})"),
    });
    Ok(SynthSequence {
        name: name.to_string(),
        frames,
        step_m: scene.step_m,
        scene_token: Some(scene_token),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use occ_geometry::transform_point;

    #[test]
    fn camera_mounts_look_where_their_names_say() {
        for (ch, yaw, t) in CAMERA_MOUNTS {
            let m = ego_from_cam(yaw, t);
            let fwd = transform_point(&m, [0.0, 0.0, 1.0]);
            let d = [fwd[0] - t[0], fwd[1] - t[1], fwd[2] - t[2]];
            let (s, c) = yaw.to_radians().sin_cos();
            assert!(
                (d[0] - c).abs() < 1e-12 && (d[1] - s).abs() < 1e-12 && d[2].abs() < 1e-12,
                "{ch}"
            );
            if ch.contains("LEFT") {
                assert!(d[1] > 0.5);
            }
            if ch.contains("RIGHT") {
                assert!(d[1] < -0.5);
            }
            if ch.contains("BACK") {
                assert!(d[0] < 0.0);
            }
            // image y axis points down
            let down = transform_point(&m, [0.0, 1.0, 0.0]);
            assert!((down[2] - t[2] + 1.0).abs() < 1e-12);
            // the quaternion written to calibrated_sensor.json reproduces the rotation
            let q = quat_from_mat4(&m);
            let r = occ_geometry::mat4_from_quat_translation(q, t).unwrap();
            for i in 0..4 {
                for j in 0..4 {
                    assert!((r[i][j] - m[i][j]).abs() < 1e-12);
                }
            }
        }
        let cam = surround_camera(704, 256);
        assert!((cam.fx - 557.216).abs() < 1e-9 && (cam.cy - (491.5 * 0.44 - 140.0)).abs() < 1e-9);
        assert_eq!(token(1, "a"), token(1, "a"));
        assert_ne!(token(1, "a"), token(2, "a"));
        assert_eq!(token(1, "a").len(), 32);
    }
}
