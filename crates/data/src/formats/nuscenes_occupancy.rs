//! nuScenes-Occupancy (OpenOccupancy) ground truth and the nuScenes v1.0 camera tables
//! (docs/formats.md §3).
//!
//! Ground truth: `nuScenes-Occupancy/scene_<scene_token>/occupancy/<lidar_token>.npy`, a sparse
//! `N x 4` array `[z, y, x, cls]` (or `N x 7` `[z, y, x, vx, vy, vz, cls]`) of occupied voxels of
//! the 512x512x40 grid ([`occ_geometry::VoxelGrid::nuscenes_occupancy`], LiDAR frame). Training
//! classes: raw 0 (noise) -> 255, raw 1..16 unchanged, voxels not listed -> 0 (empty).
//!
//! Cameras: the public nuScenes v1.0 JSON schema (`sample.json`, `sample_data.json`,
//! `calibrated_sensor.json`, `ego_pose.json`, `sensor.json`). Rotations are unit quaternions
//! `(w, x, y, z)`; `calibrated_sensor` gives `ego_from_sensor`, `ego_pose` gives
//! `global_from_ego` at the sample_data timestamp.

use super::io::{create_dir_all, read_bytes, write_atomic};
use super::npy::{read_npy, write_npy};
use crate::error::DataError;
use occ_geometry::{
    mat4_from_quat_translation, mat4_inverse, mat4_mul, CameraView, Mat4, PinholeCamera,
};
use occ_labels::{EMPTY, IGNORE};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Grid dimensions `[X, Y, Z]`.
pub const DIMS: [usize; 3] = [512, 512, 40];
/// Number of training classes (0 = empty).
pub const NUM_CLASSES: usize = 17;
/// Training class names; index 0 is "empty" (raw 0 "noise" becomes 255).
pub const CLASS_NAMES: [&str; 17] = [
    "empty",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
];

/// Raw nuScenes-Occupancy class id -> training class (0 noise -> 255; 1..16 unchanged);
/// `None` for ids above 16.
pub fn training_class(raw: i64) -> Option<u8> {
    match raw {
        0 => Some(IGNORE),
        1..=16 => Some(raw as u8),
        _ => None,
    }
}

/// Dense training grid (flat C order `[x][y][z]` of `dims`) from sparse rows `[z, y, x, .., cls]`.
/// Voxels listed several times take the majority class (ties to the smaller class).
/// Errors (as text) on out-of-range coordinates or unknown classes.
pub fn dense_from_sparse(rows: &[Vec<i64>], dims: [usize; 3]) -> Result<Vec<u8>, String> {
    let n = dims[0] * dims[1] * dims[2];
    let mut dense = vec![0u8; n];
    let mut entries: Vec<(usize, u8)> = Vec::with_capacity(rows.len());
    for (r, row) in rows.iter().enumerate() {
        if row.len() < 4 {
            return Err(format!(
                "row {r} has {} columns, need at least 4",
                row.len()
            ));
        }
        let (z, y, x) = (row[0], row[1], row[2]);
        let cls = row[row.len() - 1];
        if x < 0
            || y < 0
            || z < 0
            || x >= dims[0] as i64
            || y >= dims[1] as i64
            || z >= dims[2] as i64
        {
            return Err(format!(
                "row {r}: voxel (x={x}, y={y}, z={z}) is outside the {dims:?} grid"
            ));
        }
        let c = training_class(cls).ok_or_else(|| format!("row {r}: unknown class id {cls}"))?;
        entries.push((
            (x as usize * dims[1] + y as usize) * dims[2] + z as usize,
            c,
        ));
    }
    entries.sort_unstable();
    let mut i = 0;
    while i < entries.len() {
        let v = entries[i].0;
        let mut best = (0usize, 0u8);
        while i < entries.len() && entries[i].0 == v {
            let c = entries[i].1;
            let mut k = 0;
            while i < entries.len() && entries[i] == (v, c) {
                k += 1;
                i += 1;
            }
            if k > best.0 {
                best = (k, c);
            }
        }
        dense[v] = best.1;
    }
    Ok(dense)
}

