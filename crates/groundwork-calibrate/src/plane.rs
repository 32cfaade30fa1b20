//! The ground plane of one scan by consensus, in the sensor frame.
//!
//! RANSAC over the points of a range band, keeping only planes whose normal lies within a cone
//! around the prior's vertical (walls are never ground) and that pass below the sensor. The
//! score counts a plane's inliers and subtracts the points well below it, so that the lowest
//! well-supported plane wins: a kerb top, a loading dock or the roofs of parked cars all have
//! the road below them. The winner is refined by least squares on its inliers, then once more
//! over the band where the sensor actually sees that ground (from its first ground return
//! outward), because the ground near the vehicle is the ground the mount stands on, and
//! terrain far out may climb or fall away: the tangent below the sensor of a surface that
//! bends with the terrain, its slope across the vehicle from the lane ahead and behind.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::CalibrateError;

/// How one scan's ground plane is searched for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlaneSearchConfig {
    /// Largest angle between a plane's normal and the prior mount's vertical, radians. A
    /// prior that is wrong by more than this finds no ground or the wrong ground.
    pub max_tilt: f64,
    /// Candidate points lie this far from the sensor or farther, metres (the ego vehicle
    /// and the sensor's own housing are closer).
    pub min_range: f64,
    /// ... and no farther than this, metres.
    pub max_range: f64,
    /// The hypotheses are drawn from and scored on points this close to the sensor,
    /// metres (all of the band when too few are).
    pub coarse_range: f64,
    /// After the first fit, the plane is fitted again over ground from where the sensor
    /// first sees it to this many metres beyond (horizontal distance).
    pub band_width: f64,
    /// A point within this distance of a plane supports it, metres: the sensor's noise and
    /// a road's camber, but less than half a kerb (a wider band lets one tilted plane hold
    /// the road and the sidewalk).
    pub inlier_distance: f64,
    /// A point farther than this below a plane speaks against it (the ground is the lowest
    /// surface), metres.
    pub below_distance: f64,
    /// The refinement looks for the lowest dense layer of points within this distance of
    /// the plane, metres (a road below its sidewalks).
    pub layer_window: f64,
    /// A layer is dense when its peak holds at least this share of the densest layer's.
    pub layer_share: f64,
    /// The ground the mount stands on: one plane over the band, or the tangent below the
    /// sensor of a quadratic surface over it.
    pub surface: Surface,
    /// Points this far from the quadratic surface have no say in it (Tukey's constant),
    /// metres.
    pub surface_tolerance: f64,
    /// ... and only within this range, metres: rolling terrain falls away below the plane
    /// the vehicle stands on farther out.
    pub below_range: f64,
    /// The tangent of the curved surface is used only where the plane's leverage (see
    /// `max_leverage`) is at most this; otherwise the plane.
    pub tangent_max_leverage: f64,
    /// What one point below costs a plane, in inliers.
    pub below_penalty: f64,
    /// RANSAC hypotheses per scan.
    pub hypotheses: u32,
    /// Candidate points the hypotheses are scored on (drawn at random, seeded).
    pub sample_size: usize,
    /// A plane with fewer inliers is no ground.
    pub min_inliers: usize,
    /// ... nor one that holds a smaller share of the band's points.
    pub min_inlier_share: f64,
    /// Ground seen only far from the sensor and over a short stretch cannot separate height
    /// from pitch: a plane is refused when the sensor's foot lies more than this many
    /// standard deviations of the inliers' spread from their centre (the leverage of the
    /// height, √(1 + mᵀC⁻¹m) with m, C the mean and covariance of the inliers in the plane).
    pub max_leverage: f64,
    /// Plausible sensor heights above the ground, metres.
    pub height_limits: [f64; 2],
    /// The tangent's slope across the vehicle is taken from ground ahead and behind it, no
    /// farther than this to either side (weights fall smoothly to zero there), metres: the
    /// lane its wheels stand on. A crowned road slopes the other way beyond its centre line,
    /// and a surface over both lanes tilts the mount toward the crown (up to 0.9° on the
    /// synthetic streets). 0: the quadratic over all the ground, as for a sensor that sees
    /// its lane on one side only.
    pub lane_half_width: f64,
}

impl Default for PlaneSearchConfig {
    fn default() -> Self {
        Self {
            max_tilt: 20f64.to_radians(),
            min_range: 1.0,
            max_range: 60.0,
            coarse_range: 12.0,
            band_width: 15.0,
            inlier_distance: 0.06,
            below_distance: 0.3,
            layer_window: 0.25,
            layer_share: 0.3,
            surface: Surface::Tangent,
            surface_tolerance: 0.12,
            tangent_max_leverage: 4.0,
            below_range: 20.0,
            below_penalty: 3.0,
            hypotheses: 500,
            sample_size: 4000,
            min_inliers: 200,
            min_inlier_share: 0.05,
            max_leverage: 15.0,
            height_limits: [0.05, 10.0],
            lane_half_width: 2.0,
        }
    }
}

