//! SemanticKITTI readers, voxelisation and projection checked on the real files in
//! `$SPARSEOCC_REALDATA/semantickitti` (frames discovered by listing the folders; an external
//! folder: without it the tests print a skip line).

mod common;

use common::{iou, kitti_root};
use occ_data::formats::semantic_kitti::*;
use occ_data::image::{process_image, read_png, ImagePipelineConfig};
use occ_geometry::VoxelGrid;
use std::path::Path;

fn frames(root: &Path) -> Vec<FrameId> {
    let mut out = Vec::new();
    for seq in list_sequences(root).unwrap() {
        for frame in list_frames(root, &seq).unwrap() {
            out.push(FrameId {
                sequence: seq.clone(),
                frame,
            });
        }
    }
    assert!(
        !out.is_empty(),
        "no voxels/*.bin frames under {}",
        root.display()
    );
    out
}

#[test]
fn packed_voxel_files_sizes_and_bit_invariants() {
    let Some(root) = kitti_root() else { return };
    let p = KittiPaths::new(&root);
    for f in frames(&root) {
        let (s, fr) = (f.sequence.as_str(), f.frame.as_str());
        for ext in ["bin", "invalid", "occluded"] {
            let path = p.voxels(s, fr, ext);
            assert_eq!(
                std::fs::metadata(&path).unwrap().len(),
                262_144,
                "{}",
                path.display()
            );
        }
        let bin = read_packed_bits(&p.voxels(s, fr, "bin"), NUM_VOXELS).unwrap();
        let invalid = read_packed_bits(&p.voxels(s, fr, "invalid"), NUM_VOXELS).unwrap();
        let occluded = read_packed_bits(&p.voxels(s, fr, "occluded"), NUM_VOXELS).unwrap();
        let n_bin = bin.iter().filter(|&&b| b == 1).count();
        let n_inv = invalid.iter().filter(|&&b| b == 1).count();
        let n_occ = occluded.iter().filter(|&&b| b == 1).count();
        println!("{s}/{fr}: occupied {n_bin}, invalid {n_inv}, occluded {n_occ}");
        assert!(bin.iter().chain(&invalid).chain(&occluded).all(|&b| b <= 1));
        // a single scan fills ~0.5% of the grid; invalid and occluded regions are large
        assert!((3_000..100_000).contains(&n_bin), "{n_bin}");
        assert!(n_inv > 100_000 && n_occ > n_inv, "{n_inv} {n_occ}");
        // voxelizer semantics: an occupied voxel is never invalid, and counts as occluded
        // (it occludes itself). A wrong bit order or byte order breaks both.
        assert!(bin.iter().zip(&invalid).all(|(&b, &i)| !(b == 1 && i == 1)));
        assert!(bin.iter().zip(&occluded).all(|(&b, &o)| b == 0 || o == 1));
        // the stored z = 0 layer only holds wrapped top voxels (see VoxelGrid::semantic_kitti)
        let g = VoxelGrid::semantic_kitti();
        let z0 = (0..NUM_VOXELS)
            .filter(|&n| bin[n] == 1 && g.ijk_of(n)[2] == 0)
            .count();
        assert!(z0 * 100 < n_bin, "{z0} occupied voxels in layer z=0");
        // the writer round-trips the real file byte for byte
        let tmp = occ_testdata::TempDir::new("occ-data-test", "packed");
        let out = tmp.path().join("x.bin");
        write_packed_bits(&out, &bin).unwrap();
        assert_eq!(
            std::fs::read(&out).unwrap(),
            std::fs::read(p.voxels(s, fr, "bin")).unwrap()
        );
    }
}

