//! `sparseocc viz`: headless renders of voxel grids, camera overlays, PLY export; with
//! `--nuscenes`, one surround-camera key frame with its LiDAR points and a grid projected into
//! every camera beside a bird's-eye view.

use crate::labels_io::read_label_grid;
use crate::panels::render_panels;
use anyhow::{Context, Result};
use occ_data::image::{read_image, write_png, RgbImage};
use occ_viz::{
    render_surround, write_ply, OverlayOptions, PlyOptions, SurroundCamera, SurroundGrid,
    SurroundOptions,
};
use std::path::{Path, PathBuf};

use occ_train::dataset::{DatasetFormat, SurroundDataset};

/// Arguments of `sparseocc viz`.
#[derive(clap::Args, Debug)]
pub struct VizArgs {
    /// Ground-truth (or any) label grid: .label, .bin, .npy or labels.npz. With --nuscenes: the
    /// grid drawn over the cameras, Occ3D labels.npz or nuScenes-Occupancy .npy.
    #[arg(long, required_unless_present = "nuscenes")]
    pub labels: Option<PathBuf>,
    /// A prediction to show beside it (same kinds); with --nuscenes, the grid drawn over the
    /// cameras instead of --labels.
    #[arg(long)]
    pub pred: Option<PathBuf>,
    /// Camera image (PNG or JPEG) for an overlay panel; needs --calib.
    #[arg(long, requires = "calib", conflicts_with = "nuscenes")]
    pub image: Option<PathBuf>,
    /// SemanticKITTI calib.txt (P2, Tr) of the image.
    #[arg(long, requires = "image", conflicts_with = "nuscenes")]
    pub calib: Option<PathBuf>,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Also export the occupied voxels of --labels as a PLY point cloud.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// Height of each panel in pixels.
    #[arg(long, default_value_t = 540)]
    pub height: usize,
    /// A nuScenes-layout root (v1.0 tables, samples/): render one key frame's cameras with its
    /// LIDAR_TOP points (and --labels / --pred voxels) projected, beside a bird's-eye view.
    #[arg(long)]
    pub nuscenes: Option<PathBuf>,
    /// The frame: a sample token (with --nuscenes).
    #[arg(long, requires = "nuscenes", conflicts_with = "scene")]
    pub sample: Option<String>,
    /// The frame: a scene name (`scene-0001`), with --index (with --nuscenes).
    #[arg(long, requires = "nuscenes")]
    pub scene: Option<String>,
    /// The frame: its position among the scene's key frames, by time (default 0).
    #[arg(long, requires = "scene")]
    pub index: Option<usize>,
    /// Cameras, comma-separated, in this order (default: every camera sensor of sensor.json,
    /// the six nuScenes ones first).
    #[arg(long, requires = "nuscenes", value_delimiter = ',')]
    pub cameras: Vec<String>,
    /// Table folder below the root (default: v1.0-trainval, v1.0-mini or v1.0-test, whichever
    /// has sample.json).
    #[arg(long, requires = "nuscenes")]
    pub version: Option<String>,
    /// Width of each camera panel in the picture.
    #[arg(long, default_value_t = 800)]
    pub panel_width: usize,
    /// Depth (m) at the far (violet) end of the point colours.
    #[arg(long, default_value_t = 60.0)]
    pub max_depth: f64,
    /// Radius of a LiDAR point in pixels of a camera panel.
    #[arg(long, default_value_t = 1)]
    pub point_radius: usize,
    /// Do not read or draw the LiDAR points.
    #[arg(long)]
    pub no_points: bool,
}

