//! The synthetic SemanticKITTI-layout generator, checked through the real-format readers.

mod common;

use common::traverse;
use occ_data::formats::semantic_kitti::{
    list_frames, read_calib, read_label_raw, read_packed_bits, read_point_labels, read_poses,
    read_velodyne, LearningMap,
};
use occ_data::image::read_png;
use occ_data::synthetic::classes::{kitti_learning_class, nearest_class_by_chroma};
use occ_data::synthetic::{generate, read_synthetic_meta, Preset, SynthConfig, SynthMeta};
use occ_geometry::{mat4_inverse, mat4_mul, transform_point, Mat4, VoxelGrid};
use occ_testdata::TempDir;
use std::path::{Path, PathBuf};

fn small_cfg(seed: u64, frames: usize, image: (usize, usize)) -> SynthConfig {
    SynthConfig {
        preset: Preset::KittiSmall,
        seed,
        sequences: vec![("00".into(), frames)],
        image_size: Some(image),
    }
}

fn all_files(root: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p.strip_prefix(root).unwrap().to_path_buf());
            }
        }
    }
    out.sort();
    out
}

#[test]
fn same_seed_gives_identical_files_and_progress_is_reported() {
    let a = TempDir::new("sparseocc-synth", "det-a");
    let b = TempDir::new("sparseocc-synth", "det-b");
    let c = TempDir::new("sparseocc-synth", "det-c");
    let cfg = small_cfg(11, 2, (96, 32));
    let mut calls = Vec::new();
    let s = generate(&a.0, &cfg, &mut |d, t| calls.push((d, t))).unwrap();
    // the second run on a single thread: the output must not depend on scheduling
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    pool.install(|| generate(&b.0, &cfg, &mut |_, _| {}))
        .unwrap();
    generate(&c.0, &small_cfg(12, 2, (96, 32)), &mut |_, _| {}).unwrap();
    assert_eq!(calls.first(), Some(&(0, 4)));
    assert_eq!(calls.last(), Some(&(4, 4)));
    assert!(calls.windows(2).all(|w| w[1].0 == w[0].0 + 1));
    let fa = all_files(&a.0);
    assert_eq!(fa, all_files(&b.0));
    assert_eq!(s.files, fa.len());
    // 2 frames x (png, velodyne, labels, bin, label, invalid, occluded) + calib, poses, times, meta
    assert_eq!(fa.len(), 2 * 7 + 4);
    let mut n_diff = 0;
    for f in &fa {
        let x = std::fs::read(a.0.join(f)).unwrap();
        assert_eq!(
            x,
            std::fs::read(b.0.join(f)).unwrap(),
            "{} differs between runs",
            f.display()
        );
        if c.0.join(f).exists() && std::fs::read(c.0.join(f)).unwrap() != x {
            n_diff += 1;
        }
    }
    assert!(
        n_diff >= 10,
        "another seed changes the files ({n_diff} differ)"
    );
}

struct Seq {
    meta: SynthMeta,
    grid: VoxelGrid,
    labels: Vec<Vec<u8>>,
    invalid: Vec<Vec<u8>>,
    occluded: Vec<Vec<u8>>,
    input: Vec<Vec<u8>>,
    scans: Vec<Vec<[f32; 4]>>,
    point_labels: Vec<Vec<u32>>,
    lidar_poses: Vec<Mat4>,
    tr: Mat4,
}

/// Sequence 00 generated with `cfg` into a fresh folder (removed when the returned `TempDir` is
/// dropped), read back.
fn generated_sequence(tag: &str, cfg: SynthConfig) -> (TempDir, Seq) {
    let t = TempDir::new("sparseocc-synth", tag);
    generate(&t.0, &cfg, &mut |_, _| {}).unwrap();
    let s = read_seq(&t.0, "00");
    (t, s)
}