impl PlaneSearchConfig {
    /// Refuses settings that cannot find a plane, by field name.
    pub fn validate(&self) -> Result<(), CalibrateError> {
        let bad =
            |field: &str, why: &str| Err(CalibrateError::Config(format!("plane.{field}: {why}")));
        let finite_pos = |v: f64| v.is_finite() && v > 0.0;
        if !(finite_pos(self.max_tilt) && self.max_tilt < std::f64::consts::FRAC_PI_2) {
            return bad("max_tilt", "must be in (0, π/2) radians");
        }
        if !(self.min_range >= 0.0 && self.max_range > self.min_range && self.max_range.is_finite())
        {
            return bad(
                "min_range/max_range",
                "need 0 ≤ min_range < max_range, finite",
            );
        }
        for (f, v) in [
            ("band_width", self.band_width),
            ("coarse_range", self.coarse_range),
            ("inlier_distance", self.inlier_distance),
            ("below_distance", self.below_distance),
            ("below_range", self.below_range),
            ("layer_window", self.layer_window),
            ("surface_tolerance", self.surface_tolerance),
            ("tangent_max_leverage", self.tangent_max_leverage),
            ("max_leverage", self.max_leverage),
        ] {
            if !finite_pos(v) {
                return bad(f, "must be finite and > 0");
            }
        }
        if !(self.below_penalty.is_finite() && self.below_penalty >= 0.0) {
            return bad("below_penalty", "must be finite and ≥ 0");
        }
        if !(self.lane_half_width.is_finite() && self.lane_half_width >= 0.0) {
            return bad("lane_half_width", "must be finite and ≥ 0 (0: no lane)");
        }
        if self.hypotheses == 0 || self.sample_size < 3 {
            return bad(
                "hypotheses/sample_size",
                "need ≥ 1 hypothesis and ≥ 3 samples",
            );
        }
        if !(self.layer_share > 0.0 && self.layer_share <= 1.0) {
            return bad("layer_share", "must be in (0, 1]");
        }
        if !(0.0..=1.0).contains(&self.min_inlier_share) {
            return bad("min_inlier_share", "must be in [0, 1]");
        }
        let [lo, hi] = self.height_limits;
        if !(lo >= 0.0 && hi > lo && hi.is_finite()) {
            return bad("height_limits", "need 0 ≤ low < high, finite");
        }
        Ok(())
    }
}

/// What surface the ground near the sensor is taken to be.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Surface {
    /// One plane over the band.
    Plane,
    /// A quadratic surface over the band (rolling terrain, a crowned road), of which the
    /// plane touching it below the sensor is the mount's ground.
    Tangent,
}

