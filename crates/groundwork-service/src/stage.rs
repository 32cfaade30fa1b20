//! One shape for every stage, and the one loop that runs them.
//!
//! A stage is its state plus [`Stage::process`], which handles one message with no IPC
//! (copper-rs's task model: `start`, `process`, `stop`). [`run`] owns everything around it
//! for every stage alike: the launcher and shared-memory checks, the iceoryx2 node, topics,
//! publisher and subscribers, the stop signals, the wake-ups (and the keep-awake policy),
//! the periodic state log and the sweep for dead processes. A new stage names its topics in
//! [`Stage::WIRING`] and writes its `process`.

use std::time::{Duration, Instant};

use anyhow::Context;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;

use groundwork_msg::{MaskHeader, ProposalsHeader, ScanHeader, ScanPoint, monotonic_ns};

use crate::awake::{ScanWait, Woken};
use crate::config::{ServiceConfig, check_shared_memory};
use crate::signals;
use crate::transport::{self, EventNotifier, ScanPublisher};

/// A topic of a pipeline (`<prefix>/<name>`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Topic {
    /// Scans, from the producer.
    Scans,
    /// Ground probability masks, one per scan, from the segmenter.
    Masks,
    /// Object proposals, one message per segmented scan, from the detector.
    Proposals,
}

impl Topic {
    /// The topic's name under the pipeline's prefix.
    pub fn name(self) -> &'static str {
        match self {
            Self::Scans => "scans",
            Self::Masks => "masks",
            Self::Proposals => "proposals",
        }
    }
}

/// What a stage is handed: one message, read in place in shared memory, or a source's turn.
#[derive(Debug, Clone, Copy)]
pub enum Input<'a> {
    /// A source's turn to publish (stages that wake on no topic).
    Tick,
    /// A scan.
    Scan(&'a ScanHeader, &'a [ScanPoint]),
    /// A mask: one probability per point of its scan.
    Mask(&'a MaskHeader, &'a [f32]),
    /// Proposals: one proposal id per point of its scan (0: none).
    Proposals(&'a ProposalsHeader, &'a [u32]),
}

/// The topics a stage reads and writes.
#[derive(Debug, Clone, Copy)]
pub struct Wiring {
    /// The topic whose messages wake the stage; `None`: a source, handed [`Input::Tick`]
    /// once per [`Stage::period`].
    pub wakes_on: Option<Topic>,
    /// Topics read whenever the stage wakes, before the message that woke it: what they
    /// carry was published earlier (the scan a mask answers).
    pub reads: &'static [Topic],
    /// The topic the stage publishes, if any.
    pub publishes: Option<Topic>,
    /// Its work runs on the thread pool: the service's keep-awake policy applies to it.
    pub parallel: bool,
    /// At most one live process of this stage per pipeline (two segmenters would answer
    /// every scan twice).
    pub unique: bool,
}

/// A stage of the pipeline: its state, and what it does with each message.
pub trait Stage {
    /// The stage's name: its iceoryx2 node is `<prefix>/<NAME>`.
    const NAME: &'static str;
    /// Its topics.
    const WIRING: Wiring;
    /// What it tells when it stops.
    type Report;

    /// Called once its subscribers and publisher exist, before the first message.
    fn start(&mut self) -> anyhow::Result<()> {
        Ok(())
    }

    /// Handles one message (`received_ns`: when it was taken, monotonic), publishing
    /// through `out`. An error ends the process: a bad message is not one (count it, log
    /// it, go on).
    fn process(
        &mut self,
        input: Input<'_>,
        received_ns: u64,
        out: &mut Outbox,
    ) -> anyhow::Result<()>;

    /// Whether it has done what it was asked (`--count`).
    fn done(&self) -> bool;

    /// Called before each wait for a message: whether to go on waiting (an idle timeout,
    /// an injected stall).
    fn before_wait(&mut self) -> bool {
        true
    }

    /// A source's time from one tick's start to the next (zero: flat out).
    fn period(&self) -> Duration {
        Duration::ZERO
    }

    /// Logs its counters (every `report_interval_s`).
    fn log_state(&self);

    /// Ends the run: may read what is still queued (`rest`), and reports.
    fn stop(self, rest: &Inputs) -> anyhow::Result<Self::Report>;
}

/// The longest a stage sleeps before it looks at signals, its periodic work and
/// [`Stage::before_wait`] again.
const IDLE_WAIT: Duration = Duration::from_millis(200);

