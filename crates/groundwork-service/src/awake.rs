//! Keeping cores awake: the service's one policy that spends CPU to answer sooner, off
//! unless `keep_awake_ms` asks for it.
//!
//! On a virtual machine (and on a host with deep idle states) a core that idled through the
//! 90 ms between two scans comes back slowly: its virtual CPU halted and gave the physical
//! core away, and every parallel step of the next scan waits for it. A sensor is periodic,
//! so a stage can see the next scan coming: it learns the period from the arrivals, sleeps
//! until `keep_awake` before the next one is due, then keeps the thread pool's workers
//! spinning ([`AwakeWorkers`]: running any parallel work that appears) until the scan has
//! been processed. The cost is bounded: `keep_awake` plus the scan's own time per period on
//! each core, and at most `2·keep_awake` when a scan is late or missing; irregular arrivals
//! turn it off. The consumer's report shows what it costs, as CPU time per scan.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::transport::{EventListener, wait_or_stop};

/// Intervals the period is estimated from.
const INTERVALS: usize = 8;
/// Fewest intervals before a period is trusted.
const MIN_INTERVALS: usize = 4;
/// Largest relative deviation of any recent interval from their median for the arrivals to
/// count as periodic.
const JITTER: f64 = 0.2;

/// Learns the period of scan arrivals and predicts the next one.
#[derive(Debug, Default)]
pub struct ArrivalClock {
    last: Option<Instant>,
    intervals: VecDeque<Duration>,
}

impl ArrivalClock {
    /// A scan arrived at `at`.
    pub fn arrived(&mut self, at: Instant) {
        if let Some(last) = self.last {
            if self.intervals.len() == INTERVALS {
                self.intervals.pop_front();
            }
            self.intervals.push_back(at.saturating_duration_since(last));
        }
        self.last = Some(at);
    }

    /// The period, if the recent arrivals were periodic (three in four of the last intervals
    /// within 20 % of their median, and the median not zero).
    pub fn period(&self) -> Option<Duration> {
        if self.intervals.len() < MIN_INTERVALS {
            return None;
        }
        let mut sorted: Vec<Duration> = self.intervals.iter().copied().collect();
        sorted.sort_unstable();
        let median = sorted[sorted.len() / 2];
        let m = median.as_secs_f64();
        // One late scan makes two odd intervals (long, then short): tolerated.
        let near = self
            .intervals
            .iter()
            .filter(|d| (d.as_secs_f64() - m).abs() <= JITTER * m)
            .count();
        let regular = m > 0.0 && near * 4 >= self.intervals.len() * 3;
        regular.then_some(median)
    }

    /// When the next scan is due, if arrivals are periodic.
    pub fn next_due(&self) -> Option<Instant> {
        Some(self.last? + self.period()?)
    }
}

/// The global thread pool's workers kept awake until this is dropped: each runs any
/// parallel work that appears and otherwise yields its core to any thread that has work,
/// instead of going to sleep.
#[derive(Debug)]
pub struct AwakeWorkers {
    stop: Arc<AtomicBool>,
    /// Workers kept awake now.
    running: Arc<std::sync::atomic::AtomicUsize>,
}

impl AwakeWorkers {
    /// Keeps every worker of the global pool awake.
    pub fn start() -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let running = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let (flag, count) = (stop.clone(), running.clone());
        rayon::spawn_broadcast(move |_| {
            count.fetch_add(1, Ordering::AcqRel);
            spin_until(&flag);
            count.fetch_sub(1, Ordering::AcqRel);
        });
        Self { stop, running }
    }

    /// Workers kept awake by it now (none once it is dropped and they have noticed).
    pub fn running(&self) -> usize {
        self.running.load(Ordering::Acquire)
    }
}

impl Drop for AwakeWorkers {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
    }
}

/// On a pool worker: runs the pool's pending parallel work as it appears, and gives the
/// core to any other thread that has work when there is none, until `stop` is set. The
/// worker stays awake all along.
fn spin_until(stop: &AtomicBool) {
    while !stop.load(Ordering::Acquire) {
        if rayon::yield_now() != Some(rayon::Yield::Executed) {
            std::thread::yield_now();
        }
    }
}

