//! Helpers shared by the binary's test files (`tests/` of this crate, and the service's fault
//! tests, which are this crate's too).

use std::path::{Path, PathBuf};
use std::process::Command;

/// A small tmpfs, unmounted when dropped: a full disk and a read-only folder as a user
/// meets them (root bypasses permission bits, not a read-only mount).
pub struct Tmpfs(pub PathBuf);

impl Tmpfs {
    pub fn mount(dir: &Path, kib: u32) -> Option<Self> {
        std::fs::create_dir_all(dir).unwrap();
        let ok = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={kib}k"), "none"])
            .arg(dir)
            .status()
            .is_ok_and(|s| s.success());
        if !ok {
            // Only root can mount; CI runs as root, so there this test always runs.
            assert!(
                !rustix::process::geteuid().is_root(),
                "root could not mount a tmpfs"
            );
            assert!(
                std::env::var_os("GROUNDWORK_REQUIRE_ROOT").is_none(),
                "GROUNDWORK_REQUIRE_ROOT is set: the full-disk test needs root (a tmpfs mount)"
            );
            eprintln!("skipped: not root, and the full-disk test needs a tmpfs mount");
            return None;
        }
        Some(Self(dir.to_path_buf()))
    }

    #[allow(dead_code)] // the full-disk test of the service never makes it read-only
    pub fn read_only(&self) {
        let ok = Command::new("mount")
            .args(["-o", "remount,ro"])
            .arg(&self.0)
            .status()
            .unwrap();
        assert!(ok.success());
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}
