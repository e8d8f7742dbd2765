//! occ-viz on the real sample frames in `$SPARSEOCC_REALDATA` (an external folder found by
//! `occ_testdata`; without it the tests print a skip line): SemanticKITTI input voxels over `image_2` with `P2 · Tr`,
//! and the Occ3D sample grid.

use std::path::PathBuf;

use occ_data::formats::{occ3d, semantic_kitti as sk};
use occ_data::image::read_png;
use occ_geometry::VoxelGrid;
use occ_viz::{
    overlay_on_image, render_voxels, render_voxels_from_view, OverlayOptions, Palette,
    RenderOptions, RgbImage,
};

fn px(img: &RgbImage, x: usize, y: usize) -> [u8; 3] {
    let i = (y * img.width + x) * 3;
    [img.data[i], img.data[i + 1], img.data[i + 2]]
}

/// Fraction of pixels in the box that differ from `bg`.
fn covered(img: &RgbImage, bg: [u8; 3], x0: usize, x1: usize, y0: usize, y1: usize) -> f64 {
    let mut n = 0;
    for y in y0..y1 {
        for x in x0..x1 {
            n += (px(img, x, y) != bg) as usize;
        }
    }
    n as f64 / ((x1 - x0) * (y1 - y0)) as f64
}

#[test]
fn kitti_input_voxels_project_onto_road_not_sky_and_match_camera_render() {
    let Some(realdata) = occ_testdata::realdata() else {
        return;
    };
    let kitti = realdata.join("semantickitti");
    let grid = VoxelGrid::semantic_kitti();
    let mut checked = 0;
    for seq in sk::list_sequences(&kitti).unwrap() {
        let paths = sk::KittiPaths::new(&kitti);
        let calib = sk::read_calib(&paths.calib(&seq)).unwrap();
        for frame in sk::list_frames(&kitti, &seq).unwrap() {
            let img_path = paths.image_2(&seq, &frame);
            if !img_path.is_file() {
                continue;
            }
            let occ = sk::read_packed_bits(&paths.voxels(&seq, &frame, "bin"), grid.num_voxels())
                .unwrap();
            let img = read_png(&img_path).unwrap();
            let (w, h) = (img.width, img.height);
            let view = calib.camera_view(w, h);
            let black = RgbImage {
                width: w,
                height: h,
                data: vec![0; w * h * 3],
            };
            let mut o = OverlayOptions::new(Palette::SemanticKitti);
            o.alpha = 1.0;
            o.color_by_height = true;
            o.near_m = 1e-3;
            o.outline = false;
            let overlay =
                overlay_on_image(&black, &occ, &grid, &view.img_from_lidar(), &o).unwrap();
            let cx = view.camera.cx as usize;
            // The road in front of the car fills the bottom centre of the photo...
            let road = covered(&overlay, [0; 3], cx - 100, cx + 100, h - 40, h - 5);
            assert!(road > 0.9, "{seq}/{frame}: road box only {road:.2} covered");
            // ...and nothing in the 6.4 m high grid reaches the sky above the road's vanishing point.
            let sky = covered(&overlay, [0; 3], cx - 60, cx + 60, 0, 30);
            assert!(sky < 0.1, "{seq}/{frame}: sky box {sky:.2} covered");
            // Face rasterisation from the same camera covers the same pixels.
            let mut r = RenderOptions::new(Palette::SemanticKitti);
            r.color_by_height = true;
            let render = render_voxels_from_view(&occ, &grid, &view, &r).unwrap();
            let (mut inter, mut union) = (0usize, 0usize);
            for y in 0..h {
                for x in 0..w {
                    let a = px(&render, x, y) != r.background;
                    let b = px(&overlay, x, y) != [0; 3];
                    inter += (a && b) as usize;
                    union += (a || b) as usize;
                }
            }
            let iou = inter as f64 / union.max(1) as f64;
            eprintln!("{seq}/{frame}: road {road:.3} sky {sky:.3} render/overlay IoU {iou:.4}");
            assert!(iou > 0.97, "{seq}/{frame}: render vs overlay IoU {iou:.3}");
            checked += 1;
        }
    }
    assert!(
        checked >= 1,
        "no SemanticKITTI frame with voxels and image_2 found"
    );
}

#[test]
fn occ3d_sample_renders_its_classes() {
    let Some(realdata) = occ_testdata::realdata() else {
        return;
    };
    let dir = realdata.join("occ3d");
    let mut checked = 0;
    let mut entries: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()))
        .map(|e| e.unwrap().path().join("labels.npz"))
        .filter(|p| p.is_file())
        .collect();
    entries.sort();
    for npz in entries {
        let l = occ3d::read_labels_npz(&npz).unwrap();
        let grid = VoxelGrid {
            dims: l.dims,
            ..VoxelGrid::occ3d_nuscenes()
        };
        let opts = RenderOptions::new(Palette::Occ3d);
        let img = render_voxels(&l.semantics, &grid, &opts).unwrap();
        let cam = occ_viz::render_camera(&l.semantics, &grid, &opts).unwrap();
        let vp = cam.viewport;
        let drawn = covered(&img, opts.background, 0, vp.width, vp.y, vp.y + vp.height);
        assert!(
            drawn > 0.1,
            "{}: only {drawn:.3} of the view drawn",
            npz.display()
        );
        // Every class present (other than free) has its swatch in the legend.
        let mut present = [false; 256];
        for &c in &l.semantics {
            present[c as usize] = true;
        }
        for c in (0..17u8).filter(|&c| present[c as usize]) {
            let rgb = Palette::Occ3d.color(c).unwrap();
            let found =
                (vp.width..opts.width).any(|x| (0..opts.height).any(|y| px(&img, x, y) == rgb));
            assert!(found, "{}: no legend swatch for class {c}", npz.display());
        }
        checked += 1;
    }
    assert!(
        checked >= 1,
        "no occ3d/*/labels.npz under {}",
        dir.display()
    );
}
