//! The calibration as text: the configuration file ([`Calibration::to_toml`]), laid over
//! its preset with `--sensor <preset> --config <file>`, each changed value's old one in a
//! comment; and the summary for a terminal ([`Calibration::summary`]).

use std::fmt::Write as _;

use groundwork_core::SegmenterConfig;
use groundwork_core::config::{MountConfig, ZoneConfig};
use groundwork_core::mount_transform;

use crate::calibration::{Calibration, NearEdge};
use crate::mount::Estimate;
use crate::{CalibrateError, HeightScale, MountEstimate, ParamFit};

impl Calibration {
    /// The configuration file: what differs from the base preset, each changed value's old
    /// one in a comment, readable and loadable with `--sensor <base> --config <file>`.
    /// `name`: the configuration's name (`sensor.name`); `inputs`: where the scans came from,
    /// as the file's first comment says it. Refused when the mount was.
    pub fn to_toml(&self, name: &str, inputs: &[String]) -> Result<String, CalibrateError> {
        let est = self.estimate()?;
        let base = &self.base;
        let mut text = preset_text(&self.base_preset, name, &self.prior, est, inputs);
        if let Some(z) = self.final_zones() {
            let moved = self.near_edge.as_ref().filter(|n| n.min_range.is_some());
            text += &zones_text(&base.zones, z, moved, self.height_scale.as_ref());
        }
        if let Some(fit) = &self.parameters {
            text += &params_text(base, fit);
        } else if let Some(why) = &self.parameters_refused {
            let _ = writeln!(
                text,
                "\n# Parameters not fitted (the preset's are kept): {why}"
            );
        }
        Ok(text)
    }

    /// What was found, for a terminal: the mount against the prior, the zones' near edge and
    /// scaling, and the parameter fit (or why there was none). Empty for a refused mount.
    pub fn summary(&self) -> String {
        let Ok(est) = self.estimate() else {
            return String::new();
        };
        let mut s = summary(&self.base_preset, &self.prior, est);
        match &self.near_edge {
            Some(NearEdge {
                ground,
                was,
                min_range: Some(m),
            }) => {
                let _ = writeln!(
                    s,
                    "  near edge of the zones {m:.2} m  was {was:.2} m (ground from {:.2} m)",
                    ground.range
                );
            }
            Some(NearEdge { ground, was, .. }) => {
                let _ = writeln!(
                    s,
                    "  near edge of the zones kept at {was:.2} m (ground from {:.2} m)",
                    ground.range
                );
            }
            None => {}
        }
        if let Some(h) = &self.height_scale {
            let _ = writeln!(
                s,
                "  inner zone boundaries scaled by {:.3} with the height: {:?}  was {:?}",
                h.ratio, h.boundaries, h.was
            );
        }
        // After the mount, as in the file.
        if let Some(fit) = &self.parameters {
            s += &params_summary(fit);
        } else if let Some(why) = &self.parameters_refused {
            let _ = writeln!(s, "parameters not fitted, the preset's kept: {why}");
        }
        s
    }

    /// Why the parameters were kept for too few trusted points, if so (a warning's words).
    pub fn too_few_trusted_points(&self) -> Option<String> {
        self.parameters
            .as_ref()
            .filter(|f| f.too_few_trusted_points)
            .map(too_few_words)
    }
}

