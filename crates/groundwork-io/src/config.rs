//! Loading the segmenter configuration from TOML.

use std::fs;
use std::path::Path;

use groundwork_core::SegmenterConfig;

use crate::error::FormatError;

/// Parses and validates a segmenter configuration. Unknown keys, wrong types and
/// inconsistent values are errors naming the file (and the key, where TOML knows it).
pub fn load_config(path: &Path) -> Result<SegmenterConfig, FormatError> {
    let text = fs::read_to_string(path).map_err(|e| FormatError::io(path, e))?;
    parse_config(path, &text)
}

/// Parses configuration text; `path` is only used in error messages.
pub fn parse_config(path: &Path, text: &str) -> Result<SegmenterConfig, FormatError> {
    let cfg: SegmenterConfig = toml::from_str(text).map_err(|e| FormatError::Config {
        path: path.to_path_buf(),
        message: e.to_string().trim_end().to_string(),
    })?;
    cfg.validate().map_err(|e| FormatError::Config {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    Ok(cfg)
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let c = parse_config(p, "[gmm]\nk_max = 4\n").unwrap();
        assert_eq!(c.gmm.k_max, 4);
        assert_eq!(c.gmm.n_min, 20, "unspecified fields keep their defaults");
    }
}
