//! Service configuration (TOML, `config/service.toml`).

use std::path::Path;

use serde::{Deserialize, Serialize};

/// What a full queue does to the oldest / newest message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OverflowPolicy {
    /// A subscriber whose queue is full loses its oldest message (iceoryx2 safe overflow):
    /// publishers never block, a slow reader always sees the newest data.
    DropOldest,
    /// A full subscriber queue refuses the new message (`send` reaches fewer subscribers):
    /// publishers never block, a slow reader keeps its backlog.
    DropNewest,
}

/// Names, queue depths and sizes shared by all processes of one pipeline.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServiceConfig {
    /// Service names are `<prefix>/scans` and `<prefix>/masks`: pipelines with different
    /// prefixes run side by side.
    pub prefix: String,
    /// Largest scan (points) the shared memory is sized for; larger scans are rejected.
    pub max_points: usize,
    /// Queue depth of every scan subscriber.
    pub scan_queue: usize,
    /// Queue depth of every mask subscriber.
    pub mask_queue: usize,
    /// Samples a subscriber may hold at once.
    pub max_borrowed: usize,
    /// Behaviour of a full queue.
    pub overflow: OverflowPolicy,
    /// Subscribers per topic the memory is sized for.
    pub max_subscribers: usize,
    /// Producer rate in scans per second (0 = as fast as possible). Range: 0, or
    /// [`MIN_RATE_HZ`]..=[`MAX_RATE_HZ`].
    pub rate_hz: f64,
    /// Seconds between periodic state logs.
    pub report_interval_s: f64,
    /// Keeping cores awake: milliseconds before a periodic scan is due that the segmenter
    /// and detector stages wake their thread pool's workers and keep them spinning until
    /// the scan is processed (0: never, the default: workers sleep when idle). Cores that
    /// idled through a period come back slowly on virtual machines and hosts with deep idle
    /// states: spinning buys latency with CPU, shown per scan in the consumer's report
    /// (docs/service.md, "Keeping cores awake"). Range 0..=50. (`prewarm_ms`, its former
    /// name, is read too.)
    #[serde(alias = "prewarm_ms")]
    pub keep_awake_ms: f64,
    /// Sensor preset the segmenter stage uses (`groundwork sensors` lists them; absent:
    /// hdl64e). `--sensor` and `--config` of the stage override it.
    pub sensor: Option<String>,
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            prefix: "groundwork".into(),
            max_points: 200_000,
            scan_queue: 4,
            mask_queue: 4,
            max_borrowed: 2,
            overflow: OverflowPolicy::DropOldest,
            max_subscribers: 4,
            rate_hz: 10.0,
            report_interval_s: 2.0,
            keep_awake_ms: 0.0,
            sensor: None,
        }
    }
}

/// The slowest producer rate accepted (one scan an hour): slower is a typo, and a period
/// beyond what a timer can add to the clock.
pub const MIN_RATE_HZ: f64 = 1.0 / 3600.0;
/// The fastest producer rate accepted (faster is "as fast as possible": 0).
pub const MAX_RATE_HZ: f64 = 10_000.0;

/// Checks a producer rate (`rate_hz`, `--rate`): 0 (flat out) or in
/// [`MIN_RATE_HZ`]..=[`MAX_RATE_HZ`]; NaN and infinities are refused by name.
pub fn check_rate(name: &str, rate: f64) -> anyhow::Result<()> {
    anyhow::ensure!(
        rate == 0.0 || (MIN_RATE_HZ..=MAX_RATE_HZ).contains(&rate),
        "{name} = {rate}: must be 0 (as fast as possible) or between {MIN_RATE_HZ:.6} (one scan an hour) and {MAX_RATE_HZ} scans per second"
    );
    Ok(())
}

impl ServiceConfig {
    /// Reads and validates a service configuration; errors name the file and the key.
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let cfg: Self =
            groundwork_io::read_table(path)?
                .try_into()
                .map_err(|e: toml::de::Error| {
                    anyhow::anyhow!("{}: {}", path.display(), e.to_string().trim_end())
                })?;
        cfg.validate()
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        Ok(cfg)
    }

    /// Consistency checks.
    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            !self.prefix.is_empty() && self.prefix.len() < 200,
            "prefix must be 1..200 characters"
        );
        anyhow::ensure!(
            (1..=4_000_000).contains(&self.max_points),
            "max_points must be in 1..=4000000"
        );
        anyhow::ensure!(
            (1..=64).contains(&self.scan_queue) && (1..=64).contains(&self.mask_queue),
            "scan_queue and mask_queue must be in 1..=64"
        );
        anyhow::ensure!(
            (1..=16).contains(&self.max_borrowed),
            "max_borrowed must be in 1..=16"
        );
        anyhow::ensure!(
            (1..=32).contains(&self.max_subscribers),
            "max_subscribers must be in 1..=32"
        );
        check_rate("rate_hz", self.rate_hz)?;
        anyhow::ensure!(
            self.report_interval_s.is_finite() && self.report_interval_s > 0.0,
            "report_interval_s must be > 0"
        );
        anyhow::ensure!(
            self.keep_awake_ms.is_finite() && (0.0..=50.0).contains(&self.keep_awake_ms),
            "keep_awake_ms must be in 0..=50"
        );
        if let Some(name) = &self.sensor {
            groundwork_io::sensor_preset(name).map_err(|e| anyhow::anyhow!("sensor: {e}"))?;
        }
        Ok(())
    }

    /// How long before a due scan the parallel stages keep their workers awake (zero:
    /// never).
    pub fn keep_awake_lead(&self) -> std::time::Duration {
        std::time::Duration::from_secs_f64(self.keep_awake_ms / 1e3)
    }

    /// Shared memory the publishers may need at worst (bytes): per topic, chunk size ×
    /// (subscribers × (queue + borrowed) + loans), for scans, masks and proposals.
    pub fn shared_memory_estimate(&self) -> u64 {
        let scan_chunk = (self.max_points * 16 + 4096) as u64;
        let mask_chunk = (self.max_points * 4 + 4096) as u64;
        let proposals_chunk =
            mask_chunk + std::mem::size_of::<groundwork_msg::ProposalsHeader>() as u64;
        let subs = self.max_subscribers as u64;
        let loans = 2;
        let per_topic =
            |chunk: u64, queue: usize| chunk * (subs * (queue + self.max_borrowed) as u64 + loans);
        per_topic(scan_chunk, self.scan_queue)
            + per_topic(mask_chunk, self.mask_queue)
            + per_topic(proposals_chunk, self.mask_queue)
    }
}

