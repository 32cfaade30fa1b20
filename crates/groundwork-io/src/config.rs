//! Loading the segmenter configuration from TOML: sensor presets (built in, from
//! `config/sensors/`), and config files laid over a preset field by field.

use std::path::{Path, PathBuf};

use groundwork_core::SegmenterConfig;
use groundwork_detect::DetectorConfig;
use groundwork_pseudolabel::{PseudoLabelerConfig, RansacConfig};

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
            path: format!("--sensor {name}").into(),
            message: format!(
                "no such sensor preset (presets: {})",
                builtin_names(SENSOR_PRESETS)
            ),
        })
}

/// A sensor preset's configuration.
pub fn sensor_preset(name: &str) -> Result<SegmenterConfig, FormatError> {
    let text = sensor_preset_text(name)?;
    parse_config(Path::new(&format!("config/sensors/{name}.toml")), text)
}

/// Everything a configuration file sets: the sensor and the GMM segmenter (top-level
/// sections), the offline methods' own sections `[pseudolabeler]` and `[ransac]`, and the
/// fallback detector's `[detector]` (sensor presets tune it to their beam spacing).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MethodsConfig {
    /// Sensor, zones, GMM, ground, height filter, history.
    pub segmenter: SegmenterConfig,
    /// `[pseudolabeler]`.
    pub pseudolabeler: PseudoLabelerConfig,
    /// `[ransac]`.
    pub ransac: RansacConfig,
    /// `[detector]`.
    pub detector: DetectorConfig,
}

/// A preset (`DEFAULT_SENSOR` if None) with a config file laid over it: every field the
/// file gives replaces the preset's, tables merge key by key (a `mount` with `matrix`
/// replaces the whole mount). Unknown keys in the file are errors naming it.
pub fn load_config_over(
    preset: Option<&str>,
    path: Option<&Path>,
) -> Result<SegmenterConfig, FormatError> {
    Ok(load_methods_config_over(preset, path)?.segmenter)
}

/// [`load_config_over`] with the `[pseudolabeler]` and `[ransac]` sections too.
pub fn load_methods_config_over(
    preset: Option<&str>,
    path: Option<&Path>,
) -> Result<MethodsConfig, FormatError> {
    load_methods_config_layers(preset, path, None)
}

/// [`load_methods_config_over`] with one more layer over the file: a table built in code
/// (the Python API's keyword arguments), named `source` in errors.
pub fn load_methods_config_layers(
    preset: Option<&str>,
    path: Option<&Path>,
    overlay: Option<(&str, toml::Table)>,
) -> Result<MethodsConfig, FormatError> {
    let name = preset.unwrap_or(DEFAULT_SENSOR);
    let base = sensor_preset_text(name)?;
    let preset_path = PathBuf::from(format!("config/sensors/{name}.toml"));
    if path.is_none() && overlay.is_none() {
        return parse_methods_config(&preset_path, base);
    }
    let config_error = |path: &Path, e: &dyn std::fmt::Display| FormatError::Config {
        path: path.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    };
    let mut merged: toml::Table =
        toml::from_str(base).map_err(|e| config_error(&preset_path, &e))?;
    // Errors name the last layer given (only its keys can be unknown: the presets are
    // tested).
    let mut named = preset_path;
    if let Some(path) = path {
        let text = crate::file::read_text(path, crate::file::MAX_TEXT_BYTES)?;
        let overlay: toml::Table = toml::from_str(&text).map_err(|e| config_error(path, &e))?;
        merge(&mut merged, overlay);
        named = path.to_path_buf();
    }
    if let Some((source, table)) = overlay {
        merge(&mut merged, table);
        named = PathBuf::from(source);
    }
    split_methods(&named, merged)
}

/// Deserialises a whole configuration table: the method and detector sections apart, the rest as
/// the segmenter's (every part rejects unknown keys).
fn split_methods(path: &Path, mut table: toml::Table) -> Result<MethodsConfig, FormatError> {
    let config_error = |e: &dyn std::fmt::Display| FormatError::Config {
        path: path.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    };
    fn section<T: serde::de::DeserializeOwned + Default>(
        table: &mut toml::Table,
        name: &str,
    ) -> Result<T, String> {
        match table.remove(name) {
            None => Ok(T::default()),
            Some(v) => v
                .try_into()
                .map_err(|e: toml::de::Error| format!("[{name}]: {}", e.to_string().trim_end())),
        }
    }
    let pseudolabeler: PseudoLabelerConfig =
        section(&mut table, "pseudolabeler").map_err(|e| config_error(&e))?;
    pseudolabeler.validate().map_err(|e| config_error(&e))?;
    let ransac: RansacConfig = section(&mut table, "ransac").map_err(|e| config_error(&e))?;
    ransac.validate().map_err(|e| config_error(&e))?;
    let detector: DetectorConfig = section(&mut table, "detector").map_err(|e| config_error(&e))?;
    detector.validate().map_err(|e| config_error(&e))?;
    let segmenter: SegmenterConfig = table.try_into().map_err(|e| config_error(&e))?;
    segmenter.validate().map_err(|e| config_error(&e))?;
    Ok(MethodsConfig {
        segmenter,
        pseudolabeler,
        ransac,
        detector,
    })
}