fn read_seq(root: &Path, seq: &str) -> Seq {
    let meta = read_synthetic_meta(root)
        .unwrap()
        .expect("synthetic.json written");
    let grid = meta.grid;
    let n = grid.num_voxels();
    let map = LearningMap::semantic_kitti();
    let dir = root.join("sequences").join(seq);
    let frames = list_frames(root, seq).unwrap();
    assert_eq!(frames.len(), meta.sequences[0].frames);
    let calib = read_calib(&dir.join("calib.txt")).unwrap();
    let poses = read_poses(&dir.join("poses.txt")).unwrap();
    assert_eq!(poses.len(), frames.len());
    let tr_inv = mat4_inverse(&calib.tr).unwrap();
    let mut s = Seq {
        meta,
        grid,
        labels: vec![],
        invalid: vec![],
        occluded: vec![],
        input: vec![],
        scans: vec![],
        point_labels: vec![],
        lidar_poses: poses
            .iter()
            .map(|p| mat4_mul(&mat4_mul(&tr_inv, p), &calib.tr))
            .collect(),
        tr: calib.tr,
    };
    for f in &frames {
        let vox = dir.join("voxels");
        s.labels
            .push(map.remap(&read_label_raw(&vox.join(format!("{f}.label")), n).unwrap()));
        s.invalid
            .push(read_packed_bits(&vox.join(format!("{f}.invalid")), n).unwrap());
        s.occluded
            .push(read_packed_bits(&vox.join(format!("{f}.occluded")), n).unwrap());
        s.input
            .push(read_packed_bits(&vox.join(format!("{f}.bin")), n).unwrap());
        let pts = read_velodyne(&dir.join("velodyne").join(format!("{f}.bin"))).unwrap();
        let pl = read_point_labels(&dir.join("labels").join(format!("{f}.label"))).unwrap();
        assert_eq!(pts.len(), pl.len());
        s.scans.push(pts);
        s.point_labels.push(pl);
    }
    s
}

#[test]
fn files_read_back_and_are_mutually_consistent() {
    let t = TempDir::new("sparseocc-synth", "consistency");
    let summary = generate(&t.0, &small_cfg(3, 4, (160, 48)), &mut |_, _| {}).unwrap();
    let s = read_seq(&t.0, "00");
    assert_eq!(s.grid.dims, [128, 128, 16]);
    assert!((s.grid.voxel_size_m - 0.4).abs() < 1e-12);
    assert_eq!(s.meta.image_size, [160, 48]);
    let img = read_png(&t.0.join("sequences/00/image_2/000003.png")).unwrap();
    assert_eq!((img.width, img.height), (160, 48));
    let map = LearningMap::semantic_kitti();
    // KITTI camera axes: camera z = LiDAR x
    assert!(
        (s.tr[2][0] - 1.0).abs() < 1e-9
            && (s.tr[0][1] + 1.0).abs() < 1e-9
            && (s.tr[1][2] + 1.0).abs() < 1e-9
    );
    for f in 0..s.labels.len() {
        // voxelising the scan gives exactly the input occupancy .bin
        let mut vox = vec![0u8; s.grid.num_voxels()];
        for (p, &l) in s.scans[f].iter().zip(&s.point_labels[f]) {
            let q = [p[0] as f64, p[1] as f64, p[2] as f64];
            if let Some(ijk) = s.grid.voxel_of_point_m(q) {
                let i = s.grid.linear_index(ijk);
                vox[i] = 1;
                // and the point's label is the label of its voxel in the complete scene
                assert_eq!(
                    map.to_class((l & 0xffff) as u16),
                    s.labels[f][i],
                    "frame {f} point {p:?}"
                );
            }
        }
        assert_eq!(vox, s.input[f], "frame {f}: voxelised scan != .bin");
        // every LiDAR return is occupied in the complete scene, and seen
        for (i, &occupied) in vox.iter().enumerate() {
            if occupied == 1 {
                assert_ne!(s.labels[f][i], 0);
                assert_eq!(s.occluded[f][i], 0);
            }
            // .invalid (unseen from all poses) implies .occluded (unseen from this one)
            if s.invalid[f][i] == 1 {
                assert_eq!(s.occluded[f][i], 1);
            }
        }
        let inv = s.invalid[f].iter().filter(|&&v| v == 1).count() as f64 / vox.len() as f64;
        assert!(inv > 0.05 && inv < 0.9, "invalid fraction {inv}");
        // The drive on through the volume (SemanticKITTI's accumulated scans) observes much of
        // what this frame's own rays did not: `.invalid` is far smaller than `.occluded`.
        let occ = s.occluded[f].iter().filter(|&&v| v == 1).count() as f64 / vox.len() as f64;
        assert!(
            inv < 0.8 * occ,
            "frame {f}: invalid {inv:.3} not well below occluded {occ:.3}"
        );
    }
    // consecutive frames share a world: the LiDAR poses move forward and the labels of the
    // overlapping part agree voxel for voxel
    let step = s.lidar_poses[1][0][3] - s.lidar_poses[0][0][3];
    assert!((step - s.meta.sequences[0].step_m).abs() < 1e-6 && step > 0.5);
    let shift = (step / s.grid.voxel_size_m).round() as usize;
    let d = s.grid.dims;
    for x in 0..d[0] - shift {
        for y in 0..d[1] {
            for z in 0..d[2] {
                assert_eq!(
                    s.labels[0][s.grid.linear_index([x + shift, y, z])],
                    s.labels[1][s.grid.linear_index([x, y, z])]
                );
            }
        }
    }
    assert!(
        summary.lidar_points_per_frame > 20_000.0,
        "{}",
        summary.lidar_points_per_frame
    );
}

