//! Renderer, overlay, panels and PLY checks against occ_geometry's projection and brute force.

#[path = "../examples/common/scene.rs"]
mod scene;

use occ_geometry::{mat4_identity, transform_point, CameraView, Mat4, PinholeCamera, VoxelGrid};
use occ_viz::{
    overlay_on_image, panel_grid, render_camera, render_voxels, render_voxels_from_view,
    side_by_side, write_ply, OverlayOptions, Palette, PlyFormat, PlyOptions, RenderOptions,
    RgbImage, VizError, LABEL_STRIP_H, PANEL_GAP,
};

fn px(img: &RgbImage, x: usize, y: usize) -> [u8; 3] {
    let i = (y * img.width + x) * 3;
    [img.data[i], img.data[i + 1], img.data[i + 2]]
}

fn plain_opts(palette: Palette) -> RenderOptions {
    let mut o = RenderOptions::new(palette);
    o.width = 320;
    o.height = 200;
    o.legend = false;
    o.title = None;
    o
}

fn small_grid() -> VoxelGrid {
    VoxelGrid {
        origin_m: [0.0, -4.0, -1.0],
        voxel_size_m: 0.5,
        dims: [16, 16, 6],
    }
}

fn set(labels: &mut [u8], g: &VoxelGrid, ijk: [usize; 3], c: u8) {
    labels[(ijk[0] * g.dims[1] + ijk[1]) * g.dims[2] + ijk[2]] = c;
}

/// Shades a class colour can take (one per face direction), as produced by the renderer.
fn is_shade_of(px: [u8; 3], base: [u8; 3]) -> bool {
    // px = round(base * f) for some f in (0, 1]; check with a common f within rounding.
    let (mut lo, mut hi) = (0.0f32, 2.0f32);
    for k in 0..3 {
        if base[k] == 0 {
            if px[k] != 0 {
                return false;
            }
            continue;
        }
        lo = lo.max((px[k] as f32 - 0.5) / base[k] as f32);
        hi = hi.min((px[k] as f32 + 0.5) / base[k] as f32);
    }
    lo <= hi + 1e-4
}

#[test]
fn render_camera_projection_equals_occ_geometry() {
    let grid = VoxelGrid::semantic_kitti();
    let labels = vec![0u8; grid.num_voxels()];
    let opts = RenderOptions::new(Palette::SemanticKitti);
    let cam = render_camera(&labels, &grid, &opts).unwrap();
    let view = cam.camera_view();
    let m = view.img_from_lidar();
    for ijk in [
        [0, 0, 0],
        [255, 255, 31],
        [128, 128, 10],
        [17, 200, 3],
        [250, 3, 30],
    ] {
        let c = grid.voxel_center_m(ijk);
        let ours = cam.project(c).unwrap();
        let geo = view.project_point(c).unwrap();
        let q = transform_point(&m, c);
        for a in 0..3 {
            assert!(
                (ours[a] - geo[a]).abs() < 1e-9,
                "{ijk:?}: {ours:?} vs {geo:?}"
            );
        }
        assert!((ours[0] - q[0] / q[2]).abs() < 1e-9 && (ours[2] - q[2]).abs() < 1e-9);
        // Every voxel of the grid is in view (the camera is fitted to the grid).
        assert!(view.in_view(geo), "{ijk:?} -> {geo:?} not in view");
    }
    // The camera is behind (x < 0) and above (z > top) the grid and looks forward and down.
    let lidar_from_cam = occ_geometry::mat4_inverse(&cam.cam_from_lidar).unwrap();
    let eye = [
        lidar_from_cam[0][3],
        lidar_from_cam[1][3],
        lidar_from_cam[2][3],
    ];
    assert!(
        eye[0] < 0.0 && eye[2] > 4.4 && eye[1].abs() < 1e-9,
        "{eye:?}"
    );
    let fwd = [
        lidar_from_cam[0][2],
        lidar_from_cam[1][2],
        lidar_from_cam[2][2],
    ];
    assert!(fwd[0] > 0.3 && fwd[2] < -0.3, "{fwd:?}");
    // A point farther ahead on the ground projects higher in the image (smaller v).
    let near = view.project_point([5.0, 0.0, -1.7]).unwrap();
    let far = view.project_point([45.0, 0.0, -1.7]).unwrap();
    assert!(far[1] < near[1] && far[2] > near[2]);
    // A point on the left (y > 0) projects left of the centre line (smaller u).
    let left = view.project_point([20.0, 10.0, -1.7]).unwrap();
    let right = view.project_point([20.0, -10.0, -1.7]).unwrap();
    assert!(left[0] < right[0]);
}

