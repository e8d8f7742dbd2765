//! Occ3D-nuScenes ground truth `gts/<scene>/<token>/labels.npz` (docs/formats.md §4): a zip of three
//! `.npy` arrays `semantics`, `mask_lidar`, `mask_camera`, each (200, 200, 16) uint8 in `[x][y][z]`
//! order; class 17 = free. The public sample is DEFLATE-compressed (as `np.savez_compressed`).

use super::io::{read_bytes, write_atomic};
use super::npy::{npy_bytes, parse_npy, NpyValues};
use crate::error::DataError;
use std::io::{Read, Write};
use std::path::Path;

/// Grid dimensions `[X, Y, Z]`.
pub const DIMS: [usize; 3] = [200, 200, 16];
/// Number of classes including free.
pub const NUM_CLASSES: usize = 18;
/// The "free" (empty) class.
pub const FREE: u8 = 17;
/// Class names (0..16 follow nuScenes-lidarseg; 17 free).
pub const CLASS_NAMES: [&str; 18] = [
    "others",
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
    "free",
];

/// The three arrays of an Occ3D `labels.npz`, flat C order `[x][y][z]`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Occ3dLabels {
    pub semantics: Vec<u8>,
    pub mask_lidar: Vec<u8>,
    pub mask_camera: Vec<u8>,
    pub dims: [usize; 3],
}

/// Upper bound on one decompressed array (guards against zip bombs / lying headers).
const MAX_ENTRY_BYTES: u64 = 256 << 20;

fn read_entry(
    archive: &mut zip::ZipArchive<std::io::Cursor<&[u8]>>,
    key: &str,
    path: &Path,
) -> Result<(Vec<u8>, [usize; 3]), DataError> {
    let name = format!("{key}.npy");
    let mut file = match archive.by_name(&name) {
        Ok(f) => f,
        Err(zip::result::ZipError::FileNotFound) => {
            return Err(DataError::MissingKey {
                path: path.to_path_buf(),
                key: key.into(),
            })
        }
        Err(e) => {
            return Err(DataError::format(
                path,
                format!("cannot open `{name}`: {e}"),
            ))
        }
    };
    let mut bytes = Vec::new();
    (&mut file)
        .take(MAX_ENTRY_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| DataError::format(path, format!("cannot decompress `{name}`: {e}")))?;
    if bytes.len() as u64 > MAX_ENTRY_BYTES {
        return Err(DataError::format(
            path,
            format!("`{name}` is larger than {MAX_ENTRY_BYTES} bytes"),
        ));
    }
    let arr = parse_npy(&bytes, &path.join(&name))?;
    let dims: [usize; 3] = arr.shape.as_slice().try_into().map_err(|_| {
        DataError::format(
            path,
            format!("`{key}` has shape {:?}, expected 3D", arr.shape),
        )
    })?;
    let data = match arr.values {
        NpyValues::U8(v) => v,
        NpyValues::Bool(v) => v.into_iter().map(|b| b as u8).collect(),
        other => {
            return Err(DataError::format(
                path,
                format!("`{key}` has dtype {}, expected uint8", other.dtype_name()),
            ))
        }
    };
    Ok((data, dims))
}

