//! The whole calibration, in order: each scan's view of the mount → the mount → where the
//! scans first see ground → the zones for that mount → the parameters fitted to the
//! PseudoLabeler's labels of a sample. The `groundwork calibrate` command and Python's
//! `groundwork.calibrate` both call [`calibrate`]; [`Calibration`] is the report the
//! command writes with `--report`, and [`Calibration::to_toml`] the configuration file.
//!
//! Each scan's plane depends only on the scan and its place (the seed), so the result does
//! not depend on the number of cores or on the order the scans are looked at in.

use std::time::Instant;

use groundwork_core::SegmenterConfig;
use groundwork_core::config::{MountConfig, ZoneConfig};
use groundwork_core::mount_transform;
use groundwork_pseudolabel::PseudoLabelerConfig;
use rayon::prelude::*;
use serde::Serialize;

use crate::mount::FrameMount;
use crate::{
    CalibrateError, FitProgress, HeightScale, MountEstimate, MountSearchConfig, MountZones,
    NearEdgeConfig, NearGround, NoGround, ParamFit, ParamSearchConfig, combine,
    combine_near_ground, fit_to_pseudo_labels, frame_mount, view_near_ground, zones_for_mount,
};

/// One scan given to [`calibrate`].
#[derive(Debug, Clone)]
pub struct ScanInput {
    /// Its place among all the scans of the inputs (the seed of its plane hypotheses): the
    /// same scan at the same place gives the same view however the scans are spread.
    pub place: u64,
    /// Its name in the report (file stem, or recording and index).
    pub name: String,
    /// Its points (sensor frame), or why it could not be read.
    pub points: Result<Vec<[f32; 3]>, String>,
}

/// What [`calibrate`] does besides finding the mount.
#[derive(Debug, Clone)]
pub struct CalibrateOptions {
    /// The preset the configuration starts from, by name (the file's comments say it).
    pub base_preset: String,
    /// The mount the preset's zone layout was made for (its own, before any configuration
    /// laid over it): the inner boundaries scale with the height found over this one's.
    /// `None`: they stay.
    pub preset_mount: Option<MountConfig>,
    /// The mount search (its seed included).
    pub mount: MountSearchConfig,
    /// Where the scans first see ground.
    pub near_edge: NearEdgeConfig,
    /// Keep the zone model as it is (no near edge moved in, no scaling with the height).
    pub keep_zones: bool,
    /// The parameter fit to the PseudoLabeler's labels; `None` keeps the preset's.
    pub params: Option<ParamSearchConfig>,
    /// The parameter fit's sample: at most this many scans, spread evenly.
    pub param_scans: usize,
    /// How many scans the iterator given to [`calibrate`] yields (or at most): the sample
    /// is spread over them.
    pub expected_scans: usize,
}

impl CalibrateOptions {
    /// The defaults of `groundwork calibrate` from `base_preset`, whose own mount is
    /// `preset_mount`.
    pub fn new(
        base_preset: &str,
        preset_mount: Option<MountConfig>,
        expected_scans: usize,
    ) -> Self {
        Self {
            base_preset: base_preset.to_owned(),
            preset_mount,
            mount: MountSearchConfig::default(),
            near_edge: NearEdgeConfig::default(),
            keep_zones: false,
            params: Some(ParamSearchConfig::default()),
            param_scans: 48,
            expected_scans,
        }
    }

    /// Refuses settings that cannot calibrate, by field name.
    pub fn validate(&self) -> Result<(), CalibrateError> {
        self.mount.validate()?;
        if self.param_scans == 0 {
            return Err(CalibrateError::Config(
                "param_scans must be at least 1".into(),
            ));
        }
        if let Some(p) = &self.params {
            p.check()
                .map_err(|(field, why)| CalibrateError::Config(format!("{field}: {why}")))?;
        }
        Ok(())
    }
}

/// How far [`calibrate`] is, for a progress display.
#[derive(Debug, Clone, Copy)]
pub enum CalibrateProgress<'a> {
    /// One more scan looked at (its view of the mount found, or none).
    Looked,
    /// A scan could not be read: it is skipped (named in the report).
    Skipped {
        /// Why, as the reader said it.
        problem: &'a str,
    },
    /// The parameter fit's progress.
    Fit(FitProgress),
}

