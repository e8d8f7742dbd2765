//! Built-in synthetic driving scenes, written in the real dataset layouts so that every command
//! of the project runs on them exactly as on real data, with no download.
//!
//! # What is generated
//!
//! For each sequence a procedural street world is generated once (in metres, so the same seed
//! gives the same street at every voxel size): a straight main road with 1–2 lanes per direction,
//! an optional median, parking strips, sidewalks with curbs, perpendicular crossings with zebra
//! stripes and traffic lights, and roadside zones (urban blocks with buildings, green areas with
//! terrain, trees, bushes, hedges and fences, parking lots, industrial yards), populated with
//! parked and stopped cars, trucks, vans and buses, trailers, bicycles, motorcycles, pedestrians,
//! bicyclists, motorcyclists, street lights and traffic signs (sizes, positions and counts drawn
//! per block). Every one of the 19 SemanticKITTI classes occurs in the first frame's volume. The
//! ego drives straight along one lane (never through an object) at a per-sequence speed; each
//! frame's grid is the world seen from the ego pose. Camera images are rendered by casting one
//! ray per pixel through the voxel world (class base colours, texture noise, face lighting,
//! distance darkening, haze beyond 55 m, sky with clouds; every effect up to 55 m is
//! luminance-only so a pixel's chromaticity identifies its class, see [`classes`]); the LiDAR is
//! simulated by the same ray caster.
//!
//! # Presets
//!
//! | preset | grid (LiDAR / ego frame) | image | LiDAR | travel per frame |
//! |---|---|---|---|---|
//! | `kitti` | [`VoxelGrid::semantic_kitti`]: 256×256×32, 0.2 m, origin (0, −25.6, −2.2) | 1226×370, fx=fy=721.5377, cx=609.5593, cy=172.854 | 64 beams, +2°..−24.8°, 2048 columns, 80 m | 0.8 or 1.2 m |
//! | `kitti-small` | the same volume at 0.4 m: 128×128×16 | 613×185, intrinsics ×0.5 | 64 beams, 1024 columns | 0.8 or 1.2 m |
//! | `surround` | [`VoxelGrid::occ3d_nuscenes`]: 200×200×16, 0.4 m, [−40,−40,−1, 40,40,5.4] | 6 × 704×256 | 32 beams, +10°..−30°, 1024 columns, 70 m | 3.2, 4.0 or 4.8 m (2 Hz key frames) |
//!
//! The KITTI grid origin is z = −2.2 m, the geometry of the released SemanticKITTI voxel files
//! (see [`VoxelGrid::semantic_kitti`]), so readers treat synthetic and real files alike. The LiDAR
//! is 1.8 m above the road (road surface at LiDAR z = −1.8, a voxel boundary at both 0.2 and
//! 0.4 m), the camera 1.65 m above the road, 0.27 m ahead of the LiDAR. For `kitti-small` the
//! voxel files use the coarse dims (they are NOT 256×256×32): read `synthetic.json` (see
//! [`read_synthetic_meta`]) for the grid. A custom image size scales the intrinsics by
//! `width/1226` and `height/370` (`kitti*`); for `surround` by `width/1600` with the image cut to
//! `height` from the bottom of the scaled 1600×900 frame (like the BEVDet crop), see
//! `surround_camera`.
//!
//! # Files
//!
//! `kitti`, `kitti-small` (`OUT/sequences/XX/`): `calib.txt` (`P2 = [K | 0]`: the 4th column is
//! zero because the images are rendered from the very camera `Tr` maps to; `Tr` has the KITTI
//! axes cam x = −lidar y, cam y = −lidar z, cam z = lidar x), `poses.txt` (KITTI camera-0 poses
//! `cam0(0)_from_cam0(t) = Tr · lidar(0)_from_lidar(t) · Tr⁻¹`), `times.txt` (0.1036 s per
//! frame), `image_2/NNNNNN.png`, `velodyne/NNNNNN.bin` + `labels/NNNNNN.label` (the simulated scan;
//! raw ids, instance 0), and for every frame `voxels/NNNNNN.bin` (voxels holding a LiDAR return of
//! this frame), `.label` (complete scene, raw SemanticKITTI ids), `.invalid` (voxels that no LiDAR
//! ray and no camera pixel ray of any frame of the sequence traversed or stopped in, nor any LiDAR
//! ray of the drive on past the last frame through its whole volume, as SemanticKITTI accumulates
//! the scans that follow a frame: about a quarter of the volume, like the real frames) and
//! `.occluded` (the same for this frame's rays only).
//!
//! `surround`: `OUT/samples/<CHANNEL>/*.png` (six cameras), `OUT/samples/LIDAR_TOP/*.pcd.bin`
//! (float32 x, y, z, intensity, ring), `OUT/gts/<scene name>/<sample token>/labels.npz` (Occ3D:
//! nuScenes-lidarseg ids 0–16, 17 = free; `mask_lidar` / `mask_camera` = voxels this frame's LiDAR /
//! camera rays traversed or stopped in), and nuScenes v1.0 tables in `OUT/v1.0-trainval/`
//! (`sample`, `sample_data`, `calibrated_sensor`, `ego_pose`, `sensor`, plus `scene.json` that maps
//! scene tokens to the names used under `gts/`).
//!
//! Every preset writes `OUT/synthetic.json` ([`SynthMeta`]). Output is deterministic: the same
//! configuration gives byte-identical files, whatever the number of threads.
//! Re-running into the same folder first removes what the previous run listed in
//! `synthetic.json`; a folder holding other data under the same names is never overwritten.
//!
//! # Limitations
//!
//! The road is straight and the ego never turns (poses are pure translations along LiDAR x);
//! the world is static (stopped traffic, standing pedestrians); objects are built from boxes,
//! vertical cylinders and ellipsoids and look blocky at the voxel size; point labels carry no
//! instance ids; cameras have no lens distortion or exposure changes. Building and vehicle
//! interiors are solid (labelled) but never observed, so they are `.invalid`.
//!
//! Throughput is dominated by ray casting (one ray per pixel and per LiDAR beam and column,
//! each marking the voxels it crosses for the visibility masks).

