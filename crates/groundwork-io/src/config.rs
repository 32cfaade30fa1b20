//! Loading the segmenter configuration from TOML: sensor presets (built in, from
//! `config/sensors/`), and config files laid over a preset field by field.

pub mod methods;

use std::path::{Path, PathBuf};

use groundwork_core::SegmenterConfig;

use crate::error::FormatError;

/// The sensor presets of `config/sensors/`, built into the binary so that it works from any
/// directory: (name, TOML text).
pub const SENSOR_PRESETS: &[(&str, &str)] = &[
    (
        "hdl64e",
        include_str!("../../../config/sensors/hdl64e.toml"),
    ),
    (
        "hdl32e",
        include_str!("../../../config/sensors/hdl32e.toml"),
    ),
    ("vlp16", include_str!("../../../config/sensors/vlp16.toml")),
    (
        "vlp32c",
        include_str!("../../../config/sensors/vlp32c.toml"),
    ),
    (
        "os1-64",
        include_str!("../../../config/sensors/os1-64.toml"),
    ),
    (
        "os1-128",
        include_str!("../../../config/sensors/os1-128.toml"),
    ),
    (
        "pandar64",
        include_str!("../../../config/sensors/pandar64.toml"),
    ),
    ("livox", include_str!("../../../config/sensors/livox.toml")),
    (
        "os0-64",
        include_str!("../../../config/sensors/os0-64.toml"),
    ),
    (
        "os2-64",
        include_str!("../../../config/sensors/os2-64.toml"),
    ),
    ("xt32", include_str!("../../../config/sensors/xt32.toml")),
    ("qt128", include_str!("../../../config/sensors/qt128.toml")),
    (
        "helios",
        include_str!("../../../config/sensors/helios.toml"),
    ),
    (
        "mid360",
        include_str!("../../../config/sensors/mid360.toml"),
    ),
    ("m1", include_str!("../../../config/sensors/m1.toml")),
];

/// The preset used when none is named.
pub const DEFAULT_SENSOR: &str = "hdl64e";

/// A built-in table's entry by name (any case): (name, TOML text).
pub(crate) fn builtin(
    table: &[(&'static str, &'static str)],
    name: &str,
) -> Option<(&'static str, &'static str)> {
    table
        .iter()
        .copied()
        .find(|(n, _)| n.eq_ignore_ascii_case(name))
}

/// A built-in table's names, for error messages.
pub(crate) fn builtin_names(table: &[(&str, &str)]) -> String {
    table.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")
}

/// The TOML text of a preset, or an error listing the presets.
pub fn sensor_preset_text(name: &str) -> Result<&'static str, FormatError> {
    builtin(SENSOR_PRESETS, name)
        .map(|(_, t)| t)
        .ok_or_else(|| FormatError::Config {
            path: format!("sensor {name:?}").into(),
            message: format!(
                "no such sensor preset ({}presets: {})",
                did_you_mean(name, SENSOR_PRESETS.iter().map(|(n, _)| *n))
                    .map(|m| format!("did you mean {m:?}? "))
                    .unwrap_or_default(),
                builtin_names(SENSOR_PRESETS)
            ),
        })
}

/// The candidate closest to a mistyped name, if one is close (case and `-`/`_` aside).
pub fn did_you_mean<'a>(given: &str, candidates: impl Iterator<Item = &'a str>) -> Option<&'a str> {
    let norm = |s: &str| s.to_ascii_lowercase().replace(['-', '_'], "");
    let g = norm(given);
    candidates
        .map(|c| (strsim::jaro_winkler(&g, &norm(c)), c))
        .filter(|(score, _)| *score >= 0.8)
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, c)| c)
}

/// An unknown-key error from serde (``unknown field `pich_deg`, expected one of `height`,
/// …``) with the closest expected key suggested.
fn suggest_key(message: &str) -> Option<String> {
    let rest = message.split("unknown field `").nth(1)?;
    let (given, expected) = rest.split_once('`')?;
    let candidates = expected.split('`').skip(1).step_by(2);
    did_you_mean(given, candidates).map(|c| format!("did you mean `{c}`?"))
}

