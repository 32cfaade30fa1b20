//! The sensor mount from many scans' ground planes: each plane gives a height, roll and
//! pitch; the mount is their per-parameter median (a frame on a speed bump, on a ramp or with
//! a wrong plane does not move it), and their robust spread is the confidence. Yaw cannot be
//! seen in the ground and is kept from the prior.

use groundwork_core::config::{MountConfig, roll_pitch_of, vertical_in_sensor};
use groundwork_core::point::Pose;
use nalgebra::Vector3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::CalibrateError;
use crate::plane::{NoGround, PlaneFit, PlaneSearchConfig, ground_plane};

/// How the mount is estimated and when it is refused.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MountSearchConfig {
    /// The per-scan plane search.
    pub plane: PlaneSearchConfig,
    /// Scans with usable ground needed to state a mount.
    pub min_frames: usize,
    /// Refuse when the frames' roll or pitch spread (robust standard deviation) exceeds
    /// this, radians: the ground is not flat or the sensor moved on its mount.
    pub max_angle_spread: f64,
    /// ... or when their height spread exceeds this, metres.
    pub max_height_spread: f64,
    /// The mount found is flagged as seen from one side ([`OneSidedGround`]) when the
    /// scans' median leverage of the height exceeds this (1: ground all around the sensor;
    /// a spinning sensor gives 1.0–1.03, a forward-facing solid-state one 2.1–5).
    pub one_sided_leverage: f64,
    /// Seed of the plane hypotheses (scan k uses seed + k).
    pub seed: u64,
}

impl Default for MountSearchConfig {
    fn default() -> Self {
        Self {
            plane: PlaneSearchConfig::default(),
            min_frames: 3,
            max_angle_spread: 2f64.to_radians(),
            max_height_spread: 0.15,
            one_sided_leverage: 1.5,
            seed: 0,
        }
    }
}

impl MountSearchConfig {
    /// Refuses settings that cannot state a mount, by field name.
    pub fn validate(&self) -> Result<(), CalibrateError> {
        self.plane.validate()?;
        let bad = |f: &str| {
            Err(CalibrateError::Config(format!(
                "{f} must be finite and > 0"
            )))
        };
        if self.min_frames == 0 {
            return bad("min_frames");
        }
        if !(self.max_angle_spread.is_finite() && self.max_angle_spread > 0.0) {
            return bad("max_angle_spread");
        }
        if !(self.max_height_spread.is_finite() && self.max_height_spread > 0.0) {
            return bad("max_height_spread");
        }
        if !(self.one_sided_leverage.is_finite() && self.one_sided_leverage >= 1.0) {
            return Err(CalibrateError::Config(
                "one_sided_leverage must be finite and >= 1 (a leverage is at least 1)".into(),
            ));
        }
        Ok(())
    }
}

/// One scan's view of the mount.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameMount {
    /// Height above its ground plane, metres.
    pub height: f64,
    /// Roll, radians.
    pub roll: f64,
    /// Pitch, radians.
    pub pitch: f64,
    /// The plane it comes from.
    pub plane: PlaneFit,
}

impl FrameMount {
    /// This view as a mount (ground-aligned from sensor), yaw 0: the ground does not show
    /// yaw, and ranges and heights above the ground do not depend on it.
    pub fn pose(&self) -> Option<Pose> {
        groundwork_core::mount_transform(&MountConfig {
            height: self.height,
            roll: self.roll,
            pitch: self.pitch,
            ..Default::default()
        })
        .ok()
    }
}

/// Median and spread of one mount parameter over the frames.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Estimate {
    /// Median over the frames.
    pub value: f64,
    /// Robust standard deviation over the frames (1.4826 × median absolute deviation).
    pub spread: f64,
    /// Standard error of the median (1.2533 × spread / √frames).
    pub standard_error: f64,
}

impl Estimate {
    fn of(mut v: Vec<f64>) -> Self {
        let value = median(&mut v);
        let mut dev: Vec<f64> = v.iter().map(|x| (x - value).abs()).collect();
        let spread = 1.4826 * median(&mut dev);
        Self {
            value,
            spread,
            standard_error: 1.2533 * spread / (v.len() as f64).sqrt(),
        }
    }
}

/// Ground seen on one side of the sensor only (a forward-facing sensor, or one whose
/// vehicle hides the rest): the plane pivots about ground ahead, so a slope of that ground
/// cannot be told from the sensor's pitch (and the height moves with it). Over a long
/// drive the slopes average out; over a short stretch on a grade they do not (measured: a
/// level Livox-like sensor 1.47 m up, 24 off-road scans, found 15 cm low and 2.2° off,
/// with a small spread). Not a refusal: the same data on level ground give the right mount.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct OneSidedGround {
    /// Median over the scans of the height's leverage ([`PlaneFit::leverage`]).
    pub leverage: f64,
    /// Median over the scans of the near edge of the band the plane was fitted over,
    /// horizontal metres from the sensor.
    pub nearest: f64,
}

