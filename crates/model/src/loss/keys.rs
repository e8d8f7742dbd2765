//! The names of the loss terms a model returns ([`crate::output::ModelOutput::losses`]), typed: one
//! enum per family, each with the string the training log writes (`train_log.csv` columns, the
//! non-finite-loss message).

use std::fmt;

/// The four terms of the occupancy loss `L_occ` ([`super::occ_loss`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum OccTerm {
    /// Class-weighted cross-entropy: `ce`.
    Ce,
    /// Lovasz-softmax: `lovasz`.
    Lovasz,
    /// Geometric scene-class affinity: `geo_scal`.
    GeoScal,
    /// Semantic scene-class affinity: `sem_scal`.
    SemScal,
}

impl OccTerm {
    /// The term's name in logs.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ce => "ce",
            Self::Lovasz => "lovasz",
            Self::GeoScal => "geo_scal",
            Self::SemScal => "sem_scal",
        }
    }
}

/// The three set-prediction terms of SparseOcc's mask head, per decoder prediction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MaskTerm {
    /// Query classification cross-entropy: `mask_cls`.
    Class,
    /// Mask binary cross-entropy: `mask_bce`.
    Bce,
    /// Mask dice: `mask_dice`.
    Dice,
}

impl MaskTerm {
    /// The term's name in logs.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Class => "mask_cls",
            Self::Bce => "mask_bce",
            Self::Dice => "mask_dice",
        }
    }
}

/// One loss term of a model's output. [`fmt::Display`] gives its name in logs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LossKey {
    /// The dense baseline's voxel cross-entropy: `ce`.
    Ce,
    /// SparseOcc's coarse voxel cross-entropy: `coarse_ce`.
    CoarseCe,
    /// The LSS depth BCE (SparseOcc, dense baseline) or SparseOcc++'s depth gate: `depth`.
    Depth,
    /// SparseOcc++'s image semantic head: `sem2d`.
    Sem2d,
    /// SparseOcc++'s planar SCF bins: `scf.planar`.
    ScfPlanar,
    /// SparseOcc++'s vertical SCF bins: `scf.vertical`.
    ScfVertical,
    /// A term of `L_occ` on SparseOcc++'s final voxels: `occ.ce`, `occ.lovasz`, …
    Occ(OccTerm),
    /// A term of `L_occ` on SparseOcc++'s anchor level `l`: `anchor{l}.ce`, …
    Anchor(usize, OccTerm),
    /// A term of SparseOcc's mask head: on the last decoder prediction `mask_cls`, …; on the
    /// auxiliary prediction `i` (`aux = Some(i)`) `d{i}.mask_cls`, …
    Mask {
        /// The auxiliary decoder prediction, `None` for the last one.
        aux: Option<usize>,
        /// Which term.
        term: MaskTerm,
    },
}

impl fmt::Display for LossKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Ce => f.write_str("ce"),
            Self::CoarseCe => f.write_str("coarse_ce"),
            Self::Depth => f.write_str("depth"),
            Self::Sem2d => f.write_str("sem2d"),
            Self::ScfPlanar => f.write_str("scf.planar"),
            Self::ScfVertical => f.write_str("scf.vertical"),
            Self::Occ(t) => write!(f, "occ.{}", t.as_str()),
            Self::Anchor(l, t) => write!(f, "anchor{l}.{}", t.as_str()),
            Self::Mask { aux: None, term } => f.write_str(term.as_str()),
            Self::Mask { aux: Some(i), term } => write!(f, "d{i}.{}", term.as_str()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_print_the_names_of_the_training_log() {
        let cases = [
            (LossKey::Ce, "ce"),
            (LossKey::CoarseCe, "coarse_ce"),
            (LossKey::Depth, "depth"),
            (LossKey::Sem2d, "sem2d"),
            (LossKey::ScfPlanar, "scf.planar"),
            (LossKey::ScfVertical, "scf.vertical"),
            (LossKey::Occ(OccTerm::Ce), "occ.ce"),
            (LossKey::Occ(OccTerm::SemScal), "occ.sem_scal"),
            (LossKey::Anchor(2, OccTerm::GeoScal), "anchor2.geo_scal"),
            (LossKey::Anchor(0, OccTerm::Lovasz), "anchor0.lovasz"),
            (
                LossKey::Mask {
                    aux: None,
                    term: MaskTerm::Class,
                },
                "mask_cls",
            ),
            (
                LossKey::Mask {
                    aux: Some(1),
                    term: MaskTerm::Dice,
                },
                "d1.mask_dice",
            ),
            (
                LossKey::Mask {
                    aux: Some(0),
                    term: MaskTerm::Bce,
                },
                "d0.mask_bce",
            ),
        ];
        for (key, name) in cases {
            assert_eq!(key.to_string(), name);
        }
    }
}
