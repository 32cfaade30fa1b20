//! Scoring object proposals against instance labels (SemanticKITTI: instance id in the high
//! 16 bits of a label). An object is found when one cluster's points and the object's
//! points have a point IoU above 0.5 (the panoptic-quality matching rule: at most one
//! cluster can pass it per object).

use std::collections::BTreeMap;

use groundwork_detect::Proposal;
use serde::Serialize;

/// The object classes scored, by SemanticKITTI class ids (static and moving).
pub const OBJECT_CLASSES: &[(&str, &[u16])] = &[
    ("car", &[10, 252]),
    ("person", &[30, 254]),
    ("cyclist", &[31, 32, 253, 255]),
    ("other-vehicle", &[13, 18, 20, 257, 258, 259]),
];

/// Horizontal distance bands of the report, metres.
pub const DISTANCE_BANDS: &[(f32, f32)] = &[
    (0.0, 10.0),
    (10.0, 20.0),
    (20.0, 30.0),
    (30.0, 40.0),
    (40.0, f32::INFINITY),
];

fn class_name(class: u16) -> Option<&'static str> {
    OBJECT_CLASSES
        .iter()
        .find(|(_, ids)| ids.contains(&class))
        .map(|(n, _)| *n)
}

/// One labeled object and what became of it.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ObjectMatch {
    /// Scan it is in.
    pub scan: String,
    /// Class name ([`OBJECT_CLASSES`]).
    pub class: &'static str,
    /// The raw label (class id | instance id << 16).
    pub label: u32,
    /// Its points.
    pub points: usize,
    /// Horizontal distance of its centroid from the sensor, metres.
    pub range: f32,
    /// Point IoU with its best cluster.
    pub iou: f64,
    /// That cluster's proposal id if the IoU is above 0.5, else 0.
    pub proposal: u32,
}

/// Objects and proposals of one or more scans.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ObjectScore {
    /// Every labeled object with at least the minimum number of points.
    pub objects: Vec<ObjectMatch>,
    /// Proposals made.
    pub proposals: usize,
    /// Proposals with no labeled object (IoU ≤ 0.5 with all): poles, trunks, walls and
    /// signs carry no instance labels, so many of these are real but unlabeled things.
    pub unmatched_proposals: usize,
    /// Of those, the ones with no flag (object-like).
    pub unmatched_object_like: usize,
}

/// Matches the clusters of one scan against its labeled objects. `labels` are raw records,
/// `clusters` the detector's ids per point, `xy` the points' horizontal coordinates (any
/// frame centred on the sensor); objects with fewer than `min_points` are not scored.
pub fn score_objects(
    scan: &str,
    labels: &[u32],
    clusters: &[u32],
    xy: &[[f32; 2]],
    proposals: &[Proposal],
    min_points: usize,
) -> ObjectScore {
    // Per object: its points, centroid sum and overlap per cluster.
    #[derive(Default)]
    struct Acc {
        points: usize,
        sum: [f64; 2],
        overlap: BTreeMap<u32, usize>,
    }
    let mut objects: BTreeMap<u32, Acc> = BTreeMap::new();
    let mut cluster_size: BTreeMap<u32, usize> = BTreeMap::new();
    for ((&l, &c), p) in labels.iter().zip(clusters).zip(xy) {
        if c > 0 {
            *cluster_size.entry(c).or_default() += 1;
        }
        if l >> 16 == 0 || class_name(l as u16).is_none() {
            continue;
        }
        let a = objects.entry(l).or_default();
        a.points += 1;
        a.sum[0] += f64::from(p[0]);
        a.sum[1] += f64::from(p[1]);
        if c > 0 {
            *a.overlap.entry(c).or_default() += 1;
        }
    }
    let iou = |a: &Acc, c: u32, o: usize| {
        o as f64 / (a.points + cluster_size.get(&c).copied().unwrap_or(0) - o) as f64
    };
    let mut matched_proposals = std::collections::BTreeSet::new();
    let mut out = ObjectScore {
        proposals: proposals.len(),
        ..Default::default()
    };
    for (&label, a) in &objects {
        let best = a
            .overlap
            .iter()
            .map(|(&c, &o)| (iou(a, c, o), c))
            .max_by(|x, y| x.0.total_cmp(&y.0).then(y.1.cmp(&x.1)));
        let (best_iou, cluster) = best.unwrap_or((0.0, 0));
        if best_iou > 0.5 {
            matched_proposals.insert(cluster);
        }
        if a.points < min_points {
            continue;
        }
        let n = a.points as f64;
        out.objects.push(ObjectMatch {
            scan: scan.to_string(),
            class: class_name(label as u16).unwrap_or("other"),
            label,
            points: a.points,
            range: ((a.sum[0] / n).hypot(a.sum[1] / n)) as f32,
            iou: best_iou,
            proposal: if best_iou > 0.5 { cluster } else { 0 },
        });
    }
    for p in proposals {
        if !matched_proposals.contains(&p.id) {
            out.unmatched_proposals += 1;
            if p.flags.is_object_like() {
                out.unmatched_object_like += 1;
            }
        }
    }
    out
}

