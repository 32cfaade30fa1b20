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
    /// Reads the live processes of `cfg`'s pipeline (named `<prefix>/<stage>`).
    pub fn take(cfg: &ServiceConfig) -> Self {
        let mut s = BTreeMap::new();
        for (stage, alive, pid) in transport::pipeline_nodes(cfg) {
            if let (true, Some(t)) = (alive, process_cpu(pid)) {
                s.insert(stage, (pid, t));
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

#[cfg(test)]
mod tests {
    use super::*;

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
