//! Label maps (TerraSeg's OmniLiDAR label harmonisation): each dataset's class ids mapped
//! onto the four classes ground segmentation is scored on. The maps are data, in
//! `config/labels/` (built in); a user adds a TOML file for their own dataset.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::config::{builtin, builtin_names};
use crate::error::FormatError;
use crate::scan::read_records;

/// A label file of `labels` records for a scan of `points` points.
pub(crate) fn label_count(path: &Path, labels: u64, points: usize) -> Result<(), FormatError> {
    if labels == points as u64 {
        Ok(())
    } else {
        Err(FormatError::LabelCount {
            path: path.to_path_buf(),
            labels: usize::try_from(labels).unwrap_or(usize::MAX),
            points,
        })
    }
}

/// The harmonised class of a labelled point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LabelClass {
    /// Road, sidewalk, terrain, … as the dataset defines ground.
    Ground,
    /// Trees and bushes: ignored by the GMM paper's protocol, non-ground in TerraSeg's.
    Vegetation,
    /// Everything else.
    NonGround,
    /// Unlabelled, noise, outliers: never scored.
    Ignored,
}

/// How a label file stores one point's class.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LabelRecord {
    /// Little-endian u32: class id in the low 16 bits, instance id in the high 16.
    U32,
    /// One byte: the class id.
    U8,
}

impl LabelRecord {
    fn size(self) -> usize {
        match self {
            Self::U32 => 4,
            Self::U8 => 1,
        }
    }
}

/// One dataset's label map.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabelMap {
    /// Dataset name (`--labels-format`).
    pub name: String,
    /// Layout of the label files.
    pub record: LabelRecord,
    /// Label file name of a scan, `{stem}` standing for the scan's stem.
    pub file: String,
    /// Class ids that are ground.
    pub ground: Vec<u16>,
    /// Class ids that are vegetation.
    #[serde(default)]
    pub vegetation: Vec<u16>,
    /// Class ids never scored.
    #[serde(default)]
    pub ignored: Vec<u16>,
}

/// The built-in maps of `config/labels/`: (name, TOML text).
pub const LABEL_MAPS: &[(&str, &str)] = &[
    (
        "semantickitti",
        include_str!("../../../config/labels/semantickitti.toml"),
    ),
    (
        "nuscenes",
        include_str!("../../../config/labels/nuscenes.toml"),
    ),
    ("rellis", include_str!("../../../config/labels/rellis.toml")),
];

impl Default for LabelMap {
    /// SemanticKITTI's.
    fn default() -> Self {
        Self::semantickitti()
    }
}