/// The plane touching the ground right below the sensor: a curved surface
/// w = a + b·u + c·v + d·u² + e·u·v + f·v² + g·v³ fitted (Tukey-weighted, so kerbs and
/// objects drop out) to the points near `plane` in its own coordinates (u across the
/// vehicle, v along it: `forward` is the prior's forward axis in the sensor frame), and its
/// tangent at the sensor's foot (u = v = 0). On rolling ground a single plane over 25 m tilts
/// toward wherever the terrain is; the vehicle stands on the ground under it. Why the cubic
/// along the vehicle: a road's grade changes along it (a climb levelling off), and without it
/// the tangent's pitch leans toward the band's mean slope (0.05–0.1° on the synthetic
/// streets). Why the lane: see `PlaneSearchConfig::lane_half_width`. None when the fit is
/// singular.
fn tangent_at_foot(
    points: &[Vector3<f64>],
    plane: Plane,
    forward: &Vector3<f64>,
    cfg: &PlaneSearchConfig,
) -> Option<(Plane, f64, Vec<Vector3<f64>>)> {
    let (tolerance, inlier_distance) = (cfg.surface_tolerance, cfg.inlier_distance);
    let (window, share) = (cfg.layer_window, cfg.layer_share);
    use nalgebra::{SMatrix, SVector};
    let n = plane.n;
    let across_axis = n.cross(forward);
    let (u_axis, v_axis) = if across_axis.norm() > 0.1 {
        let u = across_axis.normalize();
        (u, n.cross(&u))
    } else {
        in_plane_axes(&n)
    };
    // The lane and the cubic need ground ahead of the vehicle and behind it, the smaller side
    // holding at least a tenth of the lane's points: extrapolated back from ground seen
    // ahead only (a forward-looking sensor), a lane's roll and a cubic's pitch swing (on two
    // real solid-state scans of one mount, heights 4 cm apart where the surface over all the
    // ground finds them 1 cm apart). Such sensors get the surface over all their ground. A
    // tenth, not more: a spinning sensor pitched 9° sees a fifth of its lane behind it.
    let (mut ahead, mut behind) = (0usize, 0usize);
    for p in points {
        if u_axis.dot(p).abs() < cfg.lane_half_width {
            if v_axis.dot(p) > 0.0 {
                ahead += 1;
            } else {
                behind += 1;
            }
        }
    }
    let lengthwise = 10 * ahead.min(behind) >= ahead + behind && ahead + behind > 0;
    const K: usize = 7;
    // Scale the coordinates so that the normal equations stay well conditioned.
    let scale = 10.0;
    let local: Vec<(SVector<f64, K>, f64, f64)> = points
        .iter()
        .map(|p| {
            let (u, v) = (u_axis.dot(p) / scale, v_axis.dot(p) / scale);
            let cubic = if lengthwise { v * v * v } else { 0.0 };
            // The lane's weight: Tukey's, across the vehicle (a lane seen at all is wider
            // than 0).
            let lateral = if lengthwise {
                let q = (u * scale / cfg.lane_half_width).abs().min(1.0);
                (1.0 - q * q) * (1.0 - q * q)
            } else {
                1.0
            };
            (
                SVector::<f64, K>::from([1.0, u, v, u * u, u * v, v * v, cubic]),
                plane.above(p),
                lateral,
            )
        })
        .collect();
    let mut coef = SVector::<f64, K>::zeros();
    // Graduated: a wide tolerance first lets the surface bend toward terrain the plane
    // missed; then, like the plane, down onto the lowest dense layer (a wide tolerance also
    // bends it up onto the sidewalks) and a tight tolerance that keeps kerbs and objects out.
    let wide = [4.0, 3.0, 2.0, 1.5, 1.0, 1.0].map(|k| (k * tolerance, false));
    let tight = [(inlier_distance, true); 4];
    for (t, settle) in wide.into_iter().chain(tight) {
        if settle
            && let Some(offset) = lowest_peak(
                local
                    .iter()
                    .filter(|(.., lateral)| *lateral > 0.0)
                    .map(|(x, w, _)| w - coef.dot(x)),
                window,
                share,
            )
        {
            coef[0] += offset;
        }
        let mut a = SMatrix::<f64, K, K>::zeros();
        let mut rhs = SVector::<f64, K>::zeros();
        if !lengthwise {
            // Without the cubic its column is empty: pinned to zero, the rest is the quadratic.
            a[(K - 1, K - 1)] = 1.0;
        }
        let mut used = 0usize;
        for (x, w, lateral) in &local {
            if *lateral <= 0.0 {
                continue;
            }
            // Settling, points above the surface have half the say of those below: the
            // ground is the lowest layer, and a surface bent up onto a sidewalk comes down.
            let d = w - coef.dot(x);
            let r = if settle && d > 0.0 {
                2.0 * d / t
            } else {
                d / t
            };
            if r.abs() >= 1.0 {
                continue;
            }
            let weight = (1.0 - r * r) * (1.0 - r * r) * lateral;
            a += weight * x * x.transpose();
            rhs += weight * *w * x;
            used += 1;
        }
        if used < 12 {
            return None;
        }
        coef = a.cholesky()?.solve(&rhs);
    }
    let (mut inliers, mut sum2) = (Vec::new(), 0.0);
    for (p, (x, w, _)) in points.iter().zip(&local) {
        let r = w - coef.dot(x);
        if r.abs() <= inlier_distance {
            inliers.push(*p);
            sum2 += r * r;
        }
    }
    let rms = (sum2 / inliers.len().max(1) as f64).sqrt();
    // The tangent at (0, 0): height a, slopes b/scale and c/scale along u and v.
    let (w0, du, dv) = (coef[0], coef[1] / scale, coef[2] / scale);
    let normal = (n - du * u_axis - dv * v_axis).normalize();
    // The tangent plane holds the foot point (0, 0, w0), which is p = (w0 − h)·n in sensor
    // coordinates (w = n·p + h), so its offset is −normal·p.
    let foot = (w0 - plane.h) * n;
    Some((
        Plane {
            n: normal,
            h: -normal.dot(&foot),
        },
        rms,
        inliers,
    ))
}

