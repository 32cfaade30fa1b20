//! The segmenter's parameters fitted to reference labels (the PseudoLabeler's, made by the
//! caller), with the mount fixed: a bounded coordinate descent on the agreement of the
//! segmenter's decisions with the labels over one part of the scans, and a held-out part
//! that decides which round's parameters are kept, so that the fit follows the sensor and
//! not the labeler's own mistakes.
//!
//! Deterministic: the segmenter gives the same bits on any number of threads, each scan is
//! segmented on its own (single frame, a fresh segmenter: no history, no height filter
//! state), agreement is counted in integers, and the knobs are tried in a fixed order.

use groundwork_core::Segmenter;
use groundwork_core::config::{GroundConfig, SegmenterConfig, Sigmoid, ZoneConfig};
use rayon::prelude::*;
use serde::Serialize;

use crate::CalibrateError;

/// One scan of the sample: its points (sensor frame) and the reference label of each
/// (ground or not).
#[derive(Debug, Clone, Copy)]
pub struct LabeledScan<'a> {
    /// Points, sensor frame, metres.
    pub points: &'a [[f32; 3]],
    /// Reference: ground per point, same length.
    pub ground: &'a [bool],
}

impl<'a> LabeledScan<'a> {
    /// Each scan of `scans` with its labels from `ground` (paired in order).
    pub fn pair(scans: &'a [Vec<[f32; 3]>], ground: &'a [Vec<bool>]) -> Vec<Self> {
        scans
            .iter()
            .zip(ground)
            .map(|(points, ground)| Self { points, ground })
            .collect()
    }
}

/// How the search runs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParamSearchConfig {
    /// Rounds over all knobs; round r steps by `STEPS[r]` of a knob's unit step.
    pub rounds: usize,
    /// Every this-many-th scan of the sample (the last of each group) is held out.
    pub held_out_every: usize,
    /// A move is taken only if it raises the fitted part's agreement (ground IoU, %) by
    /// more than this: smaller gains are the labels' noise.
    pub min_gain: f64,
    /// Only points where the labels are trusted are counted: the first ring of this width
    /// (m) around the sensor, then ring after ring outwards as long as the preset's
    /// decisions agree with the labels on at least `trust_agreement` (ground IoU, %) of the
    /// ring. The PseudoLabeler's
    /// elevation map is sure near the vehicle and can lose far ground on hills (synthetic
    /// Livox off-road: recall 99.9 % within 20 m, 48 % at 40–80 m, where the preset finds
    /// 85 %): where the two part, neither can be taken as the truth, and a fit to those
    /// labels would lose that ground too.
    pub trust_ring: f64,
    /// See `trust_ring`.
    pub trust_agreement: f64,
    /// The fitted parameters are kept only if they agree better with the held-out labels
    /// than the preset's by more than this (ground IoU, %); otherwise the preset's stay.
    /// Measured against the truth on 48 synthetic runs of every preset (docs/calibration.md):
    /// every fit kept with a held-out gain above 2.5 points gained, while below it as many
    /// fits lost as gained (down to −3.1 points), the labels' own mistakes fitted.
    pub min_held_out_gain: f64,
    /// Points a scan, on either part of the sample, that the labels or the preset call
    /// ground within the trusted range; with fewer the preset's parameters are kept unfitted.
    /// A sensor that first sees ground beyond the first ring leaves a few dozen such points
    /// a scan there, and a held-out gain of 2.5 points is then one patch of ground, not
    /// evidence (a Livox-like sensor pitched down 5°, seeing ground from 10.3 m: 78 points a
    /// held-out scan, a fit that passed the bar by 42 points and lost 15 IoU points against
    /// the truth). The sensors' ordinary sequences hold 1,300–48,000 (docs/calibration.md).
    pub min_trusted_points: u64,
    /// Also fit the layout of the two inner zones (boundary, rings, sectors). Off by
    /// default: measured against the truth on synthetic scans it gained up to 0.6 points
    /// and lost up to 0.3 (docs/calibration.md), the labels' own mistakes fitted too.
    pub fit_zones: bool,
}

impl Default for ParamSearchConfig {
    fn default() -> Self {
        Self {
            rounds: 3,
            held_out_every: 4,
            min_gain: 0.02,
            trust_ring: 10.0,
            trust_agreement: 90.0,
            min_held_out_gain: 2.5,
            min_trusted_points: 500,
            fit_zones: false,
        }
    }
}

