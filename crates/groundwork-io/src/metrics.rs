//! Scoring a mask against labels: the two papers' protocols, confusion counts and the
//! metrics both papers report. Beside the label classes it scores, so that every stage that
//! reports accuracy (the evaluation, the service's consumer) shares one definition.

use crate::LabelClass;
use serde::Serialize;

/// How vegetation is scored (the only class on which the two papers' protocols differ).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Protocol {
    /// GMM paper (and Patchwork++): vegetation is ignored.
    Gmm,
    /// TerraSeg: vegetation counts as non-ground.
    Terraseg,
}

impl std::fmt::Display for Protocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Gmm => "gmm",
            Self::Terraseg => "terraseg",
        })
    }
}

impl Protocol {
    /// `Some(true)` for ground, `Some(false)` for non-ground, `None` for ignored.
    pub fn truth(self, class: LabelClass) -> Option<bool> {
        match class {
            LabelClass::Ground => Some(true),
            LabelClass::NonGround => Some(false),
            LabelClass::Ignored => None,
            LabelClass::Vegetation => (self == Self::Terraseg).then_some(false),
        }
    }
}

/// Point counts of a binary ground / non-ground confusion matrix.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Confusion {
    /// Ground predicted as ground.
    pub tp: u64,
    /// Non-ground predicted as ground.
    pub fp: u64,
    /// Ground predicted as non-ground.
    pub fn_: u64,
    /// Non-ground predicted as non-ground.
    pub tn: u64,
    /// Points the protocol ignores.
    pub ignored: u64,
}

/// Metrics in percent. A metric whose denominator is zero is reported as 100 when the
/// numerator is zero too (nothing to get wrong) — see `ratio`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Metrics {
    /// Ground precision.
    pub precision: f64,
    /// Ground recall.
    pub recall: f64,
    /// Ground F1.
    pub f1: f64,
    /// Accuracy over non-ignored points.
    pub accuracy: f64,
    /// Ground IoU.
    pub iou_ground: f64,
    /// Non-ground IoU.
    pub iou_nonground: f64,
    /// Mean of the two IoUs.
    pub miou: f64,
}

fn ratio(num: u64, den: u64) -> f64 {
    if den == 0 {
        100.0
    } else {
        100.0 * num as f64 / den as f64
    }
}

impl Confusion {
    /// Counts predictions (probability ≥ `threshold` = ground) against harmonised labels.
    /// Panics never: extra predictions or labels beyond the shorter slice are ignored, and
    /// callers check lengths when reading the files.
    pub fn from_predictions(
        probs: &[f32],
        labels: &[LabelClass],
        protocol: Protocol,
        threshold: f32,
    ) -> Self {
        let mut c = Self::default();
        for (&p, &l) in probs.iter().zip(labels) {
            c.add(p >= threshold, protocol.truth(l));
        }
        c
    }

    /// Adds one point.
    #[inline]
    pub fn add(&mut self, predicted_ground: bool, truth: Option<bool>) {
        match (predicted_ground, truth) {
            (_, None) => self.ignored += 1,
            (true, Some(true)) => self.tp += 1,
            (true, Some(false)) => self.fp += 1,
            (false, Some(true)) => self.fn_ += 1,
            (false, Some(false)) => self.tn += 1,
        }
    }

    /// Pools another confusion into this one.
    pub fn merge(&mut self, o: &Self) {
        self.tp += o.tp;
        self.fp += o.fp;
        self.fn_ += o.fn_;
        self.tn += o.tn;
        self.ignored += o.ignored;
    }

