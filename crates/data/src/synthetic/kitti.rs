//! Writer of the SemanticKITTI layout (`kitti`, `kitti-small`).

use super::classes::{kitti_learning_class, kitti_raw_extra, NUM_SCENE_CLASSES};
use super::layout::Style;
use super::render::{render, scan, CamRig};
use super::scene::{SequenceScene, CAMERA_T_MAX_M};
use super::util::derive_seed;
use super::vis::{Marker, VisBox};
use super::{frame_id, Stats, SynthConfig, SynthSequence};
use crate::error::DataError;
use crate::formats::io::{create_dir_all, write_atomic};
use crate::formats::semantic_kitti::{
    write_calib, write_label_raw, write_packed_bits, write_point_labels, write_poses,
    write_velodyne, Calib, LearningMap,
};
use crate::image::{write_png, RgbImage};
use occ_geometry::{mat4_identity, mat4_mul, Mat4, PinholeCamera};
use std::path::Path;

/// Height of the LiDAR above the road (m). With the grid origin at z = −2.2 the road surface
/// (LiDAR z = −1.8) is a voxel boundary at 0.2 and 0.4 m.
pub(crate) const LIDAR_HEIGHT_M: f64 = 1.8;
/// Camera centre in the LiDAR frame: 0.27 m ahead, 0.15 m below (1.65 m above the road).
pub(crate) const CAMERA_IN_LIDAR_M: [f64; 3] = [0.27, 0.0, -0.15];
/// KITTI odometry image size and colour-camera intrinsics (sequence 08, docs/formats.md §2.7).
pub(crate) const KITTI_IMAGE: (usize, usize) = (1226, 370);
const KITTI_FX: f64 = 721.5377;
const KITTI_CX: f64 = 609.5593;
const KITTI_CY: f64 = 172.854;
/// Seconds between frames (KITTI odometry runs at about 9.65 Hz).
const FRAME_DT_S: f64 = 0.1036;

/// Intrinsics for an image of `width × height`: the KITTI ones scaled by `width/1226`, `height/370`.
pub(crate) fn kitti_camera(width: usize, height: usize) -> PinholeCamera {
    let sx = width as f64 / KITTI_IMAGE.0 as f64;
    let sy = height as f64 / KITTI_IMAGE.1 as f64;
    PinholeCamera {
        fx: KITTI_FX * sx,
        fy: KITTI_FX * sy,
        cx: KITTI_CX * sx,
        cy: KITTI_CY * sy,
        width,
        height,
    }
}