impl ParamSearchConfig {
    /// Refuses settings the search cannot use, naming the field.
    pub fn validate(&self) -> Result<(), CalibrateError> {
        self.check()
            .map_err(|(field, why)| CalibrateError::Config(format!("params.{field}: {why}")))
    }

    /// The first field out of its range and why: for a front end that names the field by
    /// its own flag or keyword (the CLI's `--param-trust`, Python's `param_trust`).
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        let percent = |v: f64| (0.0..=100.0).contains(&v);
        if !(1..=STEPS.len()).contains(&self.rounds) {
            return Err(("rounds", format!("1–{}, not {}", STEPS.len(), self.rounds)));
        }
        if self.held_out_every < 2 {
            return Err((
                "held_out_every",
                format!("at least 2, not {}", self.held_out_every),
            ));
        }
        if !(self.min_gain.is_finite() && self.min_gain >= 0.0) {
            return Err(("min_gain", format!("a number ≥ 0, not {}", self.min_gain)));
        }
        if !(self.trust_ring >= 0.5 && self.trust_ring.is_finite()) {
            return Err((
                "trust_ring",
                format!("at least 0.5 m, not {}", self.trust_ring),
            ));
        }
        if !percent(self.trust_agreement) {
            return Err((
                "trust_agreement",
                format!(
                    "a ground IoU in percent (0–100), not {}",
                    self.trust_agreement
                ),
            ));
        }
        if !percent(self.min_held_out_gain) {
            return Err((
                "min_held_out_gain",
                format!(
                    "in ground IoU points (0–100), not {}",
                    self.min_held_out_gain
                ),
            ));
        }
        Ok(())
    }
}

/// A `[ground]` setting that differs between two configurations: its key in the table, its
/// new and its old value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundChange {
    /// The key in `[ground]`.
    pub key: &'static str,
    /// The value in the newer configuration.
    pub new: GroundValue,
    /// ... and in the older one.
    pub old: GroundValue,
}

/// A `[ground]` value, as the configuration holds it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GroundValue {
    /// A likelihood's sigmoid.
    Sigmoid(Sigmoid),
    /// A number held as f64.
    Number(f64),
    /// The ground threshold, held as f32.
    Threshold(f32),
}

/// TOML, the shortest form that reads back as the same bits (an f32 as the f32 it is).
impl std::fmt::Display for GroundValue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Sigmoid(s) => write!(f, "{{ alpha = {}, beta = {} }}", s.alpha, s.beta),
            Self::Number(v) => write!(f, "{v}"),
            Self::Threshold(v) => write!(f, "{v}"),
        }
    }
}

/// The settings a fit may change that differ between `old` and `new`, in the table's order:
/// what the CLI writes into the file and Python returns as keyword arguments.
pub fn ground_changes(old: &GroundConfig, new: &GroundConfig) -> Vec<GroundChange> {
    use GroundValue::{Number, Sigmoid as S, Threshold};
    [
        ("flatness", S(new.flatness), S(old.flatness)),
        ("orientation", S(new.orientation), S(old.orientation)),
        ("elevation", S(new.elevation), S(old.elevation)),
        (
            "elevation_window",
            Number(new.elevation_window),
            Number(old.elevation_window),
        ),
        (
            "outlier_threshold",
            Number(new.outlier_threshold),
            Number(old.outlier_threshold),
        ),
        (
            "ground_threshold",
            Threshold(new.ground_threshold),
            Threshold(old.ground_threshold),
        ),
    ]
    .into_iter()
    .filter(|(_, n, o)| n != o)
    .map(|(key, new, old)| GroundChange { key, new, old })
    .collect()
}

/// The step of each round, as a share of a knob's unit step (log knobs: the exponent).
const STEPS: [f64; 4] = [1.0, 0.5, 0.25, 0.125];
/// Moves in one direction per knob and round, at most.
const MAX_MOVES: usize = 8;

/// A parameter the search may move.
struct Knob {
    name: &'static str,
    get: fn(&SegmenterConfig) -> f64,
    set: fn(&mut SegmenterConfig, f64),
    /// Unit step: a factor for log knobs (×/÷), an amount for linear ones (±).
    unit: f64,
    log: bool,
    /// Bounds, absolute.
    lo: f64,
    hi: f64,
}

