//! SCF ground truth and propagation on seeded random grids/anchors against brute-force definitions
//! written independently here: a literal zero-padded average pooling (PyTorch `count_include_pad=True`)
//! following Algorithm 2 line by line, and a literal dense max-pool dilation following Algorithm 1.

use occ_geometry::scf::{
    propagate, propagate_batched, propagation_to_dense, scf_ground_truth, ScfConfig,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Algorithm 2, literally: for every s_j, average-pool with kernel `k`, padding `k / 2`, zero padding
/// counted in the divisor, compare the pooled value with the voxel, overwrite with ±s_j.
fn brute_scf(occ: &[u8], dims: [usize; 3], s_max: u32, planar: bool) -> Vec<i8> {
    let [nx, ny, nz] = dims;
    let bin: Vec<f64> = occ.iter().map(|&v| if v > 0 { 1.0 } else { 0.0 }).collect();
    let mut scf = vec![0i8; occ.len()];
    for s_j in 1..=s_max as i64 {
        let k_j = 2 * s_j + 1;
        let kernel: [i64; 3] = if planar { [k_j, k_j, 1] } else { [1, 1, k_j] };
        let pad = kernel.map(|k| k / 2);
        let divisor = (kernel[0] * kernel[1] * kernel[2]) as f64;
        let mut pool = vec![0f64; occ.len()];
        for x in 0..nx as i64 {
            for y in 0..ny as i64 {
                for z in 0..nz as i64 {
                    let mut sum = 0.0;
                    for a in 0..kernel[0] {
                        for b in 0..kernel[1] {
                            for c in 0..kernel[2] {
                                let (xi, yi, zi) = (x - pad[0] + a, y - pad[1] + b, z - pad[2] + c);
                                let inside = (0..nx as i64).contains(&xi)
                                    && (0..ny as i64).contains(&yi)
                                    && (0..nz as i64).contains(&zi);
                                // Padding contributes 0 to the sum and 1 to the divisor.
                                if inside {
                                    sum +=
                                        bin[((xi as usize * ny) + yi as usize) * nz + zi as usize];
                                }
                            }
                        }
                    }
                    pool[((x as usize * ny) + y as usize) * nz + z as usize] = sum / divisor;
                }
            }
        }
        for i in 0..occ.len() {
            let homogeneous = pool[i] == bin[i];
            if homogeneous && bin[i] == 1.0 {
                scf[i] = -(s_j as i8);
            }
            if homogeneous && bin[i] == 0.0 {
                scf[i] = s_j as i8;
            }
        }
    }
    scf
}

fn random_grid(rng: &mut ChaCha8Rng, dims: [usize; 3]) -> Vec<u8> {
    let n = dims[0] * dims[1] * dims[2];
    let mut occ = vec![0u8; n];
    // A few random boxes (so interiors exist) plus salt noise; occupied values vary (any >0 counts).
    let boxes = rng.random_range(0..6);
    for _ in 0..boxes {
        let lo: [usize; 3] = std::array::from_fn(|a| rng.random_range(0..dims[a]));
        let hi: [usize; 3] =
            std::array::from_fn(|a| (lo[a] + rng.random_range(1..=dims[a])).min(dims[a]));
        let v = rng.random_range(1..=255u8);
        for x in lo[0]..hi[0] {
            for y in lo[1]..hi[1] {
                for z in lo[2]..hi[2] {
                    occ[(x * dims[1] + y) * dims[2] + z] = v;
                }
            }
        }
    }
    let noise: f64 = rng.random_range(0.0..0.1);
    for v in occ.iter_mut() {
        if rng.random_bool(noise) {
            *v = if *v == 0 { rng.random_range(1..=3) } else { 0 };
        }
    }
    occ
}

#[test]
fn scf_ground_truth_equals_literal_average_pooling() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut signs = [0usize; 3];
    for case in 0..40 {
        // Include grids smaller than the kernels (dims 1..) and larger ones.
        let dims = [
            rng.random_range(1..40usize),
            rng.random_range(1..40usize),
            rng.random_range(1..12usize),
        ];
        let occ = if case == 0 {
            vec![1u8; dims.iter().product()]
        } else {
            random_grid(&mut rng, dims)
        };
        let cfg = ScfConfig {
            s_max_planar: rng.random_range(0..12),
            s_max_vertical: rng.random_range(0..6),
        };
        let gt = scf_ground_truth(&occ, dims, &cfg).unwrap();
        let want_p = brute_scf(&occ, dims, cfg.s_max_planar, true);
        let want_v = brute_scf(&occ, dims, cfg.s_max_vertical, false);
        assert_eq!(
            gt.planar, want_p,
            "planar differs, case {case}, dims {dims:?}, cfg {cfg:?}"
        );
        assert_eq!(
            gt.vertical, want_v,
            "vertical differs, case {case}, dims {dims:?}, cfg {cfg:?}"
        );
        for &s in gt.planar.iter().chain(&gt.vertical) {
            signs[(s.signum() + 1) as usize] += 1;
        }
    }
    assert!(
        signs.iter().all(|&c| c > 1000),
        "random cases too degenerate: {signs:?}"
    );
}