/// `Tr` = `cam_from_lidar` with the KITTI axes (cam x = −lidar y, cam y = −lidar z, cam z = lidar x)
/// and the camera at [`CAMERA_IN_LIDAR_M`].
pub(crate) fn cam_from_lidar() -> Mat4 {
    let c = CAMERA_IN_LIDAR_M;
    [
        [0.0, -1.0, 0.0, c[1]],
        [0.0, 0.0, -1.0, c[2]],
        [1.0, 0.0, 0.0, -c[0]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// Inverse of [`cam_from_lidar`] (rigid: `[Rᵀ | −Rᵀt]`).
pub(crate) fn lidar_from_cam() -> Mat4 {
    let m = cam_from_lidar();
    let mut inv = mat4_identity();
    for r in 0..3 {
        for c in 0..3 {
            inv[r][c] = m[c][r];
        }
        inv[r][3] = -(0..3).map(|k| m[k][r] * m[k][3]).sum::<f64>();
    }
    inv
}

fn translation(t: [f64; 3]) -> Mat4 {
    let mut m = mat4_identity();
    for a in 0..3 {
        m[a][3] = t[a];
    }
    m
}

/// KITTI-style `times.txt` number (`1.036000e-01`).
fn kitti_time(t: f64) -> String {
    let s = format!("{t:.6e}");
    match s.split_once('e') {
        Some((m, e)) => {
            let (sign, digits) = match e.strip_prefix('-') {
                Some(d) => ('-', d),
                None => ('+', e),
            };
            format!("{m}e{sign}{digits:0>2}")
        }
        None => s,
    }
}

/// Raw SemanticKITTI id of every scene class.
fn raw_table() -> [u16; NUM_SCENE_CLASSES] {
    let map = LearningMap::semantic_kitti();
    let mut t = [0u16; NUM_SCENE_CLASSES];
    for (c, r) in t.iter_mut().enumerate() {
        *r = match kitti_raw_extra(c as u8) {
            Some(raw) => raw,
            None if c == 0 => 0,
            None => map.to_raw(c as u8),
        };
    }
    t
}

fn write_file(stats: &mut Stats, path: &Path, r: Result<(), DataError>) -> Result<(), DataError> {
    r?;
    stats.wrote(path);
    Ok(())
}

/// View positions of the drive on past the last frame, whose LiDAR scans mark what the sequence
/// observed (`.invalid` = seen from none of them nor from the written frames).
///
/// SemanticKITTI builds each frame's labels from the scans of the poses that follow it while the car
/// drives on through the 51.2 m volume ahead, so its `.invalid` marks what none of those positions
/// saw: 19-29 % of the volume in the real frames of sequences 00 and 08. Marking only the written
/// frames' own rays (a few metres of travel) leaves objects as one-voxel shells with everything behind
/// them unobserved (46-48 % invalid). The ego therefore drives on until it has passed the last
/// frame's whole volume (`grid` x extent), scanning every [`ACCUMULATION_STRIDE`]-th step (a scan
/// costs about 0.1 s on a 2-core machine; one every step of the 51.2 m would cost 6 s a sequence,
/// and a denser set adds almost nothing the next one does not see).
fn accumulation_positions(scene: &SequenceScene, frames: usize) -> Vec<[f64; 3]> {
    let Some(last) = frames.checked_sub(1).map(|i| scene.sensor_pos[i]) else {
        return Vec::new();
    };
    let extent_m = scene.grid.max_m()[0] - scene.grid.origin_m[0];
    let spacing_m = scene.step_m * ACCUMULATION_STRIDE as f64;
    let n = (extent_m / spacing_m).ceil() as usize;
    (1..=n)
        .map(|k| [last[0] + k as f64 * spacing_m, last[1], last[2]])
        .collect()
}

/// Steps of the ego between two accumulation scans (3.2-4.8 m at the `kitti*` speeds).
const ACCUMULATION_STRIDE: usize = 4;

pub(super) fn write_sequence(
    out: &Path,
    cfg: &SynthConfig,
    name: &str,
    frames: usize,
    stats: &mut Stats,
    tick: &mut dyn FnMut(),
) -> Result<SynthSequence, DataError> {
    let grid = cfg.preset.grid();
    let dims = grid.dims;
    let n_vox = grid.num_voxels();
    let scene = SequenceScene::new(
        cfg.seed,
        name,
        frames,
        Style::Kitti,
        grid,
        LIDAR_HEIGHT_M,
        &[0.8, 0.8, 1.2],
    );
    let (w, h) = cfg.image_size();
    let cam = kitti_camera(w, h);
    let lidar = cfg.preset.lidar();
    let raw_of = raw_table();
    let seq_dir = out.join("sequences").join(name);
    for sub in ["image_2", "velodyne", "labels", "voxels"] {
        create_dir_all(&seq_dir.join(sub))?;
    }
    if stats.class_voxels.len() < 20 {
        stats.class_voxels = vec![0; 20];
    }
    let off0 = scene.frame_off(0);
    let off_last = scene.frame_off(frames - 1);
    let union = VisBox::new(
        off0,
        [dims[0] + (off_last[0] - off0[0]) as usize, dims[1], dims[2]],
    );
    let l_from_c = lidar_from_cam();
    let groups = scene.frame_groups();
    let n_groups = groups.len();
    for (gi, group) in groups.into_iter().enumerate() {
        let world = scene.build_window(group.clone());
        if gi + 1 == n_groups {
            // The drive on past the last frame (LiDAR only, nothing written): see
            // `accumulation_positions`.
            let only_union = [&union];
            for pos in accumulation_positions(&scene, frames) {
                scan(&world, &lidar, pos, Some(Marker { boxes: &only_union }));
            }
        }
        for i in group {
            let fid = frame_id(i);
            let off = scene.frame_off(i);
            let frame_vis = VisBox::new(off, dims);
            let boxes = [&union, &frame_vis];
            let marker = Marker { boxes: &boxes };
            let rig = CamRig {
                cam,
                world_from_cam: mat4_mul(&translation(scene.sensor_pos[i]), &l_from_c),
            };
            let frame_seed = derive_seed(scene.seed, &format!("frame:{i}"));
            let img = render(
                &world,
                &rig,
                CAMERA_T_MAX_M,
                scene.seed,
                frame_seed,
                Some(marker),
            );
            let p = seq_dir.join("image_2").join(format!("{fid}.png"));
            write_file(
                stats,
                &p,
                write_png(
                    &p,
                    &RgbImage {
                        width: w,
                        height: h,
                        data: img,
                    },
                ),
            )?;

            let s = scan(&world, &lidar, scene.sensor_pos[i], Some(marker));
            let p = seq_dir.join("velodyne").join(format!("{fid}.bin"));
            write_file(stats, &p, write_velodyne(&p, &s.points))?;
            let point_labels: Vec<u32> = s
                .classes
                .iter()
                .map(|&c| raw_of.get(c as usize).copied().unwrap_or(0) as u32)
                .collect();
            let p = seq_dir.join("labels").join(format!("{fid}.label"));
            write_file(stats, &p, write_point_labels(&p, &point_labels))?;
            stats.lidar_points += s.points.len();

            let mut occ = vec![0u8; n_vox];
            for g in &s.voxels {
                let l = [0, 1, 2].map(|a| g[a] - off[a]);
                if (0..3).all(|a| l[a] >= 0 && l[a] < dims[a] as i64) {
                    occ[grid.linear_index([l[0] as usize, l[1] as usize, l[2] as usize])] = 1;
                }
            }
            let p = seq_dir.join("voxels").join(format!("{fid}.bin"));
            write_file(stats, &p, write_packed_bits(&p, &occ))?;

            let classes = scene.frame_classes(&world, i);
            let raw: Vec<u16> = classes
                .iter()
                .map(|&c| raw_of.get(c as usize).copied().unwrap_or(0))
                .collect();
            for &c in &classes {
                let l = kitti_learning_class(c) as usize;
                if l < 20 {
                    stats.class_voxels[l] += 1;
                }
            }
            let p = seq_dir.join("voxels").join(format!("{fid}.label"));
            write_file(stats, &p, write_label_raw(&p, &raw))?;

            let occluded: Vec<u8> = frame_vis
                .extract(off, dims)
                .into_iter()
                .map(|v| 1 - v)
                .collect();
            let p = seq_dir.join("voxels").join(format!("{fid}.occluded"));
            write_file(stats, &p, write_packed_bits(&p, &occluded))?;
            tick();
        }
    }
    for i in 0..frames {
        let off = scene.frame_off(i);
        let invalid: Vec<u8> = union
            .extract(off, dims)
            .into_iter()
            .map(|v| 1 - v)
            .collect();
        stats.unobserved += invalid.iter().map(|&v| v as f64).sum::<f64>() / n_vox as f64;
        let p = seq_dir
            .join("voxels")
            .join(format!("{}.invalid", frame_id(i)));
        write_file(stats, &p, write_packed_bits(&p, &invalid))?;
        stats.frames += 1;
        tick();
    }

    let tr = cam_from_lidar();
    let calib = Calib {
        p2: [
            [cam.fx, 0.0, cam.cx, 0.0],
            [0.0, cam.fy, cam.cy, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
        tr,
    };
    let p = seq_dir.join("calib.txt");
    write_file(stats, &p, write_calib(&p, &calib))?;
    let poses: Vec<Mat4> = (0..frames)
        .map(|i| {
            let d = [0, 1, 2].map(|a| scene.sensor_pos[i][a] - scene.sensor_pos[0][a]);
            mat4_mul(&mat4_mul(&tr, &translation(d)), &lidar_from_cam())
        })
        .collect();
    let p = seq_dir.join("poses.txt");
    write_file(stats, &p, write_poses(&p, &poses))?;
    let times: String = (0..frames)
        .map(|i| kitti_time(i as f64 * FRAME_DT_S) + "\n")
        .collect();
    let p = seq_dir.join("times.txt");
    write_file(stats, &p, write_atomic(&p, times.as_bytes()))?;
    Ok(SynthSequence {
        name: name.to_string(),
        frames,
        step_m: scene.step_m,
        scene_token: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use occ_geometry::transform_point;

    #[test]
    fn tr_has_kitti_axes_and_inverts() {
        let tr = cam_from_lidar();
        // a point 10 m ahead of the LiDAR is 9.73 m ahead of the camera, 0.15 m below its centre row
        let p = transform_point(&tr, [10.0, 0.0, 0.0]);
        assert!((p[0]).abs() < 1e-12 && (p[1] + 0.15).abs() < 1e-12 && (p[2] - 9.73).abs() < 1e-12);
        let q = transform_point(&tr, [0.0, 1.0, 0.0]);
        assert!((q[0] + 1.0).abs() < 1e-12);
        let id = mat4_mul(&tr, &lidar_from_cam());
        for (r, row) in id.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                assert!((v - if r == c { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        assert_eq!(kitti_time(0.0), "0.000000e+00");
        assert_eq!(kitti_time(0.1036), "1.036000e-01");
        assert_eq!(kitti_time(12.5), "1.250000e+01");
        let raw = raw_table();
        assert_eq!((raw[1], raw[9], raw[13], raw[20]), (10, 40, 50, 13));
        let cam = kitti_camera(613, 185);
        assert!((cam.fx - 360.76885).abs() < 1e-9 && (cam.cy - 86.427).abs() < 1e-9);
    }
}