/// A sensor preset's configuration.
pub fn sensor_preset(name: &str) -> Result<SegmenterConfig, FormatError> {
    let text = sensor_preset_text(name)?;
    parse_config(Path::new(&format!("config/sensors/{name}.toml")), text)
}

/// A preset (`DEFAULT_SENSOR` if None) with a config file laid over it: every field the
/// file gives replaces the preset's, tables merge key by key (a `mount` with `matrix`
/// replaces the whole mount). Unknown keys in the file are errors naming it.
pub fn load_config_over(
    preset: Option<&str>,
    path: Option<&Path>,
) -> Result<SegmenterConfig, FormatError> {
    let layers = load_layers(preset, DEFAULT_SENSOR, path, None)?;
    segmenter_config(&layers.named, layers.table)
}

/// The layers of a configuration merged into one table ([`load_layers`]).
#[derive(Debug, Clone)]
pub struct Layers {
    /// The preset under the other layers.
    pub preset: String,
    /// The name errors about the table should carry: the last layer given (only its keys
    /// can be wrong: the presets are tested).
    pub named: PathBuf,
    /// The layers merged.
    pub table: toml::Table,
}

/// The layers of a configuration merged into one table: a preset, the file at `path` over
/// it, and a table built in code over both (the Python API's keyword arguments, named
/// `source` in errors). The preset is `preset` if given, else the one the file names with
/// [`PRESET_KEY`], else `fallback`; a `preset` that is not the file's is refused, naming
/// both. Every file's syntax is checked here; the sections' keys by whoever reads them.
pub fn load_layers(
    preset: Option<&str>,
    fallback: &str,
    path: Option<&Path>,
    overlay: Option<(&str, toml::Table)>,
) -> Result<Layers, FormatError> {
    let file = match path {
        Some(p) => Some((p, read_table(p)?)),
        None => None,
    };
    merge_layers(preset, fallback, file, overlay)
}

/// [`load_layers`] with the file already read.
fn merge_layers(
    preset: Option<&str>,
    fallback: &str,
    mut file: Option<(&Path, toml::Table)>,
    overlay: Option<(&str, toml::Table)>,
) -> Result<Layers, FormatError> {
    let named_by_file = match &mut file {
        Some((p, table)) => take_preset(p, table)?.map(|name| (*p, name)),
        None => None,
    };
    let name = match (preset, &named_by_file) {
        (Some(given), Some((p, theirs))) if given != theirs => {
            return Err(FormatError::Config {
                path: p.to_path_buf(),
                message: format!(
                    "made for the {theirs:?} preset (its `{PRESET_KEY}` key), but the {given:?} \
                     preset was asked for: give --sensor {theirs} (Python: sensor=\"{theirs}\") \
                     or nothing, or remove the key to lay the file over another preset"
                ),
            });
        }
        (Some(given), _) => given,
        (None, Some((_, theirs))) => theirs.as_str(),
        (None, None) => fallback,
    };
    let base = sensor_preset_text(name)?;
    let preset_path = PathBuf::from(format!("config/sensors/{name}.toml"));
    let mut merged = parse_table(&preset_path, base)?;
    let mut named = preset_path;
    if let Some((path, table)) = file {
        merge(&mut merged, table);
        named = path.to_path_buf();
    }
    if let Some((source, table)) = overlay {
        merge(&mut merged, table);
        named = PathBuf::from(source);
    }
    Ok(Layers {
        preset: name.to_owned(),
        named,
        table: merged,
    })
}

/// The top-level key of a configuration file that names the preset it is laid over
/// (`groundwork calibrate` writes it): `--config` alone then uses that preset, and another
/// `--sensor` is refused, naming both.
pub const PRESET_KEY: &str = "preset";

/// [`PRESET_KEY`] taken out of a file's table: a known preset's name, or an error naming the
/// file.
fn take_preset(path: &Path, table: &mut toml::Table) -> Result<Option<String>, FormatError> {
    match table.remove(PRESET_KEY) {
        None => Ok(None),
        Some(toml::Value::String(name)) => match sensor_preset_text(&name) {
            Ok(_) => Ok(Some(name)),
            Err(e) => Err(config_error(path, &format!("{PRESET_KEY}: {e}"))),
        },
        Some(v) => Err(config_error(
            path,
            &format!("{PRESET_KEY}: a preset's name (a string), not {v}"),
        )),
    }
}