pub mod classes;
mod kitti;
pub(crate) mod layout;
pub(crate) mod render;
pub(crate) mod scene;
mod surround;
pub(crate) mod util;
pub(crate) mod vis;
pub(crate) mod world;

pub use render::LidarSpec;
pub use surround::scene_name_of;

use crate::error::DataError;
use crate::formats::io::{create_dir_all, read_bytes, write_atomic};
use occ_geometry::VoxelGrid;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// Name of the metadata file written at the output root.
pub const META_FILE: &str = "synthetic.json";
/// Value of [`SynthMeta::format`].
pub const META_FORMAT: &str = "sparseocc-synthetic";
/// Version of the generator (changes when the same seed would give different files).
pub const GENERATOR_VERSION: u32 = 2;
/// Most frames per sequence (the sequence-wide visibility bitset grows with the distance driven:
/// 20000 frames of `kitti` need about 130 MB).
pub const MAX_FRAMES: usize = 20_000;
/// nuScenes table folder written by the `surround` preset.
pub const NUSCENES_VERSION: &str = "v1.0-trainval";

/// Which dataset layout and resolution to generate.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// SemanticKITTI layout, full resolution (256×256×32 at 0.2 m, 1226×370 images).
    Kitti,
    /// SemanticKITTI layout over the same volume at 0.4 m (128×128×16), 613×185 images: for
    /// short CPU training runs.
    KittiSmall,
    /// Occ3D-nuScenes layout with six surround cameras (200×200×16 at 0.4 m).
    Surround,
}

