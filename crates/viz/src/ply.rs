//! PLY export of the drawn voxels as coloured points (one vertex per voxel centre).
//!
//! Format (binary little-endian by default, or ASCII):
//! ```text
//! ply
//! format binary_little_endian 1.0        (or: format ascii 1.0)
//! comment occ-viz voxel centres, voxel_size_m <s>, dims <X> <Y> <Z>
//! element vertex <N>
//! property float x                       (metres, LiDAR frame)
//! property float y
//! property float z
//! property uchar red
//! property uchar green
//! property uchar blue
//! property uchar label                   (class id)
//! end_header
//! ```
//! followed by N records of 3 x f32 + 4 x u8 (16 bytes) in voxel C order ([x][y][z]). The file is
//! written to a temporary name in the same folder and renamed when complete.

use std::io::{BufWriter, Write};
use std::path::Path;

use occ_geometry::VoxelGrid;
use occ_labels::IGNORE;

use crate::palette::{height_color, Palette};
use crate::render::drawn;
use crate::{check_grid, check_labels, write_atomically, VizError};

/// PLY encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlyFormat {
    /// `binary_little_endian 1.0`, 16 bytes per vertex.
    BinaryLittleEndian,
    /// `ascii 1.0`, one line per vertex: `x y z r g b label`.
    Ascii,
}

/// Options of [`write_ply`].
#[derive(Debug, Clone, PartialEq)]
pub struct PlyOptions {
    /// Class palette for the vertex colours.
    pub palette: Palette,
    /// Class id that is not exported.
    pub empty_class: u8,
    /// Class id that is not exported.
    pub ignore_class: u8,
    /// Colour by voxel centre height instead of by class.
    pub color_by_height: bool,
    /// Encoding.
    pub format: PlyFormat,
}

impl PlyOptions {
    /// Palette defaults, ignore 255, class colours, binary little-endian.
    pub fn new(palette: Palette) -> Self {
        PlyOptions {
            palette,
            empty_class: palette.default_empty_class(),
            ignore_class: IGNORE,
            color_by_height: false,
            format: PlyFormat::BinaryLittleEndian,
        }
    }
}

/// Write the drawn voxels of `labels` to `path` as a coloured point cloud (see the module doc
/// for the exact format). Returns the number of vertices written.
pub fn write_ply(
    path: &Path,
    labels: &[u8],
    grid: &VoxelGrid,
    opts: &PlyOptions,
) -> Result<usize, VizError> {
    check_grid(grid)?;
    check_labels(labels, grid)?;
    let (empty, ignore) = (opts.empty_class, opts.ignore_class);
    let n = labels.iter().filter(|&&c| drawn(c, empty, ignore)).count();
    let [_, ny, nz] = grid.dims;
    let o = grid.origin_m;
    let s = grid.voxel_size_m;
    let lut = opts.palette.lut();
    write_atomically(path, |file| {
        let mut w = BufWriter::new(file);
        let fmt = match opts.format {
            PlyFormat::BinaryLittleEndian => "binary_little_endian",
            PlyFormat::Ascii => "ascii",
        };
        write!(
            w,
            "ply\nformat {fmt} 1.0\ncomment occ-viz voxel centres, voxel_size_m {s}, dims {} {} {}\n\
             element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n\
             property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar label\n\
             end_header\n",
            grid.dims[0], grid.dims[1], grid.dims[2]
        )?;
        for (idx, &c) in labels.iter().enumerate() {
            if !drawn(c, empty, ignore) {
                continue;
            }
            let (i, j, k) = (idx / (ny * nz), (idx / nz) % ny, idx % nz);
            let p = [
                (o[0] + (i as f64 + 0.5) * s) as f32,
                (o[1] + (j as f64 + 0.5) * s) as f32,
                (o[2] + (k as f64 + 0.5) * s) as f32,
            ];
            let rgb = if opts.color_by_height {
                height_color((k as f32 + 0.5) / nz as f32)
            } else {
                lut[c as usize]
            };
            match opts.format {
                PlyFormat::BinaryLittleEndian => {
                    for v in p {
                        w.write_all(&v.to_le_bytes())?;
                    }
                    w.write_all(&[rgb[0], rgb[1], rgb[2], c])?;
                }
                PlyFormat::Ascii => {
                    writeln!(
                        w,
                        "{} {} {} {} {} {} {}",
                        p[0], p[1], p[2], rgb[0], rgb[1], rgb[2], c
                    )?;
                }
            }
        }
        w.flush()?;
        Ok(())
    })?;
    Ok(n)
}