/// The `[zones]` section: the near edge moved in (`near`), the inner boundaries scaled
/// with the height (`scale`) and the inner zones' layout as the parameter fit left it,
/// each changed value's old one in a comment.
fn zones_text(
    preset: &ZoneConfig,
    z: &ZoneConfig,
    near: Option<&NearEdge>,
    scale: Option<&HeightScale>,
) -> String {
    let list = |v: &[f64]| {
        let v: Vec<String> = v.iter().map(|v| format!("{v:?}")).collect();
        format!("[{}]", v.join(", "))
    };
    let whole = |v: &[u32]| format!("{v:?}");
    let was = |new: &str, old: &str| {
        if new == old {
            String::new()
        } else {
            format!("  # was {old}")
        }
    };
    let mut s = String::from("\n[zones]\n");
    if let Some(n) = near {
        let _ = write!(
            s,
            "# The near edge moved in to where the scans first see ground on the mount found:\n\
             # {:.2} m (the median over {} scans of the 1st percentile of the range of points\n\
             # within 15 cm of the ground), times 0.9.\n",
            n.ground.range, n.ground.scans
        );
    }
    if let Some(h) = scale {
        let _ = write!(
            s,
            "# The inner boundaries scaled by {:.3}, the height found over the preset's (beams\n\
             # meet the ground at ranges in proportion to the height); before: {:?}.\n",
            h.ratio, h.was
        );
    }
    let (old_b, new_b) = (
        preset.resolved_boundaries().unwrap_or_default(),
        z.resolved_boundaries().unwrap_or_default(),
    );
    let scaled_b = scale.map(|h| h.boundaries.as_slice());
    if (new_b[1..] != old_b[1..] && scaled_b.is_none_or(|b| b[1..] != new_b[1..]))
        || z.rings != preset.rings
        || z.sectors != preset.sectors
    {
        s += "# The inner zones' layout fitted to the PseudoLabeler's labels (see the parameters\n\
              # below).\n";
    }
    let (min_new, min_old) = (
        format!("{:?}", z.min_range),
        format!("{}", preset.min_range),
    );
    let _ = writeln!(s, "min_range = {min_new}{}", was(&min_new, &min_old));
    let (b_new, b_old) = (list(&new_b), list(&old_b));
    let _ = writeln!(s, "boundaries = {b_new}{}", was(&b_new, &b_old));
    for (key, new, old) in [
        ("rings", &z.rings, &preset.rings),
        ("sectors", &z.sectors, &preset.sectors),
    ] {
        if new != old {
            let _ = writeln!(s, "{key} = {}{}", whole(new), was(&whole(new), &whole(old)));
        }
    }
    s
}

/// The fit's figures in one line: the sample, the trusted range and the agreement with the
/// PseudoLabeler's labels (ground IoU, %) before and after.
fn fit_figures(fit: &ParamFit) -> String {
    format!(
        "{} scans ({} held out), within {} m: agreement with the PseudoLabeler, held out, \
         {:.2} -> {:.2} (fitted scans {:.2} -> {:.2})",
        fit.fitted_scans + fit.held_out_scans,
        fit.held_out_scans,
        fit.trusted_range,
        fit.held_out_before.iou(),
        fit.held_out_after.iou(),
        fit.fitted_before.iou(),
        fit.fitted_after.iou(),
    )
}

/// The fitted parameters as TOML, after the mount: what changed, each old value in a comment,
/// and the agreement with the PseudoLabeler before and after.
fn params_text(base: &SegmenterConfig, fit: &ParamFit) -> String {
    let mut s = format!(
        "\n# Parameters fitted to the PseudoLabeler's labels (ground IoU with them, within the\n\
         # range where the preset and the labels agree), from\n# {}.\n",
        fit_figures(fit)
    );
    if fit.kept_preset {
        s += &if fit.too_few_trusted_points {
            format!(
                "# Not fitted: {}.\n# The preset's parameters are kept.\n",
                too_few_words(fit)
            )
        } else if labels_hold_no_ground(fit) {
            "# The PseudoLabeler called nothing ground there: the preset's parameters are kept.\n"
                .to_owned()
        } else {
            comment_lines(&format!(
                "The preset's parameters are kept: {}.",
                not_better_words(fit)
            ))
        };
        return s;
    }
    let changes = crate::ground_changes(&base.ground, &fit.config.ground);
    if !changes.is_empty() {
        s += "[ground]\n";
    }
    for c in changes {
        let _ = writeln!(s, "{} = {}  # was {}", c.key, c.new, c.old);
    }
    s
}

/// Why a sample with too few trusted points was not fitted, in a sentence.
fn too_few_words(fit: &ParamFit) -> String {
    format!(
        "only {:.0} points a scan are ground within {} m, where the labels are trusted ({} \
         needed): too few to fit to",
        fit.trusted_points_per_scan, fit.trusted_range, fit.trusted_points_needed
    )
}

/// Why a search that ran kept the preset's parameters, in a sentence with its figures: no
/// change gained on the fitted scans, or the best round's gain on the held-out scans was
/// below the bar (and what the bar is for).
fn not_better_words(fit: &ParamFit) -> String {
    let before = fit.held_out_before.iou();
    let best = fit
        .history
        .iter()
        .skip(1)
        .max_by(|a, b| a.held_out_iou.total_cmp(&b.held_out_iou));
    match best {
        None => "no change agreed better with the labels of the fitted scans".to_owned(),
        Some(b) => format!(
            "the fit agreed {:+.2} points with the held-out scans at best ({before:.2} -> {:.2}, \
             round {}), {} {} needed; fits below that bar lost against the truth as often as \
             they gained (docs/calibration.md)",
            b.held_out_iou - before,
            b.held_out_iou,
            b.round,
            if b.held_out_iou - before > 0.0 {
                "less than the"
            } else {
                "not the"
            },
            fit.held_out_gain_needed,
        ),
    }
}

