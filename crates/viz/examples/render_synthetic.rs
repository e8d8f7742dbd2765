//! Render the procedural driving scene every way occ-viz can, for a visual check.
//!
//! `cargo run --release -p occ-viz --example render_synthetic [-- OUT_DIR]` writes to OUT_DIR
//! (default `/tmp/viz_check`): `synthetic_voxels.png` (behind-above view with legend),
//! `synthetic_height.png` (height colours), `synthetic_camera.png` (seen from a KITTI-like
//! camera), `synthetic_overlay.png` (voxels projected on that camera render, which must line up
//! exactly), `synthetic_panels.png` (the three side by side) and `synthetic.ply`.

#[path = "common/scene.rs"]
mod scene;

use std::path::PathBuf;

use occ_data::image::write_png;
use occ_geometry::{CameraView, PinholeCamera, VoxelGrid};
use occ_viz::{
    overlay_on_image, render_voxels, render_voxels_from_view, side_by_side, write_ply,
    OverlayOptions, Palette, PlyOptions, RenderOptions,
};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args()
        .nth(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/tmp/viz_check"));
    std::fs::create_dir_all(&out)?;
    let grid = VoxelGrid::semantic_kitti();
    let labels = scene::driving_scene(grid.dims, 11);

    let mut opts = RenderOptions::new(Palette::SemanticKitti);
    opts.title = Some("synthetic scene (SemanticKITTI classes)".into());
    let voxels = render_voxels(&labels, &grid, &opts)?;
    write_png(&out.join("synthetic_voxels.png"), &voxels)?;
    let mut hopts = opts.clone();
    hopts.color_by_height = true;
    hopts.title = Some("synthetic scene, coloured by height".into());
    write_png(
        &out.join("synthetic_height.png"),
        &render_voxels(&labels, &grid, &hopts)?,
    )?;

    // A KITTI-like camera: K of sequence 00's P2, 1241x376, 1.65 m above the ground layer.
    let cam = PinholeCamera {
        fx: 718.856,
        fy: 718.856,
        cx: 607.1928,
        cy: 185.2157,
        width: 1241,
        height: 376,
    };
    let cam_from_lidar = [
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0, -0.08],
        [1.0, 0.0, 0.0, -0.27],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let view = CameraView::new(cam, cam_from_lidar);
    let camera = render_voxels_from_view(&labels, &grid, &view, &opts)?;
    write_png(&out.join("synthetic_camera.png"), &camera)?;
    let mut oopts = OverlayOptions::new(Palette::SemanticKitti);
    oopts.color_by_height = true;
    let overlay = overlay_on_image(&camera, &labels, &grid, &view.img_from_lidar(), &oopts)?;
    write_png(&out.join("synthetic_overlay.png"), &overlay)?;
    let panels = side_by_side(&[
        ("camera view", &camera),
        ("height overlay", &overlay),
        ("prediction", &voxels),
    ])?;
    write_png(&out.join("synthetic_panels.png"), &panels)?;
    let n = write_ply(
        &out.join("synthetic.ply"),
        &labels,
        &grid,
        &PlyOptions::new(Palette::SemanticKitti),
    )?;
    println!("wrote {} ({n} PLY vertices)", out.display());
    Ok(())
}
