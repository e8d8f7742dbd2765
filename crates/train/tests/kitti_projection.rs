//! The camera a training sample carries (`img_from_lidar`, with the image resize/crop/flip/rotate
//! folded in) must map a labelled voxel onto the pixels of the NETWORK-INPUT image that show it.
//! Checked end to end on built-in synthetic scenes, whose renderer gives every ground class its own
//! chromaticity: the top face of every labelled ground voxel with free space above it is projected
//! into the processed image, and the pixel's colour must name the voxel's class (nearest base
//! colour among the five ground classes) for most of them — with and without the training
//! augmentation and the lateral mirror (`occ_train::mirror`). A one-voxel shift or a wrong crop/flip convention drops the agreement sharply.

use occ_data::image::{IMAGENET_MEAN, IMAGENET_STD};
use occ_data::synthetic::classes::BASE_COLOR;
use occ_data::synthetic::{generate, Preset, SynthConfig};
use occ_geometry::{project_with, VoxelGrid};
use occ_train::dataset::{Dataset, Sample};
use occ_train::mirror::mirror_sample_y;
use occ_train::RunConfig;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::path::Path;

use occ_testdata::TempDir;

/// Training ids (SemanticKITTI learning map) of the ground classes and their synthetic scene class.
const GROUND: [(u8, usize); 5] = [(9, 9), (10, 10), (11, 11), (12, 12), (17, 17)];

