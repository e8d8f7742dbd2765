//! Reading label grids of every supported kind, with the grid they live on.

use anyhow::{bail, Result};
use occ_data::formats::semantic_kitti as sk;
use occ_data::formats::voxels::{self, VoxelFile};
use occ_data::labels::LearningMap;
use occ_geometry::VoxelGrid;
use occ_train::dataset::DatasetFormat;
use occ_viz::Palette;
use std::path::Path;

/// A class grid ready to render or score.
pub struct LabelGrid {
    /// One class id per voxel, C order [x][y][z].
    pub classes: Vec<u8>,
    /// The grid.
    pub grid: VoxelGrid,
    /// The palette of the class ids.
    pub palette: Palette,
    /// True when the file held occupancy only (no classes).
    pub occupancy_only: bool,
    /// What the file holds, as a panel title: "ground truth" for class grids, "LiDAR input
    /// occupancy (.bin)" for SemanticKITTI's voxelised scan, the mask name for `.invalid` /
    /// `.occluded`.
    pub title: &'static str,
}

/// Reads a SemanticKITTI `.label` file (raw ids, any grid) on a known grid as learning classes.
pub fn read_kitti_label(path: &Path, grid: VoxelGrid) -> Result<LabelGrid> {
    let raw = sk::read_label_raw(path, grid.num_voxels())?;
    Ok(LabelGrid {
        classes: LearningMap::semantic_kitti().remap(&raw),
        grid,
        palette: Palette::SemanticKitti,
        occupancy_only: false,
        title: "ground truth",
    })
}

/// Reads a ground-truth or prediction file of a nuScenes-layout dataset on its grid: Occ3D
/// `labels.npz` (`semantics`, 17 = free) or nuScenes-Occupancy sparse `.npy` (0 = empty).
pub fn read_surround_labels(
    path: &Path,
    format: DatasetFormat,
    grid: VoxelGrid,
) -> Result<LabelGrid> {
    let (classes, palette) = match format {
        DatasetFormat::NuscenesOccupancy => (
            occ_data::formats::nuscenes_occupancy::read_sparse_occupancy(path)?,
            Palette::NuScenesOccupancy,
        ),
        _ => (
            occ_eval::folder::read_occ3d_prediction(path, grid.dims)?,
            Palette::Occ3d,
        ),
    };
    anyhow::ensure!(
        classes.len() == grid.num_voxels(),
        "{}: {} voxels, the grid {:?} has {}",
        path.display(),
        classes.len(),
        grid.dims,
        grid.num_voxels()
    );
    Ok(LabelGrid {
        classes,
        grid,
        palette,
        occupancy_only: false,
        title: "ground truth",
    })
}

/// Reads `.label` (raw SemanticKITTI ids), `.bin`/`.invalid`/`.occluded` (packed occupancy), `.npy`
/// (preprocessed class grid) or `labels.npz` (Occ3D).
pub fn read_label_grid(path: &Path) -> Result<LabelGrid> {
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default();
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or_default();
    match ext {
        "label" | "bin" | "invalid" | "occluded" | "npz" => Ok(match voxels::read_voxels(path)? {
            VoxelFile::KittiLabel { raw, grid } => LabelGrid {
                classes: LearningMap::semantic_kitti().remap(&raw),
                grid,
                palette: Palette::SemanticKitti,
                occupancy_only: false,
                title: "ground truth",
            },
            VoxelFile::KittiBits { bits, grid } => LabelGrid {
                classes: bits,
                grid,
                palette: Palette::SemanticKitti,
                occupancy_only: true,
                title: match ext {
                    "bin" => "LiDAR input occupancy (.bin)",
                    "invalid" => "invalid voxels (.invalid)",
                    _ => "occluded voxels (.occluded)",
                },
            },
            VoxelFile::Occ3d(l) => LabelGrid {
                classes: l.semantics,
                grid: VoxelGrid::occ3d_nuscenes(),
                palette: Palette::Occ3d,
                occupancy_only: false,
                title: "ground truth",
            },
        }),
        "npy" => {
            let (classes, dims) = sk::read_label_npy(path)?;
            let f = 256 / dims[0].max(1);
            let grid = VoxelGrid::semantic_kitti().downsampled(f.max(1));
            anyhow::ensure!(
                grid.dims == dims,
                "{}: dims {dims:?} are not a SemanticKITTI grid",
                path.display()
            );
            Ok(LabelGrid {
                classes,
                grid,
                palette: Palette::SemanticKitti,
                occupancy_only: false,
                title: "ground truth",
            })
        }
        _ => bail!(
            "{}: unknown label file '{name}' (expected .label, .bin, .npy or labels.npz)",
            path.display()
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn panel_titles_name_what_the_file_holds() {
        let dir = std::env::temp_dir().join(format!("sparseocc-labels-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let n = VoxelGrid::semantic_kitti().num_voxels();
        let bin = dir.join("000000.bin");
        std::fs::write(&bin, vec![0u8; n / 8]).unwrap();
        let g = read_label_grid(&bin).unwrap();
        assert!(g.occupancy_only);
        assert_eq!(g.title, "LiDAR input occupancy (.bin)");
        let inv = dir.join("000000.invalid");
        std::fs::write(&inv, vec![0u8; n / 8]).unwrap();
        assert_eq!(
            read_label_grid(&inv).unwrap().title,
            "invalid voxels (.invalid)"
        );
        let label = dir.join("000000.label");
        std::fs::write(&label, vec![0u8; n * 2]).unwrap();
        assert_eq!(read_label_grid(&label).unwrap().title, "ground truth");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