/// One scan's line in the report.
#[derive(Debug, Clone, Serialize)]
pub struct ScanReport {
    /// The scan's name (file stem, or recording and index).
    pub scan: String,
    /// Its view of the mount, if it showed usable ground.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mount: Option<FrameMount>,
    /// Why not, otherwise (no ground, or the scan could not be read).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub problem: Option<String>,
}

/// The zone model's near edge, moved (not with `keep_zones`).
#[derive(Debug, Clone, Serialize)]
pub struct NearEdge {
    /// Where the scans first see ground.
    pub ground: NearGround,
    /// `zones.min_range` of the preset, metres.
    pub was: f64,
    /// And written, if it moved.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_range: Option<f64>,
}

/// What [`calibrate`] found: the report (`groundwork calibrate --report` writes it as
/// JSON) and, through [`Calibration::to_toml`], the configuration file.
#[derive(Debug, Clone, Serialize)]
pub struct Calibration {
    /// The preset the calibration started from.
    pub base_preset: String,
    /// Its mount (the prior).
    pub prior: MountConfig,
    /// The mount found (absent when refused).
    pub mount: Option<MountEstimate>,
    /// Why it was refused (in the report as its message).
    #[serde(serialize_with = "as_message")]
    pub refused: Option<CalibrateError>,
    /// Scans looked at.
    pub scans: usize,
    /// Scans that could not be read.
    pub unreadable: usize,
    /// Every scan, in input order.
    pub per_scan: Vec<ScanReport>,
    /// The search's settings.
    pub settings: MountSearchConfig,
    /// Where the scans first see ground and the zone model's near edge (absent with
    /// `keep_zones`, or when too few scans show ground near the sensor).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub near_edge: Option<NearEdge>,
    /// The inner boundaries scaled with the height found (absent with `keep_zones`, a
    /// refused mount, or a height within 5 % of the preset's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height_scale: Option<HeightScale>,
    /// The parameter fit (unless kept), if it ran.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub parameters: Option<ParamFit>,
    /// Why the parameters were not fitted, if they were asked for and could not be.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub parameters_refused: Option<String>,
    /// Wall time, s.
    pub seconds: f64,
    /// The configuration the calibration started from (the preset with any configuration
    /// laid over it): the file says what changed from it.
    #[serde(skip)]
    pub base: SegmenterConfig,
    /// The zones for the mount found (near edge, height scaling), before the parameter
    /// fit; `None` when neither moved.
    #[serde(skip)]
    pub mount_zones: Option<ZoneConfig>,
    /// The scans outvoted in height (another sensor or mount among the inputs?), by name,
    /// with the height each saw.
    #[serde(skip)]
    pub disagreeing: Vec<(String, f64)>,
}

impl Calibration {
    /// The mount found, or why it was refused.
    pub fn estimate(&self) -> Result<&MountEstimate, CalibrateError> {
        match (&self.mount, &self.refused) {
            (Some(m), _) => Ok(m),
            (None, Some(e)) => Err(e.clone()),
            (None, None) => Err(CalibrateError::Refused("no mount found".into())),
        }
    }

    /// The zones in use: the parameter fit's (it started from the moved near edge), else
    /// the moved near edge's; `None` when the layout is the base's.
    pub fn final_zones(&self) -> Option<&ZoneConfig> {
        let fitted = self.parameters.as_ref().filter(|f| !f.kept_preset);
        fitted
            .map(|f| &f.config.zones)
            .or(self.mount_zones.as_ref())
            .filter(|z| !z.same_layout(&self.base.zones))
    }
}

/// A refusal in the report: its message.
fn as_message<S: serde::Serializer>(
    refused: &Option<CalibrateError>,
    s: S,
) -> Result<S::Ok, S::Error> {
    match refused {
        Some(e) => s.collect_str(e),
        None => s.serialize_none(),
    }
}

/// One scan looked at.
struct Looked {
    position: usize,
    line: ScanReport,
    view: Option<Result<FrameMount, NoGround>>,
    /// Whether the scan could be read (its view is taken out before the report).
    read: bool,
    near: Option<f64>,
    points: Option<Vec<[f32; 3]>>,
}

