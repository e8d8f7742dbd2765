//! Reading `train_log.csv` back (the trainer writes it: `step,lr,loss,grad_norm,seconds,terms`,
//! `terms` as `name=value` pairs joined by `;`), for learning curves.

use crate::error::TrainError;
use std::path::Path;

/// One logged step.
#[derive(Clone, Debug, PartialEq)]
pub struct LogRow {
    /// Step number (1-based, after the update).
    pub step: usize,
    /// Learning rate of the step.
    pub lr: f64,
    /// Total loss.
    pub loss: f64,
    /// Global gradient norm before clipping.
    pub grad_norm: f64,
    /// The loss terms, in the order the model returned them.
    pub terms: Vec<(String, f64)>,
}

/// Parses a training log. A repeated header (a resumed run of an older version) is skipped; a row
/// that does not parse is an error naming the file and the line.
pub fn read_train_log(path: &Path) -> Result<Vec<LogRow>, TrainError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| TrainError::Data(format!("{}: {e}", path.display())))?;
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with("step,") {
            continue;
        }
        let bad = |what: &str| {
            TrainError::Data(format!(
                "{} line {}: {what} in {line:?}",
                path.display(),
                i + 1
            ))
        };
        let f: Vec<&str> = line.splitn(6, ',').collect();
        if f.len() < 5 {
            return Err(bad("fewer than 5 fields"));
        }
        let num = |s: &str, name: &str| {
            s.parse::<f64>()
                .map_err(|_| bad(&format!("{name} is not a number")))
        };
        let mut terms = Vec::new();
        for t in f.get(5).copied().unwrap_or("").split(';') {
            if t.is_empty() {
                continue;
            }
            let (k, v) = t.split_once('=').ok_or_else(|| bad("a term without '='"))?;
            terms.push((k.to_string(), num(v, k)?));
        }
        rows.push(LogRow {
            step: f[0].parse().map_err(|_| bad("step is not an integer"))?,
            lr: num(f[1], "lr")?,
            loss: num(f[2], "loss")?,
            grad_norm: num(f[3], "grad_norm")?,
            terms,
        });
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_rows_and_terms_and_names_bad_lines() {
        let dir = std::env::temp_dir().join(format!("occ_train_log_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("train_log.csv");
        std::fs::write(
            &p,
            "step,lr,loss,grad_norm,seconds,terms\n5,3.0e-4,2.5,1.25,0.8,ce=1.50000;lovasz=1.00000\n\
             10,2.9e-4,2.0,1.0,0.7,\n",
        )
        .unwrap();
        let rows = read_train_log(&p).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].step, 5);
        assert_eq!(
            rows[0].terms,
            vec![("ce".to_string(), 1.5), ("lovasz".to_string(), 1.0)]
        );
        assert!(rows[1].terms.is_empty() && (rows[1].loss - 2.0).abs() < 1e-12);
        std::fs::write(&p, "step,lr,loss,grad_norm,seconds,terms\n5,x,2.5,1,0.8,\n").unwrap();
        let e = read_train_log(&p).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("lr"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
