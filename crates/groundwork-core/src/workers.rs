//! Running one scan's work with the thread pool's other workers awake.
//!
//! A scan alternates serial steps with parallel ones. A worker that found nothing to do for
//! a few tens of microseconds goes to sleep, and on a virtual machine a sleeping worker's
//! core halts: the hypervisor gives the physical core away and hands it back at its next
//! scheduler tick. Measured on the 2-vCPU VMs here, a worker idle for 1 ms or more joined a
//! parallel step 1 ms late (p50; 30 µs after shorter idles), so a parallel step of 2 ms
//! that followed 2 ms of serial work ran on one core. [`with_workers_awake`] runs the
//! scan on a pool worker and keeps the others spinning — ready to steal its parallel work
//! the moment it appears — until the scan is done.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Longest a helper spins: a bound on the cost of a scan that takes unusually long (the
/// wake-up it saves is then small in comparison).
const MAX_SPIN: Duration = Duration::from_millis(20);

/// Runs `f` on a worker of the global thread pool while its other workers spin (running any
/// parallel work `f` spawns) until `f` returns. Called from inside the pool (a scan among
/// others processed in parallel) it just runs `f`: the other workers have work of their own.
pub fn with_workers_awake<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    let helpers = rayon::current_num_threads().saturating_sub(1);
    if helpers == 0 || rayon::current_thread_index().is_some() {
        return f();
    }
    let done = AtomicBool::new(false);
    // The helpers are queued before `f` starts, so the first thieves take them (thieves
    // take the oldest job), and `f`'s own parallel work, queued after, goes to them.
    rayon::scope(|s| {
        for _ in 0..helpers {
            s.spawn(|_| spin_until(&done, MAX_SPIN));
        }
        let r = f();
        done.store(true, Ordering::Release);
        r
    })
}

/// On a pool worker: runs the pool's pending parallel work as it appears, and gives the
/// core to any other thread that has work when there is none (`f` above, another stage),
/// until `stop` is set or `limit` has passed. The worker stays awake all along.
pub fn spin_until(stop: &AtomicBool, limit: Duration) {
    let start = Instant::now();
    while !stop.load(Ordering::Acquire) && start.elapsed() < limit {
        if rayon::yield_now() != Some(rayon::Yield::Executed) {
            std::thread::yield_now();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    #[test]
    fn returns_what_the_work_returns_and_runs_its_parallel_parts() {
        let v: Vec<u64> = (0..10_000).collect();
        let sum = with_workers_awake(|| v.par_iter().sum::<u64>());
        assert_eq!(sum, 10_000 * 9_999 / 2);
        // Nested: inside the pool it runs the work directly.
        let nested: Vec<u64> = (0..4)
            .into_par_iter()
            .map(|k| with_workers_awake(|| v.par_iter().map(|x| x * k).sum::<u64>()))
            .collect();
        assert_eq!(nested, [0, 1, 2, 3].map(|k| k * sum));
    }
}
