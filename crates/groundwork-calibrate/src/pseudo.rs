//! The parameter fit on the PseudoLabeler's labels, whole: a sample of raw scans labelled
//! by TerraSeg's PseudoLabeler on the mount found, then [`fit_parameters`] to those labels.
//! What `groundwork calibrate` runs after the mount (and `groundwork.calibrate` in Python).

use std::sync::atomic::{AtomicUsize, Ordering};

use groundwork_core::SegmenterConfig;
use groundwork_pseudolabel::{GroundFrame, PseudoLabeler, PseudoLabelerConfig};
use rayon::prelude::*;

use crate::CalibrateError;
use crate::params::{LabeledScan, ParamFit, ParamSearchConfig, fit_parameters, too_few_scans};

/// How far [`fit_to_pseudo_labels`] has come, for a progress display.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FitProgress {
    /// Scans of the sample labelled so far, of all.
    Labelled {
        /// Labelled so far.
        done: usize,
        /// The sample's scans.
        of: usize,
    },
    /// Segmenter runs of the search so far, and at most.
    Searched {
        /// Runs so far.
        done: usize,
        /// Runs at most.
        most: usize,
    },
}

/// Each scan's points labelled ground (probability ≥ 0.5) or not by `labeler`, in parallel.
/// `labelled` is called once per scan labelled (from any thread).
pub fn pseudo_ground(
    labeler: &PseudoLabeler,
    scans: &[Vec<[f32; 3]>],
    labelled: impl Fn() + Sync,
) -> Result<Vec<Vec<bool>>, CalibrateError> {
    scans
        .par_iter()
        .enumerate()
        .map(|(k, points)| {
            let mut p = vec![0.0f32; points.len()];
            labeler.label(points, &mut p).map_err(|e| {
                CalibrateError::Refused(format!("the PseudoLabeler on scan {k} of the sample: {e}"))
            })?;
            labelled();
            Ok(p.iter().map(|&p| p >= 0.5).collect())
        })
        .collect()
}