/// One scan's ground plane: points p on it satisfy n · p + height = 0 (sensor frame).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PlaneFit {
    /// Unit normal in the sensor frame, pointing from the ground to the sensor's side.
    pub normal: [f64; 3],
    /// Distance of the sensor origin above the plane, metres.
    pub height: f64,
    /// Points within the inlier distance of the final plane.
    pub inliers: usize,
    /// Points in the band the final plane was fitted over.
    pub band_points: usize,
    /// That band, horizontal distance from the sensor, metres.
    pub band: [f64; 2],
    /// Leverage of the height (1: the sensor above the middle of its ground; large: the
    /// ground seen far off in one direction only).
    pub leverage: f64,
    /// Root mean square distance of the inliers from the plane, metres.
    pub rms: f64,
}

/// Why a scan gave no usable ground plane.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "reason", rename_all = "snake_case")]
pub enum NoGround {
    /// Fewer than three usable points in the range band.
    TooFewPoints {
        /// Finite points in the band.
        candidates: usize,
    },
    /// No plane within the tilt cone and the height limits.
    NoPlane,
    /// The best plane holds too few points.
    WeakSupport {
        /// Its inliers.
        inliers: usize,
        /// Points in its band.
        band_points: usize,
    },
    /// Ground seen too far off, over too short a stretch, to tell height from pitch.
    NarrowBand {
        /// The height's leverage (see `PlaneSearchConfig::max_leverage`).
        leverage: f64,
    },
}

impl std::fmt::Display for NoGround {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::TooFewPoints { candidates } => {
                write!(f, "only {candidates} points in the range band")
            }
            Self::NoPlane => write!(
                f,
                "no plane below the sensor within the tilt cone around the prior's vertical"
            ),
            Self::WeakSupport {
                inliers,
                band_points,
            } => write!(
                f,
                "no flat ground: the best plane holds {inliers} of {band_points} points"
            ),
            Self::NarrowBand { leverage } => write!(
                f,
                "ground seen only in a narrow band far from the sensor (leverage {leverage:.1}): \
                 height and pitch cannot be told apart"
            ),
        }
    }
}

/// A plane as unit normal (toward the sensor side) and the origin's height above it.
#[derive(Debug, Clone, Copy)]
struct Plane {
    n: Vector3<f64>,
    h: f64,
}

impl Plane {
    #[inline]
    fn above(&self, p: &Vector3<f64>) -> f64 {
        self.n.dot(p) + self.h
    }

    /// Within the tilt cone around `up` and with the sensor within the height limits above.
    fn plausible(&self, up: &Vector3<f64>, cfg: &PlaneSearchConfig) -> bool {
        let [lo, hi] = cfg.height_limits;
        self.n.dot(up) >= cfg.max_tilt.cos() && (lo..=hi).contains(&self.h)
    }

    /// Through three points, oriented toward `up`; None when they are (nearly) collinear.
    fn through(
        a: &Vector3<f64>,
        b: &Vector3<f64>,
        c: &Vector3<f64>,
        up: &Vector3<f64>,
    ) -> Option<Self> {
        let n = (b - a).cross(&(c - a));
        let len = n.norm();
        if len.is_nan() || len <= 1e-3 {
            return None;
        }
        let n = if n.dot(up) < 0.0 { -n / len } else { n / len };
        Some(Self { n, h: -n.dot(a) })
    }

    /// Least squares through `points`, oriented toward `up` (None for fewer than three).
    fn fit(points: &[Vector3<f64>], up: &Vector3<f64>) -> Option<(Self, f64)> {
        if points.len() < 3 {
            return None;
        }
        let k = points.len() as f64;
        let centroid = points.iter().sum::<Vector3<f64>>() / k;
        let mut cov = Matrix3::zeros();
        for p in points {
            let d = p - centroid;
            cov += d * d.transpose();
        }
        cov /= k;
        let eig = SymmetricEigen::new(cov);
        let (i, lambda) = eig
            .eigenvalues
            .iter()
            .copied()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))?;
        let n = eig.eigenvectors.column(i).into_owned();
        let n = if n.dot(up) < 0.0 { -n } else { n };
        Some((
            Self {
                n,
                h: -n.dot(&centroid),
            },
            lambda.max(0.0).sqrt(),
        ))
    }
}

/// The `q` quantile of `v` (reorders it); NaN for an empty slice.
fn quantile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let k = ((v.len() - 1) as f64 * q).round() as usize;
    *v.select_nth_unstable_by(k, f64::total_cmp).1
}

/// Two unit vectors that span the plane with unit normal `n`.
fn in_plane_axes(n: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let u = n.cross(&Vector3::x());
    let u = if u.norm() > 0.1 {
        u
    } else {
        n.cross(&Vector3::y())
    }
    .normalize();
    (u, n.cross(&u))
}

