//! SemanticKITTI semantic scene completion data (docs/formats.md §2).
//!
//! Layout: `<root>/sequences/XX/{calib.txt, poses.txt, image_2/NNNNNN.png, velodyne/NNNNNN.bin,
//! labels/NNNNNN.label, voxels/NNNNNN.{bin,label,invalid,occluded}}`; preprocessed labels in
//! `<root>/labels/XX/NNNNNN_1_1.npy` (and `_1_2.npy`); submissions in
//! `sequences/XX/predictions/NNNNNN.label`.
//!
//! Grid geometry: see [`occ_geometry::VoxelGrid::semantic_kitti`] for the 0.2 m z offset of the
//! released voxel files and [`released_layout_from_nominal`] for the off-by-one that causes it.

use super::io::{check_len, create_dir_all, read_bytes, read_text, write_atomic};
use super::npy::{read_npy, write_npy, NpyValues};
use crate::error::DataError;
pub use crate::labels::{downsample_labels, LearningMap};
use occ_geometry::{
    mat3_det, mat3_identity, mat3_inverse, mat3_mul, mat4_identity, mat4_mul, CameraView, Mat4,
    PinholeCamera, VoxelGrid,
};
use occ_labels::IGNORE;
use std::path::{Path, PathBuf};

/// Grid dimensions `[X, Y, Z]` of the SSC volume.
pub const DIMS: [usize; 3] = [256, 256, 32];
/// Number of voxels of the SSC volume (2,097,152).
pub const NUM_VOXELS: usize = DIMS[0] * DIMS[1] * DIMS[2];
/// Number of SSC classes including 0 = empty.
pub const NUM_CLASSES: usize = 20;
/// Class names in class-index order.
pub const CLASS_NAMES: [&str; 20] = [
    "empty",
    "car",
    "bicycle",
    "motorcycle",
    "truck",
    "other-vehicle",
    "person",
    "bicyclist",
    "motorcyclist",
    "road",
    "parking",
    "sidewalk",
    "other-ground",
    "building",
    "fence",
    "vegetation",
    "trunk",
    "terrain",
    "pole",
    "traffic-sign",
];
/// Training sequences (SemanticKITTI `semantic-kitti.yaml`).
pub const TRAIN_SEQUENCES: &[&str] = &["00", "01", "02", "03", "04", "05", "06", "07", "09", "10"];
/// Validation sequence.
pub const VAL_SEQUENCES: &[&str] = &["08"];
/// Test sequences (only `voxels/*.bin` are public).
pub const TEST_SEQUENCES: &[&str] = &[
    "11", "12", "13", "14", "15", "16", "17", "18", "19", "20", "21",
];

/// The split a sequence id belongs to: `"train"`, `"val"`, `"test"`, or `None`.
pub fn split_of(sequence: &str) -> Option<&'static str> {
    if TRAIN_SEQUENCES.contains(&sequence) {
        Some("train")
    } else if VAL_SEQUENCES.contains(&sequence) {
        Some("val")
    } else if TEST_SEQUENCES.contains(&sequence) {
        Some("test")
    } else {
        None
    }
}

/// One frame of a sequence, e.g. `("08", "000000")`.
#[derive(
    Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
pub struct FrameId {
    pub sequence: String,
    pub frame: String,
}

/// File paths of a SemanticKITTI dataset rooted at the folder that contains `sequences/`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct KittiPaths {
    pub root: PathBuf,
}