pub fn run(args: &VizArgs) -> Result<()> {
    if let Some(root) = &args.nuscenes {
        return run_surround(root, args);
    }
    let t0 = std::time::Instant::now();
    let Some(labels_p) = &args.labels else {
        anyhow::bail!("--labels is required (or --nuscenes ROOT for a surround-camera frame)");
    };
    let labels = read_label_grid(labels_p)?;
    let pred = args.pred.as_deref().map(read_label_grid).transpose()?;
    if let Some(p) = &pred {
        anyhow::ensure!(
            p.grid.dims == labels.grid.dims,
            "{}: prediction grid {:?} differs from labels grid {:?}",
            args.pred
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_default(),
            p.grid.dims,
            labels.grid.dims
        );
    }
    let image = match (&args.image, &args.calib) {
        (Some(i), Some(c)) => Some((i.as_path(), c.as_path())),
        _ => None,
    };
    render_panels(&labels, pred.as_ref(), image, &args.out, args.height)?;
    if let Some(ply) = &args.ply {
        let mut o = PlyOptions::new(labels.palette);
        o.color_by_height = labels.occupancy_only;
        let n = write_ply(ply, &labels.classes, &labels.grid, &o)?;
        eprintln!("wrote {n} voxels to {}", ply.display());
    }
    eprintln!(
        "wrote {} in {:.2} s",
        args.out.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The layout of a grid file drawn over a surround frame: Occ3D `labels.npz` (grid in the ego
/// frame at the LiDAR time) or nuScenes-Occupancy `.npy` (grid in the LiDAR frame).
fn surround_format(path: &Path) -> Result<DatasetFormat> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("npz") => Ok(DatasetFormat::Occ3d),
        Some("npy") => Ok(DatasetFormat::NuscenesOccupancy),
        _ => anyhow::bail!(
            "{}: with --nuscenes the grid must be an Occ3D labels.npz or a nuScenes-Occupancy .npy",
            path.display()
        ),
    }
}

/// `viz --nuscenes`: one key frame of a nuScenes-layout dataset, every camera with the LiDAR
/// points and the grid's voxels projected, beside a bird's-eye view with the camera frusta. The
/// cameras and points come from [`SurroundDataset::frame_views`], the dataset path's own geometry
/// (ego motion between the LiDAR and camera timestamps applied).
fn run_surround(root: &Path, args: &VizArgs) -> Result<()> {
    let t0 = std::time::Instant::now();
    if args.labels.is_some() && args.pred.is_some() {
        anyhow::bail!(
            "with --nuscenes give --labels or --pred (the grid drawn over the cameras), not both"
        );
    }
    let grid_file = args.labels.as_deref().or(args.pred.as_deref());
    let format = grid_file
        .map(surround_format)
        .transpose()?
        .unwrap_or(DatasetFormat::Occ3d);
    let scenes = vec![args.scene.clone().unwrap_or_else(|| "*".to_string())];
    let mut ds = SurroundDataset::open(
        root,
        format,
        &scenes,
        &[],
        occ_data::image::ImagePipelineConfig::semantic_kitti(),
        None,
        args.version.as_deref(),
    )?;
    let channels = if args.cameras.is_empty() {
        ds.tables().camera_channels()
    } else {
        args.cameras.clone()
    };
    if channels.is_empty() {
        anyhow::bail!(
            "{}: no sensor of modality `camera`",
            ds.tables().dir.join("sensor.json").display()
        );
    }
    ds.set_cameras(channels)?;
    let i = frame_index(&ds, args)?;
    let views = ds.frame_views(i)?;
    let points = if args.no_points {
        Vec::new()
    } else {
        views.read_points()?
    };
    // Decode the images in parallel, each header checked against its sample_data first.
    let images: Vec<RgbImage> = std::thread::scope(|s| {
        let handles: Vec<_> = views
            .cameras
            .iter()
            .map(|cam| {
                s.spawn(move || -> Result<RgbImage> {
                    let k = cam.view.camera;
                    let (w, h) = occ_data::image::read_image_size(&cam.image)?;
                    anyhow::ensure!(
                        (w, h) == (k.width, k.height),
                        "{}: image is {w}x{h} but its sample_data ({}) says {}x{}",
                        cam.image.display(),
                        cam.sample_data_token,
                        k.width,
                        k.height
                    );
                    Ok(read_image(&cam.image)?)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("image decoding thread panicked")))
            })
            .collect::<Result<Vec<_>>>()
    })?;
    let grid = ds.grid();
    let labels = grid_file
        .map(|p| crate::labels_io::read_surround_labels(p, format, grid))
        .transpose()?;
    let overlay = labels.as_ref().map(|l| {
        let mut o = OverlayOptions::new(l.palette);
        o.color_by_height = l.occupancy_only;
        o
    });
    let sgrid = labels
        .as_ref()
        .zip(overlay.as_ref())
        .map(|(l, o)| SurroundGrid {
            labels: &l.classes,
            overlay: o,
        });
    let cams: Vec<SurroundCamera> = views
        .cameras
        .iter()
        .zip(&images)
        .map(|(c, img)| SurroundCamera {
            name: &c.channel,
            image: img,
            view: &c.view,
        })
        .collect();
    let opts = SurroundOptions {
        panel_width: args.panel_width,
        point_radius: args.point_radius,
        max_depth_m: args.max_depth,
        draw_points: !args.no_points,
        title: format!("{} / {}", views.frame.sequence, views.frame.frame),
        ..SurroundOptions::default()
    };
    let t_read = t0.elapsed().as_secs_f64();
    let r = render_surround(&cams, &points, &grid, sgrid.as_ref(), &opts)?;
    let t_render = t0.elapsed().as_secs_f64() - t_read;
    if let Some(dir) = args.out.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
    }
    write_png(&args.out, &r.image)?;
    if let (Some(ply), Some(l)) = (&args.ply, &labels) {
        let mut o = PlyOptions::new(l.palette);
        o.color_by_height = l.occupancy_only;
        let n = write_ply(ply, &l.classes, &l.grid, &o)?;
        eprintln!("wrote {n} voxels to {}", ply.display());
    }
    let per_cam: Vec<String> = views
        .cameras
        .iter()
        .zip(&r.points_per_camera)
        .map(|(c, n)| format!("{} {n}", c.channel))
        .collect();
    eprintln!(
        "frame {} / {}: {} cameras, {} LiDAR points; points drawn per camera: {}",
        views.frame.sequence,
        views.frame.frame,
        cams.len(),
        points.len(),
        per_cam.join(", ")
    );
    let total = t0.elapsed().as_secs_f64();
    eprintln!(
        "wrote {} ({}x{}) in {total:.2} s (reading {t_read:.2} s, drawing {t_render:.2} s, writing {:.2} s)",
        args.out.display(),
        r.image.width,
        r.image.height,
        total - t_read - t_render
    );
    Ok(())
}

/// The frame chosen by `--sample TOKEN` or `--scene NAME [--index N]`.
fn frame_index(ds: &SurroundDataset, args: &VizArgs) -> Result<usize> {
    let sample_json = ds.tables().dir.join("sample.json");
    if let Some(tok) = &args.sample {
        if let Some(i) = ds.frames().iter().position(|f| &f.frame == tok) {
            return Ok(i);
        }
        if ds.tables().sample.iter().any(|s| &s.token == tok) {
            anyhow::bail!(
                "{}: sample {tok} belongs to no scene of {}",
                sample_json.display(),
                ds.tables().dir.join("scene.json").display()
            );
        }
        anyhow::bail!("{}: no sample with token {tok}", sample_json.display());
    }
    let Some(scene) = &args.scene else {
        anyhow::bail!("--nuscenes needs the frame: --sample TOKEN or --scene NAME [--index N]");
    };
    let index = args.index.unwrap_or(0);
    let n = ds.frames().len();
    if index >= n {
        anyhow::bail!(
            "{}: scene {scene} has {n} key-frame samples; --index {index} is out of range",
            sample_json.display()
        );
    }
    Ok(index)
}
