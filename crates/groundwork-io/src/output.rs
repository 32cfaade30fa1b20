//! Per-scan outputs: `.prob` (little-endian f32 ground probability per point) and
//! `.ground` (u8 per point, 1 = ground), both in input point order; the detector's
//! `.clusters` (little-endian u32 proposal id per point, 0 = none) are read here (the CLI
//! writes them beside its `.proposals.json`).

use std::fs;
use std::path::{Path, PathBuf};

use crate::error::FormatError;
use crate::input::ScanSource;
use crate::input::scan_stem;
use crate::recording::RecordingWriter;

/// Where per-scan results go: `.prob`/`.ground` files in a folder, or one MCAP recording
/// (PointCloud2 with `ground_probability`) for a path ending in `.mcap`.
#[derive(Debug)]
pub enum OutputTarget {
    /// A folder of `.prob` / `.ground` files.
    Files(PathBuf),
    /// One recording.
    Recording(Box<RecordingWriter>),
}

impl OutputTarget {
    /// A recording for a path ending in `.mcap`, a folder otherwise; missing folders (the
    /// recording's parent) are created. Refused before anything is read or written: an
    /// output that is one of `inputs` (the same file, however named), and a folder that
    /// cannot be written to.
    pub fn create(path: &Path, inputs: &[PathBuf]) -> Result<Self, FormatError> {
        let recording = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("mcap"));
        check_not_an_input(path, inputs)?;
        if !recording && path.exists() && !path.is_dir() {
            return Err(FormatError::Collision {
                path: path.to_path_buf(),
                message:
                    "exists and is not a folder: --out takes a folder, or a path ending in .mcap"
                        .into(),
            });
        }
        let dir = if recording {
            path.parent().filter(|d| !d.as_os_str().is_empty())
        } else {
            Some(path)
        };
        let dir = dir.unwrap_or(Path::new("."));
        fs::create_dir_all(dir).map_err(|e| FormatError::io(dir, e))?;
        check_writable(dir)?;
        Ok(if recording {
            Self::Recording(Box::new(RecordingWriter::create(path)?))
        } else {
            Self::Files(path.to_path_buf())
        })
    }
}

/// Writes `<dir>/<stem>.prob` and `<dir>/<stem>.ground`, each first to a temporary name and
/// then renamed, so that a crash never leaves a half-written file under the final name; the
/// `.ground` file is renamed last, so its presence means both are complete.
pub fn write_outputs(
    dir: &Path,
    stem: &str,
    probabilities: &[f32],
    threshold: f32,
) -> Result<(), FormatError> {
    let prob: Vec<u8> = probabilities.iter().flat_map(|p| p.to_le_bytes()).collect();
    let ground: Vec<u8> = probabilities
        .iter()
        .map(|&p| u8::from(p >= threshold))
        .collect();
    write_atomic(&dir.join(format!("{stem}.prob")), &prob)?;
    write_atomic(&dir.join(format!("{stem}.ground")), &ground)
}

/// Writes `path` through `<path>.partial` and a rename: a reader never sees it half-written,
/// and a write that fails (a full disk) leaves neither name behind.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FormatError> {
    let tmp = crate::file::partial_name(path);
    let result = fs::write(&tmp, bytes)
        .map_err(|e| FormatError::io(&tmp, e))
        .and_then(|()| fs::rename(&tmp, path).map_err(|e| FormatError::io(path, e)));
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// The files one run writes besides its per-scan outputs (a configuration, a report, a
/// picture, a synthetic sequence, a summary): the one output path every command takes.
///
/// Each file is claimed before anything is read or written, which refuses an output that
/// is one of the run's inputs (the same file however named, links followed) or that the
/// run names twice (`--out X --report X`), and notes one that exists (the run replaces it,
/// and [`OutputFiles::warn_replaced`] says so first). [`OutputFiles::write`] writes through a
/// temporary name and a rename, so a failed write (a full disk) leaves neither a partial nor
/// an empty file behind, and the error names the file.
#[derive(Debug, Default)]
pub struct OutputFiles {
    inputs: Vec<PathBuf>,
    /// Claimed, as given.
    claimed: std::collections::HashSet<PathBuf>,
    /// Each claimed file by where it is (folder resolved through links), and by its
    /// (device, inode) where it exists: two names of one place are one output.
    places: std::collections::HashMap<PathBuf, PathBuf>,
    inodes: std::collections::HashMap<(u64, u64), PathBuf>,
    existing: Vec<PathBuf>,
}

