//! Starts the three stages as separate processes and stops them cleanly.

use std::process::{Child, Command, ExitStatus};
use std::time::{Duration, Instant};

use iceoryx2::prelude::*;
use rustix::process::{Pid, Signal, kill_process};
use tracing::{info, warn};

/// One stage to start.
#[derive(Debug)]
pub struct Stage {
    /// Name for logs.
    pub name: &'static str,
    /// The command (usually this executable with a stage subcommand).
    pub command: Command,
}

/// Exit status of each stage, in start order.
pub type Outcome = Vec<(&'static str, Option<ExitStatus>)>;

fn terminate(children: &mut [(&'static str, Child)], grace: Duration) {
    for (name, c) in children.iter_mut() {
        if matches!(c.try_wait(), Ok(None)) {
            info!(stage = *name, "sending SIGTERM");
            let _ = kill_process(Pid::from_child(c), Signal::TERM);
        }
    }
    let t = Instant::now();
    while t.elapsed() < grace {
        if children
            .iter_mut()
            .all(|(_, c)| !matches!(c.try_wait(), Ok(None)))
        {
            return;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    for (name, c) in children.iter_mut() {
        if matches!(c.try_wait(), Ok(None)) {
            warn!(stage = *name, "did not stop within {grace:?}: killing");
            let _ = c.kill();
        }
    }
}

/// Starts `stages` in order (readers first, so the first scans are not lost), then waits:
/// when the stage named `finisher` exits, or on Ctrl-C / SIGTERM, the others get SIGTERM
/// and a grace period to leave cleanly (iceoryx2 removes their shared memory on exit).
pub fn run(stages: Vec<Stage>, finisher: &str) -> anyhow::Result<Outcome> {
    // A node only to learn about Ctrl-C: iceoryx2 catches SIGINT/SIGTERM and reports them
    // through `Node::wait`.
    let node = NodeBuilder::new()
        .create::<ipc::Service>()
        .map_err(|e| anyhow::anyhow!("cannot create iceoryx2 node: {e:?}"))?;
    let mut children: Vec<(&'static str, Child)> = Vec::new();
    for mut s in stages {
        match s.command.spawn() {
            Ok(c) => {
                info!(stage = s.name, pid = c.id(), "started");
                children.push((s.name, c));
                // Give each reader time to attach before the next stage starts.
                std::thread::sleep(Duration::from_millis(300));
            }
            Err(e) => {
                terminate(&mut children, Duration::from_secs(3));
                anyhow::bail!("cannot start {}: {e}", s.name);
            }
        }
    }
    loop {
        if node.wait(Duration::from_millis(100)).is_err() {
            info!("Ctrl-C: stopping the pipeline");
            break;
        }
        let mut finished = false;
        for (name, c) in children.iter_mut() {
            if let Ok(Some(status)) = c.try_wait() {
                if *name == finisher || !status.success() {
                    if !status.success() {
                        warn!(stage = *name, %status, "stage exited");
                    }
                    finished = true;
                }
            }
        }
        if finished {
            break;
        }
    }
    terminate(&mut children, Duration::from_secs(5));
    Ok(children
        .into_iter()
        .map(|(n, mut c)| (n, c.try_wait().ok().flatten()))
        .collect())
}