#[test]
fn every_semantic_class_occurs_in_a_sequence() {
    for seed in [1u64, 2, 3] {
        let (_t, s) = generated_sequence(&format!("classes-{seed}"), small_cfg(seed, 2, (32, 16)));
        let mut count = [0u64; 256];
        for l in &s.labels {
            for &c in l {
                count[c as usize] += 1;
            }
        }
        for c in 1..20 {
            assert!(
                count[c] > 0,
                "seed {seed}: class {c} never occurs; counts {:?}",
                &count[..20]
            );
        }
    }
}

/// Camera centre (LiDAR frame) and unit ray direction of pixel `(u, v)`.
fn pixel_ray(
    lidar_from_cam: &Mat4,
    cam: &occ_geometry::PinholeCamera,
    u: usize,
    v: usize,
) -> ([f64; 3], [f64; 3]) {
    let o = transform_point(lidar_from_cam, [0.0, 0.0, 0.0]);
    let dc = [
        (u as f64 - cam.cx) / cam.fx,
        (v as f64 - cam.cy) / cam.fy,
        1.0,
    ];
    let p = transform_point(lidar_from_cam, dc);
    let dv = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
    let n = (dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]).sqrt();
    (o, dv.map(|x| x / n))
}

#[test]
fn rendered_pixels_show_the_class_of_the_visible_voxel() {
    // Visible voxels: occupied voxels of the label grid that some pixel ray (traversed exactly
    // through the label grid) meets first. For each, take the pixel under its projected centre
    // (rounded, the KITTI convention) and name a class from the pixel's chromaticity (all shading
    // in the renderer is luminance-only). Two fractions are measured:
    //   strict: the pixel's own ray meets the voxel first (the pixel really shows this voxel);
    //   all:    every visible voxel (for ground voxels the centre pixel usually shows a nearer
    //           ground voxel, which may belong to another class at borders).
    let (w, h) = (306, 92);
    let (t, s) = generated_sequence("appearance", small_cfg(5, 2, (w, h)));
    let dir = t.0.join("sequences/00");
    let calib = read_calib(&dir.join("calib.txt")).unwrap();
    let view = calib.camera_view(w, h);
    let lidar_from_cam = mat4_inverse(&view.cam_from_lidar).unwrap();
    let candidates: Vec<u8> = (1..=21).collect();
    let (mut n_all, mut ok_all, mut n_strict, mut ok_strict) = (0usize, 0usize, 0usize, 0usize);
    let mut per_class = [[0usize; 2]; 20];
    for f in 0..2 {
        let img = read_png(&dir.join(format!("image_2/{f:06}.png"))).unwrap();
        let labels = &s.labels[f];
        let mut first = vec![None; w * h];
        let mut visible = vec![false; labels.len()];
        for v in 0..h {
            for u in 0..w {
                let (o, d) = pixel_ray(&lidar_from_cam, &view.camera, u, v);
                let hit = traverse(&s.grid, &|i| labels[i] != 0, o, d, 200.0).1;
                if let Some(i) = hit {
                    visible[i] = true;
                }
                first[v * w + u] = hit;
            }
        }
        for (i, &c) in labels.iter().enumerate() {
            if !visible[i] || c == 255 {
                continue;
            }
            let centre = s.grid.voxel_center_m(s.grid.ijk_of(i));
            let Some(uvd) = view.project_point(centre) else {
                continue;
            };
            let (u, v) = (uvd[0].round(), uvd[1].round());
            if u < 0.0 || v < 0.0 || u >= w as f64 || v >= h as f64 {
                continue;
            }
            let (u, v) = (u as usize, v as usize);
            let rgb = img.pixel(u, v).unwrap();
            let good =
                nearest_class_by_chroma(rgb, &candidates).map(kitti_learning_class) == Some(c);
            n_all += 1;
            ok_all += usize::from(good);
            per_class[c as usize][0] += 1;
            per_class[c as usize][1] += usize::from(good);
            if first[v * w + u] == Some(i) {
                n_strict += 1;
                ok_strict += usize::from(good);
            }
        }
    }
    let frac_all = ok_all as f64 / n_all as f64;
    let frac_strict = ok_strict as f64 / n_strict as f64;
    eprintln!(
        "appearance match: all visible voxels {ok_all}/{n_all} = {frac_all:.4}; pixel shows the voxel {ok_strict}/{n_strict} = {frac_strict:.4}; per class [visible, matched]: {per_class:?}"
    );
    assert!(
        n_all > 2000 && n_strict > 500,
        "too few visible voxels: {n_all} / {n_strict}"
    );
    assert!(frac_all >= 0.8, "appearance match fraction {frac_all}");
    assert!(
        frac_strict >= 0.95,
        "appearance match fraction where the pixel shows the voxel {frac_strict}"
    );
    let classes_seen = per_class.iter().filter(|c| c[0] > 0).count();
    assert!(classes_seen >= 14, "only {classes_seen} classes visible");
}