/// Horizontal distance of `p` from the sensor, measured in the plane.
#[inline]
fn across(p: &Vector3<f64>, n: &Vector3<f64>) -> f64 {
    (p - n * n.dot(p)).norm()
}

/// RANSAC (MSAC-scored, lowest plane preferred) over a random sample of `pool`: the best
/// plane within the tilt cone and height limits, and the share of the sample it holds.
fn consensus(
    pool: &[Vector3<f64>],
    prior_up: &Vector3<f64>,
    cfg: &PlaneSearchConfig,
    rng: &mut ChaCha8Rng,
) -> Option<(Plane, f64)> {
    if pool.len() < 3 {
        return None;
    }
    let sample: Vec<Vector3<f64>> = if pool.len() <= cfg.sample_size {
        pool.to_vec()
    } else {
        (0..cfg.sample_size)
            .map(|_| pool[rng.random_range(0..pool.len())])
            .collect()
    };
    let sample_near: Vec<bool> = sample.iter().map(|p| p.norm() <= cfg.below_range).collect();
    let inv = 1.0 / (cfg.inlier_distance * cfg.inlier_distance);
    let mut best: Option<(f64, Plane, usize)> = None;
    for _ in 0..cfg.hypotheses {
        let mut pick = || sample[rng.random_range(0..sample.len())];
        let (a, b, c) = (pick(), pick(), pick());
        let Some(plane) = Plane::through(&a, &b, &c, prior_up) else {
            continue;
        };
        if !plane.plausible(prior_up, cfg) {
            continue;
        }
        // MSAC: an inlier counts the more the closer it lies, so that a plane tilted to
        // hold a road and the sidewalk beyond its kerb within the distance loses to the road.
        let (mut support, mut inliers, mut below) = (0.0f64, 0usize, 0usize);
        for (p, &near) in sample.iter().zip(&sample_near) {
            let s = plane.above(p);
            if s.abs() <= cfg.inlier_distance {
                support += 1.0 - s * s * inv;
                inliers += 1;
            } else if near && s < -cfg.below_distance {
                below += 1;
            }
        }
        let score = support - cfg.below_penalty * below as f64;
        if best.is_none_or(|(s, ..)| score > s) {
            best = Some((score, plane, inliers));
        }
    }
    best.map(|(_, plane, inliers)| (plane, inliers as f64 / sample.len() as f64))
}

