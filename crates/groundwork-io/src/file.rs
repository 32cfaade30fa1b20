//! Opening input files, and the temporary name outputs are written under. Only regular files are read: a device (`/dev/zero`), a FIFO or a
//! socket named as a scan would fill memory or block forever, so it is refused by its kind
//! before it is opened, and no read goes past the size measured at open time.

use std::fs;
use std::io::Read;
use std::path::Path;

use crate::error::FormatError;

/// Opens `path` (symlinks followed) if it is a regular file; returns it and its size.
pub fn open_regular(path: &Path) -> Result<(fs::File, u64), FormatError> {
    let meta = fs::metadata(path).map_err(|e| FormatError::io(path, e))?;
    if !meta.is_file() {
        return Err(FormatError::NotAFile {
            path: path.to_path_buf(),
            kind: kind_name(&meta.file_type()),
        });
    }
    let file = fs::File::open(path).map_err(|e| FormatError::io(path, e))?;
    Ok((file, meta.len()))
}

/// Reads a whole regular file of at most `limit` bytes (checked before reading); a file
/// that grows while it is read is cut at the size measured first.
pub fn read_regular(path: &Path, limit: u64) -> Result<Vec<u8>, FormatError> {
    let (file, size) = open_regular(path)?;
    if size > limit {
        return Err(FormatError::malformed(
            path,
            format!("{size} bytes, more than the {limit} bytes a file of this kind may have"),
        ));
    }
    let mut bytes = Vec::with_capacity(size as usize);
    file.take(size)
        .read_to_end(&mut bytes)
        .map_err(|e| FormatError::io(path, e))?;
    Ok(bytes)
}

/// [`read_regular`] for text files (poses, calibration, configuration, label maps).
pub fn read_text(path: &Path, limit: u64) -> Result<String, FormatError> {
    String::from_utf8(read_regular(path, limit)?)
        .map_err(|_| FormatError::malformed(path, "not UTF-8 text"))
}

/// `<path>.partial`: where an output is written before it is renamed to `path`.
/// Reads the first `head.len()` bytes of `file` (fewer only if it is shorter): what its
/// magic bytes say.
pub(crate) fn read_head(
    path: &Path,
    file: &mut fs::File,
    head: &mut [u8],
) -> Result<usize, FormatError> {
    let mut n = 0;
    while n < head.len() {
        match file.read(&mut head[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(FormatError::io(path, e)),
        }
    }
    Ok(n)
}

pub(crate) fn partial_name(path: &Path) -> std::path::PathBuf {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".partial");
    std::path::PathBuf::from(tmp)
}

/// The largest text file read (a pose file of a million frames is about 100 MB).
pub const MAX_TEXT_BYTES: u64 = 256 << 20;

fn kind_name(t: &fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_dir() {
        "a folder"
    } else if t.is_fifo() {
        "a FIFO (named pipe)"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else if t.is_socket() {
        "a socket"
    } else {
        "not a regular file"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn devices_fifos_and_folders_are_refused_by_kind() {
        let dir = tempfile::tempdir().unwrap();
        let e = open_regular(dir.path()).unwrap_err().to_string();
        assert!(e.contains("a folder"), "{e}");
        let zero = dir.path().join("zero.bin");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        let e = open_regular(&zero).unwrap_err().to_string();
        assert!(
            e.contains("zero.bin") && e.contains("character device"),
            "{e}"
        );
        let fifo = dir.path().join("pipe.bin");
        let status = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(status.success());
        // Refused without opening it (opening a FIFO with no writer would block).
        let e = open_regular(&fifo).unwrap_err().to_string();
        assert!(e.contains("pipe.bin") && e.contains("FIFO"), "{e}");
        let f = dir.path().join("a.txt");
        fs::write(&f, "hello").unwrap();
        assert_eq!(read_text(&f, 5).unwrap(), "hello");
        let e = read_text(&f, 4).unwrap_err().to_string();
        assert!(e.contains("5 bytes"), "{e}");
    }
}