impl OutputFiles {
    /// The outputs of a run that reads `inputs` (every file it reads: scans, masks,
    /// configuration).
    pub fn new(inputs: &[PathBuf]) -> Self {
        Self {
            inputs: inputs.to_vec(),
            ..Self::default()
        }
    }

    /// Claims `path` as one of the run's outputs (see the type's documentation).
    pub fn claim(&mut self, path: &Path) -> Result<(), FormatError> {
        use std::os::unix::fs::MetadataExt;
        check_not_an_input(path, &self.inputs)?;
        if path.is_dir() {
            return Err(FormatError::Collision {
                path: path.to_path_buf(),
                message: "is a folder: this output is a file".into(),
            });
        }
        let place = resolved(path);
        let inode = fs::metadata(path).ok().map(|m| (m.dev(), m.ino()));
        let other = self
            .places
            .get(&place)
            .or_else(|| inode.and_then(|i| self.inodes.get(&i)));
        if let Some(other) = other {
            return Err(FormatError::Collision {
                path: path.to_path_buf(),
                message: format!(
                    "is named twice as an output of this run ({} too): one would overwrite the other",
                    other.display()
                ),
            });
        }
        if fs::symlink_metadata(path).is_ok() {
            self.existing.push(path.to_path_buf());
        }
        self.places.insert(place, path.to_path_buf());
        if let Some(i) = inode {
            self.inodes.insert(i, path.to_path_buf());
        }
        self.claimed.insert(path.to_path_buf());
        Ok(())
    }

    /// The claimed files that exist now: the run replaces them.
    pub fn existing(&self) -> &[PathBuf] {
        &self.existing
    }

    /// Says, before anything is written, which existing files the run replaces.
    pub fn warn_replaced(&self) {
        if let Some(first) = self.existing.first() {
            let place = first.parent().unwrap_or(Path::new("."));
            warn_replaced(place, &self.existing);
        }
    }

    /// Writes a claimed file: a temporary name, then a rename (its folder created first).
    pub fn write(&self, path: &Path, bytes: &[u8]) -> Result<(), FormatError> {
        if !self.claimed.contains(path) {
            return Err(FormatError::Collision {
                path: path.to_path_buf(),
                message: "an output written without being claimed first (a bug)".into(),
            });
        }
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            fs::create_dir_all(dir).map_err(|e| FormatError::io(dir, e))?;
        }
        write_atomic(path, bytes)
    }
}

/// The warning a run gives before it replaces files an earlier run left in `place`.
pub fn warn_replaced(place: &Path, files: &[PathBuf]) {
    if let [one] = files {
        tracing::warn!("{}: exists, and is replaced by this run", one.display());
    } else if let Some(first) = files.first() {
        tracing::warn!(
            "{}: {} file(s) of an earlier run are replaced as this run writes them (first {}); \
             write elsewhere to keep them",
            place.display(),
            files.len(),
            first.file_name().unwrap_or_default().to_string_lossy()
        );
    }
}

/// Where an output name points: its folder resolved through links, and its file name.
fn resolved(p: &Path) -> PathBuf {
    let dir = p.parent().filter(|d| !d.as_os_str().is_empty());
    let dir = dir.unwrap_or(Path::new("."));
    fs::canonicalize(dir)
        .unwrap_or_else(|_| dir.to_path_buf())
        .join(p.file_name().unwrap_or_default())
}

/// Refuses an output path that names the same file as an input (`--out rec.mcap rec.mcap`,
/// or through a link): writing it would destroy the input before it is read.
pub fn check_not_an_input(out: &Path, inputs: &[PathBuf]) -> Result<(), FormatError> {
    use std::os::unix::fs::MetadataExt;
    let Ok(o) = fs::metadata(out) else {
        return Ok(());
    };
    for input in inputs {
        if let Ok(i) = fs::metadata(input)
            && (i.dev(), i.ino()) == (o.dev(), o.ino())
        {
            return Err(FormatError::Collision {
                path: out.to_path_buf(),
                message: format!(
                    "the output is the input {} (writing it would destroy it): choose another --out",
                    input.display()
                ),
            });
        }
    }
    Ok(())
}

/// A folder outputs go to must take a new file: tested by creating (and removing) one, so
/// that a read-only folder is an error at the start, not one per scan.
fn check_writable(dir: &Path) -> Result<(), FormatError> {
    let probe = dir.join(format!(".groundwork-write-check-{}", std::process::id()));
    fs::File::create(&probe).map_err(|e| FormatError::io(dir, e))?;
    let _ = fs::remove_file(&probe);
    Ok(())
}