/// The ground plane of one scan (sensor-frame points) near the prior's vertical `prior_up`
/// (a unit vector in the sensor frame). `seed` fixes the hypotheses: the same scan and seed
/// give the same plane.
///
/// `prior_forward` is the prior's forward axis in the sensor frame (its x: roll turns about
/// it): the tangent's lane lies along it.
pub fn ground_plane(
    points: &[[f32; 3]],
    prior_up: &Vector3<f64>,
    prior_forward: &Vector3<f64>,
    cfg: &PlaneSearchConfig,
    seed: u64,
) -> Result<PlaneFit, NoGround> {
    let (r_lo, r_hi) = (cfg.min_range, cfg.max_range);
    let band: Vec<Vector3<f64>> = points
        .iter()
        .map(|&[x, y, z]| Vector3::new(f64::from(x), f64::from(y), f64::from(z)))
        .filter(|p| {
            let r = p.norm();
            r.is_finite() && r >= r_lo && r <= r_hi
        })
        .collect();
    if band.len() < 3 {
        return Err(NoGround::TooFewPoints {
            candidates: band.len(),
        });
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // Hypotheses from the ground near the sensor, which the vehicle stands on (rolling
    // terrain far out lies on other planes); from all of the band where the near points hold
    // no plane (a sensor pitched up sees only cars and walls close by).
    let close: Vec<Vector3<f64>> = band
        .iter()
        .filter(|p| p.norm() <= cfg.coarse_range)
        .copied()
        .collect();
    let from_close = consensus(&close, prior_up, cfg, &mut rng)
        .filter(|&(_, share)| share >= cfg.min_inlier_share);
    let Some((coarse, _)) = from_close.or_else(|| consensus(&band, prior_up, cfg, &mut rng)) else {
        return Err(NoGround::NoPlane);
    };
    // Where the sensor first sees this ground: the nearest points within half a metre of
    // the plane (2 % quantile; curved terrain leaves the plane farther out). The mount's
    // ground is fitted over the band from there.
    let mut start: Vec<f64> = band
        .iter()
        .filter(|p| coarse.above(p).abs() <= 0.5)
        .map(|p| across(p, &coarse.n))
        .collect();
    let lo = quantile(&mut start, 0.02);
    let hi = lo + cfg.band_width;
    let near: Vec<Vector3<f64>> = band
        .iter()
        .filter(|p| (lo..=hi).contains(&across(p, &coarse.n)))
        .copied()
        .collect();
    let (mut plane, mut rms, mut inliers) = refine(&near, coarse, prior_up, cfg);
    // A curved surface is extrapolated to the sensor's foot only from ground around it: from
    // ground seen far ahead alone (a forward sensor) its curvature would swing the tangent.
    if cfg.surface == Surface::Tangent
        && leverage(&inliers, &plane.n) <= cfg.tangent_max_leverage
        && let Some(t) = tangent_at_foot(&near, plane, prior_forward, cfg)
    {
        (plane, rms, inliers) = t;
    }
    if !plane.plausible(prior_up, cfg) {
        return Err(NoGround::NoPlane);
    }
    let share = inliers.len() as f64 / near.len().max(1) as f64;
    if inliers.len() < cfg.min_inliers || share < cfg.min_inlier_share {
        return Err(NoGround::WeakSupport {
            inliers: inliers.len(),
            band_points: near.len(),
        });
    }
    let leverage = leverage(&inliers, &plane.n);
    if leverage.is_nan() || leverage > cfg.max_leverage {
        return Err(NoGround::NarrowBand { leverage });
    }
    Ok(PlaneFit {
        normal: plane.n.into(),
        height: plane.h,
        inliers: inliers.len(),
        band_points: near.len(),
        band: [lo, hi],
        leverage,
        rms,
    })
}

/// How far the sensor's foot lies from the centre of the plane's points, in standard
/// deviations of their spread within the plane: √(1 + mᵀC⁻¹m), the factor by which a height
/// extrapolated to the sensor is less certain than at the points (infinite when the points
/// lie on a line).
fn leverage(points: &[Vector3<f64>], n: &Vector3<f64>) -> f64 {
    let (u, v) = in_plane_axes(n);
    let k = points.len() as f64;
    let uv: Vec<nalgebra::Vector2<f64>> = points
        .iter()
        .map(|p| nalgebra::Vector2::new(u.dot(p), v.dot(p)))
        .collect();
    let m = uv.iter().sum::<nalgebra::Vector2<f64>>() / k;
    let c = uv
        .iter()
        .map(|q| (q - m) * (q - m).transpose())
        .sum::<nalgebra::Matrix2<f64>>()
        / k;
    match c.try_inverse() {
        Some(ci) => (1.0 + (m.transpose() * ci * m)[(0, 0)]).sqrt(),
        None => f64::INFINITY,
    }
}

/// The plane moved along its normal onto the lowest dense layer of points near it: the
/// distances within ±`window` are binned by centimetre and smoothed, and the lowest local
/// peak holding at least `share` of the highest one wins. A road 6 cm below its sidewalks
/// is the ground the vehicle stands on, though the plane that holds most points may be the
/// sidewalks' or one between the two; a few multipath returns below the road are no layer.
fn lowest_layer(points: &[Vector3<f64>], plane: Plane, window: f64, share: f64) -> Plane {
    match lowest_peak(points.iter().map(|p| plane.above(p)), window, share) {
        Some(offset) => Plane {
            n: plane.n,
            h: plane.h - offset,
        },
        None => plane,
    }
}

/// The lowest dense peak of `residuals` within ±`window` (see [`lowest_layer`]).
fn lowest_peak(residuals: impl Iterator<Item = f64>, window: f64, share: f64) -> Option<f64> {
    const BIN: f64 = 0.01;
    let bins = (2.0 * window / BIN).ceil() as usize + 1;
    let mut hist = vec![0.0f64; bins];
    for s in residuals {
        if s.abs() <= window {
            hist[((s + window) / BIN) as usize] += 1.0;
        }
    }
    let smooth: Vec<f64> = (0..bins)
        .map(|i| {
            [(-2i64, 1.0), (-1, 2.0), (0, 3.0), (1, 2.0), (2, 1.0)]
                .iter()
                .filter_map(|&(d, w)| {
                    let j = i as i64 + d;
                    (0..bins as i64).contains(&j).then(|| w * hist[j as usize])
                })
                .sum::<f64>()
        })
        .collect();
    let top = smooth.iter().copied().fold(0.0, f64::max);
    if top <= 0.0 {
        return None;
    }
    (0..bins)
        .find(|&i| {
            let v = smooth[i];
            v >= share * top
                && (i == 0 || smooth[i - 1] <= v)
                && (i + 1 == bins || smooth[i + 1] < v)
        })
        .map(|i| (i as f64 + 0.5) * BIN - window)
}

/// The lowest layer, then least squares on its inliers, three times (each fit chooses the
/// next one's inliers): the plane, the inliers' rms distance and the last inliers.
fn refine(
    points: &[Vector3<f64>],
    start: Plane,
    up: &Vector3<f64>,
    cfg: &PlaneSearchConfig,
) -> (Plane, f64, Vec<Vector3<f64>>) {
    let distance = cfg.inlier_distance;
    let mut plane = start;
    let mut rms = f64::NAN;
    let inliers_of = |pl: &Plane, d: f64| -> Vec<Vector3<f64>> {
        points
            .iter()
            .filter(|p| pl.above(p).abs() <= d)
            .copied()
            .collect()
    };
    for _ in 0..3 {
        plane = lowest_layer(points, plane, cfg.layer_window, cfg.layer_share);
        match Plane::fit(&inliers_of(&plane, distance), up) {
            Some((p, r)) => (plane, rms) = (p, r),
            None => break,
        }
    }
    let inliers = inliers_of(&plane, distance);
    (plane, rms, inliers)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Ground on a polar grid: `rings` rings `dr` apart from `r0` out, `per_ring` points on
    /// each, at the height `z(x, y)` gives (none where it gives none).
    fn polar(
        (r0, dr, rings): (f32, f32, usize),
        per_ring: usize,
        z: impl Fn(f32, f32) -> Option<f32>,
    ) -> Vec<[f32; 3]> {
        let mut v = Vec::new();
        for i in 0..rings {
            let r = r0 + i as f32 * dr;
            for j in 0..per_ring {
                let a = j as f32 * std::f32::consts::TAU / per_ring as f32;
                let (x, y) = (r * a.cos(), r * a.sin());
                v.extend(z(x, y).map(|z| [x, y, z]));
            }
        }
        v
    }

    /// Flat ground `h` below a level sensor, on a polar grid from 3 to 40 m.
    fn ground(h: f32) -> Vec<[f32; 3]> {
        polar((3.0, 0.6, 60), 180, |_, _| Some(-h))
    }

    fn up() -> Vector3<f64> {
        Vector3::z()
    }

    fn fit(points: &[[f32; 3]]) -> Result<PlaneFit, NoGround> {
        ground_plane(
            points,
            &up(),
            &Vector3::x(),
            &PlaneSearchConfig::default(),
            7,
        )
    }

    #[test]
    fn flat_ground_is_found_exactly() {
        let f = fit(&ground(1.73)).unwrap();
        assert!((f.height - 1.73).abs() < 1e-6, "{f:?}");
        assert!(f.normal[2] > 1.0 - 1e-9);
        assert!(f.leverage < 1.01, "{f:?}");
    }

    /// A level sensor 1.73 m above its lane of a road crowned 1 % each way, the crown 1.75 m
    /// to its left (a vehicle in the right lane leans with it), seen from 5.8 m out as an
    /// OS1-64 sees it: beyond the crown the road falls 2 % in the sensor's frame.
    fn crowned_road(height: f32) -> Vec<[f32; 3]> {
        // Nothing beyond the kerbs.
        polar((5.8, 0.5, 50), 720, |_, y| {
            (-4.25..=7.75)
                .contains(&y)
                .then(|| -height - 0.02 * (y - 1.75).max(0.0))
        })
    }

    #[test]
    fn a_crowned_road_gives_the_lane_under_the_wheels() {
        let points = crowned_road(1.73);
        let f = fit(&points).unwrap();
        let tilt = |f: &PlaneFit| f.normal[2].clamp(-1.0, 1.0).acos().to_degrees();
        assert!(tilt(&f) < 0.05, "tilted {:.3}°: {f:?}", tilt(&f));
        assert!((f.height - 1.73).abs() < 0.01, "{f:?}");
        // Over both lanes the surface leans toward the crown: what the lane is for.
        let all_around = PlaneSearchConfig {
            lane_half_width: 0.0,
            ..Default::default()
        };
        let g = ground_plane(&points, &up(), &Vector3::x(), &all_around, 7).unwrap();
        assert!(tilt(&g) > 0.1, "tilted {:.3}°: {g:?}", tilt(&g));
    }

    #[test]
    fn walls_are_not_ground() {
        // Ground, and walls on both sides holding three times as many points.
        let mut p = ground(1.5);
        for side in [-8.0f32, 8.0] {
            for i in 0..400 {
                for k in 0..40 {
                    p.push([-20.0 + i as f32 * 0.1, side, -1.5 + k as f32 * 0.1]);
                }
            }
        }
        let f = fit(&p).unwrap();
        assert!((f.height - 1.5).abs() < 0.01, "{f:?}");
        assert!(f.normal[2] > 0.999);
    }

    #[test]
    fn a_kerb_and_sidewalk_do_not_lift_the_ground() {
        // Road 1.8 m below; a 15 cm kerb and a sidewalk beyond y = 4 m holding as many points
        // as the road in the band (a sensor driving close to the kerb).
        let mut p = Vec::new();
        for i in 0..300 {
            for j in 0..80 {
                let (x, y) = (-30.0 + i as f32 * 0.2, -8.0 + j as f32 * 0.2);
                let z = if y > 4.0 { -1.65 } else { -1.8 };
                p.push([x, y, z]);
            }
        }
        let f = fit(&p).unwrap();
        assert!((f.height - 1.8).abs() < 0.01, "{f:?}");
    }

    #[test]
    fn parked_car_roofs_do_not_become_the_ground() {
        // A car park seen from a low sensor: most returns are on roofs 1.4 m above the
        // asphalt, the asphalt shows between them.
        let mut p = Vec::new();
        for i in 0..300 {
            for j in 0..200 {
                let (x, y) = (-30.0 + i as f32 * 0.2, -20.0 + j as f32 * 0.2);
                let roof = (x.rem_euclid(5.0) < 4.0) && (y.rem_euclid(3.0) < 2.0) && x.abs() > 4.0;
                p.push([x, y, if roof { -0.6 } else { -2.0 }]);
            }
        }
        let f = fit(&p).unwrap();
        assert!((f.height - 2.0).abs() < 0.01, "{f:?}");
    }

    #[test]
    fn a_car_park_ramp_leaves_the_floor_the_ground() {
        // Level floor 1.6 m below; ahead from 8 m a ramp climbs at 8° over half the view.
        let mut p = Vec::new();
        for i in 0..250 {
            for j in 0..200 {
                let (x, y) = (-20.0 + i as f32 * 0.2, -20.0 + j as f32 * 0.2);
                let z = if x > 8.0 && y > 0.0 {
                    -1.6 + (x - 8.0) * 8f32.to_radians().tan()
                } else {
                    -1.6
                };
                p.push([x, y, z]);
            }
        }
        let f = fit(&p).unwrap();
        assert!((f.height - 1.6).abs() < 0.02, "{f:?}");
        assert!(f.normal[2] > (0.3f64).to_radians().cos(), "{f:?}");
    }

    #[test]
    fn a_scan_with_no_ground_is_refused() {
        // Only vertical walls and scattered points in the air: a tunnel wall scan.
        let mut p = Vec::new();
        for i in 0..400 {
            for k in 0..40 {
                p.push([-20.0 + i as f32 * 0.1, 6.0, -1.0 + k as f32 * 0.1]);
                p.push([
                    5.0 + (i % 97) as f32 * 0.3,
                    -3.0 + (k * 7 % 13) as f32 * 0.5,
                    (i * k % 31) as f32 * 0.2 - 3.0,
                ]);
            }
        }
        let e = fit(&p).unwrap_err();
        assert!(
            matches!(e, NoGround::WeakSupport { .. } | NoGround::NoPlane),
            "{e:?}"
        );
        assert!(!e.to_string().is_empty());
        let e = fit(&[[1.0, 0.0, -1.0]; 2]).unwrap_err();
        assert_eq!(e, NoGround::TooFewPoints { candidates: 2 });
        let nan = vec![[f32::NAN, 0.0, 0.0]; 5000];
        assert_eq!(
            fit(&nan).unwrap_err(),
            NoGround::TooFewPoints { candidates: 0 }
        );
    }

    #[test]
    fn a_narrow_strip_of_ground_is_refused() {
        // Ground seen only ahead, 14 to 16 m out (a forward sensor pitched up, behind a
        // wall of traffic): height and pitch trade off. The same strip all around is fine.
        let ring = |p: &[f32; 3]| (14.0..16.0).contains(&p[0].hypot(p[1]));
        let around: Vec<[f32; 3]> = ground(1.73).into_iter().filter(ring).collect();
        assert!((fit(&around).unwrap().height - 1.73).abs() < 1e-6);
        let mut p = Vec::new();
        for i in 0..40 {
            for j in 0..160 {
                p.push([14.0 + i as f32 * 0.05, -4.0 + j as f32 * 0.05, -1.73]);
            }
        }
        let e = fit(&p).unwrap_err();
        assert!(
            matches!(e, NoGround::NarrowBand { leverage } if leverage > 15.0),
            "{e:?}"
        );
    }

    #[test]
    fn settings_are_checked_by_name() {
        let mut c = PlaneSearchConfig::default();
        c.validate().unwrap();
        c.max_tilt = 2.0;
        assert!(c.validate().unwrap_err().to_string().contains("max_tilt"));
        let c = PlaneSearchConfig {
            height_limits: [1.0, f64::NAN],
            ..PlaneSearchConfig::default()
        };
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("height_limits")
        );
    }
}