/// Runs the stage `make` builds (after the launcher and shared-memory checks) until it is
/// done or a termination signal arrives, and returns its report.
pub fn run<S: Stage>(
    cfg: &ServiceConfig,
    make: impl FnOnce() -> anyhow::Result<S>,
) -> anyhow::Result<S::Report> {
    signals::die_with_launcher()?;
    check_shared_memory(cfg)?;
    let wiring = S::WIRING;
    let node = if wiring.unique {
        transport::unique_node(cfg, S::NAME)?
    } else {
        transport::node(cfg, S::NAME)?
    };
    signals::install(&node)?;
    // Built once the stop handlers are in: a stage that shows itself while it starts (the
    // view's server takes connections at once) must not die of a SIGINT sent on seeing it.
    let mut stage = make()?;
    let inputs = Inputs::open(&node, cfg, &wiring)?;
    let mut out = Outbox::open(&node, cfg, wiring.publishes)?;
    let listener = wiring
        .wakes_on
        .map(|t| transport::event_listener(&node, cfg, t.name()))
        .transpose()?;
    stage.start()?;
    tracing::info!(prefix = %cfg.prefix, stage = S::NAME, "started");

    let interval = Duration::from_secs_f64(cfg.report_interval_s);
    let mut last_report = Instant::now();
    let mut periodic = |stage: &S| {
        if last_report.elapsed() >= interval {
            last_report = Instant::now();
            stage.log_state();
            transport::cleanup_dead(&node);
        }
    };
    match (wiring.wakes_on, listener) {
        (Some(trigger), Some(listener)) => {
            let lead = if wiring.parallel {
                cfg.keep_awake_lead()
            } else {
                Duration::ZERO
            };
            let mut wait = ScanWait::new(lead, IDLE_WAIT);
            // Messages published before our listener existed woke nobody: look once.
            inputs.serve(trigger, &mut stage, &mut out, &mut wait)?;
            while !stage.done() && stage.before_wait() {
                // The bounded wait also lets the periodic work run while idle.
                let Woken::Look(awake) = wait.wait(&listener)? else {
                    break;
                };
                // Also serves messages whose wake-up was missed (a publisher restarted
                // between our listener's cleanups): nothing strands in the queue.
                inputs.serve(trigger, &mut stage, &mut out, &mut wait)?;
                drop(awake);
                periodic(&stage);
            }
        }
        _ => {
            while !stage.done() {
                let started = Instant::now();
                stage.process(Input::Tick, monotonic_ns(), &mut out)?;
                periodic(&stage);
                if !signals::sleep(stage.period().saturating_sub(started.elapsed())) {
                    tracing::info!("termination requested");
                    break;
                }
            }
        }
    }
    // A launcher killed with -9 (whose death is why we stop) leaves its node: sweep it.
    transport::cleanup_dead(&node);
    stage.stop(&inputs)
}

/// A message taken from a topic, held in shared memory until dropped.
enum Held {
    Scan(Sample<ipc::Service, [ScanPoint], ScanHeader>),
    Mask(Sample<ipc::Service, [f32], MaskHeader>),
    Proposals(Sample<ipc::Service, [u32], ProposalsHeader>),
}

impl Held {
    fn input(&self) -> Input<'_> {
        match self {
            Self::Scan(s) => Input::Scan(s.user_header(), s.payload()),
            Self::Mask(s) => Input::Mask(s.user_header(), s.payload()),
            Self::Proposals(s) => Input::Proposals(s.user_header(), s.payload()),
        }
    }
}

/// A stage's subscribers: the topic that wakes it and those it reads beside.
pub struct Inputs {
    scans: Option<Subscriber<ipc::Service, [ScanPoint], ScanHeader>>,
    masks: Option<Subscriber<ipc::Service, [f32], MaskHeader>>,
    proposals: Option<Subscriber<ipc::Service, [u32], ProposalsHeader>>,
    reads: &'static [Topic],
}

impl std::fmt::Debug for Inputs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Inputs")
            .field("scans", &self.scans.is_some())
            .field("masks", &self.masks.is_some())
            .field("proposals", &self.proposals.is_some())
            .finish()
    }
}

impl Inputs {
    fn open(node: &Node<ipc::Service>, cfg: &ServiceConfig, w: &Wiring) -> anyhow::Result<Self> {
        let wants = |t: Topic| w.wakes_on == Some(t) || w.reads.contains(&t);
        let scans = wants(Topic::Scans)
            .then(|| transport::scan_subscriber(&transport::scan_service(node, cfg)?, cfg))
            .transpose()?;
        let masks = wants(Topic::Masks)
            .then(|| transport::mask_subscriber(&transport::mask_service(node, cfg)?, cfg))
            .transpose()?;
        let proposals = wants(Topic::Proposals)
            .then(|| {
                transport::proposals_subscriber(&transport::proposals_service(node, cfg)?, cfg)
            })
            .transpose()?;
        Ok(Self {
            scans,
            masks,
            proposals,
            reads: w.reads,
        })
    }