/// Refuses, before anything is written, inputs whose scans would get the same output name
/// in one folder (two folders that both hold `000000.bin`, or `x.pcd` and `x.ply`): the
/// second would overwrite the first in silence. `names` is (output name, where it comes
/// from) for every scan known before reading; a recording's scans are named
/// `<stem>_<index:06>`, so a recording is listed as its `<stem>_` with `prefix` true.
pub fn check_output_names(sources: &[&ScanSource]) -> Result<(), FormatError> {
    check_names(&output_names(sources))
}

/// (output name, where it comes from, whether the name is a recording's `<stem>_` prefix)
/// for every scan of `sources` known before reading.
fn output_names(sources: &[&ScanSource]) -> Vec<(String, PathBuf, bool)> {
    let mut names = Vec::new();
    for source in sources {
        match source {
            ScanSource::Files(files) => {
                names.extend(files.iter().map(|f| (scan_stem(f), f.clone(), false)));
            }
            ScanSource::Recording { path, .. } => {
                names.push((format!("{}_", scan_stem(path)), path.clone(), true));
            }
        }
    }
    names
}

/// Whether `name` is one of a recording's scan names `<prefix><index:06>`.
fn is_recorded_name(name: &str, prefix: &str) -> bool {
    name.strip_prefix(prefix)
        .is_some_and(|rest| rest.len() >= 6 && rest.bytes().all(|b| b.is_ascii_digit()))
}

/// The files of `dir` that a run over `sources` will replace: those named after one of its
/// scans with one of the `suffixes` it writes (`.prob`, `.ground`, …), left by an earlier
/// run into the same folder. Sorted; empty when `dir` cannot be listed.
pub fn earlier_outputs(dir: &Path, sources: &[&ScanSource], suffixes: &[&str]) -> Vec<PathBuf> {
    let names = output_names(sources);
    let stems: std::collections::HashSet<&str> = names
        .iter()
        .filter(|n| !n.2)
        .map(|n| n.0.as_str())
        .collect();
    let ours = |stem: &str| {
        stems.contains(stem)
            || names
                .iter()
                .any(|(prefix, _, is_prefix)| *is_prefix && is_recorded_name(stem, prefix))
    };
    let Ok(entries) = fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut found: Vec<PathBuf> = entries
        .flatten()
        .filter(|e| {
            let name = e.file_name();
            let Some(name) = name.to_str() else {
                return false;
            };
            suffixes
                .iter()
                .any(|s| name.strip_suffix(s).is_some_and(&ours))
        })
        .map(|e| e.path())
        .collect();
    found.sort();
    found
}

fn check_names(names: &[(String, PathBuf, bool)]) -> Result<(), FormatError> {
    let mut sorted: Vec<&(String, PathBuf, bool)> = names.iter().collect();
    sorted.sort_by(|a, b| a.0.cmp(&b.0));
    for w in sorted.windows(2) {
        if w[0].0 == w[1].0 {
            return Err(collision(&w[0].1, &w[1].1, &w[0].0));
        }
    }
    // A recording `a.mcap` names its scans `a_000000`…: a file `a_000003.bin` would collide.
    for (prefix, rec, _) in names.iter().filter(|n| n.2) {
        let clash = names
            .iter()
            .find(|(name, _, is_prefix)| !is_prefix && is_recorded_name(name, prefix));
        if let Some((name, file, _)) = clash {
            return Err(collision(rec, file, name));
        }
    }
    Ok(())
}

fn collision(a: &Path, b: &Path, name: &str) -> FormatError {
    FormatError::Collision {
        path: a.to_path_buf(),
        message: format!(
            "{} would write the same outputs ({name}.*) in the output folder, overwriting one with the other: give them separate --out folders",
            b.display()
        ),
    }
}

/// Whether `<dir>/<stem>.prob` and `.ground` are both complete outputs for one scan: present
/// under their final names, 4 bytes per point and 1 byte per point for the same count.
pub fn outputs_complete(dir: &Path, stem: &str) -> bool {
    let len = |ext: &str| fs::metadata(dir.join(format!("{stem}.{ext}"))).map(|m| m.len());
    match (len("prob"), len("ground")) {
        (Ok(p), Ok(g)) => g > 0 && p == 4 * g,
        _ => false,
    }
}

/// Reads a `.clusters` file.
pub fn read_clusters(path: &Path) -> Result<Vec<u32>, FormatError> {
    read_words(path, u32::from_le_bytes)
}

