//! What each stage costs: the CPU time (user + system) of a pipeline's processes, read from
//! `/proc/<pid>/stat`, per scan. A stage that keeps cores awake to answer sooner shows it
//! here, beside the latency it buys.

use std::collections::BTreeMap;
use std::time::Duration;

use crate::config::ServiceConfig;
use crate::transport;

/// User + system CPU time of a process so far, if it can be read.
pub fn process_cpu(pid: i32) -> Option<Duration> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name (field 2) is in parentheses and may hold spaces: count from after it.
    let rest = &stat[stat.rfind(')')? + 1..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // Fields 14 and 15 of the line (utime, stime) are 11 and 12 after the name.
    let ticks: u64 = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
    let hz = rustix::param::clock_ticks_per_second().max(1);
    Some(Duration::from_nanos(
        ticks.saturating_mul(1_000_000_000) / hz,
    ))
}

/// The CPU time of every live stage of a pipeline at one moment: stage → (pid, time).
#[derive(Debug, Clone, Default)]
pub struct CpuSnapshot(BTreeMap<String, (i32, Duration)>);

impl CpuSnapshot {
    /// Reads the live processes of `cfg`'s pipeline (named `<prefix>/<stage>`). Stages
    /// that share a process (the ROS 2 bridge's three) are one entry: a process's CPU is
    /// counted once.
    pub fn take(cfg: &ServiceConfig) -> Self {
        let live = transport::pipeline_nodes(cfg)
            .into_iter()
            .filter(|n| n.1)
            .map(|(stage, _, pid)| (stage, pid));
        let mut s = BTreeMap::new();
        for (name, pid) in by_process(live) {
            if let Some(t) = process_cpu(pid) {
                s.insert(name, (pid, t));
            }
        }
        Self(s)
    }

    /// CPU milliseconds per scan of each stage between `self` and `later`, over `scans`
    /// scans; a stage that was restarted in between (another pid) is left out.
    pub fn per_scan(&self, later: &Self, scans: u64) -> BTreeMap<String, f64> {
        let mut out = BTreeMap::new();
        if scans == 0 {
            return out;
        }
        for (stage, (pid, t0)) in &self.0 {
            if let Some((p, t1)) = later.0.get(stage)
                && p == pid
            {
                let ms = t1.saturating_sub(*t0).as_secs_f64() * 1e3;
                out.insert(stage.clone(), ms / scans as f64);
            }
        }
        out
    }
}

/// Stages grouped by their process: one name per pid, the first stage's (in name order),
/// with the others it runs beside in parentheses (`ros2 (ros2-answers, ros2-detections)`).
fn by_process(stages: impl Iterator<Item = (String, i32)>) -> BTreeMap<String, i32> {
    let mut per_pid: BTreeMap<i32, Vec<String>> = BTreeMap::new();
    for (stage, pid) in stages {
        per_pid.entry(pid).or_default().push(stage);
    }
    per_pid
        .into_iter()
        .map(|(pid, mut names)| {
            names.sort();
            let name = match names.split_first() {
                Some((first, [])) => first.clone(),
                Some((first, rest)) => format!("{first} ({})", rest.join(", ")),
                None => String::new(),
            };
            (name, pid)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_of_one_process_are_counted_once() {
        let nodes = [
            ("ros2-detections", 7),
            ("segmenter", 9),
            ("ros2", 7),
            ("ros2-answers", 7),
            ("consumer", 11),
        ]
        .map(|(s, p)| (s.to_string(), p));
        let got = by_process(nodes.into_iter());
        let want: BTreeMap<String, i32> = [
            ("consumer".to_string(), 11),
            ("ros2 (ros2-answers, ros2-detections)".to_string(), 7),
            ("segmenter".to_string(), 9),
        ]
        .into_iter()
        .collect();
        assert_eq!(got, want);
    }

    #[test]
    fn this_process_cpu_time_grows_with_work() {
        let pid = std::process::id() as i32;
        let before = process_cpu(pid).unwrap();
        // Burn a few tens of milliseconds of CPU.
        let t = std::time::Instant::now();
        let mut x = 0u64;
        while t.elapsed() < Duration::from_millis(80) {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
        }
        std::hint::black_box(x);
        let after = process_cpu(pid).unwrap();
        assert!(after > before, "{before:?} → {after:?}");
        assert!(process_cpu(i32::MAX).is_none());
    }
}