/// `sample` labelled by the PseudoLabeler configured by `labeler` on `base`'s mount (the
/// mount found), then `base`'s parameters fitted to those labels by [`fit_parameters`].
pub fn fit_to_pseudo_labels(
    base: &SegmenterConfig,
    labeler: &PseudoLabelerConfig,
    sample: &[Vec<[f32; 3]>],
    search: &ParamSearchConfig,
    progress: impl Fn(FitProgress) + Sync,
) -> Result<ParamFit, CalibrateError> {
    let config =
        |what: &str, e: &dyn std::fmt::Display| CalibrateError::Config(format!("{what}: {e}"));
    // Before the labelling, which is most of the cost.
    let every = search.held_out_every.max(2);
    if sample.len() < every {
        return Err(too_few_scans(sample.len(), every));
    }
    base.validate()
        .map_err(|e| config("the calibrated mount", &e))?;
    let frame = GroundFrame::from_config(base).map_err(|e| config("the calibrated mount", &e))?;
    let labeler =
        PseudoLabeler::new(labeler.clone(), frame).map_err(|e| config("pseudolabeler", &e))?;
    let done = AtomicUsize::new(0);
    let of = sample.len();
    progress(FitProgress::Labelled { done: 0, of });
    let ground = pseudo_ground(&labeler, sample, || {
        let done = done.fetch_add(1, Ordering::Relaxed) + 1;
        progress(FitProgress::Labelled { done, of });
    })?;
    fit_parameters(
        base,
        &LabeledScan::pair(sample, &ground),
        search,
        |done, most| progress(FitProgress::Searched { done, most }),
    )
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use super::*;

    /// A level ground disc 3–40 m around a sensor `height` above it, and a box 1 m high
    /// 8 m ahead; `(points, true where ground)`.
    fn scene(height: f32, turn: f32) -> (Vec<[f32; 3]>, Vec<bool>) {
        let (mut points, mut ground) = (Vec::new(), Vec::new());
        for ring in 0..60 {
            let r = 3.0 + 0.6 * ring as f32;
            for k in 0..360 {
                let a = (k as f32 + turn).to_radians();
                points.push([r * a.cos(), r * a.sin(), -height]);
                ground.push(true);
            }
        }
        for i in 0..20 {
            for j in 0..20 {
                let (y, z) = (-1.0 + 0.1 * i as f32, -height + 0.3 + 0.05 * j as f32);
                points.push([8.0, y, z]);
                ground.push(false);
            }
        }
        (points, ground)
    }

    #[test]
    fn the_sample_is_labelled_then_fitted_with_progress_and_bad_settings_refused() {
        let base = SegmenterConfig::default();
        let h = base.sensor.mount.height as f32;
        let (scenes, truth): (Vec<_>, Vec<_>) = (0..8).map(|k| scene(h, k as f32 * 0.3)).unzip();
        let labeller = PseudoLabelerConfig::default();
        // The labels: the disc ground, the box not.
        let labeler =
            PseudoLabeler::new(labeller.clone(), GroundFrame::from_config(&base).unwrap()).unwrap();
        let calls = AtomicUsize::new(0);
        let ground = pseudo_ground(&labeler, &scenes, || {
            calls.fetch_add(1, Ordering::Relaxed);
        })
        .unwrap();
        assert_eq!(calls.into_inner(), scenes.len());
        for (g, t) in ground.iter().zip(&truth) {
            assert_eq!(g.len(), t.len());
            let agree = g.iter().zip(t).filter(|(a, b)| a == b).count();
            assert!(
                agree as f64 > 0.95 * t.len() as f64,
                "{agree} of {}",
                t.len()
            );
        }
        // The whole fit: every scan labelled once, the search's progress never past its
        // most, the sample split into fitted and held-out scans.
        let seen = Mutex::new(Vec::new());
        let fit = fit_to_pseudo_labels(
            &base,
            &labeller,
            &scenes,
            &ParamSearchConfig::default(),
            |p| seen.lock().unwrap().push(p),
        )
        .unwrap();
        let seen = seen.into_inner().unwrap();
        let mut labelled: Vec<usize> = seen
            .iter()
            .filter_map(|p| match p {
                FitProgress::Labelled { done, of } => {
                    assert_eq!(*of, scenes.len());
                    Some(*done)
                }
                FitProgress::Searched { .. } => None,
            })
            .collect();
        labelled.sort_unstable();
        assert_eq!(labelled, (0..=scenes.len()).collect::<Vec<_>>());
        let searched: Vec<(usize, usize)> = seen
            .iter()
            .filter_map(|p| match p {
                FitProgress::Searched { done, most } => Some((*done, *most)),
                FitProgress::Labelled { .. } => None,
            })
            .collect();
        assert!(!searched.is_empty() && searched.iter().all(|(d, m)| d <= m));
        assert_eq!((fit.fitted_scans, fit.held_out_scans), (6, 2));
        // A clean scene agrees with its labels from the start: nothing to gain, preset kept.
        assert!(
            fit.held_out_before.iou() > 95.0,
            "{:?}",
            fit.held_out_before
        );
        assert!(fit.kept_preset && fit.changed.is_empty());

        // A mount that is no mount, and too few scans, are refused with the reason.
        let mut bad = base.clone();
        bad.sensor.mount.height = f64::NAN;
        let e = fit_to_pseudo_labels(&bad, &labeller, &scenes, &Default::default(), |_| {});
        assert!(matches!(e, Err(CalibrateError::Config(m)) if m.contains("calibrated mount")));
        let e = fit_to_pseudo_labels(&base, &labeller, &scenes[..3], &Default::default(), |_| {});
        assert!(matches!(e, Err(CalibrateError::Refused(m)) if m.contains("too few")));
    }
}