/// Reads a file of 4-byte little-endian records.
fn read_words<T>(path: &Path, decode: fn([u8; 4]) -> T) -> Result<Vec<T>, FormatError> {
    let bytes = crate::file::read_regular(path, 4 * u64::from(u32::MAX))?;
    if bytes.len() % 4 != 0 {
        return Err(FormatError::Size {
            path: path.to_path_buf(),
            size: bytes.len() as u64,
            record: 4,
        });
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|b| decode([b[0], b[1], b[2], b[3]]))
        .collect())
}

/// Reads a `.prob` file.
pub fn read_prob(path: &Path) -> Result<Vec<f32>, FormatError> {
    read_words(path, f32::from_le_bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn earlier_outputs_are_this_runs_names_only() {
        let dir = tempfile::tempdir().unwrap();
        for name in [
            "000000.prob",
            "000000.ground",
            "000001.prob.tmp",
            "000002.clusters",
            "drive_000003.ground",
            "drive_3.ground",
            "other_000003.ground",
            "notes.txt",
        ] {
            fs::write(dir.path().join(name), b"x").unwrap();
        }
        let files = ScanSource::Files(vec!["a/000000.bin".into(), "a/000001.bin".into()]);
        let rec = ScanSource::Recording {
            path: "b/drive.mcap".into(),
            topic: None,
        };
        let found = earlier_outputs(dir.path(), &[&files, &rec], &[".prob", ".ground"]);
        let names: Vec<_> = found
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(
            names,
            ["000000.ground", "000000.prob", "drive_000003.ground"]
        );
        assert!(earlier_outputs(&dir.path().join("absent"), &[&files], &[".prob"]).is_empty());
    }

    #[test]
    fn an_output_file_is_never_an_input_nor_claimed_twice() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let scan = d.join("000000.bin");
        fs::write(&scan, [0u8; 16]).unwrap();
        std::os::unix::fs::symlink(&scan, d.join("link.bin")).unwrap();
        std::os::unix::fs::symlink(d, d.join("again")).unwrap();
        let mut out = OutputFiles::new(std::slice::from_ref(&scan));
        // The input, by its name or through a link to it or to its folder.
        for name in ["000000.bin", "link.bin", "again/000000.bin"] {
            let e = out.claim(&d.join(name)).unwrap_err().to_string();
            assert!(e.contains("destroy"), "{name}: {e}");
        }
        // One output under two names.
        out.claim(&d.join("cal.toml")).unwrap();
        let e = out
            .claim(&d.join("again/cal.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("named twice") && e.contains("cal.toml"), "{e}");
        // A folder is no output file.
        assert!(out.claim(d).is_err());
        // An existing file is noted as replaced; an unclaimed one is never written.
        fs::write(d.join("report.json"), "{}").unwrap();
        out.claim(&d.join("report.json")).unwrap();
        assert_eq!(out.existing(), [d.join("report.json")]);
        assert!(out.write(&d.join("other.txt"), b"x").is_err());
        out.write(&d.join("cal.toml"), b"a = 1\n").unwrap();
        assert_eq!(fs::read(d.join("cal.toml")).unwrap(), b"a = 1\n");
        assert_eq!(fs::read(&scan).unwrap(), [0u8; 16]);
    }

    #[test]
    fn a_failed_write_leaves_neither_name() {
        let dir = tempfile::tempdir().unwrap();
        // A folder under the temporary name: the write fails as a full disk would.
        let target = dir.path().join("x.png");
        fs::create_dir(crate::file::partial_name(&target)).unwrap();
        let mut out = OutputFiles::new(&[]);
        out.claim(&target).unwrap();
        let e = out.write(&target, b"png").unwrap_err().to_string();
        assert!(e.contains("x.png.partial"), "{e}");
        assert!(!target.exists());
    }

    #[test]
    fn outputs_round_trip_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let p = [0.0, 0.49, 0.5, 1.0];
        write_outputs(dir.path(), "000007", &p, 0.5).unwrap();
        assert_eq!(read_prob(&dir.path().join("000007.prob")).unwrap(), p);
        assert_eq!(
            fs::read(dir.path().join("000007.ground")).unwrap(),
            [0, 0, 1, 1]
        );
        assert!(outputs_complete(dir.path(), "000007"));
        // No temporary file is left behind.
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 2);
        // A missing or truncated half makes the pair incomplete.
        fs::write(dir.path().join("000007.prob"), [0u8; 12]).unwrap();
        assert!(!outputs_complete(dir.path(), "000007"));
        fs::remove_file(dir.path().join("000007.ground")).unwrap();
        assert!(!outputs_complete(dir.path(), "000007"));
    }
}