#[test]
fn invalid_never_marks_a_visible_voxel() {
    let (w, h) = (160, 48);
    let (t, s) = generated_sequence("invalid", small_cfg(8, 4, (w, h)));
    let calib = read_calib(&t.0.join("sequences/00/calib.txt")).unwrap();
    let view = calib.camera_view(w, h);
    let lidar_from_cam = mat4_inverse(&view.cam_from_lidar).unwrap();
    let nf = s.labels.len();
    let mut checked = 0usize;
    for fi in 0..nf {
        let inv_i = mat4_inverse(&s.lidar_poses[fi]).unwrap();
        // (1) LiDAR returns of every frame of the sequence, moved into frame fi's grid
        for fj in 0..nf {
            let fi_from_fj = mat4_mul(&inv_i, &s.lidar_poses[fj]);
            for p in &s.scans[fj] {
                let q = transform_point(&fi_from_fj, [p[0] as f64, p[1] as f64, p[2] as f64]);
                if let Some(ijk) = s.grid.voxel_of_point_m(q) {
                    let i = s.grid.linear_index(ijk);
                    assert_eq!(
                        s.invalid[fi][i], 0,
                        "frame {fi}: voxel {ijk:?} hit by the LiDAR of frame {fj} is invalid"
                    );
                    checked += 1;
                }
            }
        }
        // (2) every voxel on the camera pixel rays of this frame, up to and including the first
        //     occupied one
        for v in 0..h {
            for u in 0..w {
                let (o, d) = pixel_ray(&lidar_from_cam, &view.camera, u, v);
                for i in traverse(&s.grid, &|i| s.labels[fi][i] != 0, o, d, 120.0).0 {
                    assert_eq!(
                        s.invalid[fi][i],
                        0,
                        "frame {fi}: voxel {:?} on the ray of pixel ({u},{v}) is invalid",
                        s.grid.ijk_of(i)
                    );
                    assert_eq!(
                        s.occluded[fi][i],
                        0,
                        "frame {fi}: voxel {:?} on the ray of pixel ({u},{v}) is occluded",
                        s.grid.ijk_of(i)
                    );
                    checked += 1;
                }
            }
        }
    }
    assert!(checked > 100_000, "{checked}");
}

#[test]
fn missing_meta_is_none_and_bad_meta_is_an_error() {
    let t = TempDir::new("sparseocc-synth", "meta");
    std::fs::create_dir_all(&t.0).unwrap();
    assert!(read_synthetic_meta(&t.0).unwrap().is_none());
    std::fs::write(t.0.join("synthetic.json"), b"{not json").unwrap();
    let e = read_synthetic_meta(&t.0).unwrap_err();
    assert!(e.to_string().contains("synthetic.json"), "{e}");
    let bad = SynthConfig {
        preset: Preset::Kitti,
        seed: 0,
        sequences: vec![],
        image_size: None,
    };
    assert!(generate(&t.0, &bad, &mut |_, _| {}).is_err());
}
