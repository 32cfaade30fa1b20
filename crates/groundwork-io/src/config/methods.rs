//! The whole configuration of a run: the segmenter's sections and every other method's own
//! (`[pseudolabeler]`, `[ransac]`, `[detector]`), read from the same layers (a sensor
//! preset, a file over it, a table built in code), each section checked by its crate: the
//! one schema the CLI, the service and the Python package read.

use std::path::Path;

use crate::FormatError;
use crate::config::{DEFAULT_SENSOR, config_error, load_layers, parse_table, segmenter_config};
use groundwork_core::SegmenterConfig;
use groundwork_detect::DetectorConfig;
use groundwork_pseudolabel::{PseudoLabelerConfig, RansacConfig};

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

/// A preset (`DEFAULT_SENSOR` if None) with a config file laid over it, every section read.
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
    load_methods_config_named(preset, DEFAULT_SENSOR, path, overlay).map(|(_, c)| c)
}

/// [`load_methods_config_layers`], and the preset the configuration was laid over: `preset`
/// if given, else the one the file names, else `fallback` ([`load_layers`]).
pub fn load_methods_config_named(
    preset: Option<&str>,
    fallback: &str,
    path: Option<&Path>,
    overlay: Option<(&str, toml::Table)>,
) -> Result<(String, MethodsConfig), FormatError> {
    let layers = load_layers(preset, fallback, path, overlay)?;
    Ok((layers.preset, split_methods(&layers.named, layers.table)?))
}

/// Parses a whole configuration text; `path` is only used in error messages.
pub fn parse_methods_config(path: &Path, text: &str) -> Result<MethodsConfig, FormatError> {
    split_methods(path, parse_table(path, text)?)
}

/// Deserialises a whole configuration table: each method's section apart, the rest as the
/// segmenter's (every part rejects unknown keys and checks its ranges).
fn split_methods(path: &Path, mut table: toml::Table) -> Result<MethodsConfig, FormatError> {
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
    let err = |e: &dyn std::fmt::Display| config_error(path, e);
    let pseudolabeler: PseudoLabelerConfig =
        section(&mut table, "pseudolabeler").map_err(|e| err(&e))?;
    pseudolabeler.validate().map_err(|e| err(&e))?;
    let ransac: RansacConfig = section(&mut table, "ransac").map_err(|e| err(&e))?;
    ransac.validate().map_err(|e| err(&e))?;
    let detector: DetectorConfig = section(&mut table, "detector").map_err(|e| err(&e))?;
    detector.validate().map_err(|e| err(&e))?;
    Ok(MethodsConfig {
        segmenter: segmenter_config(path, table)?,
        pseudolabeler,
        ransac,
        detector,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

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
        assert_eq!(c.zones, crate::sensor_preset("vlp16").unwrap().zones);
        let bad: toml::Table = toml::from_str("[gmm]\nk_maxx = 3\n").unwrap();
        let e = load_methods_config_layers(None, Some(&p), Some(("kwargs", bad)))
            .unwrap_err()
            .to_string();
        assert!(e.contains("kwargs") && e.contains("k_maxx"), "{e}");
    }
}