impl KittiPaths {
    /// Paths below `root` (the folder containing `sequences/`).
    pub fn new(root: &Path) -> Self {
        KittiPaths {
            root: root.to_path_buf(),
        }
    }
    /// `sequences/XX`.
    pub fn sequence_dir(&self, seq: &str) -> PathBuf {
        self.root.join("sequences").join(seq)
    }
    /// `sequences/XX/calib.txt`.
    pub fn calib(&self, seq: &str) -> PathBuf {
        self.sequence_dir(seq).join("calib.txt")
    }
    /// `sequences/XX/poses.txt`.
    pub fn poses(&self, seq: &str) -> PathBuf {
        self.sequence_dir(seq).join("poses.txt")
    }
    /// `sequences/XX/image_2/NNNNNN.png`.
    pub fn image_2(&self, seq: &str, frame: &str) -> PathBuf {
        self.sequence_dir(seq)
            .join("image_2")
            .join(format!("{frame}.png"))
    }
    /// `sequences/XX/velodyne/NNNNNN.bin`.
    pub fn velodyne(&self, seq: &str, frame: &str) -> PathBuf {
        self.sequence_dir(seq)
            .join("velodyne")
            .join(format!("{frame}.bin"))
    }
    /// `sequences/XX/labels/NNNNNN.label` (per-point labels).
    pub fn point_labels(&self, seq: &str, frame: &str) -> PathBuf {
        self.sequence_dir(seq)
            .join("labels")
            .join(format!("{frame}.label"))
    }
    /// `sequences/XX/voxels/NNNNNN.<ext>` with ext one of `bin`, `label`, `invalid`, `occluded`.
    pub fn voxels(&self, seq: &str, frame: &str, ext: &str) -> PathBuf {
        self.sequence_dir(seq)
            .join("voxels")
            .join(format!("{frame}.{ext}"))
    }
    /// `labels/XX/NNNNNN_1_<scale>.npy` (preprocessed labels; scale 1 = full, 2 = half, ...).
    pub fn preprocessed_label(&self, seq: &str, frame: &str, scale: usize) -> PathBuf {
        self.root
            .join("labels")
            .join(seq)
            .join(format!("{frame}_1_{scale}.npy"))
    }
    /// `sequences/XX/predictions/NNNNNN.label` (submission).
    pub fn prediction(&self, seq: &str, frame: &str) -> PathBuf {
        self.sequence_dir(seq)
            .join("predictions")
            .join(format!("{frame}.label"))
    }
}

// ---------------------------------------------------------------------------------------------
// Bit-packed and raw voxel files

/// Read a bit-packed voxel file (`.bin`, `.invalid`, `.occluded`): `ceil(n/8)` bytes, MSB first,
/// `voxel[8k+b] = (byte[k] >> (7-b)) & 1`. Returns one 0/1 byte per voxel.
pub fn read_packed_bits(path: &Path, n_voxels: usize) -> Result<Vec<u8>, DataError> {
    let bytes = read_bytes(path)?;
    check_len(path, bytes.len(), n_voxels.div_ceil(8))?;
    Ok(unpack_bits(&bytes, n_voxels))
}

/// Unpack MSB-first bits (see [`read_packed_bits`]); missing bytes read as 0.
pub fn unpack_bits(bytes: &[u8], n_voxels: usize) -> Vec<u8> {
    (0..n_voxels)
        .map(|i| bytes.get(i / 8).map_or(0, |b| (b >> (7 - (i % 8))) & 1))
        .collect()
}

/// Pack 0/non-0 values MSB first (the last byte is zero-padded).
pub fn pack_bits(bits: &[u8]) -> Vec<u8> {
    let mut out = vec![0u8; bits.len().div_ceil(8)];
    for (i, &b) in bits.iter().enumerate() {
        if b != 0 {
            out[i / 8] |= 1 << (7 - (i % 8));
        }
    }
    out
}

/// Write a bit-packed voxel file (non-zero = 1), atomically.
pub fn write_packed_bits(path: &Path, bits: &[u8]) -> Result<(), DataError> {
    write_atomic(path, &pack_bits(bits))
}

/// Read a `.label` voxel file: little-endian uint16 raw ids, `2·n` bytes.
pub fn read_label_raw(path: &Path, n_voxels: usize) -> Result<Vec<u16>, DataError> {
    let bytes = read_bytes(path)?;
    check_len(path, bytes.len(), n_voxels * 2)?;
    Ok(bytes
        .chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect())
}

/// Write raw uint16 ids (a `.label` voxel file or a submission), atomically.
pub fn write_label_raw(path: &Path, raw: &[u16]) -> Result<(), DataError> {
    let mut bytes = Vec::with_capacity(raw.len() * 2);
    for &r in raw {
        bytes.extend_from_slice(&r.to_le_bytes());
    }
    write_atomic(path, &bytes)
}