/// The knobs, in the order they are tried: the elevation likelihood and the decision
/// threshold first (they move most on a new mount or sensor), then the shape likelihoods,
/// then (`zones`) the inner zones' layout.
fn knobs(zones: bool) -> Vec<Knob> {
    let mut knobs = vec![
        Knob {
            name: "ground.elevation.beta",
            get: |c| c.ground.elevation.beta,
            set: |c, v| c.ground.elevation.beta = v,
            unit: 0.2,
            log: false,
            lo: 0.05,
            hi: 3.0,
        },
        Knob {
            name: "ground.elevation.alpha",
            get: |c| c.ground.elevation.alpha,
            set: |c, v| c.ground.elevation.alpha = v,
            unit: 1.6,
            log: true,
            lo: 0.5,
            hi: 64.0,
        },
        Knob {
            name: "ground.ground_threshold",
            get: |c| round_sig(f64::from(c.ground.ground_threshold)),
            set: |c, v| c.ground.ground_threshold = v as f32,
            unit: 0.1,
            log: false,
            lo: 0.2,
            hi: 0.8,
        },
        Knob {
            name: "ground.elevation_window",
            get: |c| c.ground.elevation_window,
            set: |c, v| c.ground.elevation_window = v,
            unit: 1.0,
            log: false,
            lo: 0.0,
            hi: 8.0,
        },
        Knob {
            name: "ground.orientation.beta",
            get: |c| c.ground.orientation.beta,
            set: |c, v| c.ground.orientation.beta = v,
            unit: 0.1,
            log: false,
            lo: 0.1,
            hi: 1.4,
        },
        Knob {
            name: "ground.orientation.alpha",
            get: |c| c.ground.orientation.alpha,
            set: |c, v| c.ground.orientation.alpha = v,
            unit: 1.6,
            log: true,
            lo: 0.5,
            hi: 64.0,
        },
        Knob {
            name: "ground.flatness.beta",
            get: |c| c.ground.flatness.beta,
            set: |c, v| c.ground.flatness.beta = v,
            unit: 1.6,
            log: true,
            lo: 1e-3,
            hi: 1.0,
        },
        Knob {
            name: "ground.flatness.alpha",
            get: |c| c.ground.flatness.alpha,
            set: |c, v| c.ground.flatness.alpha = v,
            unit: 1.6,
            log: true,
            lo: 1.0,
            hi: 1000.0,
        },
        Knob {
            name: "ground.outlier_threshold",
            get: |c| c.ground.outlier_threshold,
            set: |c, v| c.ground.outlier_threshold = v,
            unit: 0.2,
            log: false,
            lo: 0.1,
            hi: 2.0,
        },
    ];
    if zones {
        knobs.extend(zone_knobs());
    }
    knobs
}

/// The layout of the two inner zones (`ParamSearchConfig::fit_zones`).
fn zone_knobs() -> Vec<Knob> {
    // The layout of the two inner zones, where the labels are trusted: the sensor's
    // density decides how small a segment can be and still hold enough ground to fit.
    // The outer zones are left alone: the labels seldom hold that far.
    std::iter::once(Knob {
        name: "zones.boundaries[1]",
        get: |c| boundary(c, 1),
        set: |c, v| set_boundary(c, 1, v),
        unit: 1.25,
        log: true,
        lo: 1.0,
        hi: 100.0,
    })
    .chain(zone_layout_knobs::<0>("zones.rings[0]", "zones.sectors[0]"))
    .chain(zone_layout_knobs::<1>("zones.rings[1]", "zones.sectors[1]"))
    .collect()
}

/// The rings (±1, 1–8) and sectors (×/÷1.5, 4–360) of zone `Z`, named `rings` and `sectors`.
fn zone_layout_knobs<const Z: usize>(rings: &'static str, sectors: &'static str) -> [Knob; 2] {
    [
        Knob {
            name: rings,
            get: |c| layout(c, |z| &z.rings, Z),
            set: |c, v| set_layout(c, |z| &mut z.rings, Z, v),
            unit: 1.0,
            log: false,
            lo: 1.0,
            hi: 8.0,
        },
        Knob {
            name: sectors,
            get: |c| layout(c, |z| &z.sectors, Z),
            set: |c, v| set_layout(c, |z| &mut z.sectors, Z, v),
            unit: 1.5,
            log: true,
            lo: 4.0,
            hi: 360.0,
        },
    ]
}