/// A configuration file as a table. A file that sets nothing (empty, or only comments) is
/// refused: it is what a failed write leaves, and laid over a preset it would run the
/// preset while the user believes the file is in use.
pub fn read_table(path: &Path) -> Result<toml::Table, FormatError> {
    let text = crate::file::read_text(path, crate::file::MAX_TEXT_BYTES)?;
    let table = parse_table(path, &text)?;
    if table.is_empty() {
        return Err(FormatError::Config {
            path: path.to_path_buf(),
            message: format!(
                "sets nothing ({} bytes{}): an empty configuration is refused, as it is \
                 what a failed write leaves",
                text.len(),
                if text.trim().is_empty() {
                    ""
                } else {
                    ", only comments"
                }
            ),
        });
    }
    Ok(table)
}

/// TOML text as a table; `path` names it in errors.
pub fn parse_table(path: &Path, text: &str) -> Result<toml::Table, FormatError> {
    toml::from_str(text).map_err(|e: toml::de::Error| config_error(path, &e))
}

/// A configuration error naming the file (or layer) it is about.
pub fn config_error(path: &Path, e: &dyn std::fmt::Display) -> FormatError {
    let mut message = e.to_string().trim_end().to_string();
    if let Some(hint) = suggest_key(&message) {
        message = format!("{message}\n{hint}");
    }
    FormatError::Config {
        path: path.to_path_buf(),
        message,
    }
}

/// The sections of a configuration file that are not the segmenter's: each method reads
/// and checks its own ([`methods::MethodsConfig`] reads them all).
pub const METHOD_SECTIONS: [&str; 3] = ["pseudolabeler", "ransac", "detector"];

/// The segmenter's configuration from a whole table: the method sections set aside, the rest
/// checked (unknown keys, types, ranges); `path` names it in errors.
pub fn segmenter_config(
    path: &Path,
    mut table: toml::Table,
) -> Result<SegmenterConfig, FormatError> {
    for section in METHOD_SECTIONS {
        table.remove(section);
    }
    let segmenter: SegmenterConfig = table.try_into().map_err(|e| config_error(path, &e))?;
    segmenter.validate().map_err(|e| config_error(path, &e))?;
    Ok(segmenter)
}

fn merge(base: &mut toml::Table, overlay: toml::Table) {
    // An angle in the other unit replaces the layer below's (`pitch_deg` over a preset's
    // `pitch`), rather than clash with it; one layer giving both is left to clash.
    for angle in ["roll", "pitch", "yaw"] {
        let deg = format!("{angle}_deg");
        for (given, other) in [(angle, deg.as_str()), (deg.as_str(), angle)] {
            if overlay.contains_key(given) && !overlay.contains_key(other) {
                base.remove(other);
            }
        }
    }
    for (key, value) in overlay {
        let replace_whole =
            key == "mount" && value.as_table().is_some_and(|t| t.contains_key("matrix"));
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) if !replace_whole => merge(b, o),
            (_, v) => {
                base.insert(key, v);
            }
        }
    }
}

/// Parses and validates a segmenter configuration. Unknown keys, wrong types and
/// inconsistent values are errors naming the file (and the key, where TOML knows it).
pub fn load_config(path: &Path) -> Result<SegmenterConfig, FormatError> {
    let table = read_table(path)?;
    if !table.contains_key(PRESET_KEY) {
        return segmenter_config(path, table);
    }
    // A file that names its preset is laid over it.
    let layers = merge_layers(None, DEFAULT_SENSOR, Some((path, table)), None)?;
    segmenter_config(&layers.named, layers.table)
}