/// How a stage waits for its next scan.
#[derive(Debug)]
pub struct ScanWait {
    clock: ArrivalClock,
    keep_awake: Duration,
    idle: Duration,
    /// How late the recent timed waits before a due scan returned (newest last).
    late: VecDeque<Duration>,
}

/// Most a wait is moved ahead for the wake-up's own lateness.
const MAX_EARLY: Duration = Duration::from_millis(20);

/// What a wait ended with.
#[derive(Debug)]
pub enum Woken {
    /// A termination signal: stop.
    Stop,
    /// Look for scans (there may be none: a timeout); hold the awake workers, if any,
    /// while processing them.
    Look(Option<AwakeWorkers>),
}

impl ScanWait {
    /// Waits of at most `idle` when no scan is due; `keep_awake` before a due scan the
    /// pool's workers are kept awake (zero: never).
    pub fn new(keep_awake: Duration, idle: Duration) -> Self {
        Self {
            clock: ArrivalClock::default(),
            keep_awake,
            idle,
            late: VecDeque::new(),
        }
    }

    /// How much earlier than planned to wake: the largest lateness of the recent waits (a
    /// halted virtual CPU's timer can fire milliseconds late), at most [`MAX_EARLY`].
    fn early(&self) -> Duration {
        self.late
            .iter()
            .copied()
            .max()
            .unwrap_or_default()
            .min(MAX_EARLY)
    }

    /// A scan arrived at `at` (call once per scan, in order).
    pub fn arrived(&mut self, at: Instant) {
        self.clock.arrived(at);
    }

    /// Waits on `listener` for the next scan.
    pub fn wait(&mut self, listener: &EventListener) -> anyhow::Result<Woken> {
        let now = Instant::now();
        // A scan more than `keep_awake` overdue is late or missing: wait for it asleep.
        let lead = self.keep_awake;
        let due = (self.clock.next_due()).filter(|&due| !lead.is_zero() && now < due + lead);
        let Some(due) = due else {
            return Ok(look(wait_or_stop(listener, self.idle)?, None));
        };
        let start = due.checked_sub(lead + self.early()).unwrap_or(now);
        if start > now {
            // Early scans, and the periodic work, are served without spinning.
            let until = (start - now).min(self.idle);
            if !wait_or_stop(listener, until)? {
                return Ok(Woken::Stop);
            }
            let woke = Instant::now();
            if until < start - now {
                return Ok(Woken::Look(None));
            }
            if woke < start {
                return Ok(Woken::Look(None)); // a scan came early
            }
            if self.late.len() == INTERVALS {
                self.late.pop_front();
            }
            self.late.push_back(woke - start);
        }
        // Awake from `keep_awake` before the scan is due to `keep_awake` after; a later one
        // is waited for asleep again.
        let awake = AwakeWorkers::start();
        let until = (due + lead).saturating_duration_since(Instant::now());
        Ok(look(wait_or_stop(listener, until)?, Some(awake)))
    }
}