impl Preset {
    /// The CLI name (`kitti`, `kitti-small`, `surround`).
    pub fn name(&self) -> &'static str {
        match self {
            Preset::Kitti => "kitti",
            Preset::KittiSmall => "kitti-small",
            Preset::Surround => "surround",
        }
    }

    /// The per-frame voxel grid (in the LiDAR frame for `kitti*`, the ego frame for `surround`).
    pub fn grid(&self) -> VoxelGrid {
        match self {
            Preset::Kitti => VoxelGrid::semantic_kitti(),
            Preset::KittiSmall => VoxelGrid::semantic_kitti().downsampled(2),
            Preset::Surround => VoxelGrid::occ3d_nuscenes(),
        }
    }

    /// Default image size `(width, height)`.
    pub fn default_image_size(&self) -> (usize, usize) {
        match self {
            Preset::Kitti => (1226, 370),
            Preset::KittiSmall => (613, 185),
            Preset::Surround => (704, 256),
        }
    }

    /// The simulated LiDAR.
    pub fn lidar(&self) -> LidarSpec {
        match self {
            Preset::Kitti => LidarSpec {
                beams: 64,
                elev_top_deg: 2.0,
                elev_bottom_deg: -24.8,
                columns: 2048,
                max_range_m: 80.0,
            },
            Preset::KittiSmall => LidarSpec {
                beams: 64,
                elev_top_deg: 2.0,
                elev_bottom_deg: -24.8,
                columns: 1024,
                max_range_m: 80.0,
            },
            Preset::Surround => LidarSpec {
                beams: 32,
                elev_top_deg: 10.0,
                elev_bottom_deg: -30.0,
                columns: 1024,
                max_range_m: 70.0,
            },
        }
    }

    /// Number of cameras per frame.
    pub fn num_cameras(&self) -> usize {
        match self {
            Preset::Surround => 6,
            _ => 1,
        }
    }
}

impl FromStr for Preset {
    type Err = DataError;
    fn from_str(s: &str) -> Result<Self, DataError> {
        match s {
            "kitti" => Ok(Preset::Kitti),
            "kitti-small" | "kitti_small" => Ok(Preset::KittiSmall),
            "surround" => Ok(Preset::Surround),
            _ => Err(DataError::InvalidArgument(format!(
                "unknown synthetic preset `{s}` (expected kitti, kitti-small or surround)"
            ))),
        }
    }
}

/// What to generate.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SynthConfig {
    pub preset: Preset,
    pub seed: u64,
    /// `(sequence name, number of frames)`; names become folder names (`sequences/<name>` for
    /// `kitti*`, scene `scene-<name>` for `surround`).
    pub sequences: Vec<(String, usize)>,
    /// Image size `(width, height)`; `None` = [`Preset::default_image_size`].
    pub image_size: Option<(usize, usize)>,
}

impl SynthConfig {
    /// A configuration with the preset's default image size.
    pub fn new(preset: Preset, seed: u64, sequences: Vec<(String, usize)>) -> Self {
        SynthConfig {
            preset,
            seed,
            sequences,
            image_size: None,
        }
    }

    /// The image size in effect.
    pub fn image_size(&self) -> (usize, usize) {
        self.image_size
            .unwrap_or_else(|| self.preset.default_image_size())
    }

    /// Check names, counts and sizes.
    pub fn validate(&self) -> Result<(), DataError> {
        let bad = |m: String| Err(DataError::InvalidArgument(m));
        if self.sequences.is_empty() {
            return bad("no sequences to generate".into());
        }
        for (i, (name, n)) in self.sequences.iter().enumerate() {
            if name.is_empty()
                || name.len() > 64
                || !name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
            {
                return bad(format!(
                    "sequence name `{name}`: use 1-64 letters, digits, `_` or `-`"
                ));
            }
            if *n == 0 || *n > MAX_FRAMES {
                return bad(format!(
                    "sequence `{name}`: frame count {n} is not in 1..={MAX_FRAMES}"
                ));
            }
            if self.sequences[..i].iter().any(|(o, _)| o == name) {
                return bad(format!("sequence `{name}` is listed twice"));
            }
        }
        let (w, h) = self.image_size();
        if !(8..=4096).contains(&w) || !(8..=4096).contains(&h) {
            return bad(format!(
                "image size {w}x{h}: width and height must be in 8..=4096"
            ));
        }
        Ok(())
    }
}