fn nearest_ground_class(rgb: [f32; 3]) -> u8 {
    // Chromaticity: colour divided by its sum (shading in the renderer is luminance-only).
    let chroma = |c: [f32; 3]| {
        let s = (c[0] + c[1] + c[2]).max(1e-3);
        [c[0] / s, c[1] / s, c[2] / s]
    };
    let p = chroma(rgb);
    let mut best = (f32::MAX, 0u8);
    for &(id, scene) in &GROUND {
        let b = BASE_COLOR[scene];
        let q = chroma([b[0] as f32, b[1] as f32, b[2] as f32]);
        let d = (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>();
        if d < best.0 {
            best = (d, id);
        }
    }
    best.1
}

/// Fraction of visible ground-voxel top faces whose pixel shows the voxel's class, counting only
/// voxels within two voxels (along x or y) of a different ground class, where a misplaced projection
/// shows. `shift_y` moves the projected point by that many voxels (the negative control).
fn agreement(s: &Sample, grid: &VoxelGrid, shift_y: f64) -> (usize, f64) {
    let (w, h) = s.size;
    let target = s.target.as_ref().unwrap();
    let dims = grid.dims;
    let cam = &s.cameras[0];
    let (mut n, mut ok) = (0usize, 0usize);
    for x in 0..dims[0] {
        for y in 0..dims[1] {
            for z in 0..dims[2] - 1 {
                let t = target[grid.linear_index([x, y, z])];
                if !GROUND.iter().any(|g| g.0 == t) || target[grid.linear_index([x, y, z + 1])] != 0
                {
                    continue;
                }
                let other_near = (-2i64..=2).any(|d| {
                    let xs = x as i64 + d;
                    let ys = y as i64 + d;
                    let at = |i: i64, j: i64| -> Option<u8> {
                        (i >= 0 && j >= 0 && (i as usize) < dims[0] && (j as usize) < dims[1])
                            .then(|| target[grid.linear_index([i as usize, j as usize, z])])
                    };
                    [at(xs, y as i64), at(x as i64, ys)]
                        .into_iter()
                        .flatten()
                        .any(|o| o != t && GROUND.iter().any(|g| g.0 == o))
                });
                if !other_near {
                    continue;
                }
                let c = grid.voxel_center_m([x, y, z]);
                let top = [
                    c[0],
                    c[1] + shift_y * grid.voxel_size_m,
                    c[2] + 0.5 * grid.voxel_size_m,
                ];
                let Some(uvd) = project_with(&cam.img_from_lidar, top) else {
                    continue;
                };
                let (u, v) = (uvd[0].round(), uvd[1].round());
                // Away from the image border and not too far (small, hazy faces).
                if uvd[2] > 30.0 || u < 2.0 || v < 2.0 || u > (w - 3) as f64 || v > (h - 3) as f64 {
                    continue;
                }
                let (u, v) = (u as usize, v as usize);
                let rgb = [0, 1, 2]
                    .map(|ch| s.chw[ch * w * h + v * w + u] * IMAGENET_STD[ch] + IMAGENET_MEAN[ch]);
                n += 1;
                ok += usize::from(nearest_ground_class(rgb) == t);
            }
        }
    }
    (n, ok as f64 / n.max(1) as f64)
}

#[test]
fn ground_voxels_project_onto_pixels_of_their_class() {
    let t = TempDir::new("occ_train", "ground");
    let cfg_s = SynthConfig::new(Preset::KittiSmall, 5, vec![("00".into(), 2)]);
    generate(&t.0, &cfg_s, &mut |_, _| {}).unwrap();
    // Score only what this frame's own rays saw: `.invalid` also counts the scans of the drive on
    // through the volume (ground behind a parked car is observed, but not in this frame's image),
    // so the test's copy of the data takes each frame's `.occluded` as its `.invalid`.
    let vox = t.0.join("sequences/00/voxels");
    for f in ["000000", "000001"] {
        std::fs::copy(
            vox.join(format!("{f}.occluded")),
            vox.join(format!("{f}.invalid")),
        )
        .unwrap();
    }
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/synthetic_tiny.toml"),
    )
    .unwrap();
    let mut cfg = RunConfig::from_toml(&text, "synthetic_tiny.toml").unwrap();
    // The full image augmentation of the paper configs (the demo config keeps only the mirror).
    cfg.data.resize_lim = (-0.06, 0.11);
    cfg.data.flip_prob = 0.5;
    cfg.data.rot_lim_deg = (-5.4, 5.4);
    cfg.data.mirror_prob = 0.0;
    let ds = Dataset::open(&t.0, &cfg.data, &["00".into()], &[]).unwrap();
    let grid = ds.grid();
    let mut data_mirror = cfg.data.clone();
    data_mirror.mirror_prob = 1.0;
    let ds_mirror = Dataset::open(&t.0, &data_mirror, &["00".into()], &[]).unwrap();
    // And translated by up to 6 voxels along x and y (`data.shift_voxels`, image unchanged).
    let mut data_shift = data_mirror.clone();
    data_shift.shift_voxels = (6, 6);
    let ds_shift = Dataset::open(&t.0, &data_shift, &["00".into()], &[]).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for i in 0..ds.len() {
        let plain = ds.load::<ChaCha8Rng>(i, None).unwrap();
        let (n, a) = agreement(&plain, &grid, 0.0);
        eprintln!("frame {i}: test-time transform: {n} boundary faces, agreement {a:.3}");
        assert!(n > 80 && a > 0.75, "frame {i}: {n} faces, agreement {a:.3}");
        // Negative control: the same check one voxel off must fail clearly.
        let (_, off) = agreement(&plain, &grid, 1.0);
        eprintln!("frame {i}: shifted by one voxel: agreement {off:.3}");
        assert!(
            off < a - 0.1,
            "frame {i}: shift not detected ({off:.3} vs {a:.3})"
        );
        // The lateral mirror (image flipped, cameras re-folded, labels reversed along y) keeps it.
        let mut mirrored = plain.clone();
        mirror_sample_y(&mut mirrored, &grid).unwrap();
        assert_ne!(mirrored.target, plain.target);
        let (n, a) = agreement(&mirrored, &grid, 0.0);
        eprintln!("frame {i}: mirrored: {n} boundary faces, agreement {a:.3}");
        assert!(
            n > 80 && a > 0.75,
            "frame {i} mirrored: {n} faces, agreement {a:.3}"
        );
        // Augmented (image augmentation), also always mirrored (`data.mirror_prob = 1`), also
        // mirrored and translated: 60 or more boundary faces of which over 75 % agree.
        for k in 0..3 {
            for (what, d) in [
                ("augmented", &ds),
                ("augmented and mirrored", &ds_mirror),
                ("augmented, mirrored and shifted", &ds_shift),
            ] {
                let aug = d.load(i, Some(&mut rng)).unwrap();
                let (n, a) = agreement(&aug, &grid, 0.0);
                eprintln!("frame {i}: {what} #{k}: {n} boundary faces, agreement {a:.3}");
                assert!(
                    n > 60 && a > 0.75,
                    "frame {i} {what}: {n} faces, agreement {a:.3}"
                );
            }
        }
    }
}