/// Whether the PseudoLabeler's labels of the sample hold no ground within the trusted range:
/// agreement with them is then 0 for any parameters.
fn labels_hold_no_ground(fit: &ParamFit) -> bool {
    [&fit.fitted_before, &fit.held_out_before]
        .iter()
        .all(|a| a.both + a.reference_only == 0)
}

/// Below this agreement (ground IoU with the PseudoLabeler, %) the figure is flagged as
/// saying little: on real scans where both are right it is above 90.
const WEAK_AGREEMENT: f64 = 80.0;

/// The parameter fit, for the terminal.
fn params_summary(fit: &ParamFit) -> String {
    let mut s = format!(
        "parameters from {}; {} segmenter runs\n",
        fit_figures(fit),
        fit.evaluations
    );
    // What the agreement is, and when it says little: it is not the accuracy.
    let _ = writeln!(
        s,
        "  (agreement: ground IoU between the segmenter's ground and the PseudoLabeler's within \
         {} m, a check that a change carries over to unseen scans; not accuracy against the \
         truth, which needs labels: groundwork eval)",
        fit.trusted_range
    );
    let agreement = fit.held_out_before.iou().min(fit.fitted_before.iou());
    if agreement < WEAK_AGREEMENT && !labels_hold_no_ground(fit) {
        let _ = writeln!(
            s,
            "  caution: agreement below {WEAK_AGREEMENT:.0}: the PseudoLabeler's labels differ \
             from the segmenter's ground here for reasons of their own (its elevation map, the \
             scene), so this figure says little about either; check the result with labelled \
             scans or `groundwork render --compare`"
        );
    }
    if fit.kept_preset {
        s += &if fit.too_few_trusted_points {
            format!("  kept the preset's: {}\n", too_few_words(fit))
        } else if labels_hold_no_ground(fit) {
            "  kept the preset's: the PseudoLabeler called nothing ground where its labels are \
             trusted, so they cannot teach (it can lose the ground where the terrain falls far \
             below the road: docs/offline-labels.md)\n"
                .to_owned()
        } else {
            format!("  kept the preset's: {}\n", not_better_words(fit))
        };
    }
    for c in &fit.changed {
        let _ = writeln!(s, "  {} {}  was {}", c.name, c.new, c.old);
    }
    s
}

/// `value ± error unit`, with the spread over the scans.
fn shown(e: &Estimate, scale: f64, unit: &str, digits: usize) -> String {
    format!(
        "{:.digits$}{unit} ± {:.digits$}{unit} (spread {:.digits$}{unit})",
        e.value * scale,
        e.standard_error * scale,
        e.spread * scale,
    )
}

/// What was found, for the terminal.
fn summary(base: &str, prior: &MountConfig, est: &MountEstimate) -> String {
    let d = 180.0 / std::f64::consts::PI;
    let mut s = format!(
        "mount from {} of {} scans (prior: the {base} preset's)\n",
        est.frames_used, est.frames
    );
    let _ = writeln!(
        s,
        "  height {}  was {:.3} m",
        shown(&est.height, 1.0, " m", 3),
        prior.height
    );
    let _ = writeln!(
        s,
        "  roll   {}  was {:.2}°",
        shown(&est.roll, d, "°", 2),
        prior.roll * d
    );
    let _ = writeln!(
        s,
        "  pitch  {}  was {:.2}°",
        shown(&est.pitch, d, "°", 2),
        prior.pitch * d
    );
    if let Some(o) = &est.one_sided {
        let _ = writeln!(s, "  caveat: {o}");
    }
    if !est.disagreeing.is_empty() {
        let _ = writeln!(
            s,
            "  caveat: {} scan(s) disagree in height and were outvoted (named above)",
            est.disagreeing.len()
        );
    }
    s
}

