//! Render the real sample frames for a visual check.
//!
//! `cargo run --release -p occ-viz --example render_realdata [-- OUT_DIR]`
//!
//! For every SemanticKITTI frame under `$SPARSEOCC_REALDATA/semantickitti` (default
//! `<repo root>/../shared/realdata`, an external folder the repository does not ship) that has
//! `voxels/NNNNNN.bin`, writes to OUT_DIR (default `/tmp/viz_check`):
//! - `<seq>_<frame>_voxels.png`: the input occupancy `.bin`, coloured by height;
//! - `<seq>_<frame>_overlay.png`: the same voxels projected on `image_2` with `P2 · Tr`;
//! - if the frame's `velodyne` scan and point `labels` exist, the scan voxelised with its
//!   semantic labels: `<seq>_<frame>_semantic_voxels.png` and `<seq>_<frame>_semantic_overlay.png`;
//! - `<seq>_<frame>_panels.png`: image | voxels seen from the camera | semantic overlay.
//!
//! and for every Occ3D `labels.npz` under `occ3d/*/`: `occ3d_<token>_voxels.png`.

use std::error::Error;
use std::path::PathBuf;

use occ_data::formats::{occ3d, semantic_kitti as sk};
use occ_data::image::{read_png, write_png};
use occ_data::labels::LearningMap;
use occ_geometry::VoxelGrid;
use occ_viz::{
    overlay_on_image, render_voxels, render_voxels_from_view, side_by_side, OverlayOptions,
    Palette, RenderOptions,
};

fn main() -> Result<(), Box<dyn Error>> {
    // The same lookup as the tests (`occ_testdata`), without the skip: here a missing folder is an error.
    let (root, _) = occ_testdata::Folder::Realdata.path();
    if !root.is_dir() {
        return Err(format!(
            "real data folder {} is missing (set SPARSEOCC_REALDATA)",
            root.display()
        )
        .into());
    }
    let out_dir = std::env::args()
        .nth(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/tmp/viz_check"));
    std::fs::create_dir_all(&out_dir)?;
    let mut written = Vec::new();

    let kitti = root.join("semantickitti");
    let grid = VoxelGrid::semantic_kitti();
    for seq in sk::list_sequences(&kitti)? {
        let paths = sk::KittiPaths::new(&kitti);
        let calib = sk::read_calib(&paths.calib(&seq))?;
        for frame in sk::list_frames(&kitti, &seq)? {
            let occ = sk::read_packed_bits(&paths.voxels(&seq, &frame, "bin"), grid.num_voxels())?;
            let n_occ = occ.iter().filter(|&&v| v != 0).count();
            let mut ropts = RenderOptions::new(Palette::SemanticKitti);
            ropts.color_by_height = true;
            ropts.title = Some(format!(
                "seq {seq} frame {frame}: input voxels ({n_occ} occupied)"
            ));
            let render = render_voxels(&occ, &grid, &ropts)?;
            let p = out_dir.join(format!("{seq}_{frame}_voxels.png"));
            write_png(&p, &render)?;
            written.push(p);

            let img_path = paths.image_2(&seq, &frame);
            if !img_path.is_file() {
                continue;
            }
            let img = read_png(&img_path)?;
            let view = calib.camera_view(img.width, img.height);
            let m = view.img_from_lidar();
            let mut oopts = OverlayOptions::from_render(&ropts);
            oopts.alpha = 0.55;
            let overlay = overlay_on_image(&img, &occ, &grid, &m, &oopts)?;
            let p = out_dir.join(format!("{seq}_{frame}_overlay.png"));
            write_png(&p, &overlay)?;
            written.push(p);

            let mut cam_opts = ropts.clone();
            cam_opts.title = None;
            let from_cam = render_voxels_from_view(&occ, &grid, &view, &cam_opts)?;
            let mut panels = vec![("image_2", img.clone()), ("voxels from camera", from_cam)];

            let (scan, labels) = (
                paths.velodyne(&seq, &frame),
                paths.point_labels(&seq, &frame),
            );
            if scan.is_file() && labels.is_file() {
                let (pts, pl) = sk::read_labelled_scan(&scan, &labels)?;
                let sem = sk::voxelize_scan(&pts, &pl, &grid, &LearningMap::semantic_kitti());
                let mut sopts = RenderOptions::new(Palette::SemanticKitti);
                sopts.title = Some(format!("seq {seq} frame {frame}: labelled scan, voxelised"));
                let p = out_dir.join(format!("{seq}_{frame}_semantic_voxels.png"));
                write_png(&p, &render_voxels(&sem, &grid, &sopts)?)?;
                written.push(p);
                let mut so = OverlayOptions::new(Palette::SemanticKitti);
                so.alpha = 0.6;
                let sem_overlay = overlay_on_image(&img, &sem, &grid, &m, &so)?;
                let p = out_dir.join(format!("{seq}_{frame}_semantic_overlay.png"));
                write_png(&p, &sem_overlay)?;
                written.push(p);
                panels.push(("semantic overlay", sem_overlay));
            }
            let refs: Vec<(&str, &occ_viz::RgbImage)> =
                panels.iter().map(|(l, i)| (*l, i)).collect();
            let p = out_dir.join(format!("{seq}_{frame}_panels.png"));
            write_png(&p, &side_by_side(&refs)?)?;
            written.push(p);
        }
    }

    let occ3d_dir = root.join("occ3d");
    if occ3d_dir.is_dir() {
        let mut tokens: Vec<PathBuf> = std::fs::read_dir(&occ3d_dir)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.join("labels.npz").is_file())
            .collect();
        tokens.sort();
        for dir in tokens {
            let l = occ3d::read_labels_npz(&dir.join("labels.npz"))?;
            let grid = VoxelGrid {
                dims: l.dims,
                ..VoxelGrid::occ3d_nuscenes()
            };
            let token = dir
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or("unknown");
            let mut opts = RenderOptions::new(Palette::Occ3d);
            opts.title = Some(format!("Occ3D {token}"));
            let p = out_dir.join(format!("occ3d_{token}_voxels.png"));
            write_png(&p, &render_voxels(&l.semantics, &grid, &opts)?)?;
            written.push(p);
            // Camera-visible part only (mask_camera = 0 -> ignore), as the Occ3D metric sees it.
            let masked: Vec<u8> = l
                .semantics
                .iter()
                .zip(&l.mask_camera)
                .map(|(&s, &m)| if m == 0 { 255 } else { s })
                .collect();
            opts.title = Some(format!("Occ3D {token}, mask_camera"));
            let p = out_dir.join(format!("occ3d_{token}_voxels_camera_mask.png"));
            write_png(&p, &render_voxels(&masked, &grid, &opts)?)?;
            written.push(p);
        }
    }
    for p in &written {
        println!("{}", p.display());
    }
    Ok(())
}