/// Read a sparse occupancy `.npy` (any integer or integral float dtype, shape `N x 4` or
/// `N x 7`) into the dense 512x512x40 training grid.
pub fn read_sparse_occupancy(path: &Path) -> Result<Vec<u8>, DataError> {
    let a = read_npy(path)?;
    let (n, cols) = match a.shape.as_slice() {
        [n, c] if *c == 4 || *c == 7 => (*n, *c),
        [0] => (0, 4),
        s => {
            return Err(DataError::format(
                path,
                format!("expected an N x 4 or N x 7 array, found shape {s:?}"),
            ))
        }
    };
    let vals = a.values.to_f64();
    let mut rows = Vec::with_capacity(n);
    for r in 0..n {
        let mut row = Vec::with_capacity(cols);
        for c in 0..cols {
            let v = vals[r * cols + c];
            if v.fract() != 0.0 || !v.is_finite() {
                return Err(DataError::format(
                    path,
                    format!("row {r} column {c}: {v} is not an integer"),
                ));
            }
            row.push(v as i64);
        }
        rows.push(row);
    }
    dense_from_sparse(&rows, DIMS).map_err(|e| DataError::format(path, e))
}

/// Write a dense training grid (512x512x40) as the sparse `N x 4` int64 `[z, y, x, cls]` file
/// (255 -> raw 0 noise; 0 = empty is not listed), atomically.
pub fn write_sparse_occupancy(path: &Path, dense: &[u8]) -> Result<(), DataError> {
    let n: usize = DIMS.iter().product();
    if dense.len() != n {
        return Err(DataError::InvalidArgument(format!(
            "occupancy grid has {} voxels, expected {n}",
            dense.len()
        )));
    }
    let mut flat: Vec<i64> = Vec::new();
    for (lin, &c) in dense.iter().enumerate() {
        if c == EMPTY {
            continue;
        }
        let raw = match c {
            IGNORE => 0,
            1..=16 => c as i64,
            _ => {
                return Err(DataError::InvalidArgument(format!(
                    "class {c} at flat index {lin} is not a nuScenes-Occupancy class"
                )))
            }
        };
        let z = lin % DIMS[2];
        let y = (lin / DIMS[2]) % DIMS[1];
        let x = lin / (DIMS[1] * DIMS[2]);
        flat.extend_from_slice(&[z as i64, y as i64, x as i64, raw]);
    }
    write_npy(path, &[flat.len() / 4, 4], &flat)
}

// ---------------------------------------------------------------------------------------------
// nuScenes v1.0 tables

/// `sample.json` record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    pub token: String,
    pub timestamp: i64,
    #[serde(default)]
    pub prev: String,
    #[serde(default)]
    pub next: String,
    pub scene_token: String,
}

/// `sample_data.json` record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SampleData {
    pub token: String,
    pub sample_token: String,
    pub ego_pose_token: String,
    pub calibrated_sensor_token: String,
    pub timestamp: i64,
    pub fileformat: String,
    pub is_key_frame: bool,
    pub height: u32,
    pub width: u32,
    pub filename: String,
    #[serde(default)]
    pub prev: String,
    #[serde(default)]
    pub next: String,
}

/// `calibrated_sensor.json` record: `ego_from_sensor` as translation + quaternion (w,x,y,z);
/// `camera_intrinsic` is 3x3 for cameras and empty otherwise.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibratedSensor {
    pub token: String,
    pub sensor_token: String,
    pub translation: [f64; 3],
    pub rotation: [f64; 4],
    #[serde(default)]
    pub camera_intrinsic: Vec<Vec<f64>>,
}

/// `ego_pose.json` record: `global_from_ego` at `timestamp`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EgoPose {
    pub token: String,
    pub timestamp: i64,
    pub rotation: [f64; 4],
    pub translation: [f64; 3],
}

