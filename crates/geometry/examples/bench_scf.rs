//! Benchmark of the SCF geometry (paper Sec. 4.2): Algorithm 2 ground truth on a driving-like
//! 256x256x32 grid (ground plane + boxes, as in SemanticKITTI) and Algorithm 1 propagation of 50,000
//! anchors drawn from that grid with their ground-truth distances. Prints one JSON object with the
//! median (and min) milliseconds over several runs.
//!
//! Run: `cargo run --release -p occ-geometry --example bench_scf [-- RUNS]`

use occ_geometry::scf::{propagate, scf_ground_truth, ScfConfig};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

const DIMS: [usize; 3] = [256, 256, 32];
const N_ANCHORS: usize = 50_000;

/// Ground plane (z 0..3, with gaps), about 150 boxes (cars, buildings, poles) and sparse noise.
fn driving_like_grid(rng: &mut ChaCha8Rng) -> Vec<u8> {
    let [nx, ny, nz] = DIMS;
    let idx = |x: usize, y: usize, z: usize| (x * ny + y) * nz + z;
    let mut occ = vec![0u8; nx * ny * nz];
    for x in 0..nx {
        for y in 0..ny {
            let h = 1 + usize::from((x / 16 + y / 16) % 3 == 0);
            if rng.random_bool(0.9) {
                for z in 0..h {
                    occ[idx(x, y, z)] = 1;
                }
            }
        }
    }
    for i in 0..150 {
        let (sx, sy, sz) = match i % 3 {
            0 => (
                rng.random_range(8..22),
                rng.random_range(8..12),
                rng.random_range(6..9),
            ),
            1 => (
                rng.random_range(10..40),
                rng.random_range(5..20),
                rng.random_range(10..25),
            ),
            _ => (1, 1, rng.random_range(10..30)),
        };
        let x0 = rng.random_range(0..nx);
        let y0 = rng.random_range(0..ny);
        for x in x0..(x0 + sx).min(nx) {
            for y in y0..(y0 + sy).min(ny) {
                for z in 2..(2 + sz).min(nz) {
                    occ[idx(x, y, z)] = 1;
                }
            }
        }
    }
    for v in occ.iter_mut() {
        if rng.random_bool(0.002) {
            *v = 1;
        }
    }
    occ
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let runs: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(7)
        .max(1);
    let mut rng = ChaCha8Rng::seed_from_u64(2024);
    let occ = driving_like_grid(&mut rng);
    let cfg = ScfConfig::default();

    let mut gt_ms = Vec::new();
    let mut gt = None;
    for _ in 0..runs {
        let t = Instant::now();
        let g = scf_ground_truth(&occ, DIMS, &cfg).expect("valid grid");
        gt_ms.push(t.elapsed().as_secs_f64() * 1e3);
        gt = Some(g);
    }
    let gt = gt.expect("at least one run");

    // Anchors: random occupied voxels with their GT distances (realistic interior/boundary mix).
    let occupied: Vec<usize> = (0..occ.len()).filter(|&i| occ[i] != 0).collect();
    let [_, ny, nz] = DIMS;
    let mut anchors = Vec::with_capacity(N_ANCHORS);
    let mut sp = Vec::with_capacity(N_ANCHORS);
    let mut sv = Vec::with_capacity(N_ANCHORS);
    for _ in 0..N_ANCHORS {
        let i = occupied[rng.random_range(0..occupied.len())];
        anchors.push([
            (i / (ny * nz)) as i32,
            ((i / nz) % ny) as i32,
            (i % nz) as i32,
        ]);
        sp.push(i32::from(gt.planar[i]));
        sv.push(i32::from(gt.vertical[i]));
    }
    let mut prop_ms = Vec::new();
    let mut n_new = 0;
    for _ in 0..runs {
        let t = Instant::now();
        let p = propagate(&anchors, &sp, &sv, DIMS).expect("valid anchors");
        prop_ms.push(t.elapsed().as_secs_f64() * 1e3);
        n_new = p.new_voxels.len();
    }
    let interior = sp.iter().filter(|&&s| s < 0).count();
    let json = serde_json::json!({
        "dims": DIMS,
        "runs": runs,
        "occupied_voxels": occupied.len(),
        "scf_gt_s_max": [cfg.s_max_planar, cfg.s_max_vertical],
        "scf_gt_median_ms": median(gt_ms.clone()),
        "scf_gt_min_ms": gt_ms.iter().cloned().fold(f64::INFINITY, f64::min),
        "propagate_anchors": N_ANCHORS,
        "propagate_interior_planar_anchors": interior,
        "propagate_new_voxels": n_new,
        "propagate_median_ms": median(prop_ms.clone()),
        "propagate_min_ms": prop_ms.iter().cloned().fold(f64::INFINITY, f64::min),
        "threads": 1,
    });
    println!("{json}");
}