/// Algorithm 1, literally on a dense grid: for each s_j, max-pool the indicator of anchors with
/// s == -s_j (kernel per axis, stride 1, padding = kernel/2 so the shape is kept) and accumulate.
fn brute_propagate(anchors: &[[i32; 3]], sp: &[i32], sv: &[i32], dims: [usize; 3]) -> Vec<u8> {
    let [nx, ny, nz] = dims;
    let idx = |x: usize, y: usize, z: usize| (x * ny + y) * nz + z;
    let mut m = vec![0u8; nx * ny * nz];
    for a in anchors {
        m[idx(a[0] as usize, a[1] as usize, a[2] as usize)] = 1;
    }
    let s_max = sp
        .iter()
        .chain(sv)
        .map(|s| s.unsigned_abs())
        .max()
        .unwrap_or(0) as i64;
    for (s_pred, planar) in [(sp, true), (sv, false)] {
        for s_j in 1..=s_max {
            let mut mj = vec![0u8; m.len()];
            let mut any = false;
            for (a, &s) in anchors.iter().zip(s_pred) {
                if s as i64 == -s_j {
                    mj[idx(a[0] as usize, a[1] as usize, a[2] as usize)] = 1;
                    any = true;
                }
            }
            if !any {
                continue;
            }
            let r: [i64; 3] = if planar { [s_j, s_j, 0] } else { [0, 0, s_j] };
            for x in 0..nx as i64 {
                for y in 0..ny as i64 {
                    for z in 0..nz as i64 {
                        let mut mx = 0u8;
                        for dx in -r[0]..=r[0] {
                            for dy in -r[1]..=r[1] {
                                for dz in -r[2]..=r[2] {
                                    let (xi, yi, zi) = (x + dx, y + dy, z + dz);
                                    if (0..nx as i64).contains(&xi)
                                        && (0..ny as i64).contains(&yi)
                                        && (0..nz as i64).contains(&zi)
                                    {
                                        mx = mx.max(mj[idx(xi as usize, yi as usize, zi as usize)]);
                                    }
                                }
                            }
                        }
                        let i = idx(x as usize, y as usize, z as usize);
                        m[i] = m[i].saturating_add(mx);
                    }
                }
            }
        }
    }
    m.iter().map(|&v| u8::from(v > 0)).collect()
}

fn random_anchors(
    rng: &mut ChaCha8Rng,
    dims: [usize; 3],
    n: usize,
) -> (Vec<[i32; 3]>, Vec<i32>, Vec<i32>) {
    let anchors: Vec<[i32; 3]> = (0..n)
        .map(|_| std::array::from_fn(|a| rng.random_range(0..dims[a]) as i32))
        .collect();
    let sp = (0..n).map(|_| rng.random_range(-10..=10)).collect();
    let sv = (0..n).map(|_| rng.random_range(-3..=3)).collect();
    (anchors, sp, sv)
}

#[test]
fn propagation_equals_literal_dense_dilation() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut total_new = 0;
    for case in 0..30 {
        let dims = [
            rng.random_range(1..30usize),
            rng.random_range(1..30usize),
            rng.random_range(1..10usize),
        ];
        let n = rng.random_range(0..60usize);
        let (anchors, sp, sv) = random_anchors(&mut rng, dims, n);
        let prop = propagate(&anchors, &sp, &sv, dims).unwrap();
        let want = brute_propagate(&anchors, &sp, &sv, dims);
        let got = propagation_to_dense(&anchors, &prop, dims).unwrap();
        assert_eq!(got, want, "case {case}, dims {dims:?}, {n} anchors");
        // Sorted, unique, disjoint from anchors, and exactly the dense set minus the anchors.
        assert!(prop.new_voxels.windows(2).all(|w| w[0] < w[1]));
        let anchor_set: std::collections::HashSet<_> = anchors.iter().copied().collect();
        assert!(prop.new_voxels.iter().all(|v| !anchor_set.contains(v)));
        assert_eq!(
            anchor_set.len() + prop.new_voxels.len(),
            want.iter().filter(|&&v| v == 1).count()
        );
        total_new += prop.new_voxels.len();
    }
    assert!(total_new > 1000, "random cases too degenerate");
}

#[test]
fn batched_propagation_equals_per_element() {
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let dims = [17, 23, 6];
    let mut all = Vec::new();
    let mut all_sp = Vec::new();
    let mut all_sv = Vec::new();
    let mut want = Vec::new();
    for b in 0..3 {
        let (anchors, sp, sv) = random_anchors(&mut rng, dims, 40);
        let single = propagate(&anchors, &sp, &sv, dims).unwrap();
        want.extend(single.new_voxels.iter().map(|v| [b, v[0], v[1], v[2]]));
        all.extend(anchors.iter().map(|v| [b, v[0], v[1], v[2]]));
        all_sp.extend(sp);
        all_sv.extend(sv);
    }
    // Interleave the batch elements: the result must not depend on anchor order.
    let mut order: Vec<usize> = (0..all.len()).collect();
    for i in (1..order.len()).rev() {
        order.swap(i, rng.random_range(0..=i));
    }
    let anchors: Vec<[i32; 4]> = order.iter().map(|&i| all[i]).collect();
    let sp: Vec<i32> = order.iter().map(|&i| all_sp[i]).collect();
    let sv: Vec<i32> = order.iter().map(|&i| all_sv[i]).collect();
    let got = propagate_batched(&anchors, &sp, &sv, dims).unwrap();
    assert!(!want.is_empty());
    assert_eq!(got.new_voxels, want);
}