/// `sensor.json` record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sensor {
    pub token: String,
    pub channel: String,
    pub modality: String,
}

/// The six surround cameras in the order used by BEVDet / OccFormer / SparseOcc.
pub const CAMERA_CHANNELS: [&str; 6] = [
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
];
/// The LiDAR channel whose frame the occupancy ground truth lives in.
pub const LIDAR_CHANNEL: &str = "LIDAR_TOP";

/// The five nuScenes tables needed for camera geometry, with token indices.
#[derive(Clone, Debug, Default)]
pub struct NuscenesTables {
    /// Folder the tables were read from (used in error messages; empty if built in memory).
    pub dir: PathBuf,
    pub sample: Vec<Sample>,
    pub sample_data: Vec<SampleData>,
    pub calibrated_sensor: Vec<CalibratedSensor>,
    pub ego_pose: Vec<EgoPose>,
    pub sensor: Vec<Sensor>,
    idx_sample: HashMap<String, usize>,
    idx_calib: HashMap<String, usize>,
    idx_ego: HashMap<String, usize>,
    idx_sensor: HashMap<String, usize>,
    key_frames_of_sample: HashMap<String, Vec<usize>>,
}

/// One camera of a sample.
#[derive(Clone, Debug, PartialEq)]
pub struct NuscenesCamera {
    pub channel: String,
    pub sample_data_token: String,
    /// Path relative to the dataset root, e.g. `samples/CAM_FRONT/....jpg`.
    pub filename: String,
    pub timestamp: i64,
    /// Intrinsics, image size, and `cam_from_lidar` (see [`NuscenesTables::sample_cameras`]).
    pub view: CameraView,
    /// `cam_from_ego` where ego is the ego pose at the LiDAR timestamp (for Occ3D, whose grid is
    /// in that ego frame).
    pub cam_from_ego_lidar: Mat4,
}

/// The LiDAR reference and six cameras of one key-frame sample.
#[derive(Clone, Debug, PartialEq)]
pub struct SampleCameras {
    pub sample_token: String,
    pub scene_token: String,
    pub lidar_token: String,
    pub lidar_filename: String,
    /// `ego_from_lidar` (LiDAR calibration).
    pub ego_from_lidar: Mat4,
    /// `global_from_ego` at the LiDAR timestamp.
    pub global_from_ego: Mat4,
    /// In [`CAMERA_CHANNELS`] order (or the order asked of [`NuscenesTables::sample_cameras_of`]).
    pub cameras: Vec<NuscenesCamera>,
}

fn load_table<T: for<'de> Deserialize<'de>>(dir: &Path, name: &str) -> Result<Vec<T>, DataError> {
    let path = dir.join(name);
    let bytes = read_bytes(&path)?;
    serde_json::from_slice(&bytes).map_err(|e| DataError::Parse {
        path,
        line: e.line(),
        detail: e.to_string(),
    })
}

fn write_table<T: Serialize>(dir: &Path, name: &str, rows: &[T]) -> Result<(), DataError> {
    let path = dir.join(name);
    let bytes =
        serde_json::to_vec_pretty(rows).map_err(|e| DataError::format(&path, e.to_string()))?;
    write_atomic(&path, &bytes)
}

impl NuscenesTables {
    /// Build from in-memory records (indices are computed here).
    pub fn new(
        dir: PathBuf,
        sample: Vec<Sample>,
        sample_data: Vec<SampleData>,
        calibrated_sensor: Vec<CalibratedSensor>,
        ego_pose: Vec<EgoPose>,
        sensor: Vec<Sensor>,
    ) -> Self {
        let mut t = NuscenesTables {
            dir,
            sample,
            sample_data,
            calibrated_sensor,
            ego_pose,
            sensor,
            ..Default::default()
        };
        t.reindex();
        t
    }