/// Parses a whole configuration text (sensor, segmenter and method sections); `path` is
/// only used in error messages.
pub fn parse_methods_config(path: &Path, text: &str) -> Result<MethodsConfig, FormatError> {
    let table: toml::Table = toml::from_str(text).map_err(|e| FormatError::Config {
        path: path.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })?;
    split_methods(path, table)
}

fn merge(base: &mut toml::Table, overlay: toml::Table) {
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
    let text = crate::file::read_text(path, crate::file::MAX_TEXT_BYTES)?;
    parse_config(path, &text)
}

/// Parses configuration text (method sections are checked, then set aside); `path` is only
/// used in error messages.
pub fn parse_config(path: &Path, text: &str) -> Result<SegmenterConfig, FormatError> {
    Ok(parse_methods_config(path, text)?.segmenter)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

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
    fn method_sections_are_read_and_checked_apart_from_the_segmenter() {
        let p = Path::new("mine.toml");
        let c = parse_methods_config(
            p,
            "[gmm]\nk_max = 4\n[pseudolabeler]\nseed = 7\nhidden = [16, 16]\n[ransac]\niterations = 50\n",
        )
        .unwrap();
        assert_eq!(c.segmenter.gmm.k_max, 4);
        assert_eq!(c.pseudolabeler.seed, 7);
        assert_eq!(c.pseudolabeler.hidden, [16, 16]);
        assert_eq!(
            c.pseudolabeler.ground_distance, 0.40,
            "paper's default kept"
        );
        assert_eq!(c.ransac.iterations, 50);
        let e = parse_methods_config(p, "[pseudolabeler]\nhuber = 0.1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("mine.toml") && e.contains("huber"), "{e}");
        let e = parse_methods_config(p, "[ransac]\nmax_tilt_deg = 120.0\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("ransac.max_tilt_deg"), "{e}");
        let e = parse_methods_config(p, "[pseudolabeler]\nprefilter_quantile = 0.5e2\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("pseudolabeler.prefilter_quantile"), "{e}");
        let c = parse_methods_config(p, "[detector]\ncluster_distance = 0.4\n").unwrap();
        assert_eq!(c.detector.cluster_distance, 0.4);
        let e = parse_methods_config(p, "[detector]\nmin_points = 0\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("detector.min_points"), "{e}");
        let e = parse_methods_config(p, "[detector]\nradius = 1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("radius"), "{e}");
        // The presets tune the detector to their beam spacing.
        let vlp16 = load_methods_config_over(Some("vlp16"), None).unwrap();
        assert_eq!(vlp16.detector.vertical_distance_per_metre, 0.05);
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

    #[test]
    fn a_table_in_code_is_laid_over_the_file_and_names_itself_in_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("mine.toml");
        fs::write(&p, "[gmm]\nk_max = 4\n[ground]\nground_threshold = 0.7\n").unwrap();
        let overlay: toml::Table = toml::from_str("[ground]\nground_threshold = 0.6\n").unwrap();
        let c = load_methods_config_layers(Some("vlp16"), Some(&p), Some(("kwargs", overlay)))
            .unwrap()
            .segmenter;
        // The last layer wins; the file's other keys and the preset's stay.
        assert_eq!(c.ground.ground_threshold, 0.6);
        assert_eq!(c.gmm.k_max, 4);
        assert_eq!(c.zones, sensor_preset("vlp16").unwrap().zones);
        let bad: toml::Table = toml::from_str("[gmm]\nk_maxx = 3\n").unwrap();
        let e = load_methods_config_layers(None, Some(&p), Some(("kwargs", bad)))
            .unwrap_err()
            .to_string();
        assert!(e.contains("kwargs") && e.contains("k_maxx"), "{e}");
    }
}