#[test]
fn calibration_poses_scans_and_labels_parse() {
    let Some(root) = kitti_root() else { return };
    let p = KittiPaths::new(&root);
    for seq in list_sequences(&root).unwrap() {
        let c = read_calib(&p.calib(&seq)).unwrap();
        // KITTI odometry: square pixels, principal point near the image centre
        assert!((c.p2[0][0] - c.p2[1][1]).abs() < 1e-6 && c.p2[0][0] > 600.0 && c.p2[0][0] < 800.0);
        assert!(
            c.p2[0][2] > 550.0 && c.p2[0][2] < 650.0 && c.p2[1][2] > 150.0 && c.p2[1][2] < 200.0
        );
        // Tr is a rotation (velodyne x forward -> camera z forward) plus a small translation
        let r = c.tr;
        for i in 0..3 {
            for j in 0..3 {
                let d: f64 = (0..3).map(|k| r[i][k] * r[j][k]).sum();
                assert!(
                    (d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-4,
                    "Tr not orthonormal"
                );
            }
        }
        assert!(r[2][0] > 0.99, "velodyne x must map to camera z: {r:?}");
        assert!(r[0][1] < -0.99, "velodyne y (left) must map to camera -x");
        // the baseline of camera 2 relative to cam0: about +6 cm in x
        let t = c.cam2_from_cam0();
        assert!(t[0][3] > 0.04 && t[0][3] < 0.08, "{}", t[0][3]);
        let poses = read_poses(&p.poses(&seq)).unwrap();
        let times = std::fs::read_to_string(p.sequence_dir(&seq).join("times.txt")).unwrap();
        assert_eq!(
            poses.len(),
            times.lines().filter(|l| !l.trim().is_empty()).count()
        );
        assert!(
            poses[0][0][0] > 0.999 && poses[0][0][3].abs() < 1e-6,
            "first pose is identity"
        );
        for fr in list_frames(&root, &seq).unwrap() {
            let (pts, labels) =
                read_labelled_scan(&p.velodyne(&seq, &fr), &p.point_labels(&seq, &fr)).unwrap();
            assert!(pts.len() > 50_000);
            let m = LearningMap::semantic_kitti();
            let classes = m.remap_point_labels(&labels);
            let n_road = classes.iter().filter(|&&c| c == 9).count();
            let n_known = classes.iter().filter(|&&c| c != 255 && c != 0).count();
            println!(
                "{seq}/{fr}: {} points, {n_road} road, {n_known} labelled",
                pts.len()
            );
            assert!(n_known * 2 > pts.len(), "most points carry a known class");
            // road points lie ~1.7 m below the sensor
            let mut zs: Vec<f32> = pts
                .iter()
                .zip(&classes)
                .filter(|(_, &c)| c == 9)
                .map(|(p, _)| p[2])
                .collect();
            zs.sort_by(f32::total_cmp);
            let med = zs[zs.len() / 2];
            assert!((-2.1..-1.3).contains(&med), "median road height {med}");
        }
    }
}

#[test]
fn voxelised_scan_agrees_with_official_input_bin() {
    let Some(root) = kitti_root() else { return };
    let p = KittiPaths::new(&root);
    let map = LearningMap::semantic_kitti();
    for f in frames(&root) {
        let (s, fr) = (f.sequence.as_str(), f.frame.as_str());
        let bin = read_packed_bits(&p.voxels(s, fr, "bin"), NUM_VOXELS).unwrap();
        let (pts, labels) = read_labelled_scan(&p.velodyne(s, fr), &p.point_labels(s, fr)).unwrap();

        // 1. exact emulation of the voxelizer (filters, vote, f32, off-by-one layout)
        let emu = emulate_input_occupancy(&pts, &labels);
        let mismatches = emu.iter().zip(&bin).filter(|(a, b)| a != b).count();
        let (_, _, iou_emu) = iou(&emu, &bin);

        // 2. plain voxelisation on the corrected grid (origin z = -2.2)
        let sem = voxelize_scan(&pts, &labels, &VoxelGrid::semantic_kitti(), &map);
        let (_, _, iou_fixed) = iou(&sem, &bin);
        // 3. the nominal origin z = -2.0 used by MonoScene/SparseOcc configs
        let sem_nominal = voxelize_scan(&pts, &labels, &VoxelGrid::semantic_kitti_nominal(), &map);
        let (_, _, iou_nominal) = iou(&sem_nominal, &bin);
        // 4. all points, no vote filter (occupied = any point): how far the naive approach is
        let naive = voxelize_scan_with(
            &pts,
            &labels,
            &VoxelGrid::semantic_kitti(),
            &map,
            &VoxelizeOptions::all_points(),
        );
        let (_, _, iou_naive) = iou(&naive, &bin);
        println!(
            "{s}/{fr}: IoU vs official .bin: emulation {iou_emu:.6} ({mismatches} differing voxels), \
             origin z=-2.2 {iou_fixed:.4}, origin z=-2.0 {iou_nominal:.4}, z=-2.2 all points {iou_naive:.4}"
        );
        assert_eq!(
            mismatches, 0,
            "emulated voxelizer must reproduce {s}/{fr}.bin"
        );
        assert!(iou_fixed > 0.9, "{iou_fixed}");
        assert!(iou_nominal < 0.5, "{iou_nominal}");
        assert!(iou_fixed > iou_nominal + 0.4);
    }
}

#[test]
fn occupied_voxels_project_into_image_2() {
    let Some(root) = kitti_root() else { return };
    let p = KittiPaths::new(&root);
    let g = VoxelGrid::semantic_kitti();
    for f in frames(&root) {
        let (s, fr) = (f.sequence.as_str(), f.frame.as_str());
        let img = read_png(&p.image_2(s, fr)).unwrap();
        assert!(
            (1200..1260).contains(&img.width) && (360..380).contains(&img.height),
            "{}x{}",
            img.width,
            img.height
        );
        let calib = read_calib(&p.calib(s)).unwrap();
        let view = calib.camera_view(img.width, img.height);
        let bin = read_packed_bits(&p.voxels(s, fr, "bin"), NUM_VOXELS).unwrap();
        // front part: inside the camera's horizontal field of view (|y| < 0.7 x, ±35°) and
        // beyond the car's bonnet (x > 5 m)
        let (mut n_front, mut n_front_in, mut n_all, mut n_all_in) = (0, 0, 0, 0);
        for (n, _) in bin.iter().enumerate().filter(|(_, &b)| b == 1) {
            let c = g.voxel_center_m(g.ijk_of(n));
            let inside = view.project_point(c).is_some_and(|uvd| view.in_view(uvd));
            n_all += 1;
            n_all_in += inside as usize;
            if c[0] > 5.0 && c[1].abs() < 0.7 * c[0] {
                n_front += 1;
                n_front_in += inside as usize;
            }
        }
        let frac_front = n_front_in as f64 / n_front as f64;
        let frac_all = n_all_in as f64 / n_all as f64;
        // MonoScene's projection (ignoring P2's 4th column) differs by the ~6 cm baseline
        let c = g.voxel_center_m([100, 128, 10]); // ~20 m ahead
        let a = view.project_point(c).unwrap();
        let b = calib
            .camera_view_monoscene(img.width, img.height)
            .project_point(c)
            .unwrap();
        let du = a[0] - b[0];
        println!("{s}/{fr}: {n_front_in}/{n_front} front voxels in image ({frac_front:.4}); all occupied {n_all_in}/{n_all} ({frac_all:.4}); MonoScene baseline shift at 20 m: {du:.2} px");
        assert!(frac_front > 0.9, "{frac_front}");
        assert!(frac_all > 0.3 && frac_all < frac_front);
        assert!(du.abs() > 0.5 && du.abs() < 5.0);
    }
}

#[test]
fn image_pipeline_on_real_images() {
    let Some(root) = kitti_root() else { return };
    let p = KittiPaths::new(&root);
    let cfg = ImagePipelineConfig::semantic_kitti();
    for f in frames(&root) {
        let img = read_png(&p.image_2(&f.sequence, &f.frame)).unwrap();
        let aug = cfg.test_aug(img.width, img.height);
        let out = process_image(&img, &aug).unwrap();
        assert_eq!((out.width, out.height), (1280, 384));
        assert_eq!(out.chw.len(), 3 * 1280 * 384);
        let mean: f64 = out.chw.iter().map(|&v| v as f64).sum::<f64>() / out.chw.len() as f64;
        assert!(mean.abs() < 1.5, "normalised mean {mean}");
        // bottom crop: the last output row is the last (resized) image row
        let (_, new_h) = aug.resized_dims(img.width, img.height);
        assert_eq!(aug.crop_y0 as usize, new_h - 384);
    }
}

#[test]
fn every_real_file_reads() {
    let Some(root) = kitti_root() else { return };
    let p = KittiPaths::new(&root);
    let mut n_files = 0;
    for seq in list_sequences(&root).unwrap() {
        let dir = p.sequence_dir(&seq);
        let mut size = None;
        for f in list_stems(&dir.join("image_2"), "png").unwrap() {
            let img = read_png(&p.image_2(&seq, &f)).unwrap();
            assert_eq!(img.data.len(), img.width * img.height * 3);
            // one camera per sequence: every image has the same size
            assert_eq!(
                *size.get_or_insert((img.width, img.height)),
                (img.width, img.height)
            );
            n_files += 1;
        }
        for f in list_stems(&dir.join("velodyne"), "bin").unwrap() {
            let pts = read_velodyne(&p.velodyne(&seq, &f)).unwrap();
            assert!(pts.iter().all(|q| q.iter().all(|v| v.is_finite())));
            let r_max = pts
                .iter()
                .map(|q| (q[0] * q[0] + q[1] * q[1]).sqrt())
                .fold(0f32, f32::max);
            assert!((50.0..130.0).contains(&r_max), "HDL-64 max range {r_max}");
            n_files += 1;
        }
        for f in list_stems(&dir.join("labels"), "label").unwrap() {
            let l = read_point_labels(&p.point_labels(&seq, &f)).unwrap();
            assert_eq!(l.len(), read_velodyne(&p.velodyne(&seq, &f)).unwrap().len());
            n_files += 1;
        }
        for ext in ["bin", "invalid", "occluded", "label"] {
            for f in list_stems(&dir.join("voxels"), ext).unwrap() {
                let path = p.voxels(&seq, &f, ext);
                if ext == "label" {
                    read_label_raw(&path, NUM_VOXELS).unwrap();
                } else {
                    read_packed_bits(&path, NUM_VOXELS).unwrap();
                }
                n_files += 1;
            }
        }
        read_calib(&p.calib(&seq)).unwrap();
        read_poses(&p.poses(&seq)).unwrap();
        n_files += 2;
    }
    println!("read {n_files} SemanticKITTI files");
    assert!(n_files >= 10);
}