/// Fails with a clear message if `/dev/shm` cannot hold what the configuration may need: a
/// too-small tmpfs would otherwise kill the process with SIGBUS on first write.
pub fn check_shared_memory(cfg: &ServiceConfig) -> anyhow::Result<()> {
    let need = cfg.shared_memory_estimate();
    let st = rustix::fs::statvfs("/dev/shm")
        .map_err(|e| anyhow::anyhow!("/dev/shm: cannot query free space: {e}"))?;
    let free = st.f_bavail * st.f_frsize;
    anyhow::ensure!(
        free >= need,
        "/dev/shm has {} MiB free but this configuration may need {} MiB \
         (max_points {}, queues {}/{}, {} subscribers): lower max_points or the queue depths, \
         or enlarge /dev/shm",
        free >> 20,
        need >> 20,
        cfg.max_points,
        cfg.scan_queue,
        cfg.mask_queue,
        cfg.max_subscribers
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn defaults_validate_and_bad_values_do_not() {
        ServiceConfig::default().validate().unwrap();
        let bad = ServiceConfig {
            scan_queue: 0,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
        let e = toml::from_str::<ServiceConfig>("prefx = \"a\"")
            .unwrap_err()
            .to_string();
        assert!(e.contains("prefx"), "{e}");
    }

    #[test]
    fn the_sensor_key_names_a_preset() {
        let c: ServiceConfig = toml::from_str("sensor = \"os1-64\"").unwrap();
        c.validate().unwrap();
        let c: ServiceConfig = toml::from_str("sensor = \"hdl99\"").unwrap();
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("hdl99") && e.contains("os1-128"), "{e}");
    }

    #[test]
    fn keeping_cores_awake_is_off_by_default_and_its_former_name_still_reads() {
        assert_eq!(ServiceConfig::default().keep_awake_lead(), Duration::ZERO);
        let c: ServiceConfig = toml::from_str("keep_awake_ms = 10").unwrap();
        assert_eq!(c.keep_awake_lead(), Duration::from_millis(10));
        let c: ServiceConfig = toml::from_str("prewarm_ms = 4").unwrap();
        assert_eq!(c.keep_awake_lead(), Duration::from_millis(4));
        let c: ServiceConfig = toml::from_str("keep_awake_ms = 80").unwrap();
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("keep_awake_ms")
        );
    }

    #[test]
    fn shared_memory_check_refuses_absurd_sizes() {
        let huge = ServiceConfig {
            max_points: 4_000_000,
            scan_queue: 64,
            mask_queue: 64,
            max_subscribers: 32,
            ..Default::default()
        };
        // 4M points × 16 B × 32 × 66 ≈ 135 GB: no /dev/shm here is that big.
        let e = check_shared_memory(&huge).unwrap_err().to_string();
        assert!(e.contains("/dev/shm") && e.contains("max_points"), "{e}");
        check_shared_memory(&ServiceConfig::default()).unwrap();
    }

    #[test]
    fn mangled_service_files_are_errors_naming_the_file_never_panics() {
        let text = include_str!("../../../config/service.toml");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("service.toml");
        let junk = [
            "=",
            "[",
            "\"",
            "max_points = -1",
            "\u{0}",
            "rate_hz = nan",
            "x",
        ];
        let mut accepted = 0;
        // Every cut of the file, each with every piece of junk inserted at the cut.
        for cut in (0..=text.len()).filter(|&c| text.is_char_boundary(c)) {
            for j in junk {
                let mangled = format!("{}{j}{}", &text[..cut], &text[cut..]);
                std::fs::write(&path, mangled).unwrap();
                match ServiceConfig::load(&path) {
                    Ok(c) => {
                        c.validate().unwrap();
                        accepted += 1;
                    }
                    Err(e) => assert!(e.to_string().contains("service.toml"), "{e}"),
                }
            }
        }
        assert!(
            accepted > 0,
            "some insertions land in comments and are harmless"
        );
        std::fs::write(&path, [0xff, 0xfe, 0x00, 0x41]).unwrap();
        let e = ServiceConfig::load(&path).unwrap_err().to_string();
        assert!(e.contains("service.toml"), "{e}");
    }
}