/// Zone boundary `i` in use (NaN for a layout without one: the knob then never moves).
fn boundary(c: &SegmenterConfig, i: usize) -> f64 {
    c.zones
        .resolved_boundaries()
        .ok()
        .and_then(|b| b.get(i).copied())
        .unwrap_or(f64::NAN)
}

/// Sets zone boundary `i`, writing the boundaries out, kept at least 0.5 m from its
/// neighbours (the zones' order is never swapped).
fn set_boundary(c: &mut SegmenterConfig, i: usize, v: f64) {
    let Ok(mut b) = c.zones.resolved_boundaries() else {
        return;
    };
    if i == 0 || i + 1 >= b.len() {
        return;
    }
    b[i] = round_sig(v.clamp(b[i - 1] + 0.5, b[i + 1] - 0.5));
    c.zones.boundaries = Some(b);
}

/// Rings or sectors of zone `i` (NaN where the layout has no such zone).
fn layout(c: &SegmenterConfig, of: fn(&ZoneConfig) -> &Vec<u32>, i: usize) -> f64 {
    of(&c.zones).get(i).map_or(f64::NAN, |&n| f64::from(n))
}

/// Sets rings or sectors of zone `i` to the nearest whole number.
fn set_layout(c: &mut SegmenterConfig, of: fn(&mut ZoneConfig) -> &mut Vec<u32>, i: usize, v: f64) {
    if let Some(n) = of(&mut c.zones).get_mut(i) {
        *n = v.round().max(1.0) as u32;
    }
}

impl Knob {
    /// The value `moves` steps of `share` away from `v` (negative: down), within bounds,
    /// rounded to 4 significant digits so that the file written reads cleanly.
    fn stepped(&self, v: f64, share: f64, moves: i32) -> f64 {
        let w = if self.log {
            v * self.unit.powf(share * f64::from(moves))
        } else {
            v + self.unit * share * f64::from(moves)
        };
        round_sig(w.clamp(self.lo, self.hi))
    }
}

fn round_sig(v: f64) -> f64 {
    if v == 0.0 || !v.is_finite() {
        return v;
    }
    let digits = 4 - 1 - v.abs().log10().floor() as i32;
    let scale = 10f64.powi(digits);
    (v * scale).round() / scale
}

/// Agreement of decisions with reference labels, pooled over scans.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Agreement {
    /// Ground in both.
    pub both: u64,
    /// Ground in the segmenter's decisions only.
    pub segmenter_only: u64,
    /// Ground in the reference only.
    pub reference_only: u64,
}

impl Agreement {
    /// Ground IoU in percent (100 when neither calls anything ground).
    pub fn iou(&self) -> f64 {
        let union = self.both + self.segmenter_only + self.reference_only;
        if union == 0 {
            100.0
        } else {
            100.0 * self.both as f64 / union as f64
        }
    }

    fn add(self, o: Self) -> Self {
        Self {
            both: self.both + o.both,
            segmenter_only: self.segmenter_only + o.segmenter_only,
            reference_only: self.reference_only + o.reference_only,
        }
    }
}

/// Agreement after one round of the search (round 0: the preset).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RoundScore {
    /// The round.
    pub round: usize,
    /// Ground IoU (%) with the labels on the fitted part.
    pub fitted_iou: f64,
    /// The same on the held-out part.
    pub held_out_iou: f64,
}

/// One parameter the fit changed.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParamChange {
    /// Its path in the configuration (`ground.elevation.beta`).
    pub name: &'static str,
    /// The preset's value.
    pub old: f64,
    /// The fitted value.
    pub new: f64,
}