/// Write a submission file `sequences/XX/predictions/NNNNNN.label` below `out_root` from a class
/// grid (classes -> raw ids via `learning_map_inv`; 255 -> 0). Creates the folder.
pub fn write_prediction(
    out_root: &Path,
    frame: &FrameId,
    classes: &[u8],
    map: &LearningMap,
) -> Result<PathBuf, DataError> {
    if classes.len() != NUM_VOXELS {
        return Err(DataError::InvalidArgument(format!(
            "prediction for {}/{} has {} voxels, expected {NUM_VOXELS}",
            frame.sequence,
            frame.frame,
            classes.len()
        )));
    }
    let path = KittiPaths::new(out_root).prediction(&frame.sequence, &frame.frame);
    if let Some(dir) = path.parent() {
        create_dir_all(dir)?;
    }
    write_label_raw(&path, &map.inverse_remap(classes))?;
    Ok(path)
}

/// Preprocessed SSC target (docs/formats.md §2.5): `lut[label]`, then 255 where
/// `invalid == 1`.
pub fn preprocess_labels(
    raw: &[u16],
    invalid: &[u8],
    map: &LearningMap,
) -> Result<Vec<u8>, DataError> {
    if raw.len() != invalid.len() {
        return Err(DataError::InvalidArgument(format!(
            "label grid has {} voxels but invalid mask has {}",
            raw.len(),
            invalid.len()
        )));
    }
    Ok(raw
        .iter()
        .zip(invalid)
        .map(|(&r, &inv)| if inv == 1 { IGNORE } else { map.to_class(r) })
        .collect())
}

/// Read a preprocessed label grid `labels/XX/NNNNNN_1_S.npy`. The official files are float32;
/// any integer or float dtype holding integers in 0..=255 is accepted. Returns the flat C-order
/// labels and the shape, which must be 3D.
pub fn read_label_npy(path: &Path) -> Result<(Vec<u8>, [usize; 3]), DataError> {
    let a = read_npy(path)?;
    let dims: [usize; 3] = a.shape.as_slice().try_into().map_err(|_| {
        DataError::format(
            path,
            format!("expected a 3D label grid, found shape {:?}", a.shape),
        )
    })?;
    let out: Vec<u8> = match &a.values {
        NpyValues::U8(v) => v.clone(),
        other => {
            let f = other.to_f64();
            let mut out = Vec::with_capacity(f.len());
            for (i, &x) in f.iter().enumerate() {
                if !(0.0..=255.0).contains(&x) || x.fract() != 0.0 {
                    return Err(DataError::format(
                        path,
                        format!("label value {x} at flat index {i} is not an integer in 0..=255"),
                    ));
                }
                out.push(x as u8);
            }
            out
        }
    };
    Ok((out, dims))
}

/// Write a preprocessed label grid as float32 `.npy` of shape `dims` (the official dtype).
pub fn write_label_npy(path: &Path, labels: &[u8], dims: [usize; 3]) -> Result<(), DataError> {
    let f: Vec<f32> = labels.iter().map(|&v| v as f32).collect();
    write_npy(path, &dims, &f)
}

// ---------------------------------------------------------------------------------------------
// Calibration and poses

/// Camera-2 calibration of a sequence (`calib.txt`).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Calib {
    /// `P2`: 3x4 projection of the rectified left colour camera (from rectified cam0 coordinates).
    pub p2: [[f64; 4]; 3],
    /// `Tr`: velodyne -> rectified cam0, padded to 4x4 (`cam0_from_velo`).
    pub tr: Mat4,
}

fn parse_12(path: &Path, line_no: usize, key: &str, rest: &str) -> Result<[f64; 12], DataError> {
    let vals: Vec<&str> = rest.split_whitespace().collect();
    if vals.len() != 12 {
        return Err(DataError::Parse {
            path: path.to_path_buf(),
            line: line_no,
            detail: format!("`{key}` needs 12 numbers, found {}", vals.len()),
        });
    }
    let mut out = [0.0; 12];
    for (o, v) in out.iter_mut().zip(vals) {
        *o = v
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| DataError::Parse {
                path: path.to_path_buf(),
                line: line_no,
                detail: format!("`{key}`: `{v}` is not a finite number"),
            })?;
    }
    Ok(out)
}

fn mat34(v: &[f64; 12]) -> [[f64; 4]; 3] {
    [
        [v[0], v[1], v[2], v[3]],
        [v[4], v[5], v[6], v[7]],
        [v[8], v[9], v[10], v[11]],
    ]
}

fn pad44(m: &[[f64; 4]; 3]) -> Mat4 {
    [m[0], m[1], m[2], [0.0, 0.0, 0.0, 1.0]]
}