impl LabelMap {
    /// Parses a map; `path` names it in errors.
    pub fn parse(path: &Path, text: &str) -> Result<Self, FormatError> {
        let map: Self = toml::from_str(text).map_err(|e| FormatError::Config {
            path: path.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        if !map.file.contains("{stem}") {
            return Err(FormatError::Config {
                path: path.to_path_buf(),
                message: "file must contain {stem}".into(),
            });
        }
        let mut seen = std::collections::BTreeSet::new();
        let all = map.ground.iter().chain(&map.vegetation).chain(&map.ignored);
        if let Some(id) = all.into_iter().find(|&&id| !seen.insert(id)) {
            return Err(FormatError::Config {
                path: path.to_path_buf(),
                message: format!("class id {id} is listed twice"),
            });
        }
        Ok(map)
    }

    /// A built-in map by name, or a map file by path (a user's own dataset).
    pub fn load(name_or_path: &str) -> Result<Self, FormatError> {
        if let Some((name, text)) = builtin(LABEL_MAPS, name_or_path) {
            return Self::parse(Path::new(&format!("config/labels/{name}.toml")), text);
        }
        let path = Path::new(name_or_path);
        if path.is_file() {
            let text = crate::file::read_text(path, crate::file::MAX_TEXT_BYTES)?;
            return Self::parse(path, &text);
        }
        Err(FormatError::Config {
            path: path.to_path_buf(),
            message: format!(
                "neither a built-in label map ({}) nor a map file",
                builtin_names(LABEL_MAPS)
            ),
        })
    }

    /// SemanticKITTI's map, the default.
    pub fn semantickitti() -> Self {
        #[allow(clippy::expect_used)] // built in at compile time, and tested to parse
        Self::load("semantickitti").expect("built-in semantickitti label map parses")
    }

    /// The harmonised class of a class id.
    pub fn class(&self, id: u16) -> LabelClass {
        if self.ignored.contains(&id) {
            LabelClass::Ignored
        } else if self.ground.contains(&id) {
            LabelClass::Ground
        } else if self.vegetation.contains(&id) {
            LabelClass::Vegetation
        } else {
            LabelClass::NonGround
        }
    }

    /// The label file of the scan `stem` in `dir`.
    pub fn file_for(&self, dir: &Path, stem: &str) -> PathBuf {
        dir.join(self.file.replace("{stem}", stem))
    }

    /// Reads a label file of `points` records and harmonises it. The size must match the
    /// scan (checked before reading).
    pub fn read(&self, path: &Path, points: usize) -> Result<Vec<LabelClass>, FormatError> {
        Ok(self
            .read_raw(path, points)?
            .into_iter()
            .map(|r| self.class(r as u16))
            .collect())
    }

    /// Reads a label file of `points` records as they are: for the u32 layout the class id
    /// in the low 16 bits and the instance id in the high 16 (SemanticKITTI), for the u8
    /// layout the class id alone.
    pub fn read_raw(&self, path: &Path, points: usize) -> Result<Vec<u32>, FormatError> {
        let bytes = read_records(path, self.record.size(), |labels| {
            label_count(path, labels, points)
        })?;
        Ok(match self.record {
            LabelRecord::U32 => bytes
                .chunks_exact(4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
            LabelRecord::U8 => bytes.iter().map(|&b| u32::from(b)).collect(),
        })
    }
}

/// Where the labels of an input are looked for, in order (the first that is a folder wins):
/// a folder's `labels/` (and, for a `velodyne/` folder, its sequence's); for a scan file, SemanticKITTI's `<seq>/labels/` beside its
/// `<seq>/velodyne/`, then a `labels/` folder beside the file. Every command that finds
/// labels by itself (`eval`, `render --compare`, the consumer's live accuracy) looks here.
pub fn label_folders(input: &Path) -> Vec<PathBuf> {
    if input.is_dir() {
        let mut c = vec![input.join("labels")];
        // `<seq>/velodyne/` given itself: its sequence's labels.
        if input.file_name().is_some_and(|n| n == "velodyne")
            && let Some(seq) = input.parent()
        {
            c.push(seq.join("labels"));
        }
        return c;
    }
    let dir = input.parent().unwrap_or(Path::new("."));
    let mut c = Vec::new();
    if let Some(seq) = dir.parent() {
        c.push(seq.join("labels"));
    }
    c.push(dir.join("labels"));
    c
}

/// The first of [`label_folders`] that exists.
pub fn label_folder(input: &Path) -> Option<PathBuf> {
    label_folders(input).into_iter().find(|d| d.is_dir())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

    #[test]
    fn built_in_maps_parse_and_harmonise() {
        for (name, _) in LABEL_MAPS {
            let m = LabelMap::load(name).unwrap();
            assert_eq!(m.name, *name);
        }
        let kitti = LabelMap::semantickitti();
        assert_eq!(kitti.class(40), LabelClass::Ground);
        assert_eq!(kitti.class(70), LabelClass::Vegetation);
        assert_eq!(kitti.class(10), LabelClass::NonGround);
        assert_eq!(kitti.class(1), LabelClass::Ignored);
        let rellis = LabelMap::load("rellis").unwrap();
        for ground in [1, 3, 10, 23, 31, 33] {
            assert_eq!(
                rellis.class(ground),
                LabelClass::Ground,
                "RELLIS id {ground}"
            );
        }
        assert_eq!(rellis.class(4), LabelClass::Vegetation); // tree
        assert_eq!(rellis.class(17), LabelClass::NonGround); // person
        let nu = LabelMap::load("NuScenes").unwrap();
        assert_eq!(nu.class(24), LabelClass::Ground); // driveable surface
        assert_eq!(nu.class(17), LabelClass::NonGround); // vehicle.car
    }

    #[test]
    fn label_files_of_both_layouts_read_and_must_match_the_scan() {
        let dir = tempfile::tempdir().unwrap();
        let kitti = LabelMap::semantickitti();
        let p = kitti.file_for(dir.path(), "000003");
        // Instance ids in the high half do not change the class.
        let raw: Vec<u8> = [40u32 | (7 << 16), 10 | (3 << 16), 70]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        fs::write(&p, raw).unwrap();
        assert_eq!(
            kitti.read(&p, 3).unwrap(),
            [
                LabelClass::Ground,
                LabelClass::NonGround,
                LabelClass::Vegetation
            ]
        );
        let e = kitti.read(&p, 4).unwrap_err().to_string();
        assert!(e.contains("000003.label") && e.contains("3 labels"), "{e}");

        let nu = LabelMap::load("nuscenes").unwrap();
        let p = nu.file_for(dir.path(), "n015__LIDAR_TOP__1");
        assert!(p.ends_with("n015__LIDAR_TOP__1_lidarseg.bin"));
        fs::write(&p, [24u8, 0, 17, 30]).unwrap();
        assert_eq!(
            nu.read(&p, 4).unwrap(),
            [
                LabelClass::Ground,
                LabelClass::Ignored,
                LabelClass::NonGround,
                LabelClass::Vegetation
            ]
        );
    }

    #[test]
    fn a_users_map_file_is_checked() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("mine.toml");
        fs::write(&p, "name = \"mine\"\nrecord = \"u32\"\nfile = \"{stem}.label\"\nground = [5, 6]\nignored = [6]\n").unwrap();
        let e = LabelMap::load(p.to_str().unwrap()).unwrap_err().to_string();
        assert!(e.contains("mine.toml") && e.contains("6"), "{e}");
        fs::write(
            &p,
            "name = \"mine\"\nrecord = \"u16\"\nfile = \"{stem}.label\"\nground = [5]\n",
        )
        .unwrap();
        assert!(LabelMap::load(p.to_str().unwrap()).is_err());
        fs::write(
            &p,
            "name = \"mine\"\nrecord = \"u32\"\nfile = \"{stem}.label\"\nground = [5]\n",
        )
        .unwrap();
        assert_eq!(
            LabelMap::load(p.to_str().unwrap()).unwrap().class(5),
            LabelClass::Ground
        );
        assert!(LabelMap::load("no-such-dataset").is_err());
    }
}