/// The outcome of a parameter fit.
#[derive(Debug, Clone, Serialize)]
pub struct ParamFit {
    /// The configuration to use (the preset's when `kept_preset`).
    #[serde(skip)]
    pub config: SegmenterConfig,
    /// Parameters that changed (empty when `kept_preset`).
    pub changed: Vec<ParamChange>,
    /// Agreement on the fitted part with the preset's parameters, and with the result.
    pub fitted_before: Agreement,
    /// The same with the fitted parameters.
    pub fitted_after: Agreement,
    /// Agreement on the held-out part, before and after.
    pub held_out_before: Agreement,
    /// The same with the fitted parameters.
    pub held_out_after: Agreement,
    /// Scans fitted on and held out.
    pub fitted_scans: usize,
    /// Scans held out.
    pub held_out_scans: usize,
    /// Segmenter runs over the fitted part (each a pass over its scans).
    pub evaluations: usize,
    /// Rounds run, and the round whose parameters were kept (0: the preset's).
    pub rounds: usize,
    /// See `rounds`.
    pub kept_round: usize,
    /// True when no round agreed better with the held-out labels than the preset (by more
    /// than `ParamSearchConfig::min_held_out_gain`), or when there was too little to fit to
    /// (`too_few_trusted_points`).
    pub kept_preset: bool,
    /// Points a scan called ground by the labels or the preset within the trusted range,
    /// the fewer of the two parts'.
    pub trusted_points_per_scan: f64,
    /// True when that is below `ParamSearchConfig::min_trusted_points`: no search was run.
    pub too_few_trusted_points: bool,
    /// `ParamSearchConfig::min_trusted_points` of the fit.
    pub trusted_points_needed: u64,
    /// `ParamSearchConfig::min_held_out_gain` of the fit.
    pub held_out_gain_needed: f64,
    /// Every round's agreement, the preset's first.
    pub history: Vec<RoundScore>,
    /// Only points within this horizontal distance of the sensor (m) were counted: where
    /// the preset and the labels agreed (`ParamSearchConfig::trust_ring`).
    pub trusted_range: f64,
    /// The preset's agreement with the labels, ring by ring, out to the first ring not
    /// trusted (ground IoU, %).
    pub ring_agreement: Vec<f64>,
}

/// Agreement of `cfg`'s single-frame decisions with the labels of `scans`, each scan
/// segmented on its own (in parallel).
pub fn agreement(
    cfg: &SegmenterConfig,
    scans: &[LabeledScan],
    max_range: f64,
) -> Result<Agreement, CalibrateError> {
    Ok(agreement_by_ring(cfg, scans, max_range, 1)?[0])
}

/// [`agreement`] in `rings` rings of `width` metres from the sensor (points beyond the last
/// are not counted).
pub fn agreement_by_ring(
    cfg: &SegmenterConfig,
    scans: &[LabeledScan],
    width: f64,
    rings: usize,
) -> Result<Vec<Agreement>, CalibrateError> {
    let threshold = cfg.decision_threshold();
    scans
        .par_iter()
        .map(|s| {
            let mut seg = Segmenter::new(cfg.clone())
                .map_err(|e| CalibrateError::Config(format!("fitted parameters: {e}")))?;
            let mut p = vec![0.0f32; s.points.len()];
            seg.segment(s.points, None, &mut p)
                .map_err(|e| CalibrateError::Refused(format!("a scan of the sample: {e}")))?;
            let mut a = vec![Agreement::default(); rings];
            let ring = s.points.iter().map(|q| {
                let r = f64::from(q[0]).hypot(f64::from(q[1]));
                (r / width) as usize
            });
            for ((&p, &g), ring) in p.iter().zip(s.ground).zip(ring) {
                let Some(a) = a.get_mut(ring) else {
                    continue;
                };
                match (p >= threshold, g) {
                    (true, true) => a.both += 1,
                    (true, false) => a.segmenter_only += 1,
                    (false, true) => a.reference_only += 1,
                    (false, false) => {}
                }
            }
            Ok(a)
        })
        .try_reduce(
            || vec![Agreement::default(); rings],
            |a, b| Ok(a.into_iter().zip(b).map(|(a, b)| a.add(b)).collect()),
        )
}

/// The refusal of a sample of `n` scans that cannot hold one in `every` out.
pub(crate) fn too_few_scans(n: usize, every: usize) -> CalibrateError {
    CalibrateError::Refused(format!(
        "{n} scans are too few to fit parameters: at least {every} are needed (one in \
         {every} is held out to judge the fit)"
    ))
}

/// Rings of the trust test: out to 500 m, beyond any sensor's ground.
const TRUST_REACH: f64 = 500.0;