/// Parse a sequence list like `00:40,08:10` (name:frames, comma separated). A part `A-B:N` with `A`
/// and `B` all digits stands for the sequences `A, A+1, …, B` of `N` frames each, written with the
/// width of `A` (`00-02:4` = `00:4,01:4,02:4`; `8-10:1` = `8:1,9:1,10:1`); `A > B` is an error. Other
/// names with a `-` (`scene-a:3`) are plain names.
pub fn parse_sequences(spec: &str) -> Result<Vec<(String, usize)>, DataError> {
    let mut out = Vec::new();
    for part in spec.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let Some((name, n)) = part.split_once(':') else {
            return Err(DataError::InvalidArgument(format!(
                "sequence `{part}`: expected NAME:FRAMES or FIRST-LAST:FRAMES, e.g. 00:40 or 00-07:4"
            )));
        };
        let n: usize = n.trim().parse().map_err(|_| {
            DataError::InvalidArgument(format!("sequence `{part}`: `{n}` is not a frame count"))
        })?;
        let name = name.trim();
        let numeric = |t: &str| !t.is_empty() && t.bytes().all(|c| c.is_ascii_digit());
        match name.split_once('-') {
            // Both ends all digits: a range. Anything else with a `-` is a plain name (`scene-a`).
            Some((a, b)) if numeric(a) && numeric(b) => {
                let bad = || {
                    DataError::InvalidArgument(format!(
                        "sequence range `{part}`: FIRST-LAST needs FIRST <= LAST and at most 10000 sequences, e.g. 00-07:4"
                    ))
                };
                let first: u32 = a.parse().map_err(|_| bad())?;
                let last: u32 = b.parse().map_err(|_| bad())?;
                if first > last || last - first >= 10_000 {
                    return Err(bad());
                }
                let width = a.len();
                out.extend((first..=last).map(|i| (format!("{i:0width$}"), n)));
            }
            _ => out.push((name.to_string(), n)),
        }
    }
    if out.is_empty() {
        return Err(DataError::InvalidArgument(format!(
            "no sequences in `{spec}`"
        )));
    }
    Ok(out)
}

/// One generated sequence, as recorded in `synthetic.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SynthSequence {
    /// Sequence name (`sequences/<name>` or scene `scene-<name>`).
    pub name: String,
    pub frames: usize,
    /// Ego travel per frame (m).
    pub step_m: f64,
    /// nuScenes scene token (`surround` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_token: Option<String>,
}

/// Contents of `OUT/synthetic.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SynthMeta {
    /// Always [`META_FORMAT`].
    pub format: String,
    pub generator_version: u32,
    pub preset: Preset,
    /// `semantic_kitti` or `occ3d_nuscenes`.
    pub layout: String,
    pub seed: u64,
    /// The grid of every voxel file (LiDAR frame for `kitti*`, ego frame for `surround`).
    pub grid: VoxelGrid,
    /// `[width, height]` of every image.
    pub image_size: [usize; 2],
    pub num_cameras: usize,
    pub lidar: LidarSpec,
    pub sequences: Vec<SynthSequence>,
    /// nuScenes table folder below the root (`surround` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nuscenes_version: Option<String>,
    /// `false` while [`generate`] is writing (an interrupted run leaves `false`).
    #[serde(default = "default_true")]
    pub complete: bool,
}

fn default_true() -> bool {
    true
}