/// Parse `calib.txt` (`KEY: 12 numbers` per line; parsing stops at the first empty line, as
/// MonoScene/SparseOcc `read_calib`). `P2` and `Tr` are required.
pub fn read_calib(path: &Path) -> Result<Calib, DataError> {
    let text = read_text(path)?;
    let mut p2 = None;
    let mut tr = None;
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            break;
        }
        let Some((key, rest)) = line.split_once(':') else {
            return Err(DataError::Parse {
                path: path.to_path_buf(),
                line: i + 1,
                detail: "expected `KEY: values`".into(),
            });
        };
        let key = key.trim();
        match key {
            "P2" => p2 = Some(mat34(&parse_12(path, i + 1, key, rest)?)),
            "Tr" => tr = Some(mat34(&parse_12(path, i + 1, key, rest)?)),
            _ => {}
        }
    }
    let p2 = p2.ok_or_else(|| DataError::MissingKey {
        path: path.to_path_buf(),
        key: "P2".into(),
    })?;
    let tr = tr.ok_or_else(|| DataError::MissingKey {
        path: path.to_path_buf(),
        key: "Tr".into(),
    })?;
    Calib::from_rows(p2, tr).map_err(|detail| DataError::format(path, detail))
}

/// How far `Tr[:3,:3]·Tr[:3,:3]ᵀ` may lie from the identity (largest entry), for
/// [`Calib::from_rows`]: rotations written with 4 significant digits pass, scales do not.
pub const ROTATION_TOLERANCE: f64 = 1e-3;

impl Calib {
    /// A calibration from the 3x4 `P2` and `Tr` matrices (as `calib.txt` holds them), or the
    /// problem in words. Refused, because the projection would be silently wrong:
    /// - a value that is not finite;
    /// - `P2[:3,:3]` that is not a pinhole intrinsic matrix `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`
    ///   with `fx, fy > 0` (the camera is read from `fx, fy, cx, cy` alone: a skew, a scaled or
    ///   negated third row would be dropped);
    /// - `Tr[:3,:3]` that is not a rotation (`Tr` moves velodyne points rigidly into the camera
    ///   frame: a scale, a reflection or a zero block would move them elsewhere). KITTI's files
    ///   are orthonormal to about 1e-7; up to [`ROTATION_TOLERANCE`] is accepted.
    pub fn from_rows(p2: [[f64; 4]; 3], tr: [[f64; 4]; 3]) -> Result<Calib, String> {
        if p2.iter().chain(&tr).flatten().any(|v| !v.is_finite()) {
            return Err("P2 and Tr must hold finite numbers".into());
        }
        let (fx, fy) = (p2[0][0], p2[1][1]);
        let scale = fx.abs().max(fy.abs());
        let off_pinhole = [p2[0][1], p2[1][0], p2[2][0], p2[2][1]]
            .iter()
            .any(|v| v.abs() > 1e-6 * scale)
            || (p2[2][2] - 1.0).abs() > 1e-6;
        if fx <= 0.0 || fy <= 0.0 || off_pinhole {
            let k: Vec<[f64; 3]> = p2.iter().map(|r| [r[0], r[1], r[2]]).collect();
            return Err(format!(
                "P2[:3,:3] must be a pinhole intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] \
                 with fx, fy > 0, got {k:?}"
            ));
        }
        let r: [[f64; 3]; 3] = std::array::from_fn(|i| [tr[i][0], tr[i][1], tr[i][2]]);
        let rt: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| r[j][i]));
        let (rrt, id) = (mat3_mul(&r, &rt), mat3_identity());
        let dev = (0..9)
            .map(|k| (rrt[k / 3][k % 3] - id[k / 3][k % 3]).abs())
            .fold(0.0, f64::max);
        let det = mat3_det(&r);
        if dev > ROTATION_TOLERANCE || det <= 0.0 {
            return Err(format!(
                "Tr[:3,:3] must be a rotation (Tr maps velodyne points rigidly into the camera \
                 frame), got {r:?}: R·Rᵀ differs from I by {dev:.2e}, det(R) = {det:.4}"
            ));
        }
        Ok(Calib { p2, tr: pad44(&tr) })
    }
}