/// Parses configuration text (method sections set aside); `path` is only used in error
/// messages.
pub fn parse_config(path: &Path, text: &str) -> Result<SegmenterConfig, FormatError> {
    segmenter_config(path, parse_table(path, text)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

    #[test]
    fn a_file_that_names_its_preset_is_laid_over_it_and_refuses_another() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("cal.toml");
        fs::write(&p, "preset = \"vlp16\"\n\n[sensor.mount]\nheight = 0.9\n").unwrap();
        let vlp16 = sensor_preset("vlp16").unwrap();
        // Alone, and with the same preset named: the preset's zones, the file's mount.
        for given in [None, Some("vlp16")] {
            let c = load_config_over(given, Some(&p)).unwrap();
            assert_eq!(c.zones, vlp16.zones);
            assert_eq!(c.sensor.mount.height, 0.9);
        }
        assert_eq!(
            load_config(&p).unwrap(),
            load_config_over(None, Some(&p)).unwrap()
        );
        let layers = |given| load_layers(given, DEFAULT_SENSOR, Some(&p), None);
        assert_eq!(layers(None).unwrap().preset, "vlp16");
        // Another preset asked for: refused, naming the file and both presets.
        let e = load_config_over(Some("hdl64e"), Some(&p))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("cal.toml") && e.contains("\"vlp16\"") && e.contains("\"hdl64e\""),
            "{e}"
        );
        // A name that is no preset, or no name at all.
        fs::write(&p, "preset = \"vlp61\"\n").unwrap();
        let e = load_config_over(None, Some(&p)).unwrap_err().to_string();
        assert!(e.contains("cal.toml") && e.contains("vlp16"), "{e}");
        fs::write(&p, "preset = 16\n").unwrap();
        let e = load_config_over(None, Some(&p)).unwrap_err().to_string();
        assert!(
            e.contains("cal.toml") && e.contains("a preset's name"),
            "{e}"
        );
        // A file without the key is laid over the default, as before.
        fs::write(&p, "[gmm]\nk_max = 4\n").unwrap();
        assert_eq!(layers(None).unwrap().preset, DEFAULT_SENSOR);
        assert_eq!(
            load_layers(None, "os1-64", Some(&p), None).unwrap().preset,
            "os1-64",
            "the fallback, for a file that names no preset"
        );
        let c = load_config_over(None, Some(&p)).unwrap();
        assert_eq!(c.zones, sensor_preset(DEFAULT_SENSOR).unwrap().zones);
    }

    #[test]
    fn mount_angles_may_be_given_in_degrees_but_not_twice() {
        let p = Path::new("mine.toml");
        let c = parse_config(
            p,
            "[sensor.mount]\nheight = 2.2\npitch_deg = 6\nroll = 0.1\nyaw_deg = -90",
        )
        .unwrap();
        let m = &c.sensor.mount;
        assert_eq!((m.height, m.roll), (2.2, 0.1));
        assert!((m.pitch - 6f64.to_radians()).abs() < 1e-15);
        assert!((m.yaw + std::f64::consts::FRAC_PI_2).abs() < 1e-15);
        let e = parse_config(p, "[sensor.mount]\npitch = 0.1\npitch_deg = 6")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("mine.toml")
                && e.contains("pitch (radians) or pitch_deg (degrees), not both"),
            "{e}"
        );
        let e = parse_config(p, "[sensor.mount]\npich_deg = 6")
            .unwrap_err()
            .to_string();
        assert!(e.contains("pich_deg"), "{e}");
        // A pitch in degrees over a preset's pitch in radians replaces it (and back).
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("tilt.toml");
        fs::write(&f, "[sensor.mount]\npitch_deg = -4\nroll = 0.05\n").unwrap();
        let c = load_config_over(Some("livox"), Some(&f)).unwrap();
        assert!((c.sensor.mount.pitch + 4f64.to_radians()).abs() < 1e-15);
        assert_eq!(c.sensor.mount.roll, 0.05);
        assert_eq!(
            c.sensor.mount.height,
            sensor_preset("livox").unwrap().sensor.mount.height
        );
    }

    #[test]
    fn a_mistyped_key_or_preset_gets_the_closest_name() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("typo.toml");
        fs::write(&p, "[sensor.mount]\npich_deg = -2\n").unwrap();
        let e = load_config_over(Some("vlp16"), Some(&p))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("pich_deg") && e.contains("did you mean `pitch_deg`?"),
            "{e}"
        );
        let e = sensor_preset("vlp-16").unwrap_err().to_string();
        assert!(
            e.contains("did you mean \"vlp16\"") && !e.contains("--sensor"),
            "{e}"
        );
        // Nothing close: no guess.
        fs::write(&p, "[sensor.mount]\nzzzzzz = 1\n").unwrap();
        let e = load_config_over(Some("vlp16"), Some(&p))
            .unwrap_err()
            .to_string();
        assert!(!e.contains("did you mean"), "{e}");
    }

    #[test]
    fn a_file_that_sets_nothing_is_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        for (name, text) in [("empty.toml", ""), ("comments.toml", "# nothing\n\n")] {
            let p = dir.path().join(name);
            fs::write(&p, text).unwrap();
            let e = load_config_over(Some("vlp16"), Some(&p))
                .unwrap_err()
                .to_string();
            assert!(e.contains(name) && e.contains("sets nothing"), "{e}");
            assert!(load_config(&p).is_err());
        }
    }

    #[test]
    fn unknown_keys_and_bad_values_are_errors_naming_the_file() {
        let p = Path::new("sensor.toml");
        let e = parse_config(p, "[gmm]\nk_maxx = 3\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("sensor.toml") && e.contains("k_maxx"), "{e}");
        let e = parse_config(p, "[zones]\nmax_range = 1.0\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("zones.max_range"), "{e}");
        let e = parse_config(p, "[history]\nframes = \"many\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("sensor.toml"), "{e}");
        let e = parse_config(p, "[history]\nquery = \"per_point\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("sensor.toml") && e.contains("per_point"), "{e}");
        let c = parse_config(p, "[history]\nquery = \"per_frame\"\n").unwrap();
        assert_eq!(
            c.history.query,
            groundwork_core::config::PastQuery::PerFrame
        );
        let c = parse_config(p, "[gmm]\nk_max = 4\n").unwrap();
        assert_eq!(c.gmm.k_max, 4);
        assert_eq!(c.gmm.n_min, 20, "unspecified fields keep their defaults");
    }

    #[test]
    fn every_preset_is_valid_and_named_after_its_file() {
        for (name, _) in SENSOR_PRESETS {
            let c = sensor_preset(name).unwrap();
            assert_eq!(c.sensor.name, *name);
            groundwork_core::mount_transform(&c.sensor.mount).unwrap();
        }
        let e = sensor_preset("hdl65e").unwrap_err().to_string();
        assert!(e.contains("hdl65e") && e.contains("vlp16"), "{e}");
    }

    #[test]
    fn a_config_file_overrides_single_fields_of_a_preset() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("mine.toml");
        fs::write(
            &p,
            "[sensor]\nmount = { height = 0.6, pitch = 0.1 }\n[gmm]\nk_max = 4\n",
        )
        .unwrap();
        let c = load_config_over(Some("vlp16"), Some(&p)).unwrap();
        let preset = sensor_preset("vlp16").unwrap();
        assert_eq!(c.sensor.mount.height, 0.6);
        assert_eq!(c.sensor.mount.pitch, 0.1);
        assert_eq!(c.gmm.k_max, 4);
        // Everything else is the preset's.
        assert_eq!(c.zones, preset.zones);
        assert_eq!(c.gmm.n_min, preset.gmm.n_min);
        assert_eq!(c.sensor.max_points, preset.sensor.max_points);
        // A matrix replaces the preset's height/roll/pitch/yaw.
        fs::write(
            &p,
            "[sensor.mount]\nmatrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.6], [0, 0, 0, 1]]\n",
        )
        .unwrap();
        let c = load_config_over(None, Some(&p)).unwrap();
        assert_eq!(c.sensor.mount.height, 0.0);
        assert!(c.sensor.mount.matrix.is_some());
        // Unknown keys name the user's file.
        fs::write(&p, "[sensor]\nheight = 0.6\n").unwrap();
        let e = load_config_over(None, Some(&p)).unwrap_err().to_string();
        assert!(e.contains("mine.toml") && e.contains("height"), "{e}");
    }
}