impl std::fmt::Display for OneSidedGround {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "the ground was seen on one side of the sensor only (from {:.1} m, leverage \
             {:.1}): a slope of that ground reads as pitch and height, so this mount holds \
             if the ground seen was, over the scans, as level as the ground under the \
             vehicle; scans spread over a longer drive, or taken on a stretch known to be \
             level, make it so",
            self.nearest, self.leverage
        )
    }
}

/// The mount found in the scans.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MountEstimate {
    /// Sensor height above the ground, metres.
    pub height: Estimate,
    /// Roll, radians.
    pub roll: Estimate,
    /// Pitch, radians.
    pub pitch: Estimate,
    /// Yaw, radians (the prior's: the ground does not show it).
    pub yaw: f64,
    /// Scans that gave a plane.
    pub frames_used: usize,
    /// Scans looked at.
    pub frames: usize,
    /// Set when the scans saw the ground on one side only: what the mount assumes.
    pub one_sided: Option<OneSidedGround>,
    /// The scans (places in the list given to [`combine`]) whose height is further from the
    /// one found than the search's height tolerance: another sensor or mount among the
    /// inputs. Outvoted by the median, and named so the user can see them.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub disagreeing: Vec<usize>,
}

impl MountEstimate {
    /// As a mount configuration (height, roll, pitch, yaw).
    pub fn mount(&self) -> MountConfig {
        MountConfig {
            height: self.height.value,
            roll: self.roll.value,
            pitch: self.pitch.value,
            yaw: self.yaw,
            ..Default::default()
        }
    }
}

/// The prior's vertical in the sensor frame, and its yaw.
pub fn prior_up(prior: &Pose) -> (Vector3<f64>, f64) {
    (vertical_in_sensor(prior), prior.rotation.euler_angles().2)
}

/// One scan's view of the mount (its index `k` picks its hypotheses' seed).
pub fn frame_mount(
    points: &[[f32; 3]],
    prior: &Pose,
    cfg: &MountSearchConfig,
    k: u64,
) -> Result<FrameMount, NoGround> {
    let (up, _) = prior_up(prior);
    // The vehicle's forward axis in the sensor frame: the tangent's lane lies along it.
    let forward = prior.rotation.inverse() * Vector3::x();
    let plane = ground_plane(points, &up, &forward, &cfg.plane, cfg.seed.wrapping_add(k))?;
    let (roll, pitch) = roll_pitch_of(&Vector3::from(plane.normal));
    Ok(FrameMount {
        height: plane.height,
        roll,
        pitch,
        plane,
    })
}

/// The mount from the scans' views (`Err` entries are scans without usable ground), or why
/// the data cannot determine it.
pub fn combine(
    frames: &[Result<FrameMount, NoGround>],
    prior: &Pose,
    cfg: &MountSearchConfig,
) -> Result<MountEstimate, CalibrateError> {
    let good: Vec<&FrameMount> = frames.iter().filter_map(|f| f.as_ref().ok()).collect();
    if good.len() < cfg.min_frames.max(1) {
        let mut reasons: Vec<String> = frames
            .iter()
            .filter_map(|f| f.as_ref().err().map(ToString::to_string))
            .collect();
        reasons.sort();
        reasons.dedup();
        return Err(CalibrateError::Refused(format!(
            "{} of {} scans show usable ground, {} needed{}",
            good.len(),
            frames.len(),
            cfg.min_frames.max(1),
            if reasons.is_empty() {
                String::new()
            } else {
                format!(" ({})", reasons.join("; "))
            }
        )));
    }
    let est = MountEstimate {
        height: Estimate::of(good.iter().map(|f| f.height).collect()),
        roll: Estimate::of(good.iter().map(|f| f.roll).collect()),
        pitch: Estimate::of(good.iter().map(|f| f.pitch).collect()),
        yaw: prior_up(prior).1,
        frames_used: good.len(),
        frames: frames.len(),
        one_sided: one_sided(&good, cfg),
        disagreeing: Vec::new(),
    };
    let worst = est.roll.spread.max(est.pitch.spread);
    if worst > cfg.max_angle_spread || est.height.spread > cfg.max_height_spread {
        return Err(CalibrateError::Refused(format!(
            "the scans disagree about the ground: roll spread {:.2}°, pitch {:.2}°, height \
             {:.3} m over {} scans (limits {:.1}° and {:.2} m): not flat ground, or the sensor \
             moved",
            est.roll.spread.to_degrees(),
            est.pitch.spread.to_degrees(),
            est.height.spread,
            good.len(),
            cfg.max_angle_spread.to_degrees(),
            cfg.max_height_spread,
        )));
    }
    let disagreeing: Vec<usize> = frames
        .iter()
        .enumerate()
        .filter(|(_, f)| {
            f.as_ref()
                .is_ok_and(|f| (f.height - est.height.value).abs() > cfg.max_height_spread)
        })
        .map(|(k, _)| k)
        .collect();
    // A quarter or more: no mount the inputs share, whatever the median says.
    if 4 * disagreeing.len() >= good.len() {
        let heights: Vec<String> = disagreeing
            .iter()
            .take(5)
            .filter_map(|&k| frames[k].as_ref().ok())
            .map(|f| format!("{:.2} m", f.height))
            .collect();
        return Err(CalibrateError::Refused(format!(
            "{} of {} scans put the sensor more than {:.2} m from the median height {:.3} m \
             ({}{}): scans of more than one sensor or mount; calibrate each apart",
            disagreeing.len(),
            good.len(),
            cfg.max_height_spread,
            est.height.value,
            heights.join(", "),
            if disagreeing.len() > 5 { ", …" } else { "" }
        )));
    }
    let est = MountEstimate { disagreeing, ..est };
    Ok(est)
}