    fn reindex(&mut self) {
        self.idx_sample = self
            .sample
            .iter()
            .enumerate()
            .map(|(i, r)| (r.token.clone(), i))
            .collect();
        self.idx_calib = self
            .calibrated_sensor
            .iter()
            .enumerate()
            .map(|(i, r)| (r.token.clone(), i))
            .collect();
        self.idx_ego = self
            .ego_pose
            .iter()
            .enumerate()
            .map(|(i, r)| (r.token.clone(), i))
            .collect();
        self.idx_sensor = self
            .sensor
            .iter()
            .enumerate()
            .map(|(i, r)| (r.token.clone(), i))
            .collect();
        self.key_frames_of_sample.clear();
        for (i, sd) in self.sample_data.iter().enumerate() {
            if sd.is_key_frame {
                self.key_frames_of_sample
                    .entry(sd.sample_token.clone())
                    .or_default()
                    .push(i);
            }
        }
    }

    /// Read the five tables from a nuScenes version folder (e.g. `v1.0-trainval/`). Unknown
    /// JSON fields are ignored; missing required fields are errors naming the file.
    pub fn load(dir: &Path) -> Result<Self, DataError> {
        Ok(Self::new(
            dir.to_path_buf(),
            load_table(dir, "sample.json")?,
            load_table(dir, "sample_data.json")?,
            load_table(dir, "calibrated_sensor.json")?,
            load_table(dir, "ego_pose.json")?,
            load_table(dir, "sensor.json")?,
        ))
    }

    /// Write the five tables as JSON (creating `dir`), each atomically.
    pub fn write(&self, dir: &Path) -> Result<(), DataError> {
        create_dir_all(dir)?;
        write_table(dir, "sample.json", &self.sample)?;
        write_table(dir, "sample_data.json", &self.sample_data)?;
        write_table(dir, "calibrated_sensor.json", &self.calibrated_sensor)?;
        write_table(dir, "ego_pose.json", &self.ego_pose)?;
        write_table(dir, "sensor.json", &self.sensor)
    }