fn look(go_on: bool, awake: Option<AwakeWorkers>) -> Woken {
    if go_on {
        Woken::Look(awake)
    } else {
        Woken::Stop
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn periodic_arrivals_predict_the_next_and_irregular_ones_do_not() {
        let t0 = Instant::now();
        let mut c = ArrivalClock::default();
        let ms = Duration::from_millis;
        for k in 0..4 {
            c.arrived(t0 + ms(100 * k));
        }
        assert_eq!(c.next_due(), None, "three intervals are not enough");
        c.arrived(t0 + ms(400));
        assert_eq!(c.period(), Some(ms(100)));
        assert_eq!(c.next_due(), Some(t0 + ms(500)));
        // Sensor jitter of a few milliseconds keeps the period.
        c.arrived(t0 + ms(497));
        assert_eq!(c.period(), Some(ms(100)));
        // A dropped scan (one 200 ms gap) keeps the period.
        c.arrived(t0 + ms(697));
        assert_eq!(c.next_due(), Some(t0 + ms(797)));
        // Arrivals that wander (alternately 50 and 150 ms apart) are not periodic.
        let mut t = 697;
        for k in 0..INTERVALS as u64 {
            t += if k % 2 == 0 { 50 } else { 150 };
            c.arrived(t0 + ms(t));
        }
        assert_eq!(c.next_due(), None);
        // Back-to-back bursts (zero intervals) never count as periodic.
        let mut b = ArrivalClock::default();
        for _ in 0..6 {
            b.arrived(t0);
        }
        assert_eq!(b.period(), None);
    }

    #[test]
    fn a_due_scan_is_awaited_spinning_and_a_missing_one_asleep() {
        let cfg = crate::ServiceConfig {
            prefix: format!("gw-awake-test-{}", std::process::id()),
            ..Default::default()
        };
        let node = crate::transport::node(&cfg, "awake-test").unwrap();
        let listener = crate::transport::event_listener(&node, &cfg, "scans").unwrap();
        let notifier = crate::transport::event_notifier(&node, &cfg, "scans").unwrap();
        let ms = Duration::from_millis;
        // Margins wide enough for a loaded CI machine.
        let (lead, idle) = (ms(5), ms(300));
        let mut w = ScanWait::new(lead, idle);
        // Not periodic yet: a plain idle wait, no workers kept awake.
        assert!(matches!(w.wait(&listener).unwrap(), Woken::Look(None)));
        // A 200 ms sensor whose next scan is due 150 ms from now.
        let now = Instant::now();
        for k in (0..6u32).rev() {
            w.arrived(now + ms(150) - ms(200) * (k + 1));
        }
        let due = now + ms(150);
        match w.wait(&listener).unwrap() {
            Woken::Look(Some(_awake)) => {}
            other => panic!("expected to spin for the due scan, got {other:?}"),
        }
        // No scan came: the workers were awake until `lead` past the due time, not longer than
        // that plus a scheduling slice.
        let t = Instant::now();
        assert!(
            t + ms(1) >= due + lead,
            "stopped spinning {:?} early",
            (due + lead) - t
        );
        // Now overdue: asleep, for the idle timeout.
        let before = Instant::now();
        assert!(matches!(w.wait(&listener).unwrap(), Woken::Look(None)));
        assert!(before.elapsed() + ms(1) >= idle);
        // A scan that arrives early wakes the wait at once, workers asleep.
        w.arrived(Instant::now());
        for _ in 0..6 {
            let last = w.clock.last.unwrap();
            w.arrived(last + ms(200));
        }
        // (The clock expects the next scan over a second ahead; a notification is there
        // first.)
        notifier.notify().unwrap();
        let before = Instant::now();
        assert!(matches!(w.wait(&listener).unwrap(), Woken::Look(None)));
        assert!(
            before.elapsed() < idle,
            "an early scan must not wait out the timeout"
        );
    }

    #[test]
    fn awake_workers_run_parallel_work_and_sleep_again_when_dropped() {
        let s = AwakeWorkers::start();
        let running = s.running.clone();
        let until = |want: &dyn Fn(usize) -> bool| {
            let t = Instant::now();
            while !want(running.load(Ordering::Acquire)) {
                assert!(
                    t.elapsed() < Duration::from_secs(5),
                    "{} spinning",
                    running.load(Ordering::Acquire)
                );
                std::thread::sleep(Duration::from_millis(1));
            }
        };
        until(&|n| n > 0);
        // Parallel work still completes while the workers spin (they run it).
        let sum: u64 = {
            use rayon::prelude::*;
            (0..100_000u64).into_par_iter().sum()
        };
        assert_eq!(sum, 100_000 * 99_999 / 2);
        drop(s);
        // Every worker returns to sleep (a broadcast alone would not tell: awake workers run broadcast
        // jobs too).
        until(&|n| n == 0);
        // The workers are free again: a broadcast reaches every one of them.
        let seen = rayon::broadcast(|c| c.index());
        assert_eq!(seen.len(), rayon::current_num_threads());
    }
}