/// Read `root/synthetic.json`: `Ok(None)` when the file does not exist (a real dataset),
/// an error naming the file when it is unreadable or malformed.
pub fn read_synthetic_meta(root: &Path) -> Result<Option<SynthMeta>, DataError> {
    let path = root.join(META_FILE);
    if !path.exists() {
        return Ok(None);
    }
    let bytes = read_bytes(&path)?;
    let meta: SynthMeta = serde_json::from_slice(&bytes).map_err(|e| DataError::Parse {
        path: path.clone(),
        line: e.line(),
        detail: e.to_string(),
    })?;
    if meta.format != META_FORMAT {
        return Err(DataError::format(
            &path,
            format!("`format` is `{}`, expected `{META_FORMAT}`", meta.format),
        ));
    }
    let g = &meta.grid;
    if g.dims.iter().any(|&d| d == 0 || d > 4096)
        || g.voxel_size_m.is_nan()
        || g.voxel_size_m <= 0.0
        || g.origin_m.iter().any(|v| !v.is_finite())
    {
        return Err(DataError::format(&path, format!("invalid grid {g:?}")));
    }
    Ok(Some(meta))
}

/// What [`generate`] did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SynthSummary {
    pub root: PathBuf,
    pub preset: Preset,
    pub sequences: Vec<SynthSequence>,
    /// Frames written (all sequences).
    pub frames: usize,
    /// Files written and their total size.
    pub files: usize,
    pub bytes: u64,
    pub seconds: f64,
    pub frames_per_second: f64,
    /// Voxel count per class over all frames' grids: SemanticKITTI learning classes 0..=19
    /// (`kitti*`; ignored ids not counted) or Occ3D classes 0..=17 (`surround`).
    pub class_voxels: Vec<u64>,
    /// Mean fraction of grid voxels marked `.invalid` (`kitti*`) or with `mask_camera = 0`
    /// (`surround`).
    pub unobserved_fraction: f64,
    /// Mean LiDAR points per frame.
    pub lidar_points_per_frame: f64,
}

/// The file [`write_summary`] writes in the dataset folder.
pub const SUMMARY_FILE: &str = "synth_summary.json";

/// Writes `summary` as pretty JSON to `out/synth_summary.json`, atomically (what `sparseocc
/// synth` and the Python package's `synth` leave beside the data).
pub fn write_summary(out: &Path, summary: &SynthSummary) -> Result<PathBuf, DataError> {
    let path = out.join(SUMMARY_FILE);
    let text = serde_json::to_string_pretty(summary)
        .map_err(|e| DataError::InvalidArgument(format!("synth summary as JSON: {e}")))?;
    crate::formats::io::write_atomic(&path, text.as_bytes())?;
    Ok(path)
}

/// Counters shared by the writers.
#[derive(Default)]
pub(crate) struct Stats {
    pub files: usize,
    pub bytes: u64,
    pub class_voxels: Vec<u64>,
    pub unobserved: f64,
    pub lidar_points: usize,
    pub frames: usize,
}

impl Stats {
    pub(crate) fn wrote(&mut self, path: &Path) {
        self.files += 1;
        self.bytes += std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
    }
}