/// Whether the scans saw their ground on one side only (the median leverage above
/// `cfg.one_sided_leverage`), and from where.
fn one_sided(good: &[&FrameMount], cfg: &MountSearchConfig) -> Option<OneSidedGround> {
    let mut leverage: Vec<f64> = good.iter().map(|f| f.plane.leverage).collect();
    let mut nearest: Vec<f64> = good.iter().map(|f| f.plane.band[0]).collect();
    let leverage = median(&mut leverage);
    (leverage > cfg.one_sided_leverage).then(|| OneSidedGround {
        leverage,
        nearest: median(&mut nearest),
    })
}

/// Every scan's view of the mount (in parallel: each depends only on its scan and its
/// place), and the mount they give or why they cannot: [`frame_mount`] then [`combine`],
/// for callers that hold the scans (the CLI streams them).
pub fn estimate_mount<S: AsRef<[[f32; 3]]> + Sync>(
    scans: &[S],
    prior: &Pose,
    cfg: &MountSearchConfig,
) -> (
    Vec<Result<FrameMount, NoGround>>,
    Result<MountEstimate, CalibrateError>,
) {
    let views: Vec<_> = scans
        .par_iter()
        .enumerate()
        .map(|(k, s)| frame_mount(s.as_ref(), prior, cfg, k as u64))
        .collect();
    let estimate = combine(&views, prior, cfg);
    (views, estimate)
}

