//! The examples end to end: `publish-scans` feeds a real segmenter and detector (the
//! `groundwork` stages as processes) and reads the masks back; `nearest-obstacle` reads the
//! same pipeline's masks and proposals beside it.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The `groundwork` binary, built beside the examples by `cargo test --workspace`.
fn groundwork() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_BIN_EXE_publish-scans"));
    let exe = dir.parent().unwrap().join("groundwork");
    assert!(
        exe.is_file(),
        "{} missing: build the CLI too (cargo test --workspace, or cargo build -p groundwork-cli)",
        exe.display()
    );
    exe
}

/// A child stopped with SIGTERM (a clean leave) when dropped.
struct Stage(Child);

impl Drop for Stage {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.0.id().to_string()])
            .status();
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(5) {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn stage(args: &[&str]) -> Stage {
    Stage(
        Command::new(groundwork())
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    )
}

#[test]
fn your_scans_in_masks_and_obstacles_out() {
    let prefix = format!("gwtest-examples-{}", std::process::id());
    let _segmenter = stage(&["segmenter", "--prefix", &prefix, "--frames", "1"]);
    let _detector = stage(&["detector", "--prefix", &prefix]);
    std::thread::sleep(Duration::from_millis(700));
    let watcher = Command::new(env!("CARGO_BIN_EXE_nearest-obstacle"))
        .args([&prefix, "5"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let published = Command::new(env!("CARGO_BIN_EXE_publish-scans"))
        .args([&prefix, "8"])
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&published.stdout);
    assert!(
        published.status.success(),
        "{out}\n{}",
        String::from_utf8_lossy(&published.stderr)
    );
    // Every scan answered with one probability per point, about half of them ground.
    let answers: Vec<&str> = out.lines().collect();
    assert_eq!(answers.len(), 8, "{out}");
    for (k, line) in answers.iter().enumerate() {
        let words: Vec<&str> = line.split_whitespace().collect();
        let at = format!("{k}:");
        assert_eq!(words[..3], ["scan", at.as_str(), "124668"], "{line}");
        let ground: f64 = words[4].parse().unwrap();
        assert!((0.4..0.75).contains(&(ground / 124_668.0)), "{line}");
    }
    // The watcher saw the masks and, for five scans, the nearest obstacle.
    let seen = watcher.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&seen.stdout);
    assert!(seen.status.success(), "{text}");
    let nearest: Vec<f64> = text
        .lines()
        .filter_map(|l| l.split(" at ").nth(1))
        .map(|r| r.split(' ').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(nearest.len(), 5, "{text}");
    assert!(nearest.iter().all(|&m| m > 2.0 && m < 40.0), "{text}");
    assert!(text.contains("% ground"), "{text}");
}