    fn take(&self, topic: Topic) -> anyhow::Result<Option<Held>> {
        let what = topic.name();
        let held = match topic {
            Topic::Scans => self
                .scans
                .as_ref()
                .map(|s| s.receive().map(|m| m.map(Held::Scan))),
            Topic::Masks => self
                .masks
                .as_ref()
                .map(|s| s.receive().map(|m| m.map(Held::Mask))),
            Topic::Proposals => self
                .proposals
                .as_ref()
                .map(|s| s.receive().map(|m| m.map(Held::Proposals))),
        };
        match held {
            None => anyhow::bail!("this stage does not subscribe to {what}"),
            Some(r) => r.with_context(|| format!("receive from {what}")),
        }
    }

    /// Hands every message queued on `topic` to `f` (with the time it was taken); returns
    /// how many there were.
    pub fn read(
        &self,
        topic: Topic,
        mut f: impl FnMut(Input<'_>, u64) -> anyhow::Result<()>,
    ) -> anyhow::Result<u64> {
        let mut n = 0;
        while let Some(m) = self.take(topic)? {
            f(m.input(), monotonic_ns())?;
            n += 1;
        }
        Ok(n)
    }

    /// Serves every queued message of `trigger`: each is taken and stamped, then what the
    /// side topics hold is read, then the message is processed.
    fn serve<S: Stage>(
        &self,
        trigger: Topic,
        stage: &mut S,
        out: &mut Outbox,
        wait: &mut ScanWait,
    ) -> anyhow::Result<()> {
        loop {
            let next = self.take(trigger)?;
            let received_ns = monotonic_ns();
            if next.is_some() {
                wait.arrived(Instant::now());
            }
            for &side in self.reads {
                self.read(side, |input, at| stage.process(input, at, out))?;
            }
            let Some(message) = next else {
                return Ok(());
            };
            stage.process(message.input(), received_ns, out)?;
            drop(message);
            if stage.done() {
                return Ok(());
            }
        }
    }
}

/// The publisher of a stage's topic, and the notifier that wakes its readers. Each send
/// stamps the message's publication time and reports how many subscribers it reached.
pub struct Outbox {
    port: Port,
    notifier: Option<EventNotifier>,
}

enum Port {
    None,
    Scans(ScanPublisher),
    Masks(iceoryx2::port::publisher::Publisher<ipc::Service, [f32], MaskHeader>),
    Proposals(iceoryx2::port::publisher::Publisher<ipc::Service, [u32], ProposalsHeader>),
}

impl std::fmt::Debug for Outbox {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let port = match self.port {
            Port::None => "none",
            Port::Scans(_) => "scans",
            Port::Masks(_) => "masks",
            Port::Proposals(_) => "proposals",
        };
        f.debug_struct("Outbox").field("publishes", &port).finish()
    }
}

impl Outbox {
    fn open(
        node: &Node<ipc::Service>,
        cfg: &ServiceConfig,
        topic: Option<Topic>,
    ) -> anyhow::Result<Self> {
        let port = match topic {
            None => Port::None,
            Some(Topic::Scans) => Port::Scans(transport::scan_publisher(
                &transport::scan_service(node, cfg)?,
                cfg,
            )?),
            Some(Topic::Masks) => Port::Masks(transport::mask_publisher(
                &transport::mask_service(node, cfg)?,
                cfg,
            )?),
            Some(Topic::Proposals) => Port::Proposals(transport::proposals_publisher(
                &transport::proposals_service(node, cfg)?,
                cfg,
            )?),
        };
        let notifier = topic
            .map(|t| transport::event_notifier(node, cfg, t.name()))
            .transpose()?;
        Ok(Self { port, notifier })
    }

    fn wake_readers(&self) {
        if let Some(n) = &self.notifier {
            // A reader that misses a wake-up finds the message at its next look.
            let _ = n.notify();
        }
    }

    /// Publishes a scan of `len` points, point `i` given by `point(i)`: the one copy on
    /// the hot path, from the source straight into shared memory.
    pub fn send_scan(
        &mut self,
        len: usize,
        point: impl FnMut(usize) -> ScanPoint,
        mut header: ScanHeader,
    ) -> anyhow::Result<usize> {
        let Port::Scans(p) = &self.port else {
            anyhow::bail!("this stage publishes no scans");
        };
        let sample = p
            .loan_slice_uninit(len)
            .map_err(|e| anyhow::anyhow!("loan of {len} points: {e:?}"))?;
        let mut sample = sample.write_from_fn(point);
        header.stamps.published_ns = monotonic_ns();
        *sample.user_header_mut() = header;
        let reached = sample.send().context("send scan")?;
        self.wake_readers();
        Ok(reached)
    }

