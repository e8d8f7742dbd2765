//! Learning curves: `RUN/curves.png` from `RUN/train_log.csv` (the total loss and the sum of each
//! group of terms over the steps, log scale), with the validation scores in the title when
//! validation ran.

use anyhow::{Context, Result};
use occ_train::log::read_train_log;
use occ_viz::plot::{line_plot, PlotSpec, Series};
use std::path::{Path, PathBuf};

/// Line colours, one per series (the total first, in black).
const COLORS: [[u8; 3]; 10] = [
    [0, 0, 0],
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [23, 190, 207],
];

/// Writes `run/curves.png` from `run/train_log.csv`; `val` is the `(IoU, mIoU)` of the validation
/// that ran after training, if any. Returns the path written.
pub fn write_curves(run: &Path, val: Option<(f64, f64)>) -> Result<PathBuf> {
    let rows = read_train_log(&run.join("train_log.csv"))?;
    let mut series = vec![Series {
        name: "total".into(),
        color: COLORS[0],
        points: rows.iter().map(|r| (r.step as f64, r.loss)).collect(),
    }];
    for r in &rows {
        // Terms are grouped by the part before their first '.' (`occ.ce` + `occ.lovasz` + … = `occ`,
        // one line per anchor level, `scf`): 19 lines of SparseOcc++ would hide each other.
        let mut groups: Vec<(String, f64)> = Vec::new();
        for (name, v) in &r.terms {
            let g = name.split('.').next().unwrap_or(name).to_string();
            match groups.iter_mut().find(|(n, _)| *n == g) {
                Some((_, sum)) => *sum += v,
                None => groups.push((g, *v)),
            }
        }
        for (name, v) in &groups {
            let i = match series.iter().position(|s| &s.name == name) {
                Some(i) => i,
                None => {
                    series.push(Series {
                        name: name.clone(),
                        color: COLORS[series.len() % COLORS.len()],
                        points: Vec::new(),
                    });
                    series.len() - 1
                }
            };
            // Log scale: a term that is exactly 0 at a step is left out there.
            if *v > 0.0 {
                series[i].points.push((r.step as f64, *v));
            }
        }
    }
    let title = match val {
        Some((iou, miou)) => format!(
            "training loss ({} logged steps), validation IoU {iou:.3}, mIoU {miou:.3}",
            rows.len()
        ),
        None => format!("training loss ({} logged steps)", rows.len()),
    };
    let spec = PlotSpec {
        title,
        x_label: "step".into(),
        y_label: "loss".into(),
        log_x: false,
        log_y: true,
        series,
    };
    let img = line_plot(&spec, 1000, 600)?;
    let out = run.join("curves.png");
    occ_data::image::write_png(&out, &img).with_context(|| format!("writing {}", out.display()))?;
    Ok(out)
}
