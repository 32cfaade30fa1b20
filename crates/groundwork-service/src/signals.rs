//! What ends a stage, and what does not.
//!
//! SIGINT, SIGTERM and SIGHUP (an ssh session closing) request a clean stop: the stage
//! finishes the message in hand, writes its report and leaves, and iceoryx2 removes its
//! shared memory. Every other signal — SIGCONT after a SIGSTOP (a debugger, `kill -STOP`
//! while profiling, a suspended terminal), SIGURG, SIGPROF — only interrupts a wait, which
//! is then resumed.
//!
//! iceoryx2 catches SIGINT and SIGTERM itself but remembers only the *last* signal, which
//! a following SIGCONT overwrites, and reading it consumes it; SIGHUP it leaves fatal. So
//! the stop request is a flag of our own, set by async-signal-safe handlers (signal-hook)
//! that chain to iceoryx2's.

use std::sync::Arc;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use iceoryx2::node::NodeWaitFailure;
use iceoryx2::prelude::*;
use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};

static STOP: OnceLock<Arc<AtomicBool>> = OnceLock::new();

/// Installs the stop handlers (once per process). Call after creating the process's node:
/// iceoryx2 installs its own handlers lazily, without chaining, and would replace ours if
/// it did so later, so it is made to do so first.
pub fn install(node: &Node<ipc::Service>) -> anyhow::Result<()> {
    let flag = STOP.get_or_init(|| Arc::new(AtomicBool::new(false)));
    if node.wait(Duration::ZERO) == Err(NodeWaitFailure::TerminationRequest) {
        flag.store(true, Ordering::SeqCst);
    }
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            for sig in [SIGINT, SIGTERM, SIGHUP] {
                signal_hook::flag::register(sig, Arc::clone(flag))
                    .map_err(|e| format!("cannot install the handler of signal {sig}: {e}"))?;
            }
            Ok(())
        })
        .clone()
        .map_err(|e| anyhow::anyhow!(e))
}

/// Whether SIGINT, SIGTERM or SIGHUP arrived since [`install`].
pub fn stop_requested() -> bool {
    STOP.get().is_some_and(|f| f.load(Ordering::SeqCst))
}

/// Sleeps for `d` unless a stop is requested (checked at least every 50 ms); a signal that
/// interrupts the sleep (SIGCONT) does not shorten it. Returns whether to go on.
pub fn sleep(d: Duration) -> bool {
    // Duration::MAX: until a stop is requested.
    let end = std::time::Instant::now().checked_add(d);
    loop {
        if stop_requested() {
            return false;
        }
        let left = end.map_or(Duration::MAX, |e| {
            e.saturating_duration_since(std::time::Instant::now())
        });
        if left.is_zero() {
            return true;
        }
        std::thread::sleep(left.min(Duration::from_millis(50)));
    }
}

/// The exit code of a stage that a signal stopped before it finished its work (the
/// consumer before its `--count`, or any stage the launcher runs and did not stop itself):
/// the launcher restarts it or fails the pipeline, as for a death.
pub const STOPPED_EXIT_CODE: u8 = 4;

/// Whether this process was started by the launcher.
pub fn under_launcher() -> bool {
    std::env::var_os(PARENT_ENV).is_some()
}

/// The environment variable through which the launcher tells a stage its pid.
pub const PARENT_ENV: &str = "GROUNDWORK_LAUNCHER_PID";

/// A stage started by the launcher dies with it: if the launcher is killed (even with -9)
/// the kernel sends this stage SIGTERM, which stops it cleanly. Without the launcher's
/// variable in the environment this does nothing.
pub fn die_with_launcher() -> anyhow::Result<()> {
    let Ok(pid) = std::env::var(PARENT_ENV) else {
        return Ok(());
    };
    let pid: i32 = pid
        .parse()
        .map_err(|_| anyhow::anyhow!("{PARENT_ENV}={pid}: not a process id"))?;
    rustix::process::set_parent_process_death_signal(Some(rustix::process::Signal::TERM))
        .map_err(|e| anyhow::anyhow!("cannot ask for a parent-death signal: {e}"))?;
    // The launcher may have died before the request above: then no signal will come.
    let parent = rustix::process::getppid().map_or(0, |p| p.as_raw_nonzero().get());
    anyhow::ensure!(
        parent == pid,
        "the launcher (pid {pid}) is gone: not starting"
    );
    Ok(())
}
