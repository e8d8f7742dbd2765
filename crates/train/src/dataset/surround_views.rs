//! A surround frame's cameras and LiDAR sweep in the label grid's frame, at full resolution and
//! before any augmentation ([`SurroundFrameViews`], [`SurroundDataset::frame_views`]).

use super::surround::SurroundFrame;
use super::{DatasetFormat, FrameRef, SurroundDataset};
use crate::error::TrainError;
use occ_data::formats::nuscenes_occupancy::{self as nocc, SampleCameras};
use occ_geometry::{transform_point, CameraView, Mat4};
use std::path::PathBuf;

/// One camera of a frame at full resolution, mapping the label grid's frame to its pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct SurroundView {
    /// Channel (`CAM_FRONT`, or a custom rig's name).
    pub channel: String,
    /// The camera's `sample_data` token.
    pub sample_data_token: String,
    /// The image file.
    pub image: PathBuf,
    /// Intrinsics and image size of the tables; `cam_from_lidar` maps the label grid's frame to
    /// the camera at its own timestamp (ego motion between the LiDAR and camera timestamps
    /// applied); no augmentation.
    pub view: CameraView,
}

/// The cameras and LiDAR sweep of one frame, in the label grid's frame (what
/// [`SurroundDataset::load`] builds a [`Sample`](super::Sample) from, before any image
/// augmentation).
#[derive(Clone, Debug, PartialEq)]
pub struct SurroundFrameViews {
    /// Scene name and sample token.
    pub frame: FrameRef,
    /// The cameras in the dataset's order.
    pub cameras: Vec<SurroundView>,
    /// The key-frame `LIDAR_TOP` file.
    pub lidar: PathBuf,
    /// `grid_from_lidar`: the LiDAR calibration for Occ3D (grid in the ego frame at the LiDAR
    /// time), the identity for nuScenes-Occupancy (grid in the LiDAR frame).
    pub grid_from_lidar: Mat4,
}

impl SurroundFrameViews {
    /// The LiDAR sweep's points in the label grid's frame (metres).
    pub fn read_points(&self) -> Result<Vec<[f32; 3]>, TrainError> {
        let pts = nocc::read_lidar_pcd_bin(&self.lidar)?;
        Ok(pts
            .iter()
            .map(|q| transform_point(&self.grid_from_lidar, q.map(f64::from)).map(|v| v as f32))
            .collect())
    }
}
impl SurroundDataset {
    /// The cameras (full resolution, label grid's frame) and LiDAR file of frame `i`, exactly as
    /// [`SurroundDataset::load`] uses them before the image augmentation.
    pub fn frame_views(&self, i: usize) -> Result<SurroundFrameViews, TrainError> {
        let (f, cams) = self.cameras_of(i)?;
        Ok(self.views_of(f, &cams))
    }

    pub(super) fn views_of(&self, f: &SurroundFrame, cams: &SampleCameras) -> SurroundFrameViews {
        let cameras = cams
            .cameras
            .iter()
            .map(|cam| {
                let cam_from_grid = match self.format {
                    DatasetFormat::Occ3d => cam.cam_from_ego_lidar,
                    _ => cam.view.cam_from_lidar,
                };
                SurroundView {
                    channel: cam.channel.clone(),
                    sample_data_token: cam.sample_data_token.clone(),
                    image: self.root.join(&cam.filename),
                    view: CameraView::new(cam.view.camera, cam_from_grid),
                }
            })
            .collect();
        SurroundFrameViews {
            frame: f.frame.clone(),
            cameras,
            lidar: self.root.join(&cams.lidar_filename),
            grid_from_lidar: self
                .grid_from_lidar(cams)
                .unwrap_or_else(occ_geometry::mat4_identity),
        }
    }
    /// `grid_from_lidar`: Occ3D grids live in the ego frame at the LiDAR time, nuScenes-Occupancy
    /// grids in the LiDAR frame.
    fn grid_from_lidar(&self, cams: &SampleCameras) -> Option<Mat4> {
        (self.format == DatasetFormat::Occ3d).then_some(cams.ego_from_lidar)
    }
}
