//! One voxel file of any kind the datasets ship, recognised by its name (docs/formats.md): the
//! SemanticKITTI `.label` (raw uint16 ids) and bit-packed `.bin` / `.invalid` / `.occluded` files,
//! and Occ3D's `labels.npz`. What `sparseocc viz` and the Python package's `read_voxels` /
//! `write_voxels` read and write.
//!
//! SemanticKITTI files carry no shape: the grid is found from the voxel count (256x256x32 and its
//! 1/2 and 1/4 downsamplings), or from a `synthetic.json` in a folder above the file (the generated
//! datasets' grids).

use crate::error::DataError;
use crate::formats::occ3d::{self, Occ3dLabels};
use crate::formats::semantic_kitti as sk;
use occ_geometry::VoxelGrid;
use std::path::Path;

/// What a voxel file holds, by its name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelFileKind {
    /// SemanticKITTI `.label`: one little-endian uint16 raw label id per voxel.
    KittiLabel,
    /// SemanticKITTI bit-packed occupancy (`.bin`), unobserved (`.invalid`) or occluded
    /// (`.occluded`) voxels: one bit per voxel, MSB first.
    KittiBits,
    /// Occ3D `labels.npz` (`semantics`, `mask_lidar`, `mask_camera`).
    Occ3d,
}

impl VoxelFileKind {
    /// The kind of `path` from its extension; an error naming the file otherwise.
    pub fn of(path: &Path) -> Result<Self, DataError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or_default();
        match ext {
            "label" => Ok(VoxelFileKind::KittiLabel),
            "bin" | "invalid" | "occluded" => Ok(VoxelFileKind::KittiBits),
            "npz" => Ok(VoxelFileKind::Occ3d),
            _ => Err(DataError::format(
                path,
                "unknown voxel file (expected .label, .bin, .invalid, .occluded or an Occ3D labels.npz)",
            )),
        }
    }
}

/// The contents of one voxel file.
#[derive(Clone, Debug, PartialEq)]
pub enum VoxelFile {
    /// `.label`: raw ids, flat `[X][Y][Z]` on `grid`.
    KittiLabel { raw: Vec<u16>, grid: VoxelGrid },
    /// `.bin` / `.invalid` / `.occluded`: 0/1 per voxel, flat `[X][Y][Z]` on `grid`.
    KittiBits { bits: Vec<u8>, grid: VoxelGrid },
    /// Occ3D `labels.npz`.
    Occ3d(Occ3dLabels),
}

/// The SemanticKITTI-volume grid of `n` voxels for the file `path`: a `synthetic.json` in a folder
/// above it whose grid has `n` voxels, else the full grid (256x256x32) or its 1/2 or 1/4
/// downsampling.
pub fn kitti_grid_for(path: &Path, n: usize) -> Result<VoxelGrid, DataError> {
    let mut dir = path.parent();
    while let Some(d) = dir {
        if let Ok(Some(meta)) = crate::synthetic::read_synthetic_meta(d) {
            if meta.grid.num_voxels() == n {
                return Ok(meta.grid);
            }
        }
        dir = d.parent();
    }
    for f in [1, 2, 4] {
        let g = VoxelGrid::semantic_kitti().downsampled(f);
        if g.num_voxels() == n {
            return Ok(g);
        }
    }
    Err(DataError::format(
        path,
        format!(
            "{n} voxels matches no SemanticKITTI grid (256x256x32 or /2, /4) and no synthetic.json above it"
        ),
    ))
}

fn file_len(path: &Path) -> Result<usize, DataError> {
    std::fs::metadata(path)
        .map(|m| m.len() as usize)
        .map_err(|e| DataError::io(path, e))
}