/// Fits the knobs of `base` to the labels of `scans` (see the module notes). `progress` is
/// called with (evaluations done, evaluations at most).
pub fn fit_parameters(
    base: &SegmenterConfig,
    scans: &[LabeledScan],
    cfg: &ParamSearchConfig,
    progress: impl Fn(usize, usize),
) -> Result<ParamFit, CalibrateError> {
    cfg.validate()?;
    if let Some(s) = scans.iter().find(|s| s.points.len() != s.ground.len()) {
        return Err(CalibrateError::Config(format!(
            "a scan of {} points came with {} labels",
            s.points.len(),
            s.ground.len()
        )));
    }
    // The parameters are fitted to what they decide, the mixtures' labels: terrain
    // following, a later step that repairs many of the same misses (most of all far out),
    // would hide from the held-out guard what a fit gains, and keep a preset that loses
    // once the terrain no longer makes up for it (the solid-state sequence 04: 87 against
    // 94). The fitted configuration carries the preset's terrain again.
    let preset = base;
    let mut base = base.clone();
    base.terrain.enabled = false;
    let base = &base;
    let every = cfg.held_out_every;
    let held: Vec<LabeledScan> = scans
        .iter()
        .enumerate()
        .filter(|(k, _)| k % every == every - 1)
        .map(|(_, s)| *s)
        .collect();
    let fitted: Vec<LabeledScan> = scans
        .iter()
        .enumerate()
        .filter(|(k, _)| k % every != every - 1)
        .map(|(_, s)| *s)
        .collect();
    if held.is_empty() || fitted.is_empty() {
        return Err(too_few_scans(scans.len(), every));
    }
    let reference_ground: usize = scans
        .iter()
        .map(|s| s.ground.iter().filter(|&&g| g).count())
        .sum();
    if reference_ground == 0 {
        return Err(CalibrateError::Refused(
            "the reference labels call no point ground: nothing to fit to".into(),
        ));
    }

    // Where the labels are trusted (see `trust_ring`). The first ring always is: near the
    // vehicle the labeler is at its surest, and a preset that disagrees there is what most
    // needs the fit.
    // The preset's rings, per part, serve both the trust test and the agreements before
    // the search: one pass of the segmenter over the sample.
    let rings = (TRUST_REACH / cfg.trust_ring).ceil() as usize;
    let fitted_rings = agreement_by_ring(base, &fitted, cfg.trust_ring, rings)?;
    let held_rings = agreement_by_ring(base, &held, cfg.trust_ring, rings)?;
    let by_ring: Vec<Agreement> = fitted_rings
        .iter()
        .zip(&held_rings)
        .map(|(a, b)| a.add(*b))
        .collect();
    let trusted_rings = 1 + by_ring[1..]
        .iter()
        .take_while(|a| a.iou() >= cfg.trust_agreement)
        .count();
    let trusted_range = trusted_rings as f64 * cfg.trust_ring;
    let within = |r: &[Agreement]| {
        r[..trusted_rings]
            .iter()
            .fold(Agreement::default(), |a, b| a.add(*b))
    };
    // A configuration's agreement with some scans' labels over the trusted rings.
    let trusted =
        |c: &SegmenterConfig, part: &[LabeledScan]| -> Result<Agreement, CalibrateError> {
            Ok(within(&agreement_by_ring(
                c,
                part,
                cfg.trust_ring,
                trusted_rings,
            )?))
        };
    let knobs = knobs(cfg.fit_zones);
    let most = 1 + cfg.rounds * knobs.len() * 2 * MAX_MOVES;
    let mut evaluations = 1;
    progress(evaluations, most);
    let mut eval = |c: &SegmenterConfig| -> Result<Agreement, CalibrateError> {
        evaluations += 1;
        progress(evaluations, most);
        trusted(c, &fitted)
    };
    let fitted_before = within(&fitted_rings);
    let held_out_before = within(&held_rings);
    let per_scan = |a: &Agreement, scans: usize| {
        (a.both + a.segmenter_only + a.reference_only) as f64 / scans as f64
    };
    let trusted_points_per_scan =
        per_scan(&fitted_before, fitted.len()).min(per_scan(&held_out_before, held.len()));
    let too_few_trusted_points = trusted_points_per_scan < cfg.min_trusted_points as f64;
    // Too little to fit to: no round runs, and the preset's parameters stay.
    let search_rounds = if too_few_trusted_points {
        0
    } else {
        cfg.rounds
    };
    let (mut current, mut score) = (base.clone(), fitted_before);
    let mut best = (0, base.clone(), fitted_before, held_out_before);
    let mut history = vec![RoundScore {
        round: 0,
        fitted_iou: fitted_before.iou(),
        held_out_iou: held_out_before.iou(),
    }];
    let mut rounds = 0;
    for &share in &STEPS[..search_rounds] {
        rounds += 1;
        let mut moved = false;
        for knob in &knobs {
            // Up first, then down; in one direction as long as it keeps gaining.
            for dir in [1, -1] {
                let mut taken = false;
                for _ in 0..MAX_MOVES {
                    let v = (knob.get)(&current);
                    let w = knob.stepped(v, share, dir);
                    if w == v || !v.is_finite() {
                        break;
                    }
                    let mut trial = current.clone();
                    (knob.set)(&mut trial, w);
                    // A whole-number knob's half step, a boundary held by its neighbour:
                    // the same configuration again.
                    if trial == current || trial.validate().is_err() {
                        break;
                    }
                    let a = eval(&trial)?;
                    if a.iou() > score.iou() + cfg.min_gain {
                        (current, score, taken) = (trial, a, true);
                    } else {
                        break;
                    }
                }
                moved |= taken;
                if taken {
                    break; // the other direction cannot gain from the same start
                }
            }
        }
        if !moved {
            break;
        }
        // The held-out part decides which round is kept.
        let h = trusted(&current, &held)?;
        history.push(RoundScore {
            round: rounds,
            fitted_iou: score.iou(),
            held_out_iou: h.iou(),
        });
        if h.iou() > best.3.iou() && h.iou() > held_out_before.iou() + cfg.min_held_out_gain {
            best = (rounds, current.clone(), score, h);
        }
    }
    let (kept_round, mut config, fitted_after, held_out_after) = best;
    config.terrain = preset.terrain.clone();
    let changed = knobs
        .iter()
        .filter_map(|k| {
            let (old, new) = ((k.get)(base), (k.get)(&config));
            // NaN: a zone the layout does not have, never moved.
            (old != new && !(old.is_nan() && new.is_nan())).then_some(ParamChange {
                name: k.name,
                old,
                new,
            })
        })
        .collect();
    Ok(ParamFit {
        config,
        changed,
        fitted_before,
        fitted_after,
        held_out_before,
        held_out_after,
        fitted_scans: fitted.len(),
        held_out_scans: held.len(),
        evaluations,
        rounds,
        kept_round,
        kept_preset: kept_round == 0,
        trusted_points_per_scan,
        too_few_trusted_points,
        trusted_points_needed: cfg.min_trusted_points,
        held_out_gain_needed: cfg.min_held_out_gain,
        history,
        trusted_range,
        ring_agreement: by_ring
            .iter()
            .take(trusted_rings + 1)
            .map(Agreement::iou)
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ground_changes_list_what_moved_as_it_reads_back() {
        let old = SegmenterConfig::default().ground;
        assert!(ground_changes(&old, &old).is_empty());
        let mut new = old.clone();
        new.elevation.beta = 0.6;
        new.ground_threshold = 0.7;
        let changes = ground_changes(&old, &new);
        let keys: Vec<&str> = changes.iter().map(|c| c.key).collect();
        assert_eq!(keys, ["elevation", "ground_threshold"]);
        assert_eq!(
            changes[0].new.to_string(),
            format!("{{ alpha = {}, beta = 0.6 }}", old.elevation.alpha)
        );
        // The f32 threshold as the shortest text of the f32, not of its f64 (0.699999988…).
        assert_eq!(changes[1].new.to_string(), "0.7");
        assert_eq!(changes[1].old, GroundValue::Threshold(old.ground_threshold));
    }

    #[test]
    fn a_setting_out_of_range_is_named() {
        assert_eq!(ParamSearchConfig::default().check(), Ok(()));
        let field = |c: ParamSearchConfig| c.check().unwrap_err().0;
        let d = ParamSearchConfig::default;
        assert_eq!(field(ParamSearchConfig { rounds: 0, ..d() }), "rounds");
        assert_eq!(
            field(ParamSearchConfig {
                held_out_every: 1,
                ..d()
            }),
            "held_out_every"
        );
        assert_eq!(
            field(ParamSearchConfig {
                min_gain: f64::NAN,
                ..d()
            }),
            "min_gain"
        );
        assert_eq!(
            field(ParamSearchConfig {
                trust_agreement: 120.0,
                ..d()
            }),
            "trust_agreement"
        );
        assert_eq!(
            field(ParamSearchConfig {
                min_held_out_gain: 101.0,
                ..d()
            }),
            "min_held_out_gain"
        );
        let e = ParamSearchConfig {
            trust_ring: 0.1,
            ..d()
        }
        .validate()
        .unwrap_err();
        assert!(e.to_string().contains("params.trust_ring"), "{e}");
    }

    #[test]
    fn steps_stay_in_bounds_and_read_cleanly() {
        for k in knobs(true) {
            let base = SegmenterConfig::default();
            let v = (k.get)(&base);
            assert!(
                v >= k.lo && v <= k.hi,
                "{} default {v} outside bounds",
                k.name
            );
            let mut w = v;
            for _ in 0..100 {
                w = k.stepped(w, 1.0, 1);
            }
            assert_eq!(w, round_sig(k.hi), "{}", k.name);
            for _ in 0..200 {
                w = k.stepped(w, 1.0, -1);
            }
            assert_eq!(w, round_sig(k.lo), "{}", k.name);
        }
        assert_eq!(round_sig(0.123456), 0.1235);
        assert_eq!(round_sig(1234.5), 1235.0);
    }

    #[test]
    fn layout_knobs_keep_the_zones_in_order_and_whole() {
        let base = SegmenterConfig::default();
        let b = base.zones.resolved_boundaries().unwrap();
        let mut c = base.clone();
        // Far past the next boundary: held 0.5 m short of it, the others untouched.
        set_boundary(&mut c, 1, 1000.0);
        let moved = c.zones.resolved_boundaries().unwrap();
        assert_eq!(moved[1], round_sig(b[2] - 0.5));
        assert_eq!((moved[0], &moved[2..]), (b[0], &b[2..]));
        set_boundary(&mut c, 1, 0.0);
        assert_eq!(boundary(&c, 1), round_sig(b[0] + 0.5));
        assert!(c.validate().is_ok());
        // The model's edges are not layout knobs.
        let mut d = base.clone();
        set_boundary(&mut d, 0, 1.0);
        set_boundary(&mut d, b.len() - 1, 1.0);
        assert_eq!(d, base);
        // Whole numbers, at least one; a zone the layout lacks reads NaN and is never set.
        set_layout(&mut d, |z| &mut z.sectors, 0, 23.6);
        set_layout(&mut d, |z| &mut z.rings, 1, 0.2);
        assert_eq!((d.zones.sectors[0], d.zones.rings[1]), (24, 1));
        assert!(layout(&d, |z| &z.rings, 9).is_nan());
        set_layout(&mut d, |z| &mut z.rings, 9, 3.0);
        assert_eq!(d.zones.rings.len(), base.zones.rings.len());
    }

    #[test]
    fn too_few_scans_or_no_ground_are_refused_with_the_reason() {
        let pts = vec![[5.0f32, 0.0, -1.7]; 10];
        let g = vec![true; 10];
        let scan = LabeledScan {
            points: &pts,
            ground: &g,
        };
        let cfg = ParamSearchConfig::default();
        let base = SegmenterConfig::default();
        let e = fit_parameters(&base, &[scan; 3], &cfg, |_, _| {}).unwrap_err();
        assert!(e.to_string().contains("too few"), "{e}");
        let none = vec![false; 10];
        let blank = LabeledScan {
            points: &pts,
            ground: &none,
        };
        let e = fit_parameters(&base, &[blank; 4], &cfg, |_, _| {}).unwrap_err();
        assert!(e.to_string().contains("no point ground"), "{e}");
        let short = LabeledScan {
            points: &pts,
            ground: &none[..3],
        };
        let e = fit_parameters(&base, &[short; 4], &cfg, |_, _| {}).unwrap_err();
        assert!(
            e.to_string().contains("10 points came with 3 labels"),
            "{e}"
        );
    }
}