/// Parse `labels.npz` bytes (`path` is used in error messages). Checks that the three arrays
/// share one 3D shape, `semantics <= 17` and the masks are 0/1.
pub fn parse_labels_npz(bytes: &[u8], path: &Path) -> Result<Occ3dLabels, DataError> {
    let mut archive = zip::ZipArchive::new(std::io::Cursor::new(bytes))
        .map_err(|e| DataError::format(path, format!("not a valid .npz (zip): {e}")))?;
    let (semantics, dims) = read_entry(&mut archive, "semantics", path)?;
    let (mask_lidar, dl) = read_entry(&mut archive, "mask_lidar", path)?;
    let (mask_camera, dc) = read_entry(&mut archive, "mask_camera", path)?;
    if dl != dims || dc != dims {
        return Err(DataError::format(
            path,
            format!(
                "array shapes differ: semantics {dims:?}, mask_lidar {dl:?}, mask_camera {dc:?}"
            ),
        ));
    }
    if let Some((i, &v)) = semantics
        .iter()
        .enumerate()
        .find(|(_, &v)| v as usize >= NUM_CLASSES)
    {
        return Err(DataError::format(
            path,
            format!("semantics value {v} at flat index {i} is not a class (0..=17)"),
        ));
    }
    for (name, m) in [("mask_lidar", &mask_lidar), ("mask_camera", &mask_camera)] {
        if let Some((i, &v)) = m.iter().enumerate().find(|(_, &v)| v > 1) {
            return Err(DataError::format(
                path,
                format!("{name} value {v} at flat index {i} is not 0/1"),
            ));
        }
    }
    Ok(Occ3dLabels {
        semantics,
        mask_lidar,
        mask_camera,
        dims,
    })
}

/// Read an Occ3D `labels.npz`.
pub fn read_labels_npz(path: &Path) -> Result<Occ3dLabels, DataError> {
    let bytes = read_bytes(path)?;
    parse_labels_npz(&bytes, path)
}

/// Serialise as a DEFLATE-compressed `.npz` (like `np.savez_compressed`).
pub fn labels_npz_bytes(l: &Occ3dLabels) -> Result<Vec<u8>, DataError> {
    let n: usize = l.dims.iter().product();
    for (name, v) in [
        ("semantics", &l.semantics),
        ("mask_lidar", &l.mask_lidar),
        ("mask_camera", &l.mask_camera),
    ] {
        if v.len() != n {
            return Err(DataError::InvalidArgument(format!(
                "Occ3D {name} has {} values, dims {:?} need {n}",
                v.len(),
                l.dims
            )));
        }
    }
    let zerr =
        |e: zip::result::ZipError| DataError::InvalidArgument(format!("zip writing failed: {e}"));
    let ierr = |e: std::io::Error| DataError::InvalidArgument(format!("zip writing failed: {e}"));
    let mut zw = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    for (name, v) in [
        ("semantics", &l.semantics),
        ("mask_lidar", &l.mask_lidar),
        ("mask_camera", &l.mask_camera),
    ] {
        zw.start_file(format!("{name}.npy"), opts).map_err(zerr)?;
        zw.write_all(&npy_bytes(&l.dims, v)?).map_err(ierr)?;
    }
    Ok(zw.finish().map_err(zerr)?.into_inner())
}

/// The checks [`read_labels_npz`] makes of the values: classes 0..=17, masks 0/1 (`path` names
/// the file in the error).
pub fn check_labels(path: &Path, l: &Occ3dLabels) -> Result<(), DataError> {
    if let Some((i, &v)) = l
        .semantics
        .iter()
        .enumerate()
        .find(|(_, &v)| v as usize >= NUM_CLASSES)
    {
        return Err(DataError::InvalidArgument(format!(
            "{}: Occ3D semantics value {v} at flat index {i} is not a class (0..=17)",
            path.display()
        )));
    }
    for (name, m) in [
        ("mask_lidar", &l.mask_lidar),
        ("mask_camera", &l.mask_camera),
    ] {
        if let Some((i, &v)) = m.iter().enumerate().find(|(_, &v)| v > 1) {
            return Err(DataError::InvalidArgument(format!(
                "{}: Occ3D {name} value {v} at flat index {i} is not 0/1",
                path.display()
            )));
        }
    }
    Ok(())
}

/// Write an Occ3D `labels.npz` (DEFLATE), atomically. Any values are written (prediction files
/// may hold invalid ids, which the scorer counts); [`check_labels`] is what [`read_labels_npz`]
/// demands of a ground-truth file.
pub fn write_labels_npz(path: &Path, l: &Occ3dLabels) -> Result<(), DataError> {
    let bytes = labels_npz_bytes(l)?;
    write_atomic(path, &bytes)
}
