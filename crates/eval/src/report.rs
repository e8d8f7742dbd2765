//! Serialisable evaluation report and its terminal table.
//!
//! All metrics are fractions in `[0, 1]` (multiply by 100 for the papers' tables). A metric that is
//! undefined (0/0 where the official numpy code yields NaN) is `NaN` in memory and `null` in JSON.

use crate::protocol::Protocol;
use serde::de::{MapAccess, Visitor};
use serde::ser::SerializeMap;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::fmt::Write as _;

/// Metrics of one evaluation (see [`crate::protocol`] for the formulas).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Protocol used (`"semantickitti"`, `"nuscenes-occupancy"`, `"occ3d"`).
    pub dataset: Protocol,
    /// Number of frames scored.
    pub frames: u64,
    /// Number of voxels that entered the confusion matrix.
    pub evaluated_voxels: u64,
    /// Evaluated voxels whose prediction was not a class index (scored as the empty class).
    pub invalid_predictions: u64,
    /// Completion (geometry) IoU: SemanticKITTI "IoU Cmpltn", nuScenes-Occupancy SC IoU, Occ3D
    /// occupied-vs-free IoU.
    #[serde(with = "nan_as_null")]
    pub iou: f64,
    /// Completion precision.
    #[serde(with = "nan_as_null")]
    pub precision: f64,
    /// Completion recall.
    #[serde(with = "nan_as_null")]
    pub recall: f64,
    /// Mean IoU over the protocol's mIoU classes.
    #[serde(with = "nan_as_null")]
    pub miou: f64,
    /// IoU of each mIoU class, in class order (a JSON object keeping that order).
    pub per_class: PerClass,
    /// Accumulated confusion matrix, rows = prediction, columns = ground truth; lets reports of
    /// several shards be merged with [`crate::Evaluator::from_report`].
    pub confusion: Vec<Vec<u64>>,
}

/// Ordered list of `(class name, IoU)`, serialised as a JSON object in class order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PerClass(pub Vec<(String, f64)>);

impl EvalReport {
    /// Share of the evaluated ground-truth voxels of the classes `gt_classes` that are predicted
    /// occupied (any class but 0), from the confusion matrix: the completion recall restricted to
    /// those classes. `NaN` when none of them was evaluated.
    pub fn occupied_recall_of(&self, gt_classes: &[usize]) -> f64 {
        let (mut found, mut total) = (0u64, 0u64);
        for (pred, row) in self.confusion.iter().enumerate() {
            for &gt in gt_classes {
                let n = row.get(gt).copied().unwrap_or(0);
                total += n;
                if pred != 0 {
                    found += n;
                }
            }
        }
        if total == 0 {
            f64::NAN
        } else {
            found as f64 / total as f64
        }
    }

    /// [`Self::occupied_recall_of`] over every class but empty and the ground classes (SemanticKITTI:
    /// [`crate::protocol::SEMANTIC_KITTI_GROUND_CLASSES`]): how much of what stands on the ground
    /// (vehicles, people, buildings, vegetation, fences, poles, signs) is found.
    pub fn non_ground_recall(&self, ground: &[usize]) -> f64 {
        let n = self.confusion.first().map_or(0, Vec::len);
        let classes: Vec<usize> = (1..n).filter(|c| !ground.contains(c)).collect();
        self.occupied_recall_of(&classes)
    }
}

impl PerClass {
    /// IoU of the class called `name`.
    pub fn get(&self, name: &str) -> Option<f64> {
        self.0.iter().find(|(n, _)| n == name).map(|&(_, v)| v)
    }
}

impl Serialize for PerClass {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut m = s.serialize_map(Some(self.0.len()))?;
        for (k, v) in &self.0 {
            m.serialize_entry(k, &finite_or_none(*v))?;
        }
        m.end()
    }
}

impl<'de> Deserialize<'de> for PerClass {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = PerClass;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an object of class name -> IoU (number or null)")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut a: A) -> Result<PerClass, A::Error> {
                let mut out = Vec::new();
                while let Some((k, v)) = a.next_entry::<String, Option<f64>>()? {
                    out.push((k, v.unwrap_or(f64::NAN)));
                }
                Ok(PerClass(out))
            }
        }
        d.deserialize_map(V)
    }
}

fn finite_or_none(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

mod nan_as_null {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};
    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        super::finite_or_none(*v).serialize(s)
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
    }
}

fn pct(v: f64) -> String {
    if v.is_finite() {
        format!("{:6.2}", v * 100.0)
    } else {
        "   n/a".to_string()
    }
}

/// Terminal table of a report: one line per mIoU class, then mIoU and the geometry metrics, in
/// percent (two decimals, as the official scripts print them); undefined values print as `n/a`.
pub fn format_table(r: &EvalReport) -> String {
    let width = r
        .per_class
        .0
        .iter()
        .map(|(n, _)| n.len())
        .chain([14])
        .max()
        .unwrap_or(14);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{} evaluation: {} frames, {} voxels evaluated",
        r.dataset.name(),
        r.frames,
        r.evaluated_voxels
    );
    let _ = writeln!(s, "{:<width$}  IoU (%)", "class");
    let _ = writeln!(s, "{}", "-".repeat(width + 9));
    for (name, iou) in &r.per_class.0 {
        let _ = writeln!(s, "{name:<width$}  {}", pct(*iou));
    }
    let _ = writeln!(s, "{}", "-".repeat(width + 9));
    for (name, v) in [
        ("mIoU", r.miou),
        ("completion IoU", r.iou),
        ("precision", r.precision),
        ("recall", r.recall),
    ] {
        let _ = writeln!(s, "{name:<width$}  {}", pct(v));
    }
    if r.invalid_predictions > 0 {
        let _ = writeln!(
            s,
            "warning: {} evaluated voxels had a prediction that is not a class (scored as empty)",
            r.invalid_predictions
        );
    }
    s
}