    fn table_path(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    fn channel_of(&self, sd: &SampleData) -> Result<(&CalibratedSensor, &Sensor), DataError> {
        let cs = self
            .idx_calib
            .get(&sd.calibrated_sensor_token)
            .map(|&i| &self.calibrated_sensor[i])
            .ok_or_else(|| {
                DataError::format(
                    &self.table_path("calibrated_sensor.json"),
                    format!(
                        "no calibrated_sensor with token {} (sample_data {})",
                        sd.calibrated_sensor_token, sd.token
                    ),
                )
            })?;
        let s = self
            .idx_sensor
            .get(&cs.sensor_token)
            .map(|&i| &self.sensor[i])
            .ok_or_else(|| {
                DataError::format(
                    &self.table_path("sensor.json"),
                    format!(
                        "no sensor with token {} (calibrated_sensor {})",
                        cs.sensor_token, cs.token
                    ),
                )
            })?;
        Ok((cs, s))
    }

    fn pose_of(&self, sd: &SampleData) -> Result<Mat4, DataError> {
        let path = self.table_path("ego_pose.json");
        let ep = self
            .idx_ego
            .get(&sd.ego_pose_token)
            .map(|&i| &self.ego_pose[i])
            .ok_or_else(|| {
                DataError::format(
                    &path,
                    format!(
                        "no ego_pose with token {} (sample_data {})",
                        sd.ego_pose_token, sd.token
                    ),
                )
            })?;
        mat4_from_quat_translation(ep.rotation, ep.translation).ok_or_else(|| {
            DataError::format(
                &path,
                format!("ego_pose {} has an invalid rotation/translation", ep.token),
            )
        })
    }

    /// Tokens of all samples, in table order.
    pub fn sample_tokens(&self) -> Vec<&str> {
        self.sample.iter().map(|s| s.token.as_str()).collect()
    }

    /// The key-frame LiDAR and six cameras of a sample, with
    /// `cam_from_lidar = cam_from_ego(t_cam) · ego(t_cam)_from_global · global_from_ego(t_lidar) · ego_from_lidar`,
    /// i.e. LiDAR -> ego at the LiDAR time -> global -> ego at the camera time -> camera (as
    /// BEVDet/OccFormer/SparseOcc build `lidar2cam`, with ego motion between the two timestamps).
    pub fn sample_cameras(&self, sample_token: &str) -> Result<SampleCameras, DataError> {
        self.sample_cameras_of(sample_token, &CAMERA_CHANNELS)
    }

    /// The camera channels of the rig in `sensor.json`: every sensor of modality `camera`, the six
    /// nuScenes channels first in [`CAMERA_CHANNELS`] order, then any others in table order (a
    /// custom rig may have any number of cameras, under any channel names).
    pub fn camera_channels(&self) -> Vec<String> {
        let cams: Vec<&str> = self
            .sensor
            .iter()
            .filter(|s| s.modality == "camera")
            .map(|s| s.channel.as_str())
            .collect();
        let mut out: Vec<String> = CAMERA_CHANNELS
            .iter()
            .filter(|c| cams.contains(c))
            .map(|c| c.to_string())
            .collect();
        for c in cams {
            if !out.iter().any(|o| o == c) {
                out.push(c.to_string());
            }
        }
        out
    }

    /// Like [`NuscenesTables::sample_cameras`], for the cameras `channels` in that order (a custom
    /// rig; see [`NuscenesTables::camera_channels`]). Every channel needs a key-frame `sample_data`
    /// row of the sample, else an error naming `sample_data.json`, the sample and the channel.
    pub fn sample_cameras_of<S: AsRef<str>>(
        &self,
        sample_token: &str,
        channels: &[S],
    ) -> Result<SampleCameras, DataError> {
        let sample = self
            .idx_sample
            .get(sample_token)
            .map(|&i| &self.sample[i])
            .ok_or_else(|| {
                DataError::format(
                    &self.table_path("sample.json"),
                    format!("no sample with token {sample_token}"),
                )
            })?;
        let sd_path = self.table_path("sample_data.json");
        let cs_path = self.table_path("calibrated_sensor.json");
        let key = self
            .key_frames_of_sample
            .get(sample_token)
            .map(|v| v.as_slice())
            .unwrap_or(&[]);
        let mut by_channel: HashMap<&str, &SampleData> = HashMap::new();
        for &i in key {
            let sd = &self.sample_data[i];
            let (_, s) = self.channel_of(sd)?;
            by_channel.insert(s.channel.as_str(), sd);
        }
        let lidar = *by_channel.get(LIDAR_CHANNEL).ok_or_else(|| {
            DataError::format(
                &sd_path,
                format!("sample {sample_token} has no key-frame {LIDAR_CHANNEL} sample_data"),
            )
        })?;
        let (lcs, _) = self.channel_of(lidar)?;
        let ego_from_lidar =
            mat4_from_quat_translation(lcs.rotation, lcs.translation).ok_or_else(|| {
                DataError::format(
                    &cs_path,
                    format!("calibrated_sensor {} has an invalid rotation", lcs.token),
                )
            })?;
        let global_from_ego_l = self.pose_of(lidar)?;
        let global_from_lidar = mat4_mul(&global_from_ego_l, &ego_from_lidar);
        let mut cameras = Vec::with_capacity(channels.len());
        for ch in channels {
            let ch = ch.as_ref();
            let sd = *by_channel.get(ch).ok_or_else(|| {
                DataError::format(
                    &sd_path,
                    format!("sample {sample_token} has no key-frame {ch} sample_data"),
                )
            })?;
            let (cs, _) = self.channel_of(sd)?;
            let k = &cs.camera_intrinsic;
            if k.len() != 3 || k.iter().any(|r| r.len() != 3) {
                return Err(DataError::format(
                    &cs_path,
                    format!(
                        "calibrated_sensor {} ({ch}) camera_intrinsic is not 3x3",
                        cs.token
                    ),
                ));
            }
            if k[0][1].abs() > 1e-9
                || k[1][0].abs() > 1e-9
                || k[2][0].abs() > 1e-9
                || k[2][1].abs() > 1e-9
                || (k[2][2] - 1.0).abs() > 1e-9
                || !(k[0][0] > 0.0 && k[1][1] > 0.0)
            {
                return Err(DataError::format(&cs_path, format!("calibrated_sensor {} ({ch}) camera_intrinsic {k:?} is not a zero-skew pinhole matrix", cs.token)));
            }
            let ego_from_cam =
                mat4_from_quat_translation(cs.rotation, cs.translation).ok_or_else(|| {
                    DataError::format(
                        &cs_path,
                        format!("calibrated_sensor {} has an invalid rotation", cs.token),
                    )
                })?;
            let global_from_cam = mat4_mul(&self.pose_of(sd)?, &ego_from_cam);
            let cam_from_global = mat4_inverse(&global_from_cam).ok_or_else(|| {
                DataError::format(&cs_path, format!("camera pose of {} is singular", sd.token))
            })?;
            let cam_from_lidar = mat4_mul(&cam_from_global, &global_from_lidar);
            let cam_from_ego_lidar = mat4_mul(&cam_from_global, &global_from_ego_l);
            let camera = PinholeCamera {
                fx: k[0][0],
                fy: k[1][1],
                cx: k[0][2],
                cy: k[1][2],
                width: sd.width as usize,
                height: sd.height as usize,
            };
            cameras.push(NuscenesCamera {
                channel: ch.to_string(),
                sample_data_token: sd.token.clone(),
                filename: sd.filename.clone(),
                timestamp: sd.timestamp,
                view: CameraView::new(camera, cam_from_lidar),
                cam_from_ego_lidar,
            });
        }
        Ok(SampleCameras {
            sample_token: sample.token.clone(),
            scene_token: sample.scene_token.clone(),
            lidar_token: lidar.token.clone(),
            lidar_filename: lidar.filename.clone(),
            ego_from_lidar,
            global_from_ego: global_from_ego_l,
            cameras,
        })
    }

    /// Path of the OpenOccupancy ground truth of a sample below `occ_root`:
    /// `scene_<scene_token>/occupancy/<lidar_token>.npy`.
    pub fn occupancy_path(&self, occ_root: &Path, cams: &SampleCameras) -> PathBuf {
        occ_root
            .join(format!("scene_{}", cams.scene_token))
            .join("occupancy")
            .join(format!("{}.npy", cams.lidar_token))
    }
}

/// Read a nuScenes LiDAR sweep `samples/LIDAR_TOP/*.pcd.bin`: little-endian float32 records of
/// five values (x, y, z in metres in the LiDAR frame, intensity, ring index); returns `[x, y, z]`.
/// A size that is not a multiple of 20 bytes, or a non-finite coordinate, is an error naming the file.
pub fn read_lidar_pcd_bin(path: &Path) -> Result<Vec<[f32; 3]>, DataError> {
    let bytes = read_bytes(path)?;
    if bytes.len() % 20 != 0 {
        return Err(DataError::format(
            path,
            format!(
                "{} bytes is not a whole number of 5 x float32 points (20 bytes each)",
                bytes.len()
            ),
        ));
    }
    let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    let mut out = Vec::with_capacity(bytes.len() / 20);
    for (i, rec) in bytes.chunks_exact(20).enumerate() {
        let p = [f(&rec[0..4]), f(&rec[4..8]), f(&rec[8..12])];
        if !p.iter().all(|v| v.is_finite()) {
            return Err(DataError::format(
                path,
                format!("point {i} has a non-finite coordinate {p:?}"),
            ));
        }
        out.push(p);
    }
    Ok(out)
}

/// `scene.json` record (only the fields this project needs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneRow {
    pub token: String,
    pub name: String,
}

/// Read `scene.json` of a nuScenes version folder (scene token and name).
pub fn read_scenes(dir: &Path) -> Result<Vec<SceneRow>, DataError> {
    load_table(dir, "scene.json")
}