    /// The metrics of these counts.
    pub fn metrics(&self) -> Metrics {
        let (tp, fp, fn_, tn) = (self.tp, self.fp, self.fn_, self.tn);
        let precision = ratio(tp, tp + fp);
        let recall = ratio(tp, tp + fn_);
        let f1 = if precision + recall > 0.0 {
            2.0 * precision * recall / (precision + recall)
        } else {
            0.0
        };
        let iou_ground = ratio(tp, tp + fp + fn_);
        let iou_nonground = ratio(tn, tn + fp + fn_);
        Metrics {
            precision,
            recall,
            f1,
            accuracy: ratio(tp + tn, tp + fp + fn_ + tn),
            iou_ground,
            iou_nonground,
            miou: (iou_ground + iou_nonground) / 2.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn protocols_differ_only_on_vegetation() {
        use LabelClass::*;
        for c in [Ground, NonGround, Ignored] {
            assert_eq!(Protocol::Gmm.truth(c), Protocol::Terraseg.truth(c));
        }
        assert_eq!(Protocol::Gmm.truth(Vegetation), None);
        assert_eq!(Protocol::Terraseg.truth(Vegetation), Some(false));
        assert_eq!(Protocol::Gmm.truth(Ground), Some(true));
        assert_eq!(Protocol::Gmm.truth(Ignored), None);
    }

    #[test]
    fn metrics_of_a_known_matrix() {
        // labels: road, road, car, car, vegetation, unlabeled
        let map = crate::LabelMap::semantickitti();
        let labels: Vec<LabelClass> = [40, 40, 10, 10, 70, 0].map(|l| map.class(l)).to_vec();
        let probs = [0.9, 0.2, 0.7, 0.1, 0.9, 0.9];
        let c = Confusion::from_predictions(&probs, &labels, Protocol::Gmm, 0.5);
        assert_eq!((c.tp, c.fn_, c.fp, c.tn, c.ignored), (1, 1, 1, 1, 2));
        let m = c.metrics();
        assert!((m.precision - 50.0).abs() < 1e-12);
        assert!((m.recall - 50.0).abs() < 1e-12);
        assert!((m.iou_ground - 100.0 / 3.0).abs() < 1e-12);
        assert!((m.accuracy - 50.0).abs() < 1e-12);
        let t = Confusion::from_predictions(&probs, &labels, Protocol::Terraseg, 0.5);
        assert_eq!((t.fp, t.ignored), (2, 1));
        let mut pooled = c;
        pooled.merge(&t);
        assert_eq!(pooled.tp, 2);
    }
}

/// How often points are ground at each probability: ten equal-width bins of the
/// probability, each with its points, their mean probability and the fraction that is
/// ground; scored points only (the protocol's ignored classes are left out).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Reliability {
    /// Points per bin ([0, 0.1), [0.1, 0.2), …, [0.9, 1]).
    pub points: [u64; 10],
    /// Sum of the probabilities per bin.
    pub probability_sum: [f64; 10],
    /// Ground points per bin.
    pub ground: [u64; 10],
}

/// One bin of a [`Reliability`], as a table prints it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ReliabilityBin {
    /// The bin's lower edge.
    pub from: f64,
    /// Points in it.
    pub points: u64,
    /// Their mean probability.
    pub mean_probability: f64,
    /// The fraction of them that is ground.
    pub ground_fraction: f64,
}

impl Reliability {
    /// Counts predictions against harmonised labels.
    pub fn from_predictions(probs: &[f32], labels: &[LabelClass], protocol: Protocol) -> Self {
        let mut r = Self::default();
        for (&p, &l) in probs.iter().zip(labels) {
            if let Some(truth) = protocol.truth(l) {
                let p = if p.is_finite() {
                    p.clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let b = ((p * 10.0) as usize).min(9);
                r.points[b] += 1;
                r.probability_sum[b] += f64::from(p);
                r.ground[b] += u64::from(truth);
            }
        }
        r
    }

    /// Pools another into this one.
    pub fn merge(&mut self, o: &Self) {
        for b in 0..10 {
            self.points[b] += o.points[b];
            self.probability_sum[b] += o.probability_sum[b];
            self.ground[b] += o.ground[b];
        }
    }

    /// The bins that hold points.
    pub fn bins(&self) -> Vec<ReliabilityBin> {
        (0..10)
            .filter(|&b| self.points[b] > 0)
            .map(|b| {
                let n = self.points[b] as f64;
                ReliabilityBin {
                    from: b as f64 / 10.0,
                    points: self.points[b],
                    mean_probability: self.probability_sum[b] / n,
                    ground_fraction: self.ground[b] as f64 / n,
                }
            })
            .collect()
    }

    /// Expected calibration error: the points' mean gap between probability and ground
    /// fraction, bin by bin (0: a probability says how often points are ground).
    pub fn expected_calibration_error(&self) -> f64 {
        let total: u64 = self.points.iter().sum();
        if total == 0 {
            return 0.0;
        }
        self.bins()
            .iter()
            .map(|b| {
                b.points as f64 / total as f64 * (b.mean_probability - b.ground_fraction).abs()
            })
            .sum()
    }
}