/// Reads a voxel file of any [`VoxelFileKind`].
pub fn read_voxels(path: &Path) -> Result<VoxelFile, DataError> {
    match VoxelFileKind::of(path)? {
        VoxelFileKind::KittiLabel => {
            let len = file_len(path)?;
            if len % 2 != 0 {
                return Err(DataError::format(
                    path,
                    format!("{len} bytes is not a whole number of uint16 labels"),
                ));
            }
            let grid = kitti_grid_for(path, len / 2)?;
            Ok(VoxelFile::KittiLabel {
                raw: sk::read_label_raw(path, grid.num_voxels())?,
                grid,
            })
        }
        VoxelFileKind::KittiBits => {
            let grid = kitti_grid_for(path, file_len(path)? * 8)?;
            Ok(VoxelFile::KittiBits {
                bits: sk::read_packed_bits(path, grid.num_voxels())?,
                grid,
            })
        }
        VoxelFileKind::Occ3d => Ok(VoxelFile::Occ3d(occ3d::read_labels_npz(path)?)),
    }
}

/// Writes `file` to `path` (its kind must match the name), creating the folder; atomically (a
/// temporary name beside it, renamed when complete). What the reader would reject or read
/// differently is refused: bits other than 0/1, Occ3D classes above 17 or masks other than 0/1,
/// and a SemanticKITTI grid other than the one [`kitti_grid_for`] finds for the file's size (the
/// file stores no shape: a transposed `[Z, Y, X]` array would be read back as `[X, Y, Z]`).
pub fn write_voxels(path: &Path, file: &VoxelFile) -> Result<(), DataError> {
    let kind = VoxelFileKind::of(path)?;
    let want = match file {
        VoxelFile::KittiLabel { .. } => VoxelFileKind::KittiLabel,
        VoxelFile::KittiBits { .. } => VoxelFileKind::KittiBits,
        VoxelFile::Occ3d(_) => VoxelFileKind::Occ3d,
    };
    if kind != want {
        return Err(DataError::InvalidArgument(format!(
            "{}: the name says {kind:?} but the data is {want:?}",
            path.display()
        )));
    }
    let check_len = |n: usize, grid: &VoxelGrid| {
        if n != grid.num_voxels() {
            return Err(DataError::InvalidArgument(format!(
                "{}: {n} values for a {:?} grid ({} voxels)",
                path.display(),
                grid.dims,
                grid.num_voxels()
            )));
        }
        Ok(())
    };
    let check_read_back = |grid: &VoxelGrid| {
        let n = grid.num_voxels();
        let known = kitti_grid_for(path, n).ok().map(|g| g.dims);
        if known == Some(grid.dims) {
            return Ok(());
        }
        let read_as = match known {
            Some(dims) => format!("would be read back as {dims:?}"),
            None => "match no grid the reader knows (256x256x32 or /2, /4, or the grid of a \
                     synthetic.json above the file)"
                .to_string(),
        };
        Err(DataError::InvalidArgument(format!(
            "{}: a SemanticKITTI voxel file stores no shape, and the {n} values of a {:?} array \
             {read_as}; the layout is [X, Y, Z]",
            path.display(),
            grid.dims
        )))
    };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| DataError::io(dir, e))?;
    }
    match file {
        VoxelFile::KittiLabel { raw, grid } => {
            check_len(raw.len(), grid)?;
            check_read_back(grid)?;
            sk::write_label_raw(path, raw)
        }
        VoxelFile::KittiBits { bits, grid } => {
            check_len(bits.len(), grid)?;
            if let Some((i, &v)) = bits.iter().enumerate().find(|(_, &v)| v > 1) {
                return Err(DataError::InvalidArgument(format!(
                    "{}: value {v} at flat index {i} is not 0/1",
                    path.display()
                )));
            }
            check_read_back(grid)?;
            sk::write_packed_bits(path, bits)
        }
        VoxelFile::Occ3d(l) => {
            occ3d::check_labels(path, l)?;
            occ3d::write_labels_npz(path, l)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("occ-voxels-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn round_trips_of_every_kind_with_the_grid_found_from_the_size() {
        let d = tmp("rt");
        let grid = VoxelGrid::semantic_kitti().downsampled(2);
        let n = grid.num_voxels();
        let raw: Vec<u16> = (0..n).map(|i| (i % 260) as u16).collect();
        let label = VoxelFile::KittiLabel { raw, grid };
        let p = d.join("a/b/000000.label");
        write_voxels(&p, &label).unwrap();
        assert_eq!(read_voxels(&p).unwrap(), label);
        let bits = VoxelFile::KittiBits {
            bits: (0..n).map(|i| (i % 3 == 0) as u8).collect(),
            grid,
        };
        let p = d.join("000000.invalid");
        write_voxels(&p, &bits).unwrap();
        assert_eq!(read_voxels(&p).unwrap(), bits);
        let dims = [4, 5, 3];
        let m = 60;
        let occ = VoxelFile::Occ3d(Occ3dLabels {
            semantics: (0..m).map(|i| (i % 18) as u8).collect(),
            mask_lidar: (0..m).map(|i| (i % 2) as u8).collect(),
            mask_camera: vec![1; m],
            dims,
        });
        let p = d.join("scene/tok/labels.npz");
        write_voxels(&p, &occ).unwrap();
        assert_eq!(read_voxels(&p).unwrap(), occ);
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn what_the_reader_rejects_is_not_written() {
        let d = tmp("bad");
        let grid = VoxelGrid::semantic_kitti().downsampled(4);
        let n = grid.num_voxels();
        let mut bits = vec![0u8; n];
        bits[7] = 2;
        let e = write_voxels(&d.join("x.bin"), &VoxelFile::KittiBits { bits, grid }).unwrap_err();
        assert!(e.to_string().contains("flat index 7"), "{e}");
        let e = write_voxels(
            &d.join("x.label"),
            &VoxelFile::KittiLabel {
                raw: vec![0; n - 1],
                grid,
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("values for a"), "{e}");
        let mut l = Occ3dLabels {
            semantics: vec![0; 8],
            mask_lidar: vec![1; 8],
            mask_camera: vec![1; 8],
            dims: [2, 2, 2],
        };
        l.semantics[3] = 18;
        let e = write_voxels(&d.join("labels.npz"), &VoxelFile::Occ3d(l.clone())).unwrap_err();
        assert!(e.to_string().contains("semantics value 18"), "{e}");
        l.semantics[3] = 0;
        l.mask_camera[1] = 5;
        assert!(write_voxels(&d.join("labels.npz"), &VoxelFile::Occ3d(l)).is_err());
        // A SemanticKITTI file stores no shape: an array the reader would take for another grid
        // (transposed), or for none, is refused.
        let [x, y, z] = grid.dims;
        for dims in [[z, y, x], [3, 3, 3]] {
            let other = VoxelGrid { dims, ..grid };
            let n = other.num_voxels();
            for file in [
                VoxelFile::KittiLabel {
                    raw: vec![0; n],
                    grid: other,
                },
                VoxelFile::KittiBits {
                    bits: vec![0; n],
                    grid: other,
                },
            ] {
                let p = d.join(if matches!(file, VoxelFile::KittiLabel { .. }) {
                    "y.label"
                } else {
                    "y.invalid"
                });
                let e = write_voxels(&p, &file).unwrap_err().to_string();
                assert!(
                    e.contains("stores no shape") && e.contains(&format!("{dims:?}")),
                    "{e}"
                );
            }
        }
        // Name and data disagree; unknown names.
        let e = write_voxels(
            &d.join("x.label"),
            &VoxelFile::KittiBits {
                bits: vec![0; n],
                grid,
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("the name says"), "{e}");
        assert!(read_voxels(&d.join("x.txt")).is_err());
        // Nothing was left behind by the refused writes.
        let left: Vec<_> = std::fs::read_dir(&d)
            .map(|r| r.flatten().map(|e| e.file_name()).collect())
            .unwrap_or_default();
        assert!(left.is_empty(), "{left:?}");
        // A size that is no grid.
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(d.join("odd.label"), [0u8; 10]).unwrap();
        let e = read_voxels(&d.join("odd.label")).unwrap_err();
        assert!(
            e.to_string().contains("matches no SemanticKITTI grid"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&d);
    }
}