/// The configuration file: what differs from the base preset, each changed value's old one
/// in a comment, readable and loadable with `--sensor <base> --config <file>`.
fn preset_text(
    base: &str,
    name: &str,
    prior: &MountConfig,
    est: &MountEstimate,
    inputs: &[String],
) -> String {
    let d = 180.0 / std::f64::consts::PI;
    let mut s = format!(
        "# Calibrated by `groundwork calibrate` from {} of {} scans of {}.\n\
         # Use: groundwork segment --config <this file> ... (it names its preset)\n\
         # It holds what differs from the {base} preset; each changed value's old one is in\n\
         # the comment after it, with the estimate's standard error and its spread over the\n\
         # scans.\n\n\
         preset = {base:?}\n\n\
         [sensor]\n\
         name = {name:?}  # was {:?}\n\n\
         [sensor.mount]\n",
        est.frames_used,
        est.frames,
        inputs.join(", "),
        base,
    );
    let m = est.mount();
    if prior.matrix.is_some() {
        // The preset gives a matrix; the file must too (a mount is one or the other).
        let h = mount_transform(&m).map(|t| t.to_homogeneous());
        if let Ok(h) = h {
            let rows: Vec<String> = (0..4)
                .map(|r| {
                    let v: Vec<String> = (0..4).map(|c| format!("{:.6}", h[(r, c)])).collect();
                    format!("[{}]", v.join(", "))
                })
                .collect();
            let _ = writeln!(
                s,
                "matrix = [{}]  # the preset gave a matrix",
                rows.join(", ")
            );
        }
    } else {
        let _ = writeln!(
            s,
            "height = {:.4}  # was {}; ± {:.4} m (spread {:.4} m)",
            m.height, prior.height, est.height.standard_error, est.height.spread
        );
        for (key, new, old, e) in [
            ("roll_deg", m.roll, prior.roll, &est.roll),
            ("pitch_deg", m.pitch, prior.pitch, &est.pitch),
        ] {
            let _ = writeln!(
                s,
                "{key} = {:.3}  # was {:.3}°; ± {:.3}° (spread {:.3}°)",
                new * d,
                old * d,
                e.standard_error * d,
                e.spread * d
            );
        }
        let _ = writeln!(
            s,
            "yaw_deg = {:.3}  # kept: the ground does not show yaw",
            m.yaw * d
        );
    }
    if let Some(o) = &est.one_sided {
        s += &comment_lines(&format!("Caveat: {o}."));
    }
    s
}