    /// Publishes a scan of `len` points, which `fill` writes in place in shared memory (a
    /// zeroed sample: for sources that copy faster in one pass than point by point),
    /// unless `fill` says no (returns false: a source that checks its points as it copies
    /// them). Then nothing is published, the loan goes back, and the answer is `None`.
    pub fn send_scan_filled(
        &mut self,
        len: usize,
        fill: impl FnOnce(&mut [ScanPoint]) -> bool,
        mut header: ScanHeader,
    ) -> anyhow::Result<Option<usize>> {
        let Port::Scans(p) = &self.port else {
            anyhow::bail!("this stage publishes no scans");
        };
        let mut sample = p
            .loan_slice(len)
            .map_err(|e| anyhow::anyhow!("loan of {len} points: {e:?}"))?;
        if !fill(sample.payload_mut()) {
            return Ok(None);
        }
        header.stamps.published_ns = monotonic_ns();
        *sample.user_header_mut() = header;
        let reached = sample.send().context("send scan")?;
        self.wake_readers();
        Ok(Some(reached))
    }

    /// Publishes a mask of `len` values, which `fill` writes in place in shared memory,
    /// with the header `fill` returns.
    pub fn send_mask(
        &mut self,
        len: usize,
        fill: impl FnOnce(&mut [f32]) -> MaskHeader,
    ) -> anyhow::Result<usize> {
        let Port::Masks(p) = &self.port else {
            anyhow::bail!("this stage publishes no masks");
        };
        let mut mask = p
            .loan_slice(len)
            .map_err(|e| anyhow::anyhow!("loan mask of {len}: {e:?}"))?;
        let mut header = fill(mask.payload_mut());
        header.stamps.segmenter_published_ns = monotonic_ns();
        *mask.user_header_mut() = header;
        let reached = mask.send().context("send mask")?;
        self.wake_readers();
        Ok(reached)
    }