/// Median of a non-empty slice (reorders it; the mean of the middle two for even lengths).
pub(crate) fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use groundwork_core::mount_transform;
    use proptest::prelude::*;

    /// A scene in the ground frame: flat ground on a polar grid from 2 to 45 m, a few boxes
    /// (cars) and a wall, seen by a sensor at `mount`: returned in the sensor frame.
    fn scene_seen_from(mount: &MountConfig, jitter: u32) -> Vec<[f32; 3]> {
        let t = mount_transform(mount).unwrap();
        let mut world = Vec::new();
        for i in 0..70 {
            let r = 2.0 + f64::from(i) * 0.62;
            for j in 0..240 {
                let a = f64::from(j) * std::f64::consts::TAU / 240.0;
                // A few millimetres of deterministic roughness.
                let z = 0.004 * f64::from((i * 31 + j * 17 + jitter) % 7) - 0.012;
                world.push(Vector3::new(r * a.cos(), r * a.sin(), z));
            }
        }
        for (cx, cy) in [(8.0, 3.0), (-6.0, -4.0), (15.0, -5.0)] {
            for i in 0..40 {
                for k in 0..15 {
                    world.push(Vector3::new(
                        cx + f64::from(i) * 0.1,
                        cy,
                        0.1 * f64::from(k),
                    ));
                }
            }
        }
        for i in 0..300 {
            for k in 0..30 {
                world.push(Vector3::new(
                    -20.0 + f64::from(i) * 0.15,
                    12.0,
                    0.15 * f64::from(k),
                ));
            }
        }
        world
            .into_iter()
            .map(|w| {
                let p = t.inverse_transform_point(&w.into());
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect()
    }

    fn calibrate(
        frames: &[Vec<[f32; 3]>],
        prior: &MountConfig,
    ) -> Result<MountEstimate, CalibrateError> {
        let prior = mount_transform(prior).unwrap();
        estimate_mount(frames, &prior, &MountSearchConfig::default()).1
    }

    #[test]
    fn settings_are_checked_by_name() {
        MountSearchConfig::default().validate().unwrap();
        let c = MountSearchConfig {
            max_height_spread: -1.0,
            ..MountSearchConfig::default()
        };
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("max_height_spread")
        );
    }

    #[test]
    fn too_few_frames_and_disagreeing_frames_are_refused_with_the_reason() {
        let level = MountConfig {
            height: 1.5,
            ..Default::default()
        };
        let one = vec![scene_seen_from(&level, 0)];
        let e = calibrate(&one, &level).unwrap_err().to_string();
        assert!(e.contains("1 of 1 scans") && e.contains("3 needed"), "{e}");
        let none = vec![vec![[1.0f32, 2.0, 3.0]; 10]; 4];
        let e = calibrate(&none, &level).unwrap_err().to_string();
        assert!(
            e.contains("0 of 4") && e.contains("no plane below the sensor"),
            "{e}"
        );
        // Frames seen from sensors 1.0, 1.5 and 2.0 m high: no single mount.
        let frames: Vec<_> = [1.0, 1.5, 2.0, 1.0, 2.0]
            .iter()
            .map(|&h| {
                scene_seen_from(
                    &MountConfig {
                        height: h,
                        ..Default::default()
                    },
                    0,
                )
            })
            .collect();
        let e = calibrate(&frames, &level).unwrap_err().to_string();
        assert!(e.contains("disagree"), "{e}");
    }

    #[test]
    fn ground_seen_ahead_only_is_flagged_and_ground_all_around_is_not() {
        let truth = MountConfig {
            height: 1.4,
            pitch: -0.03,
            ..Default::default()
        };
        let around: Vec<_> = (0..4).map(|k| scene_seen_from(&truth, k)).collect();
        let e = calibrate(&around, &truth).unwrap();
        assert_eq!(e.one_sided, None, "{e:?}");
        // The same scenes through a forward sensor's window: 90° wide, from 5 m on.
        let ahead: Vec<Vec<[f32; 3]>> = around
            .iter()
            .map(|s| {
                let forward = |p: &&[f32; 3]| p[0] > 5.0 && p[1].abs() < p[0];
                s.iter().filter(forward).copied().collect()
            })
            .collect();
        let e = calibrate(&ahead, &truth).unwrap();
        let o = e.one_sided.expect("ground ahead only");
        assert!(o.leverage > 1.5 && (5.0..7.0).contains(&o.nearest), "{o:?}");
        // On level ground the mount is still right; the flag says what it assumed.
        assert!((e.height.value - 1.4).abs() < 0.01, "{e:?}");
        assert!((e.pitch.value + 0.03).abs() < 0.2f64.to_radians(), "{e:?}");
        assert!(o.to_string().contains("one side of the sensor only"));
        // The threshold is a setting.
        let lenient = MountSearchConfig {
            one_sided_leverage: o.leverage + 0.1,
            ..MountSearchConfig::default()
        };
        let prior = mount_transform(&truth).unwrap();
        assert_eq!(
            estimate_mount(&ahead, &prior, &lenient)
                .1
                .unwrap()
                .one_sided,
            None
        );
    }

    #[test]
    fn a_frame_on_a_bump_does_not_move_the_mount() {
        let truth = MountConfig {
            height: 1.2,
            pitch: 0.05,
            ..Default::default()
        };
        let mut frames: Vec<_> = (0..4).map(|k| scene_seen_from(&truth, k)).collect();
        let bumped = MountConfig {
            pitch: 0.15,
            ..truth.clone()
        };
        frames.push(scene_seen_from(&bumped, 9));
        let e = calibrate(
            &frames,
            &MountConfig {
                height: 1.0,
                ..Default::default()
            },
        )
        .unwrap();
        assert!((e.pitch.value - 0.05).abs() < 1e-3, "{e:?}");
        assert_eq!((e.frames_used, e.frames), (5, 5));
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]
        /// A scene seen through a known mount and calibrated from a level prior gives the
        /// mount back.
        #[test]
        fn a_known_mount_is_recovered(
            height in 0.4f64..2.6,
            roll in -6f64..6.0,
            pitch in -11f64..11.0,
            yaw in -3f64..3.0,
        ) {
            let truth = MountConfig {
                height,
                roll: roll.to_radians(),
                pitch: pitch.to_radians(),
                yaw,
                matrix: None,
            };
            let frames: Vec<_> = (0..3).map(|k| scene_seen_from(&truth, k)).collect();
            let prior = MountConfig { height: 1.5, yaw, ..Default::default() };
            let e = calibrate(&frames, &prior).unwrap();
            prop_assert!((e.height.value - height).abs() < 0.02, "{e:?}");
            prop_assert!((e.roll.value - truth.roll).abs() < 0.2f64.to_radians(), "{e:?}");
            prop_assert!((e.pitch.value - truth.pitch).abs() < 0.2f64.to_radians(), "{e:?}");
            prop_assert!((e.yaw - yaw).abs() < 1e-9);
        }
    }
}
