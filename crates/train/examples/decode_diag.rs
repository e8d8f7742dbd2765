//! Diagnostic: is the occupancy of the objects in a trained run's class probabilities, and only lost
//! by the argmax decoding? Scores the held-out frames with the argmax (what `infer` writes) and with
//! an occupancy-first decoding (occupied when `1 - p_empty > tau`, then the most likely non-empty
//! class), on the valid voxels, test-time mirror included.
//!
//! `cargo run --release -p occ-train --example decode_diag -- RUN_DIR DATA_DIR SEQ [FRAMES]`
mod common;

use burn::backend::NdArray;
use occ_train::dataset::collate;
use occ_train::mirror::mirror_sample_y;

type B = NdArray<f32>;

/// Ground classes of the SemanticKITTI learning map (road, parking, sidewalk, other-ground, terrain).
const GROUND: [usize; 5] = [9, 10, 11, 12, 17];

struct Score {
    conf: Vec<Vec<u64>>,
}

impl Score {
    fn new(nc: usize) -> Self {
        Self {
            conf: vec![vec![0; nc]; nc],
        }
    }
    fn report(&self, name: &str) {
        let nc = self.conf.len();
        let (mut tp, mut fp, mut fnn) = (0u64, 0u64, 0u64);
        let (mut ng_total, mut ng_found) = (0u64, 0u64);
        for g in 0..nc {
            for p in 0..nc {
                let n = self.conf[g][p];
                match (g != 0, p != 0) {
                    (true, true) => tp += n,
                    (false, true) => fp += n,
                    (true, false) => fnn += n,
                    _ => {}
                }
                if g != 0 && !GROUND.contains(&g) {
                    ng_total += n;
                    if p != 0 {
                        ng_found += n;
                    }
                }
            }
        }
        let mut ious = Vec::new();
        for c in 1..nc {
            let tpc = self.conf[c][c];
            let row: u64 = self.conf[c].iter().sum();
            let col: u64 = (0..nc).map(|g| self.conf[g][c]).sum();
            let union = row + col - tpc;
            if union > 0 {
                ious.push(tpc as f64 / union as f64);
            }
        }
        let miou = ious.iter().sum::<f64>() / (nc - 1) as f64;
        println!(
            "{name:>14}: IoU {:.3}  precision {:.3}  recall {:.3}  mIoU(19) {:.3}  non-ground recall {:.3}",
            tp as f64 / (tp + fp + fnn).max(1) as f64,
            tp as f64 / (tp + fp).max(1) as f64,
            tp as f64 / (tp + fnn).max(1) as f64,
            miou,
            ng_found as f64 / ng_total.max(1) as f64
        );
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let device = Default::default();
    let (cfg, grid, model, ds, frames) = common::open_run::<B>("decode_diag", &device)?;
    let nc = cfg.model.num_classes;
    let taus = [0.5, 0.4, 0.3, 0.25, 0.2, 0.15, 0.1];
    let mut argmax = Score::new(nc);
    let mut occ_first: Vec<Score> = taus.iter().map(|_| Score::new(nc)).collect();
    // Histogram of p_occ (10 bins) of valid non-ground occupied voxels; bin 0 also holds the ones
    // outside the predicted set.
    let mut hist = [0u64; 11];
    let [nx, ny, nz] = grid.dims;
    for i in 0..frames.min(ds.len()) {
        let s = ds.load::<rand_chacha::ChaCha8Rng>(i, None)?;
        let target = s.target.clone().ok_or("frame without labels")?;
        let probs_of =
            |s: &occ_train::dataset::Sample| -> Result<Vec<f32>, Box<dyn std::error::Error>> {
                let mut batch = collate::<B>(std::slice::from_ref(s), grid, &device)?;
                batch.target = None;
                let out = model.forward(&batch)?;
                Ok(out
                    .dense_probabilities(1, grid.dims)
                    .pop()
                    .unwrap_or_default())
            };
        let p = probs_of(&s)?;
        let mut m = s.clone();
        m.target = None;
        mirror_sample_y(&mut m, &grid)?;
        let pm = probs_of(&m)?;
        for x in 0..nx {
            for y in 0..ny {
                for z in 0..nz {
                    let v = (x * ny + y) * nz + z;
                    let g = target[v];
                    if g == 255 {
                        continue;
                    }
                    let vm = (x * ny + (ny - 1 - y)) * nz + z;
                    let mut q = vec![0f32; nc];
                    for k in 0..nc {
                        q[k] = p[v * nc + k] + pm[vm * nc + k];
                    }
                    let total: f32 = q.iter().sum();
                    let best = (0..nc).max_by(|&a, &b| q[a].total_cmp(&q[b])).unwrap_or(0);
                    let best = if total > 0.0 { best } else { 0 };
                    argmax.conf[g as usize][best] += 1;
                    let p_occ = if total > 0.0 {
                        (total - q[0]) / total
                    } else {
                        0.0
                    };
                    let best_occ = (1..nc).max_by(|&a, &b| q[a].total_cmp(&q[b])).unwrap_or(1);
                    for (t, sc) in taus.iter().zip(&mut occ_first) {
                        let pred = if total > 0.0 && p_occ > *t {
                            best_occ
                        } else {
                            0
                        };
                        sc.conf[g as usize][pred] += 1;
                    }
                    if g != 0 && !GROUND.contains(&(g as usize)) {
                        let b = if total > 0.0 {
                            1 + ((p_occ * 10.0) as usize).min(9)
                        } else {
                            0
                        };
                        hist[b] += 1;
                    }
                }
            }
        }
        eprintln!("frame {i} done");
    }
    argmax.report("argmax");
    for (t, sc) in taus.iter().zip(&occ_first) {
        sc.report(&format!("p_occ > {t}"));
    }
    let n: u64 = hist.iter().sum();
    println!(
        "valid non-ground occupied voxels: {n}; outside the predicted set {:.3}; p_occ deciles of the rest: {}",
        hist[0] as f64 / n.max(1) as f64,
        hist[1..]
            .iter()
            .map(|h| format!("{:.3}", *h as f64 / n.max(1) as f64))
            .collect::<Vec<_>>()
            .join(" ")
    );
    Ok(())
}