#[test]
fn single_voxel_lights_exactly_its_projected_silhouette() {
    let grid = VoxelGrid::semantic_kitti();
    let opts = plain_opts(Palette::SemanticKitti);
    for ijk in [[40usize, 100usize, 12usize], [200, 30, 5], [128, 128, 0]] {
        let mut labels = vec![0u8; grid.num_voxels()];
        set(&mut labels, &grid, ijk, 1);
        let img = render_voxels(&labels, &grid, &opts).unwrap();
        let view = render_camera(&labels, &grid, &opts).unwrap().camera_view();
        let centre = view.project_point(grid.voxel_center_m(ijk)).unwrap();
        // Silhouette = convex hull of the 8 projected corners; compare by bounding boxes.
        let s = grid.voxel_size_m;
        let c = grid.voxel_center_m(ijk);
        let (mut u0, mut u1, mut v0, mut v1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for q in 0..8 {
            let p = [
                c[0] + if q & 1 == 0 { -0.5 } else { 0.5 } * s,
                c[1] + if q & 2 == 0 { -0.5 } else { 0.5 } * s,
                c[2] + if q & 4 == 0 { -0.5 } else { 0.5 } * s,
            ];
            let uv = view.project_point(p).unwrap();
            u0 = u0.min(uv[0]);
            u1 = u1.max(uv[0]);
            v0 = v0.min(uv[1]);
            v1 = v1.max(uv[1]);
        }
        let bg = opts.background;
        let mut lit = Vec::new();
        for y in 0..img.height {
            for x in 0..img.width {
                let p = px(&img, x, y);
                if p != bg {
                    assert!(is_shade_of(p, [100, 150, 245]), "pixel {x},{y} = {p:?}");
                    lit.push((x as f64, y as f64));
                }
            }
        }
        assert!(!lit.is_empty(), "voxel {ijk:?} not drawn");
        for &(x, y) in &lit {
            assert!(
                x >= u0 - 1e-3 && x <= u1 + 1e-3 && y >= v0 - 1e-3 && y <= v1 + 1e-3,
                "lit pixel ({x},{y}) outside the projected box u[{u0},{u1}] v[{v0},{v1}]"
            );
        }
        // The lit pixels reach the box on every side (to within one pixel) and include the
        // pixel of the projected centre.
        let lx0 = lit.iter().map(|p| p.0).fold(f64::MAX, f64::min);
        let lx1 = lit.iter().map(|p| p.0).fold(f64::MIN, f64::max);
        let ly0 = lit.iter().map(|p| p.1).fold(f64::MAX, f64::min);
        let ly1 = lit.iter().map(|p| p.1).fold(f64::MIN, f64::max);
        assert!(lx0 - u0 < 1.0 && u1 - lx1 < 1.0 && ly0 - v0 < 1.0 && v1 - ly1 < 1.0);
        let (cu, cv) = (centre[0].round() as usize, centre[1].round() as usize);
        assert_ne!(px(&img, cu, cv), bg, "projected centre {centre:?} not lit");
    }
}

#[test]
fn empty_and_ignored_voxels_render_background_only() {
    for (palette, grid) in [
        (Palette::SemanticKitti, VoxelGrid::semantic_kitti()),
        (Palette::Occ3d, VoxelGrid::occ3d_nuscenes()),
    ] {
        let opts = plain_opts(palette);
        let n = grid.num_voxels();
        let empty = palette.default_empty_class();
        // All empty; all ignore; a mix of both.
        for labels in [
            vec![empty; n],
            vec![255u8; n],
            (0..n)
                .map(|i| if i % 3 == 0 { 255 } else { empty })
                .collect::<Vec<u8>>(),
        ] {
            let img = render_voxels(&labels, &grid, &opts).unwrap();
            assert_eq!((img.width, img.height), (opts.width, opts.height));
            assert!(
                img.data.chunks(3).all(|p| p == opts.background),
                "{palette:?}"
            );
        }
    }
    // A custom empty class (e.g. 5) and ignore class (e.g. 7) are not drawn either, while the
    // palette's usual empty class then is.
    let grid = small_grid();
    let mut opts = plain_opts(Palette::SemanticKitti);
    opts.empty_class = 5;
    opts.ignore_class = 7;
    let labels: Vec<u8> = (0..grid.num_voxels())
        .map(|i| if i % 2 == 0 { 5 } else { 7 })
        .collect();
    let img = render_voxels(&labels, &grid, &opts).unwrap();
    assert!(img.data.chunks(3).all(|p| p == opts.background));
    let zeros = vec![0u8; grid.num_voxels()];
    let img = render_voxels(&zeros, &grid, &opts).unwrap();
    assert!(img.data.chunks(3).any(|p| p != opts.background));
}

/// LiDAR (x fwd, y left, z up) -> camera (x right, y down, z fwd), both at the origin.
const FORWARD: Mat4 = [
    [0.0, -1.0, 0.0, 0.0],
    [0.0, 0.0, -1.0, 0.0],
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// A `width` x `height` camera of focal length 100 px with its principal point at (64, 48).
fn camera_f100(width: usize, height: usize) -> PinholeCamera {
    PinholeCamera {
        fx: 100.0,
        fy: 100.0,
        cx: 64.0,
        cy: 48.0,
        width,
        height,
    }
}

#[test]
fn zbuffer_near_voxel_occludes_far_one_in_both_index_orders() {
    // A camera at the origin looking along +x (forward) and one looking along -x (backward),
    // so that the near voxel comes first in C order for one and last for the other.
    let grid = VoxelGrid {
        origin_m: [-10.0, -2.5, -2.5],
        voxel_size_m: 1.0,
        dims: [20, 5, 5],
    };
    let cam = camera_f100(129, 97);
    let back: Mat4 = [
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0, 0.0],
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let opts = plain_opts(Palette::SemanticKitti);
    for (m, near_i, far_i) in [(FORWARD, 13usize, 17usize), (back, 6, 2)] {
        let view = CameraView::new(cam, m);
        // Near voxel: building (yellow), far voxel: car (blue); both centred on the optical axis.
        for (near_c, far_c) in [(13u8, 1u8), (1, 13)] {
            let mut labels = vec![0u8; grid.num_voxels()];
            set(&mut labels, &grid, [near_i, 2, 2], near_c);
            set(&mut labels, &grid, [far_i, 2, 2], far_c);
            let img = render_voxels_from_view(&labels, &grid, &view, &opts).unwrap();
            let centre = px(&img, 64, 48);
            let near_rgb = Palette::SemanticKitti.color(near_c).unwrap();
            assert!(
                is_shade_of(centre, near_rgb),
                "{centre:?} is not a shade of {near_rgb:?}"
            );
            // Alone, the far voxel is visible at the same pixel.
            let mut alone = vec![0u8; grid.num_voxels()];
            set(&mut alone, &grid, [far_i, 2, 2], far_c);
            let img = render_voxels_from_view(&alone, &grid, &view, &opts).unwrap();
            let far_rgb = Palette::SemanticKitti.color(far_c).unwrap();
            assert!(is_shade_of(px(&img, 64, 48), far_rgb));
        }
    }
}

/// A small grid and a forward-looking camera for overlay tests: voxel (i, 5, 5) is centred on
/// the optical axis.
fn overlay_setup() -> (VoxelGrid, CameraView) {
    let grid = VoxelGrid {
        origin_m: [2.0, -2.75, -2.75],
        voxel_size_m: 0.5,
        dims: [20, 11, 11],
    };
    (grid, CameraView::new(camera_f100(128, 96), FORWARD))
}

fn grey_image(w: usize, h: usize, v: u8) -> RgbImage {
    RgbImage {
        width: w,
        height: h,
        data: vec![v; w * h * 3],
    }
}

/// [`overlay_setup`]'s grid and projection, a grey 128x96 image (value 100), and labels with a near
/// building voxel (13, centre x = 3.75 m) and a far car voxel (1, centre x = 9.75 m) on the optical
/// axis.
fn near_and_far_voxel() -> (VoxelGrid, Mat4, RgbImage, Vec<u8>) {
    let (grid, view) = overlay_setup();
    let mut labels = vec![0u8; grid.num_voxels()];
    set(&mut labels, &grid, [3, 5, 5], 13);
    set(&mut labels, &grid, [15, 5, 5], 1);
    (
        grid,
        view.img_from_lidar(),
        grey_image(128, 96, 100),
        labels,
    )
}

#[test]
fn overlay_paints_far_first_and_blends() {
    let (grid, m, img, labels) = near_and_far_voxel();
    let p = Palette::SemanticKitti;
    let (nrgb, frgb) = (p.color(13).unwrap(), p.color(1).unwrap());

    let mut opts = OverlayOptions::new(p);
    opts.alpha = 1.0;
    let out = overlay_on_image(&img, &labels, &grid, &m, &opts).unwrap();
    assert_eq!(px(&out, 64, 48), nrgb, "near voxel must be painted last");

    // alpha 0.5: centre = blend(blend(grey, far), near); a pixel covered only by the near voxel
    // (its footprint is ~13 px wide, the far one's ~5 px) = blend(grey, near).
    opts.alpha = 0.5;
    let out = overlay_on_image(&img, &labels, &grid, &m, &opts).unwrap();
    let b = |d: [u8; 3], s: [u8; 3]| -> [u8; 3] {
        [0, 1, 2].map(|k| (d[k] as f32 * 0.5 + s[k] as f32 * 0.5).round() as u8)
    };
    assert_eq!(px(&out, 64, 48), b(b([100; 3], frgb), nrgb));
    assert_eq!(px(&out, 64 + 6, 48), b([100; 3], nrgb));
    assert_eq!(px(&out, 64 + 20, 48), [100; 3]);
    assert_eq!(px(&out, 2, 2), [100; 3]);

    // Footprint of the near voxel = projected cube silhouette: corners at depth 3.5 m span
    // u = 64 +- 100*0.25/3.5 = 64 +- 7.14, so columns 57..=71 are covered on the centre row.
    let covered: Vec<usize> = (0..128).filter(|&x| px(&out, x, 48) != [100; 3]).collect();
    assert_eq!(covered.first(), Some(&57));
    assert_eq!(covered.last(), Some(&71));
}

#[test]
fn overlay_nearest_only_blends_each_pixel_once_with_the_nearest_voxel() {
    let (grid, m, img, mut labels) = near_and_far_voxel();
    let p = Palette::SemanticKitti;
    let (nrgb, frgb) = (p.color(13).unwrap(), p.color(1).unwrap());
    let mut opts = OverlayOptions::new(p);
    opts.outline = false;
    opts.nearest_only = true;
    let b = |d: [u8; 3], s: [u8; 3]| -> [u8; 3] {
        [0, 1, 2].map(|k| (d[k] as f32 * 0.5 + s[k] as f32 * 0.5).round() as u8)
    };
    let out = overlay_on_image(&img, &labels, &grid, &m, &opts).unwrap();
    // The centre is covered by both: only the near one, blended once over the image.
    assert_eq!(px(&out, 64, 48), b([100; 3], nrgb));
    assert_eq!(px(&out, 64 + 6, 48), b([100; 3], nrgb));
    assert_eq!(px(&out, 64 + 20, 48), [100; 3]);
    // Without the near voxel the far one shows, once.
    set(&mut labels, &grid, [3, 5, 5], 0);
    let out = overlay_on_image(&img, &labels, &grid, &m, &opts).unwrap();
    assert_eq!(px(&out, 64, 48), b([100; 3], frgb));
}

#[test]
fn panel_grid_lays_out_rows_of_equal_cells() {
    let panels: Vec<RgbImage> = (0..5).map(|i| grey_image(40, 20, 50 * i as u8)).collect();
    let refs: Vec<(&str, &RgbImage)> = panels.iter().map(|p| ("cam", p)).collect();
    let out = panel_grid(&refs, 3).unwrap();
    assert_eq!(out.width, PANEL_GAP + 3 * (40 + PANEL_GAP));
    assert_eq!(out.height, PANEL_GAP + 2 * (LABEL_STRIP_H + 20 + PANEL_GAP));
    for (i, _) in panels.iter().enumerate() {
        let (r, c) = (i / 3, i % 3);
        let x = PANEL_GAP + c * (40 + PANEL_GAP);
        let y = PANEL_GAP + r * (LABEL_STRIP_H + 20 + PANEL_GAP) + LABEL_STRIP_H;
        assert_eq!(px(&out, x, y), [50 * i as u8; 3], "panel {i}");
        assert_eq!(px(&out, x + 39, y + 19), [50 * i as u8; 3], "panel {i}");
    }
    // A narrower panel is scaled to the cell width, aspect kept, centred vertically.
    let small = grey_image(20, 5, 7);
    let big = grey_image(40, 20, 9);
    let out = panel_grid(&[("a", &big), ("b", &small)], 2).unwrap();
    let x = PANEL_GAP + 40 + PANEL_GAP;
    let y = PANEL_GAP + LABEL_STRIP_H;
    assert_eq!(px(&out, x + 20, y + 10), [7; 3]);
    assert_ne!(px(&out, x + 20, y + 2), [7; 3]);
    assert!(panel_grid(&refs, 0).is_err());
    assert!(panel_grid(&[], 2).is_err());
}

#[test]
fn overlay_skips_empty_ignore_and_voxels_behind_camera() {
    let (grid, view) = overlay_setup();
    let img = grey_image(128, 96, 50);
    let mut labels = vec![0u8; grid.num_voxels()];
    set(&mut labels, &grid, [4, 5, 5], 255);
    let opts = OverlayOptions::new(Palette::SemanticKitti);
    let out = overlay_on_image(&img, &labels, &grid, &view.img_from_lidar(), &opts).unwrap();
    assert_eq!(out, img);
    // Camera looking backwards: the whole grid is behind it.
    let mut back = view;
    back.cam_from_lidar[2] = [-1.0, 0.0, 0.0, 0.0];
    back.cam_from_lidar[0] = [0.0, 1.0, 0.0, 0.0];
    set(&mut labels, &grid, [4, 5, 5], 1);
    let out = overlay_on_image(&img, &labels, &grid, &back.img_from_lidar(), &opts).unwrap();
    assert_eq!(out, img);
    let out = overlay_on_image(&img, &labels, &grid, &view.img_from_lidar(), &opts).unwrap();
    assert_ne!(out, img);
}

#[test]
fn render_from_view_and_overlay_agree_on_a_scene() {
    // Two independent paths (face rasterisation with z-buffer vs. projected-cube silhouettes):
    // the pixels covered by the scene must be the same up to edge pixels.
    let grid = VoxelGrid::semantic_kitti();
    let labels = scene::driving_scene(grid.dims, 3);
    // KITTI-like camera: 1.65 m above ground at the LiDAR position, looking forward.
    let cam = PinholeCamera {
        fx: 360.0,
        fy: 360.0,
        cx: 310.0,
        cy: 90.0,
        width: 620,
        height: 188,
    };
    let cam_from_lidar: Mat4 = [
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0, -0.08],
        [1.0, 0.0, 0.0, -0.27],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let view = CameraView::new(cam, cam_from_lidar);
    let ropts = plain_opts(Palette::SemanticKitti);
    let render = render_voxels_from_view(&labels, &grid, &view, &ropts).unwrap();
    let mut oopts = OverlayOptions::new(Palette::SemanticKitti);
    oopts.alpha = 1.0;
    oopts.near_m = 1e-3;
    let blank = grey_image(620, 188, 0);
    let overlay = overlay_on_image(&blank, &labels, &grid, &view.img_from_lidar(), &oopts).unwrap();
    let (mut inter, mut union, mut same_class) = (0usize, 0usize, 0usize);
    for y in 0..188 {
        for x in 0..620 {
            let a = px(&render, x, y) != ropts.background;
            let b = px(&overlay, x, y) != [0, 0, 0];
            inter += (a && b) as usize;
            union += (a || b) as usize;
            if a && b && is_shade_of(px(&render, x, y), px(&overlay, x, y)) {
                same_class += 1;
            }
        }
    }
    let iou = inter as f64 / union as f64;
    assert!(
        union > 20_000,
        "scene should fill much of the view: {union}"
    );
    assert!(iou > 0.98, "coverage IoU {iou}");
    // The visible class agrees (overlay with alpha 1 paints the nearest voxel last).
    assert!(
        same_class as f64 > 0.95 * inter as f64,
        "{same_class} of {inter}"
    );
}

#[test]
fn height_mode_colours_by_layer() {
    let grid = small_grid();
    let mut labels = vec![0u8; grid.num_voxels()];
    // A single column: with top faces visible, the top colour must be the top layer's.
    for k in 0..6 {
        set(&mut labels, &grid, [8, 8, k], 1);
    }
    let mut opts = plain_opts(Palette::SemanticKitti);
    opts.color_by_height = true;
    let img = render_voxels(&labels, &grid, &opts).unwrap();
    let view = render_camera(&labels, &grid, &opts).unwrap().camera_view();
    let mut top = grid.voxel_center_m([8, 8, 5]);
    top[2] += 0.25;
    let uv = view.project_point(top).unwrap();
    let p = px(&img, uv[0].round() as usize, uv[1].round() as usize);
    assert!(is_shade_of(p, occ_viz::height_color(5.5 / 6.0)), "{p:?}");
    let mut bottom = grid.voxel_center_m([8, 8, 0]);
    bottom[0] -= 0.25;
    let uv = view.project_point(bottom).unwrap();
    let p = px(&img, uv[0].round() as usize, uv[1].round() as usize);
    assert!(is_shade_of(p, occ_viz::height_color(0.5 / 6.0)), "{p:?}");
}

#[test]
fn legend_and_title_change_layout_not_scene_content() {
    let grid = VoxelGrid::semantic_kitti();
    let labels = scene::driving_scene(grid.dims, 1);
    let mut opts = RenderOptions::new(Palette::SemanticKitti);
    opts.title = Some("Prediction - seq 08 frame 000000".into());
    let a = render_voxels(&labels, &grid, &opts).unwrap();
    let b = render_voxels(&labels, &grid, &opts).unwrap();
    assert_eq!(a, b, "rendering must be deterministic");
    let cam = render_camera(&labels, &grid, &opts).unwrap();
    assert!(cam.viewport.y > 0 && cam.viewport.x + cam.viewport.width < opts.width);
    // The legend column holds each present class's exact colour (as a swatch).
    for c in [1u8, 9, 13, 15] {
        let rgb = Palette::SemanticKitti.color(c).unwrap();
        let found =
            (cam.viewport.width..opts.width).any(|x| (0..opts.height).any(|y| px(&a, x, y) == rgb));
        assert!(found, "no swatch for class {c}");
    }
    // The framing does not depend on which classes are present (pred | GT panels line up).
    let mut few = vec![0u8; grid.num_voxels()];
    few[12345] = 1;
    assert_eq!(render_camera(&few, &grid, &opts).unwrap(), cam);
    // Too large an image is an error, not an allocation failure.
    opts.width = 1 << 20;
    opts.height = 1 << 20;
    assert!(matches!(
        render_voxels(&labels, &grid, &opts),
        Err(VizError::InvalidOptions(_))
    ));
    opts.height = 720;
    // Too small an image is an error, not a panic.
    opts.width = 100;
    assert!(matches!(
        render_voxels(&labels, &grid, &opts),
        Err(VizError::InvalidOptions(_))
    ));
}

#[test]
fn bad_inputs_are_errors() {
    let grid = small_grid();
    let opts = plain_opts(Palette::SemanticKitti);
    let e = render_voxels(&[0u8; 10], &grid, &opts).unwrap_err();
    assert!(
        matches!(
            e,
            VizError::LabelSize {
                expected: 1536,
                got: 10,
                ..
            }
        ),
        "{e}"
    );
    let mut bad = grid;
    bad.voxel_size_m = 0.0;
    assert!(matches!(
        render_voxels(&vec![0u8; grid.num_voxels()], &bad, &opts),
        Err(VizError::InvalidGrid(_))
    ));
    let mut bad = grid;
    bad.dims = [0, 4, 4];
    assert!(render_voxels(&[], &bad, &opts).is_err());
    let img = RgbImage {
        width: 10,
        height: 10,
        data: vec![0; 7],
    };
    let o = OverlayOptions::new(Palette::SemanticKitti);
    let labels = vec![0u8; grid.num_voxels()];
    assert!(matches!(
        overlay_on_image(&img, &labels, &grid, &mat4_identity(), &o),
        Err(VizError::InvalidImage(_))
    ));
    let mut nan = mat4_identity();
    nan[0][0] = f64::NAN;
    let img = grey_image(10, 10, 0);
    assert!(overlay_on_image(&img, &labels, &grid, &nan, &o).is_err());
    assert!(side_by_side(&[]).is_err());
}

#[test]
fn side_by_side_scales_to_one_height_and_labels() {
    let a = grey_image(100, 50, 200);
    let b = grey_image(30, 100, 10);
    let out = side_by_side(&[("image", &a), ("prediction", &b)]).unwrap();
    // a scaled to 200x100, b stays 30x100.
    assert_eq!(out.width, PANEL_GAP + 200 + PANEL_GAP + 30 + PANEL_GAP);
    assert_eq!(out.height, PANEL_GAP + LABEL_STRIP_H + 100 + PANEL_GAP);
    let top = PANEL_GAP + LABEL_STRIP_H;
    assert_eq!(px(&out, PANEL_GAP, top), [200; 3]);
    assert_eq!(px(&out, PANEL_GAP + 199, top + 99), [200; 3]);
    assert_eq!(px(&out, PANEL_GAP + 200 + PANEL_GAP, top), [10; 3]);
    // Label text is drawn in the strip above each panel (light pixels on the dark strip).
    let strip_has_text = |x0: usize, x1: usize| {
        (x0..x1).any(|x| (PANEL_GAP..top).any(|y| px(&out, x, y) == [240, 240, 240]))
    };
    assert!(strip_has_text(PANEL_GAP, PANEL_GAP + 200));
}

fn parse_ply_header(bytes: &[u8]) -> (Vec<String>, usize) {
    let end = b"end_header\n";
    let pos = bytes
        .windows(end.len())
        .position(|w| w == end)
        .expect("no end_header")
        + end.len();
    let text = std::str::from_utf8(&bytes[..pos]).unwrap();
    (text.lines().map(String::from).collect(), pos)
}

#[test]
fn ply_header_and_vertices_match_drawn_voxels() {
    let dir = std::env::temp_dir().join(format!("occ_viz_ply_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let grid = small_grid();
    let mut labels = vec![0u8; grid.num_voxels()];
    let drawn = [([0, 0, 0], 9u8), ([3, 7, 2], 1), ([15, 15, 5], 13)];
    for (ijk, c) in drawn {
        set(&mut labels, &grid, ijk, c);
    }
    set(&mut labels, &grid, [5, 5, 5], 255); // ignored: not exported

    let path = dir.join("scene.ply");
    let n = write_ply(
        &path,
        &labels,
        &grid,
        &PlyOptions::new(Palette::SemanticKitti),
    )
    .unwrap();
    assert_eq!(n, 3);
    let bytes = std::fs::read(&path).unwrap();
    let (header, body) = parse_ply_header(&bytes);
    assert_eq!(header[0], "ply");
    assert_eq!(header[1], "format binary_little_endian 1.0");
    assert!(header.contains(&"element vertex 3".to_string()));
    let props: Vec<&String> = header
        .iter()
        .filter(|l| l.starts_with("property"))
        .collect();
    assert_eq!(props.len(), 7);
    assert_eq!(bytes.len() - body, 3 * 16);
    // Records in C order: first is voxel (0,0,0), road.
    for (r, (ijk, c)) in drawn.iter().enumerate() {
        let rec = &bytes[body + 16 * r..body + 16 * (r + 1)];
        let f = |o: usize| f32::from_le_bytes(rec[o..o + 4].try_into().unwrap()) as f64;
        let centre = grid.voxel_center_m(*ijk);
        for (a, want) in centre.iter().enumerate() {
            assert!((f(4 * a) - want).abs() < 1e-5);
        }
        assert_eq!(&rec[12..15], &Palette::SemanticKitti.color(*c).unwrap());
        assert_eq!(rec[15], *c);
    }

    let mut opts = PlyOptions::new(Palette::SemanticKitti);
    opts.format = PlyFormat::Ascii;
    let apath = dir.join("scene_ascii.ply");
    assert_eq!(write_ply(&apath, &labels, &grid, &opts).unwrap(), 3);
    let text = std::fs::read_to_string(&apath).unwrap();
    let (header, _) = parse_ply_header(text.as_bytes());
    assert_eq!(header[1], "format ascii 1.0");
    let body: Vec<&str> = text.split("end_header\n").nth(1).unwrap().lines().collect();
    assert_eq!(body.len(), 3);
    assert_eq!(body[1].split(' ').count(), 7);
    assert!(body[1].ends_with(" 100 150 245 1"), "{}", body[1]);

    // No temporary files are left; a missing folder is a typed error naming the path.
    let names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names.len(), 2, "{names:?}");
    let missing = dir.join("no_such_dir").join("x.ply");
    match write_ply(&missing, &labels, &grid, &opts) {
        Err(VizError::Io { path, .. }) => assert_eq!(path, missing),
        other => panic!("expected Io error, got {other:?}"),
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn draw_text_marks_pixels_and_reports_width() {
    let mut img = grey_image(80, 20, 0);
    let w = occ_viz::draw_text(&mut img, 1, 1, "Car 1", 1, [255, 0, 0]).unwrap();
    assert_eq!(w, 5 * 6 - 1);
    let red: Vec<(usize, usize)> = (0..20)
        .flat_map(|y| (0..80).map(move |x| (x, y)))
        .filter(|&(x, y)| px(&img, x, y) == [255, 0, 0])
        .collect();
    assert!(!red.is_empty());
    assert!(red
        .iter()
        .all(|&(x, y)| (1..1 + w).contains(&x) && (1..1 + 9).contains(&y)));
}