impl ObjectScore {
    /// Pools another scan's score into this one.
    pub fn merge(&mut self, o: ObjectScore) {
        self.objects.extend(o.objects);
        self.proposals += o.proposals;
        self.unmatched_proposals += o.unmatched_proposals;
        self.unmatched_object_like += o.unmatched_object_like;
    }

    /// (found, total) objects of `class` within `max_range` metres.
    pub fn recall(&self, class: &str, max_range: f32) -> (usize, usize) {
        let of: Vec<_> = self
            .objects
            .iter()
            .filter(|o| o.class == class && o.range <= max_range)
            .collect();
        (of.iter().filter(|o| o.proposal > 0).count(), of.len())
    }

    /// A table: found / labeled per class and distance band, and the proposals' fate.
    pub fn table(&self) -> String {
        let mut s = String::from("class           ");
        for (lo, hi) in DISTANCE_BANDS {
            let band = if hi.is_finite() {
                format!("{lo:.0}-{hi:.0} m")
            } else {
                format!(">{lo:.0} m")
            };
            s += &format!("{band:>9}");
        }
        s += "      all\n";
        for (class, _) in OBJECT_CLASSES {
            let of: Vec<_> = self.objects.iter().filter(|o| o.class == *class).collect();
            if of.is_empty() {
                continue;
            }
            s += &format!("{class:16}");
            let cell = |v: Vec<&&ObjectMatch>| {
                let found = v.iter().filter(|o| o.proposal > 0).count();
                format!("{:>9}", format!("{found}/{}", v.len()))
            };
            for (lo, hi) in DISTANCE_BANDS {
                s += &cell(
                    of.iter()
                        .filter(|o| o.range >= *lo && o.range < *hi)
                        .collect(),
                );
            }
            s += &cell(of.iter().collect());
            s += "\n";
        }
        s += &format!(
            "proposals {}, matching no labeled object {} (object-like {})\n",
            self.proposals, self.unmatched_proposals, self.unmatched_object_like
        );
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use groundwork_detect::ProposalFlags;

    fn proposal(id: u32) -> Proposal {
        Proposal {
            id,
            centroid: [0.0; 3],
            center: [0.0; 2],
            yaw: 0.0,
            length: 1.0,
            width: 1.0,
            ground_z: 0.0,
            bottom: 0.0,
            height: 1.0,
            points: 1,
            flags: ProposalFlags::default(),
        }
    }

    #[test]
    fn an_object_is_found_only_above_half_iou() {
        let car = 10 | (5 << 16);
        let person = 30 | (6 << 16);
        // Car: 4 points, 3 in cluster 1 (with 1 road point): IoU 3/5. Person: 2 points,
        // split over clusters 2 and 3: IoU 1/2, not found.
        let labels = [car, car, car, car, 40, person, person];
        let clusters = [1, 1, 1, 0, 1, 2, 3];
        let xy = [[10.0, 0.0]; 7];
        let props: Vec<_> = (1..=3).map(proposal).collect();
        let s = score_objects("s", &labels, &clusters, &xy, &props, 1);
        assert_eq!(s.recall("car", 40.0), (1, 1));
        assert_eq!(s.recall("person", 40.0), (0, 1));
        assert!((s.objects[0].iou - 0.6).abs() < 1e-12);
        assert_eq!(s.unmatched_proposals, 2);
        // Too few points: not scored, but still matches its proposal.
        let s = score_objects("s", &labels, &clusters, &xy, &props, 5);
        assert_eq!(s.objects.len(), 0);
        assert_eq!(s.unmatched_proposals, 2);
        assert!(s.table().contains("proposals 3"));
    }
}