    /// Publishes proposals: one id per point of the scan, and the header.
    pub fn send_proposals(
        &mut self,
        ids: &[u32],
        mut header: ProposalsHeader,
    ) -> anyhow::Result<usize> {
        let Port::Proposals(p) = &self.port else {
            anyhow::bail!("this stage publishes no proposals");
        };
        let mut sample = p
            .loan_slice_uninit(ids.len())
            .map_err(|e| anyhow::anyhow!("loan proposals of {}: {e:?}", ids.len()))?
            .write_from_slice(ids);
        header.detector_published_ns = monotonic_ns();
        *sample.user_header_mut() = header;
        let reached = sample.send().context("send proposals")?;
        self.wake_readers();
        Ok(reached)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const N: u64 = 12;

    /// Publishes `N` scans of `k + 1` points (x = k), one every 5 ms.
    struct Source {
        sent: u64,
    }

    impl Stage for Source {
        const NAME: &'static str = "source";
        const WIRING: Wiring = Wiring {
            wakes_on: None,
            reads: &[],
            publishes: Some(Topic::Scans),
            parallel: false,
            unique: true,
        };
        type Report = u64;

        fn process(&mut self, input: Input<'_>, now: u64, out: &mut Outbox) -> anyhow::Result<()> {
            assert!(matches!(input, Input::Tick));
            let k = self.sent;
            let header = ScanHeader {
                sequence: k,
                point_count: k as u32 + 1,
                sensor_timestamp_ns: now,
                ..ScanHeader::default()
            };
            let point = |_| ScanPoint {
                x: k as f32,
                ..ScanPoint::default()
            };
            out.send_scan(k as usize + 1, point, header)?;
            self.sent += 1;
            Ok(())
        }
        fn done(&self) -> bool {
            self.sent >= N
        }
        fn period(&self) -> Duration {
            Duration::from_millis(5)
        }
        fn log_state(&self) {}
        fn stop(self, _: &Inputs) -> anyhow::Result<u64> {
            // A leaving publisher takes its samples with it: stay until they are read.
            std::thread::sleep(Duration::from_millis(500));
            Ok(self.sent)
        }
    }

    /// Answers each scan with a mask of its points' x doubled.
    struct Doubler {
        answered: u64,
    }

    impl Stage for Doubler {
        const NAME: &'static str = "doubler";
        const WIRING: Wiring = Wiring {
            wakes_on: Some(Topic::Scans),
            reads: &[],
            publishes: Some(Topic::Masks),
            parallel: true,
            unique: true,
        };
        type Report = u64;

        fn process(&mut self, input: Input<'_>, at: u64, out: &mut Outbox) -> anyhow::Result<()> {
            let Input::Scan(h, points) = input else {
                anyhow::bail!("a doubler is handed scans only");
            };
            out.send_mask(points.len(), |mask| {
                for (m, p) in mask.iter_mut().zip(points) {
                    *m = 2.0 * p.x;
                }
                let mut header = MaskHeader {
                    scan_sequence: h.sequence,
                    point_count: points.len() as u32,
                    ..MaskHeader::default()
                };
                header.stamps.segmenter_received_ns = at;
                header
            })?;
            self.answered += 1;
            Ok(())
        }
        fn done(&self) -> bool {
            self.answered >= N
        }
        fn log_state(&self) {}
        fn stop(self, _: &Inputs) -> anyhow::Result<u64> {
            std::thread::sleep(Duration::from_millis(500));
            Ok(self.answered)
        }
    }

    /// Wakes on masks, reads scans beside: writes down what it was handed, in order.
    #[derive(Default)]
    struct Collector {
        seen: Vec<String>,
        masks: u64,
    }

    impl Stage for Collector {
        const NAME: &'static str = "collector";
        const WIRING: Wiring = Wiring {
            wakes_on: Some(Topic::Masks),
            reads: &[Topic::Scans],
            publishes: None,
            parallel: false,
            unique: false,
        };
        type Report = Vec<String>;

        fn process(&mut self, input: Input<'_>, _: u64, out: &mut Outbox) -> anyhow::Result<()> {
            match input {
                Input::Scan(h, _) => self.seen.push(format!("scan {}", h.sequence)),
                Input::Mask(h, values) => {
                    let want = 2.0 * h.scan_sequence as f32;
                    assert!(values.iter().all(|&v| v == want), "{values:?}");
                    assert!(h.stamps.segmenter_published_ns >= h.stamps.segmenter_received_ns);
                    self.seen
                        .push(format!("mask {} of {}", h.scan_sequence, values.len()));
                    self.masks += 1;
                }
                _ => anyhow::bail!("unexpected input"),
            }
            // It publishes nothing: trying is an error, not a silent loss.
            assert!(out.send_mask(1, |_| MaskHeader::default()).is_err());
            Ok(())
        }
        fn done(&self) -> bool {
            self.masks >= N
        }
        fn log_state(&self) {}
        fn stop(self, _: &Inputs) -> anyhow::Result<Vec<String>> {
            Ok(self.seen)
        }
    }

    #[test]
    fn the_runner_wires_stages_by_their_topics_and_hands_side_reads_first() {
        let cfg = ServiceConfig {
            prefix: format!("gw-stage-test-{}", std::process::id()),
            ..Default::default()
        };
        let (c1, c2) = (cfg.clone(), cfg.clone());
        let collector = std::thread::spawn(move || run(&c1, || Ok(Collector::default())));
        let doubler = std::thread::spawn(move || run(&c2, || Ok(Doubler { answered: 0 })));
        // Both listen before the first scan is out (a topic keeps no history).
        let t = Instant::now();
        while transport::pipeline_nodes(&cfg)
            .iter()
            .filter(|n| n.1)
            .count()
            < 2
        {
            assert!(
                t.elapsed() < Duration::from_secs(10),
                "stages did not start"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
        std::thread::sleep(Duration::from_millis(100));
        // A second doubler is refused while one runs.
        let again = run(&cfg, || Ok(Doubler { answered: 0 }));
        assert!(again.unwrap_err().to_string().contains("another doubler"));
        assert_eq!(run(&cfg, || Ok(Source { sent: 0 })).unwrap(), N);
        assert_eq!(doubler.join().unwrap().unwrap(), N);
        let seen = collector.join().unwrap().unwrap();
        // Every scan, each read before the mask that answers it, and the masks in order.
        let masks: Vec<&String> = seen.iter().filter(|s| s.starts_with("mask")).collect();
        assert_eq!(masks.len() as u64, N, "{seen:?}");
        for k in 0..N {
            let scan = seen.iter().position(|s| *s == format!("scan {k}"));
            let mask = seen
                .iter()
                .position(|s| *s == format!("mask {k} of {}", k + 1));
            assert!(
                matches!((scan, mask), (Some(s), Some(m)) if s < m),
                "{k}: {seen:?}"
            );
        }
    }
}