fn fmt_row12(m: &[[f64; 4]; 3]) -> String {
    m.iter()
        .flat_map(|r| r.iter())
        .map(|v| format!("{v:.12e}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Write `calib.txt` with the `P2` and `Tr` lines, atomically.
pub fn write_calib(path: &Path, c: &Calib) -> Result<(), DataError> {
    let tr34 = [c.tr[0], c.tr[1], c.tr[2]];
    let text = format!("P2: {}\nTr: {}\n", fmt_row12(&c.p2), fmt_row12(&tr34));
    write_atomic(path, text.as_bytes())
}

impl Calib {
    /// Intrinsics `K = P2[:3,:3]` as a pinhole camera of the given image size.
    pub fn camera(&self, width: usize, height: usize) -> PinholeCamera {
        PinholeCamera {
            fx: self.p2[0][0],
            fy: self.p2[1][1],
            cx: self.p2[0][2],
            cy: self.p2[1][2],
            width,
            height,
        }
    }

    /// `cam2_from_cam0 = [I | K⁻¹·P2[:,3]]`: the rectified left colour camera sits ~6 cm left
    /// of cam0, encoded in P2's 4th column (`P2 = K·[I | t]`).
    pub fn cam2_from_cam0(&self) -> Mat4 {
        let k = [
            [self.p2[0][0], self.p2[0][1], self.p2[0][2]],
            [self.p2[1][0], self.p2[1][1], self.p2[1][2]],
            [self.p2[2][0], self.p2[2][1], self.p2[2][2]],
        ];
        let mut m = mat4_identity();
        if let Some(kinv) = mat3_inverse(&k) {
            for r in 0..3 {
                m[r][3] = (0..3).map(|c| kinv[r][c] * self.p2[c][3]).sum();
            }
        }
        m
    }

    /// The image_2 camera seen from the velodyne: `cam_from_lidar = cam2_from_cam0 · Tr`, so
    /// that `img_from_lidar = P2 · Tr` exactly (SparseOcc uses the full P2, docs/formats.md §2.7).
    pub fn camera_view(&self, width: usize, height: usize) -> CameraView {
        CameraView::new(
            self.camera(width, height),
            mat4_mul(&self.cam2_from_cam0(), &self.tr),
        )
    }

    /// MonoScene's variant (`vox2pix`): `cam_from_lidar = Tr`, ignoring P2's 4th column
    /// (about 0.06 m, i.e. ~1-4 px at typical depths).
    pub fn camera_view_monoscene(&self, width: usize, height: usize) -> CameraView {
        CameraView::new(self.camera(width, height), self.tr)
    }
}

/// Read `poses.txt`: one 3x4 row-major matrix (12 numbers) per line, padded to 4x4.
/// These are `cam0(t=0)_from_cam0(t)` poses. Empty lines are skipped.
pub fn read_poses(path: &Path) -> Result<Vec<Mat4>, DataError> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        out.push(pad44(&mat34(&parse_12(path, i + 1, "pose", line)?)));
    }
    Ok(out)
}

/// Write `poses.txt`, atomically.
pub fn write_poses(path: &Path, poses: &[Mat4]) -> Result<(), DataError> {
    let mut text = String::new();
    for p in poses {
        text.push_str(&fmt_row12(&[p[0], p[1], p[2]]));
        text.push('\n');
    }
    write_atomic(path, text.as_bytes())
}

// ---------------------------------------------------------------------------------------------
// LiDAR scans

/// Read a velodyne scan: float32 `(x, y, z, intensity)` records (16 bytes each).
pub fn read_velodyne(path: &Path) -> Result<Vec<[f32; 4]>, DataError> {
    let bytes = read_bytes(path)?;
    if bytes.len() % 16 != 0 {
        return Err(DataError::WrongSize {
            path: path.to_path_buf(),
            detail: format!(
                "{} bytes is not a multiple of 16 (4 x float32 per point); truncated?",
                bytes.len()
            ),
        });
    }
    Ok(bytes
        .chunks_exact(16)
        .map(|c| {
            let f = |o: usize| f32::from_le_bytes([c[o], c[o + 1], c[o + 2], c[o + 3]]);
            [f(0), f(4), f(8), f(12)]
        })
        .collect())
}

/// Write a velodyne scan, atomically.
pub fn write_velodyne(path: &Path, pts: &[[f32; 4]]) -> Result<(), DataError> {
    let mut bytes = Vec::with_capacity(pts.len() * 16);
    for p in pts {
        for v in p {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    write_atomic(path, &bytes)
}

/// Read per-point labels: uint32, low 16 bits = semantic raw id, high 16 bits = instance.
pub fn read_point_labels(path: &Path) -> Result<Vec<u32>, DataError> {
    let bytes = read_bytes(path)?;
    if bytes.len() % 4 != 0 {
        return Err(DataError::WrongSize {
            path: path.to_path_buf(),
            detail: format!(
                "{} bytes is not a multiple of 4 (uint32 per point); truncated?",
                bytes.len()
            ),
        });
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

/// Write per-point labels, atomically.
pub fn write_point_labels(path: &Path, l: &[u32]) -> Result<(), DataError> {
    let mut bytes = Vec::with_capacity(l.len() * 4);
    for v in l {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    write_atomic(path, &bytes)
}

/// Read a scan and its labels, checking that they have the same number of points.
pub fn read_labelled_scan(
    scan: &Path,
    labels: &Path,
) -> Result<(Vec<[f32; 4]>, Vec<u32>), DataError> {
    let pts = read_velodyne(scan)?;
    let l = read_point_labels(labels)?;
    if pts.len() != l.len() {
        return Err(DataError::WrongSize {
            path: labels.to_path_buf(),
            detail: format!(
                "{} labels for {} points in {}",
                l.len(),
                pts.len(),
                scan.display()
            ),
        });
    }
    Ok((pts, l))
}

// ---------------------------------------------------------------------------------------------
// Voxelisation

/// Point filters and arithmetic of the voxelisation, after jbehley/voxelizer (the tool that
/// made the SemanticKITTI voxel files; its `semantic_kitti.cfg` and `Config` defaults).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VoxelizeOptions {
    /// Points closer than this (3D range from the sensor) are dropped (voxelizer: 2.5 m).
    pub min_range_m: f32,
    /// Points farther than this are dropped (voxelizer: 70 m).
    pub max_range_m: f32,
    /// Drop points on the recording car: `-2 < x < 3` and `|y| < 2` (voxelizer `hidecar`).
    pub hide_car: bool,
}

impl VoxelizeOptions {
    /// The settings used for the released SemanticKITTI voxel files.
    pub fn semantic_kitti() -> Self {
        VoxelizeOptions {
            min_range_m: 2.5,
            max_range_m: 70.0,
            hide_car: true,
        }
    }
    /// Keep every point.
    pub fn all_points() -> Self {
        VoxelizeOptions {
            min_range_m: 0.0,
            max_range_m: f32::INFINITY,
            hide_car: false,
        }
    }
}

/// Per voxel, the majority raw semantic id (`label & 0xFFFF`) of the points that fall in it,
/// ties to the smaller id (the voxelizer iterates a sorted map and keeps the first maximum);
/// `None` for voxels without points. Index arithmetic is float32 as in the voxelizer:
/// `floor((p - origin) / voxel_size)`. Extra entries of the longer input slice are ignored.
pub fn voxelize_majority_raw(
    points: &[[f32; 4]],
    point_labels: &[u32],
    grid: &VoxelGrid,
    opts: &VoxelizeOptions,
) -> Vec<Option<u16>> {
    let origin = [
        grid.origin_m[0] as f32,
        grid.origin_m[1] as f32,
        grid.origin_m[2] as f32,
    ];
    let size = grid.voxel_size_m as f32;
    let mut pairs: Vec<(usize, u16)> = Vec::with_capacity(points.len());
    for (p, &l) in points.iter().zip(point_labels) {
        let range = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        if !(range >= opts.min_range_m && range <= opts.max_range_m) {
            continue;
        }
        if opts.hide_car && p[0] < 3.0 && p[0] > -2.0 && p[1].abs() < 2.0 {
            continue;
        }
        let mut ijk = [0usize; 3];
        let mut inside = true;
        for a in 0..3 {
            let f = ((p[a] - origin[a]) / size).floor();
            if !(f >= 0.0 && f < grid.dims[a] as f32) {
                inside = false;
                break;
            }
            ijk[a] = f as usize;
        }
        if inside {
            pairs.push((grid.linear_index(ijk), (l & 0xFFFF) as u16));
        }
    }
    pairs.sort_unstable();
    let mut out = vec![None; grid.num_voxels()];
    let mut i = 0;
    while i < pairs.len() {
        let v = pairs[i].0;
        let mut best = (0usize, 0u16);
        while i < pairs.len() && pairs[i].0 == v {
            let raw = pairs[i].1;
            let mut n = 0;
            while i < pairs.len() && pairs[i] == (v, raw) {
                n += 1;
                i += 1;
            }
            if n > best.0 {
                best = (n, raw);
            }
        }
        out[v] = Some(best.1);
    }
    out
}

/// Voxelise a labelled scan into a semantic class grid on `grid` (flat C order): each voxel
/// with points gets the learning-map class of its majority raw id (see
/// [`voxelize_majority_raw`], with [`VoxelizeOptions::semantic_kitti`] filters); voxels without
/// points are 0. Raw 0 (unlabeled) majorities give 0, so `class != 0` is exactly the
/// occupancy the official input `.bin` encodes (`maxLabel > 0`).
pub fn voxelize_scan(
    points: &[[f32; 4]],
    point_labels: &[u32],
    grid: &VoxelGrid,
    map: &LearningMap,
) -> Vec<u8> {
    voxelize_scan_with(
        points,
        point_labels,
        grid,
        map,
        &VoxelizeOptions::semantic_kitti(),
    )
}

/// [`voxelize_scan`] with explicit point filters.
pub fn voxelize_scan_with(
    points: &[[f32; 4]],
    point_labels: &[u32],
    grid: &VoxelGrid,
    map: &LearningMap,
    opts: &VoxelizeOptions,
) -> Vec<u8> {
    voxelize_majority_raw(points, point_labels, grid, opts)
        .into_iter()
        .map(|r| r.map_or(0, |raw| map.to_class(raw)))
        .collect()
}

/// Re-create the layout of the released SemanticKITTI voxel files from a grid voxelised on the
/// nominal extent ([`VoxelGrid::semantic_kitti_nominal`]): `stored[n + 1] = nominal[n]`,
/// `stored[0] = default`, the last nominal voxel is dropped.
///
/// This is the flat-index off-by-one of jbehley/voxelizer before commit e5989b8 (June 2020,
/// "Fix off-by-one error when writing out voxel grid"; the loop incremented its counter before
/// writing). With z fastest it moves every voxel up one z index (so the files look 0.2 m lower,
/// origin z = -2.2) and wraps each column's top voxel into z = 0 of the next column.
pub fn released_layout_from_nominal<T: Copy + Default>(nominal: &[T]) -> Vec<T> {
    let mut out = Vec::with_capacity(nominal.len());
    if !nominal.is_empty() {
        out.push(T::default());
        out.extend_from_slice(&nominal[..nominal.len() - 1]);
    }
    out
}

/// Inverse of [`released_layout_from_nominal`]: `nominal[n] = stored[n + 1]`; the last nominal
/// voxel (top of the last column), which the files do not contain, is `default`.
pub fn nominal_layout_from_released<T: Copy + Default>(stored: &[T]) -> Vec<T> {
    let mut out = Vec::with_capacity(stored.len());
    if !stored.is_empty() {
        out.extend_from_slice(&stored[1..]);
        out.push(T::default());
    }
    out
}

/// Emulate the official input occupancy `voxels/NNNNNN.bin` from the frame's scan and labels:
/// voxelise on the nominal extent with the voxelizer's filters, occupied where the majority raw
/// id is > 0, then apply the released off-by-one layout. On the real frames in
/// real sample files (the external `SPARSEOCC_REALDATA` folder) this reproduces the `.bin` files bit for bit.
pub fn emulate_input_occupancy(points: &[[f32; 4]], point_labels: &[u32]) -> Vec<u8> {
    let nominal: Vec<u8> = voxelize_majority_raw(
        points,
        point_labels,
        &VoxelGrid::semantic_kitti_nominal(),
        &VoxelizeOptions::semantic_kitti(),
    )
    .into_iter()
    .map(|r| matches!(r, Some(raw) if raw > 0) as u8)
    .collect();
    released_layout_from_nominal(&nominal)
}

// ---------------------------------------------------------------------------------------------
// Listing

/// Sorted ids (file stems) of the files with extension `ext` in `dir`; empty if `dir` is absent.
pub fn list_stems(dir: &Path, ext: &str) -> Result<Vec<String>, DataError> {
    let rd = match std::fs::read_dir(dir) {
        Ok(rd) => rd,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(DataError::io(dir, e)),
    };
    let mut out = Vec::new();
    for entry in rd {
        let entry = entry.map_err(|e| DataError::io(dir, e))?;
        let p = entry.path();
        if p.extension().and_then(|e| e.to_str()) == Some(ext) && p.is_file() {
            if let Some(stem) = p.file_stem().and_then(|s| s.to_str()) {
                out.push(stem.to_string());
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The SSC frames of a sequence: the stems of `sequences/XX/voxels/*.bin`, sorted.
/// `root` is the dataset folder containing `sequences/`. A missing sequence folder is an error;
/// a sequence without `voxels/` has no SSC frames.
pub fn list_frames(root: &Path, sequence: &str) -> Result<Vec<String>, DataError> {
    let paths = KittiPaths::new(root);
    let seq_dir = paths.sequence_dir(sequence);
    if !seq_dir.is_dir() {
        return Err(DataError::NotFound {
            path: seq_dir,
            what: format!("sequence {sequence}"),
        });
    }
    list_stems(&seq_dir.join("voxels"), "bin")
}

/// Sequence ids present under `root/sequences`, sorted.
pub fn list_sequences(root: &Path) -> Result<Vec<String>, DataError> {
    let dir = root.join("sequences");
    let rd = std::fs::read_dir(&dir).map_err(|e| DataError::io(&dir, e))?;
    let mut out = Vec::new();
    for entry in rd {
        let entry = entry.map_err(|e| DataError::io(&dir, e))?;
        if entry.path().is_dir() {
            if let Some(name) = entry.file_name().to_str() {
                out.push(name.to_string());
            }
        }
    }
    out.sort();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bit_packing_is_msb_first() {
        let bits = [1u8, 0, 0, 0, 0, 0, 0, 1, 0, 1];
        let packed = pack_bits(&bits);
        assert_eq!(packed, vec![0b1000_0001, 0b0100_0000]);
        assert_eq!(unpack_bits(&packed, 10), bits.to_vec());
        assert_eq!(unpack_bits(&[0xA5], 8), vec![1, 0, 1, 0, 0, 1, 0, 1]);
    }

    #[test]
    fn released_layout_shift_round_trip() {
        let nominal: Vec<u8> = (1..=64).collect();
        let stored = released_layout_from_nominal(&nominal);
        assert_eq!(stored[0], 0);
        assert_eq!(stored[1], 1);
        assert_eq!(stored[63], 63);
        let back = nominal_layout_from_released(&stored);
        assert_eq!(&back[..63], &nominal[..63]);
        assert_eq!(back[63], 0);
    }

    #[test]
    fn voxelize_majority_ties_to_smaller_raw_id() {
        let g = VoxelGrid {
            origin_m: [0.0, 0.0, 0.0],
            voxel_size_m: 1.0,
            dims: [2, 2, 2],
        };
        let pts = [
            [0.5f32, 0.5, 0.5, 0.0],
            [0.6, 0.5, 0.5, 0.0],
            [0.7, 0.5, 0.5, 0.0],
            [0.8, 0.5, 0.5, 0.0],
            [1.5, 1.5, 1.5, 0.0],
            [5.0, 0.0, 0.0, 0.0],
        ];
        let labels = [40u32, 10 | (3 << 16), 10, 40, 0, 10];
        let m = voxelize_majority_raw(&pts, &labels, &g, &VoxelizeOptions::all_points());
        assert_eq!(m[0], Some(10));
        assert_eq!(m[7], Some(0));
        assert_eq!(m.iter().filter(|v| v.is_some()).count(), 2);
        let map = LearningMap::semantic_kitti();
        let c = voxelize_scan_with(&pts, &labels, &g, &map, &VoxelizeOptions::all_points());
        assert_eq!(c[0], 1);
        assert_eq!(c[7], 0);
        // the default (voxelizer) filters drop all of these near-range points
        assert!(voxelize_scan(&pts, &labels, &g, &map)
            .iter()
            .all(|&v| v == 0));
    }

    #[test]
    fn splits() {
        assert_eq!(split_of("08"), Some("val"));
        assert_eq!(split_of("09"), Some("train"));
        assert_eq!(split_of("21"), Some("test"));
        assert_eq!(split_of("22"), None);
        let all: Vec<&str> = TRAIN_SEQUENCES
            .iter()
            .chain(VAL_SEQUENCES)
            .chain(TEST_SEQUENCES)
            .copied()
            .collect();
        assert_eq!(all.len(), 22);
    }
}