/// Generate every sequence of `cfg` below `out` (created if needed; existing files of the same
/// names are replaced). `progress(done, total)` is called as work advances, in steps: for
/// `kitti*` two per frame (rendered, then its `.invalid` written after the sequence), for
/// `surround` one per frame.
pub fn generate(
    out: &Path,
    cfg: &SynthConfig,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<SynthSummary, DataError> {
    cfg.validate()?;
    let t0 = std::time::Instant::now();
    create_dir_all(out)?;
    clean_previous(out, cfg)?;
    let placeholder: Vec<SynthSequence> = cfg
        .sequences
        .iter()
        .map(|(name, frames)| SynthSequence {
            name: name.clone(),
            frames: *frames,
            step_m: 0.0,
            scene_token: None,
        })
        .collect();
    write_meta(out, &meta_of(cfg, placeholder, false))?;
    let total_frames: usize = cfg.sequences.iter().map(|s| s.1).sum();
    let steps_per_frame = if cfg.preset == Preset::Surround { 1 } else { 2 };
    let total = total_frames * steps_per_frame;
    let mut done = 0usize;
    progress(0, total);
    let mut stats = Stats::default();
    let mut seqs = Vec::new();
    let mut tables = surround::Tables::default();
    for (name, frames) in &cfg.sequences {
        let mut tick = || {
            done += 1;
            progress(done, total);
        };
        let seq = match cfg.preset {
            Preset::Kitti | Preset::KittiSmall => {
                kitti::write_sequence(out, cfg, name, *frames, &mut stats, &mut tick)?
            }
            Preset::Surround => {
                surround::write_scene(out, cfg, name, *frames, &mut stats, &mut tables, &mut tick)?
            }
        };
        seqs.push(seq);
    }
    if cfg.preset == Preset::Surround {
        tables.write(out, &mut stats)?;
    }
    let meta_path = write_meta(out, &meta_of(cfg, seqs.clone(), true))?;
    stats.wrote(&meta_path);
    let seconds = t0.elapsed().as_secs_f64();
    let frames = stats.frames;
    Ok(SynthSummary {
        root: out.to_path_buf(),
        preset: cfg.preset,
        sequences: seqs,
        frames,
        files: stats.files,
        bytes: stats.bytes,
        seconds,
        frames_per_second: if seconds > 0.0 {
            frames as f64 / seconds
        } else {
            0.0
        },
        class_voxels: stats.class_voxels,
        unobserved_fraction: if frames > 0 {
            stats.unobserved / frames as f64
        } else {
            0.0
        },
        lidar_points_per_frame: if frames > 0 {
            stats.lidar_points as f64 / frames as f64
        } else {
            0.0
        },
    })
}

fn meta_of(cfg: &SynthConfig, sequences: Vec<SynthSequence>, complete: bool) -> SynthMeta {
    let (w, h) = cfg.image_size();
    SynthMeta {
        format: META_FORMAT.into(),
        generator_version: GENERATOR_VERSION,
        preset: cfg.preset,
        layout: if cfg.preset == Preset::Surround {
            "occ3d_nuscenes".into()
        } else {
            "semantic_kitti".into()
        },
        seed: cfg.seed,
        grid: cfg.preset.grid(),
        image_size: [w, h],
        num_cameras: cfg.preset.num_cameras(),
        lidar: cfg.preset.lidar(),
        sequences,
        nuscenes_version: (cfg.preset == Preset::Surround).then(|| NUSCENES_VERSION.to_string()),
        complete,
    }
}

fn write_meta(out: &Path, meta: &SynthMeta) -> Result<PathBuf, DataError> {
    let path = out.join(META_FILE);
    let text =
        serde_json::to_vec_pretty(meta).map_err(|e| DataError::format(&path, e.to_string()))?;
    write_atomic(&path, &text)?;
    Ok(path)
}

/// The folders and file-name prefixes a sequence of `preset` occupies below the root.
fn sequence_paths(
    out: &Path,
    preset: Preset,
    name: &str,
) -> (Vec<PathBuf>, Vec<(PathBuf, String)>) {
    match preset {
        Preset::Kitti | Preset::KittiSmall => (vec![out.join("sequences").join(name)], Vec::new()),
        Preset::Surround => {
            let scene = scene_name_of(name);
            let samples = crate::formats::nuscenes_occupancy::CAMERA_CHANNELS
                .iter()
                .chain(std::iter::once(
                    &crate::formats::nuscenes_occupancy::LIDAR_CHANNEL,
                ))
                .map(|ch| (out.join("samples").join(ch), format!("{scene}__")))
                .collect();
            (vec![out.join("gts").join(&scene)], samples)
        }
    }
}

fn remove_path(p: &Path) -> Result<(), DataError> {
    let r = if p.is_dir() {
        std::fs::remove_dir_all(p)
    } else {
        std::fs::remove_file(p)
    };
    match r {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(DataError::io(p, e)),
    }
}

/// Remove what an earlier synthetic run recorded in `out/synthetic.json` (so that no stale
/// frame survives), and refuse to write over anything else.
fn clean_previous(out: &Path, cfg: &SynthConfig) -> Result<(), DataError> {
    if let Some(prev) = read_synthetic_meta(out)? {
        for s in &prev.sequences {
            let (dirs, prefixed) = sequence_paths(out, prev.preset, &s.name);
            for d in dirs {
                remove_path(&d)?;
            }
            for (dir, prefix) in prefixed {
                let Ok(rd) = std::fs::read_dir(&dir) else {
                    continue;
                };
                for e in rd.flatten() {
                    if e.file_name().to_string_lossy().starts_with(&prefix) {
                        remove_path(&e.path())?;
                    }
                }
            }
        }
        if let Some(v) = &prev.nuscenes_version {
            if !v.is_empty() && !v.contains(['/', '\\']) && v != ".." {
                remove_path(&out.join(v))?;
            }
        }
    }
    let mut existing: Vec<PathBuf> = Vec::new();
    for (name, _) in &cfg.sequences {
        existing.extend(
            sequence_paths(out, cfg.preset, name)
                .0
                .into_iter()
                .filter(|p| p.exists()),
        );
    }
    if cfg.preset == Preset::Surround && out.join(NUSCENES_VERSION).exists() {
        existing.push(out.join(NUSCENES_VERSION));
    }
    if let Some(p) = existing.first() {
        return Err(DataError::InvalidArgument(format!(
            "refusing to overwrite {}: it was not written by an earlier synthetic run recorded in {} (remove it or choose another output folder)",
            p.display(),
            out.join(META_FILE).display()
        )));
    }
    Ok(())
}

/// Zero-padded 6-digit frame id (`000042`).
pub(crate) fn frame_id(i: usize) -> String {
    format!("{i:06}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_and_validate() {
        assert_eq!(
            parse_sequences("00:40,08:10").unwrap(),
            vec![("00".to_string(), 40), ("08".to_string(), 10)]
        );
        assert!(parse_sequences("00").is_err());
        assert!(parse_sequences("00:x").is_err());
        assert!(parse_sequences("").is_err());
        let r = parse_sequences("00-02:4, 10:1,8-10:2").unwrap();
        let names: Vec<&str> = r.iter().map(|s| s.0.as_str()).collect();
        assert_eq!(names, ["00", "01", "02", "10", "8", "9", "10"]);
        assert_eq!(
            r.iter().map(|s| s.1).collect::<Vec<_>>(),
            [4, 4, 4, 1, 2, 2, 2]
        );
        assert_eq!(
            parse_sequences("07-07:3").unwrap(),
            vec![("07".to_string(), 3)]
        );
        for bad in ["03-01:4", "0-99999:1", "00-02:x"] {
            let e = parse_sequences(bad).unwrap_err().to_string();
            assert!(e.contains(bad), "{bad}: {e}");
        }
        for plain in ["scene-a", "00-", "-3", "00-0x"] {
            assert_eq!(
                parse_sequences(&format!("{plain}:2")).unwrap(),
                vec![(plain.to_string(), 2)]
            );
        }
        let mut c = SynthConfig::new(Preset::KittiSmall, 1, vec![("00".into(), 3)]);
        assert!(c.validate().is_ok());
        c.sequences.push(("00".into(), 2));
        assert!(c.validate().is_err());
        c.sequences = vec![("../x".into(), 2)];
        assert!(c.validate().is_err());
        c.sequences = vec![("01".into(), 0)];
        assert!(c.validate().is_err());
        c.sequences = vec![("01".into(), 1)];
        c.image_size = Some((4, 100));
        assert!(c.validate().is_err());
        for p in [Preset::Kitti, Preset::KittiSmall, Preset::Surround] {
            assert_eq!(p.name().parse::<Preset>().unwrap(), p);
        }
        assert!("nope".parse::<Preset>().is_err());
        assert_eq!(Preset::KittiSmall.grid().dims, [128, 128, 16]);
    }
}