/// Calibrates `base` (the preset with any configuration over it) from `scans`: see the
/// module's documentation for the steps. A refused mount is a [`Calibration`] too (its
/// report says why, [`Calibration::estimate`] returns the refusal); `Err` is for settings
/// that cannot calibrate. A parameter fit that cannot be done keeps the preset's
/// parameters and says why (`parameters_refused`).
pub fn calibrate<I>(
    scans: I,
    base: &SegmenterConfig,
    labeler: &PseudoLabelerConfig,
    options: &CalibrateOptions,
    progress: impl Fn(CalibrateProgress<'_>) + Sync,
) -> Result<Calibration, CalibrateError>
where
    I: Iterator<Item = ScanInput> + Send,
{
    let started = Instant::now();
    options.validate()?;
    let prior_mount = base.sensor.mount.clone();
    let prior = mount_transform(&prior_mount)
        .map_err(|e| CalibrateError::Config(format!("sensor.mount: {e}")))?;
    let settings = &options.mount;
    let (ego_radius, near_cfg) = (base.sensor.ego_radius, &options.near_edge);
    // Every `keep`-th scan looked at is kept for the parameter fit's sample.
    let keep = options
        .params
        .as_ref()
        .map(|_| options.expected_scans.div_ceil(options.param_scans).max(1));
    let mut looked: Vec<Looked> = scans
        .enumerate()
        .par_bridge()
        .map(|(position, scan)| {
            look(
                position,
                scan,
                &prior,
                settings,
                (!options.keep_zones).then_some((ego_radius, near_cfg)),
                keep,
                &progress,
            )
        })
        .collect();
    looked.sort_by_key(|v| v.position);
    let unreadable = looked.iter().filter(|v| !v.read).count();
    let frames: Vec<Result<FrameMount, NoGround>> =
        looked.iter_mut().filter_map(|v| v.view.take()).collect();
    let result = combine(&frames, &prior, settings);
    // `disagreeing` counts the scans that were read, in order.
    let read: Vec<&Looked> = looked.iter().filter(|v| v.read).collect();
    let disagreeing = result
        .as_ref()
        .map(|est| {
            est.disagreeing
                .iter()
                .filter_map(|&k| {
                    let height = frames.get(k)?.as_ref().ok()?.height;
                    Some((read.get(k)?.line.scan.clone(), height))
                })
                .collect()
        })
        .unwrap_or_default();
    let near = combine_near_ground(looked.iter().filter_map(|v| v.near).collect());
    // The zones follow the mount found (not with keep_zones): the near edge where the
    // scans first see ground, the inner boundaries the height against the preset's.
    let height = result
        .as_ref()
        .ok()
        .filter(|_| !options.keep_zones)
        .map(|e| e.mount().height);
    let MountZones {
        zones,
        near_edge: min_range,
        height_scale,
    } = zones_for_mount(
        &base.zones,
        near.as_ref(),
        height.zip(options.preset_mount.as_ref()),
        ego_radius,
        near_cfg,
    );
    let near_edge = near.map(|ground| NearEdge {
        min_range,
        was: base.zones.min_range,
        ground,
    });
    let sample: Vec<Vec<[f32; 3]>> = looked
        .iter_mut()
        .filter_map(|v| v.points.take())
        .take(options.param_scans)
        .collect();
    let (parameters, parameters_refused) = match (&result, &options.params) {
        (Ok(est), Some(search)) => {
            // On the mount found, with the zones moved for it.
            let mut on_mount = base.clone();
            on_mount.sensor.mount = est.mount();
            if let Some(z) = &zones {
                on_mount.zones = z.clone();
            }
            match fit_to_pseudo_labels(&on_mount, labeler, &sample, search, |p| {
                progress(CalibrateProgress::Fit(p));
            }) {
                Ok(fit) => (Some(fit), None),
                // The mount is calibrated: a refusal here is the parameters' alone, and the
                // preset's parameters are a valid outcome.
                Err(e) => (None, Some(e.reason())),
            }
        }
        _ => (None, None),
    };
    Ok(Calibration {
        base_preset: options.base_preset.clone(),
        prior: prior_mount,
        refused: result.as_ref().err().cloned(),
        mount: result.ok(),
        scans: looked.len(),
        unreadable,
        per_scan: looked.into_iter().map(|v| v.line).collect(),
        settings: settings.clone(),
        near_edge,
        height_scale,
        parameters,
        parameters_refused,
        seconds: started.elapsed().as_secs_f64(),
        base: base.clone(),
        mount_zones: zones,
        disagreeing,
    })
}

/// One scan's view of the mount, where it first sees ground on that view (`near`: the ego
/// radius and settings, unless the zones are kept) and its points if it is in the sample
/// (every `keep`-th scan).
fn look(
    position: usize,
    scan: ScanInput,
    prior: &groundwork_core::point::Pose,
    settings: &MountSearchConfig,
    near: Option<(f64, &NearEdgeConfig)>,
    keep: Option<usize>,
    progress: &(impl Fn(CalibrateProgress<'_>) + Sync),
) -> Looked {
    let (mut points, mut near_range) = (None, None);
    let (mount, problem, view) = match scan.points {
        Ok(xyz) => {
            let m = frame_mount(&xyz, prior, settings, scan.place);
            if let (Ok(view), Some((ego, cfg))) = (&m, near) {
                near_range = view_near_ground(&xyz, view, ego, cfg);
            }
            if keep.is_some_and(|e| position.is_multiple_of(e)) {
                points = Some(xyz);
            }
            match m {
                Ok(m) => (Some(m.clone()), None, Some(Ok(m))),
                Err(no) => (None, Some(no.to_string()), Some(Err(no))),
            }
        }
        Err(e) => {
            progress(CalibrateProgress::Skipped { problem: &e });
            (None, Some(e), None)
        }
    };
    progress(CalibrateProgress::Looked);
    Looked {
        position,
        line: ScanReport {
            scan: scan.name,
            mount,
            problem,
        },
        read: view.is_some(),
        view,
        near: near_range,
        points,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat ground `height` below the sensor, rings of points from 4 to 30 m.
    fn flat(height: f32) -> Vec<[f32; 3]> {
        (0..3600)
            .map(|i| {
                let (a, r) = ((i % 360) as f32 * 0.0174533, 4.0 + (i / 360) as f32 * 2.6);
                [r * a.cos(), r * a.sin(), -height]
            })
            .collect()
    }

    fn scans(points: Vec<Result<Vec<[f32; 3]>, String>>) -> impl Iterator<Item = ScanInput> + Send {
        points.into_iter().enumerate().map(|(k, points)| ScanInput {
            place: k as u64,
            name: format!("s{k}"),
            points,
        })
    }

    #[test]
    fn the_mount_of_flat_scans_is_found_and_written_and_unreadable_ones_are_named() {
        let base = SegmenterConfig::default();
        let options = CalibrateOptions {
            params: None,
            ..CalibrateOptions::new("hdl64e", Some(base.sensor.mount.clone()), 5)
        };
        let mut input: Vec<_> = (0..4).map(|_| Ok(flat(1.9))).collect();
        input.insert(2, Err("s2.bin: truncated".to_owned()));
        let looked = std::sync::atomic::AtomicUsize::new(0);
        let cal = calibrate(scans(input), &base, &Default::default(), &options, |p| {
            if let CalibrateProgress::Looked = p {
                looked.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        })
        .unwrap();
        assert_eq!(looked.into_inner(), 5);
        assert_eq!((cal.scans, cal.unreadable), (5, 1));
        assert_eq!(
            cal.per_scan[2].problem.as_deref(),
            Some("s2.bin: truncated")
        );
        let est = cal.estimate().unwrap();
        assert!((est.height.value - 1.9).abs() < 0.01, "{est:?}");
        let text = cal.to_toml("mine", &["here".to_owned()]).unwrap();
        assert!(
            text.contains("height = 1.9000") && text.contains("of here."),
            "{text}"
        );
        assert!(
            cal.summary().starts_with("mount from 4 of 4 scans"),
            "{}",
            cal.summary()
        );
    }

    #[test]
    fn too_few_scans_are_refused_with_the_reason_and_nothing_to_write() {
        let base = SegmenterConfig::default();
        let options = CalibrateOptions::new("hdl64e", None, 2);
        let cal = calibrate(
            scans(vec![Ok(flat(1.7)), Ok(flat(1.7))]),
            &base,
            &Default::default(),
            &options,
            |_| {},
        )
        .unwrap();
        let why = cal.estimate().unwrap_err().to_string();
        assert!(why.contains("2 of 2 scans"), "{why}");
        let report = serde_json::to_value(&cal).unwrap();
        assert_eq!(report["refused"], why.as_str());
        assert!(cal.to_toml("mine", &[]).is_err() && cal.summary().is_empty());
        // Settings that cannot calibrate are an error before any scan is looked at.
        let bad = CalibrateOptions {
            param_scans: 0,
            ..options
        };
        let e = calibrate(scans(vec![]), &base, &Default::default(), &bad, |_| {});
        assert!(e.unwrap_err().to_string().contains("param_scans"));
    }
}