/// `text` as TOML comment lines of at most about 90 characters, broken between words.
fn comment_lines(text: &str) -> String {
    let mut out = String::new();
    let mut line = String::from("#");
    for word in text.split_whitespace() {
        if line.len() > 1 && line.len() + 1 + word.len() > 90 {
            out += &line;
            out.push('\n');
            line = String::from("#");
        }
        line.push(' ');
        line += word;
    }
    out + &line + "\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    fn est(v: [f64; 3]) -> MountEstimate {
        let e = |value| Estimate {
            value,
            spread: 0.01,
            standard_error: 0.004,
        };
        MountEstimate {
            height: e(v[0]),
            roll: e(v[1]),
            pitch: e(v[2]),
            yaw: 0.0,
            frames_used: 5,
            frames: 6,
            one_sided: None,
            disagreeing: Vec::new(),
        }
    }

    #[test]
    fn a_fit_to_labels_without_ground_says_why_the_preset_is_kept() {
        let none = crate::Agreement {
            both: 0,
            segmenter_only: 900,
            reference_only: 0,
        };
        let fit = ParamFit {
            config: SegmenterConfig::default(),
            changed: Vec::new(),
            fitted_before: none,
            fitted_after: none,
            held_out_before: none,
            held_out_after: none,
            fitted_scans: 18,
            held_out_scans: 6,
            evaluations: 19,
            rounds: 1,
            kept_round: 0,
            kept_preset: true,
            trusted_points_per_scan: 0.0,
            too_few_trusted_points: false,
            trusted_points_needed: 500,
            held_out_gain_needed: 2.5,
            history: Vec::new(),
            trusted_range: 10.0,
            ring_agreement: vec![0.0],
        };
        let base = SegmenterConfig::default();
        assert!(params_summary(&fit).contains("called nothing ground"));
        assert!(params_text(&base, &fit).contains("called nothing ground"));
        // Labels with ground that no change agreed better with: the usual words.
        let some = crate::Agreement { both: 50, ..none };
        let fit = ParamFit {
            held_out_before: some,
            fitted_before: some,
            ..fit
        };
        assert!(params_summary(&fit).contains("no change agreed better"));
        assert!(params_text(&base, &fit).contains("no change agreed better"));
        // A search whose best round gained too little on the held-out scans: said with
        // the figures and the bar.
        let b = fit.held_out_before.iou();
        let round = |round, held_out_iou| crate::RoundScore {
            round,
            fitted_iou: 90.0,
            held_out_iou,
        };
        let short = ParamFit {
            history: vec![round(0, b), round(1, b + 0.5), round(2, b + 0.73)],
            held_out_gain_needed: 2.5,
            ..fit.clone()
        };
        let said = params_summary(&short);
        assert!(
            said.contains("+0.73 points")
                && said.contains("round 2")
                && said.contains("2.5 needed"),
            "{said}"
        );
        let text = params_text(&base, &short);
        assert!(
            text.contains("+0.73 points")
                && text
                    .lines()
                    .skip_while(|l| !l.starts_with("# The preset's parameters are kept"))
                    .all(|l| l.starts_with("# ") && l.len() <= 92),
            "{text}"
        );
        // Too few trusted points: said with the figures.
        let sparse = ParamFit {
            trusted_points_per_scan: 115.4,
            too_few_trusted_points: true,
            ..fit
        };
        let said = params_summary(&sparse);
        assert!(
            said.contains("only 115 points a scan") && said.contains("500 needed"),
            "{said}"
        );
        assert!(params_text(&base, &sparse).contains("# Not fitted: only 115 points a scan"));
    }

    #[test]
    fn the_written_file_loads_over_its_preset_and_gives_the_mount() {
        let dir = tempfile::tempdir().unwrap();
        for base in ["vlp16", "livox", "hdl32e"] {
            let prior = groundwork_io::sensor_preset(base).unwrap().sensor.mount;
            // The estimate keeps the prior's yaw, as `combine` does.
            let e = MountEstimate {
                yaw: prior.yaw,
                ..est([1.9, 0.1, -0.07])
            };
            let text = preset_text(base, "mine", &prior, &e, &["a".to_owned()]);
            let path = dir.path().join(format!("{base}.toml"));
            std::fs::write(&path, &text).unwrap();
            let c = groundwork_io::load_config_over(Some(base), Some(&path)).unwrap();
            let m = &c.sensor.mount;
            assert!((m.height - 1.9).abs() < 1e-4, "{text}");
            assert!(
                (m.roll - 0.1).abs() < 1e-4 && (m.pitch + 0.07).abs() < 1e-4,
                "{text}"
            );
            assert!((m.yaw - prior.yaw).abs() < 1e-4, "{text}");
            assert_eq!(c.sensor.name, "mine");
            assert!(text.contains(&format!("# was {}", prior.height)), "{text}");
        }
    }

    #[test]
    fn ground_seen_on_one_side_is_said_in_comments_and_the_file_still_loads() {
        let prior = groundwork_io::sensor_preset("livox").unwrap().sensor.mount;
        let one_sided = crate::OneSidedGround {
            leverage: 3.2,
            nearest: 6.3,
        };
        let e = MountEstimate {
            yaw: prior.yaw,
            one_sided: Some(one_sided),
            ..est([1.3, 0.0, 0.04])
        };
        let text = preset_text("livox", "mine", &prior, &e, &["a".to_owned()]);
        let caveat: Vec<&str> = text
            .lines()
            .skip_while(|l| !l.starts_with("# Caveat"))
            .collect();
        assert!(caveat.len() >= 3, "{text}");
        assert!(
            caveat.iter().all(|l| l.starts_with("# ") && l.len() <= 92),
            "{text}"
        );
        let joined: Vec<&str> = caveat.iter().map(|l| &l[2..]).collect();
        assert_eq!(joined.join(" "), format!("Caveat: {one_sided}."));
        assert!(summary("livox", &prior, &e).contains("from 6.3 m, leverage 3.2"));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mine.toml");
        std::fs::write(&path, &text).unwrap();
        let c = groundwork_io::load_config_over(Some("livox"), Some(&path)).unwrap();
        assert!((c.sensor.mount.height - 1.3).abs() < 1e-4);
        // Told nothing of the kind, the file says nothing of it.
        let plain = preset_text("livox", "mine", &prior, &est([1.3, 0.0, 0.04]), &[]);
        assert!(
            !plain.contains("Caveat")
                && !summary("livox", &prior, &est([1.3, 0.0, 0.04])).contains("caveat")
        );
    }
}
