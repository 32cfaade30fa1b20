//! Starts the stages as separate processes, supervises them, and stops them cleanly.
//!
//! - Each stage dies with the launcher: it gets SIGTERM from the kernel if the launcher dies,
//!   even of kill -9 (see [`crate::signals::die_with_launcher`]).
//! - SIGINT, SIGTERM and SIGHUP stop the pipeline cleanly: every stage gets SIGTERM and a
//!   grace period, writes its report and removes its shared memory.
//! - A stage that ends while the pipeline runs (killed by a signal, any exit code; only
//!   the finishing stage may end, and only with 0 or 1) fails the pipeline — or, with
//!   `max_restarts`, is started again up to that many times (counted and logged), since
//!   every stage is built to rejoin a running pipeline.
//! - Exit codes of stages: 0 done, 1 done but some input was bad (counted, reported),
//!   2 and above: error.

use std::process::{Child, Command, ExitStatus};
use std::time::{Duration, Instant};

use rustix::process::{Pid, Signal, kill_process};
use tracing::{error, info, warn};

use crate::config::ServiceConfig;
use crate::{signals, transport};

/// One stage to start.
#[derive(Debug)]
pub struct Stage {
    /// Name for logs.
    pub name: &'static str,
    /// The command (usually this executable with a stage subcommand).
    pub command: Command,
}

/// How one stage ended.
#[derive(Debug)]
pub struct StageOutcome {
    /// The stage.
    pub name: &'static str,
    /// Its last process's exit status (None: could not be collected).
    pub status: Option<ExitStatus>,
    /// It ended while the pipeline was being stopped (a signal to the launcher, or another
    /// stage's failure): "stopped by a signal" is then the stop asked for.
    pub stopped_with_pipeline: bool,
    /// Times it was started again after dying.
    pub restarts: u32,
    /// Why it failed the pipeline, if it did.
    pub failure: Option<String>,
}

/// How the pipeline ended.
#[derive(Debug)]
pub struct Outcome {
    /// Per stage, in start order.
    pub stages: Vec<StageOutcome>,
}

impl Outcome {
    /// Whether the run succeeded: no stage failed and every stage ended with exit code 0.
    pub fn success(&self) -> bool {
        self.stages.iter().all(|s| {
            s.failure.is_none()
                && s.status.is_some_and(|st| {
                    st.success()
                        || (s.stopped_with_pipeline
                            && st.code() == Some(i32::from(signals::STOPPED_EXIT_CODE)))
                })
        })
    }
}

/// Whether an exit status means the stage finished its work (0, or 1: finished with bad
/// input counted), as opposed to dying.
fn finished(status: &ExitStatus) -> bool {
    matches!(status.code(), Some(0 | 1))
}

/// An exit status in words ("exited with code 0", "killed by signal 9").
pub fn describe(status: &ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match (status.code(), status.signal()) {
        (_, Some(sig)) => format!("killed by signal {sig}"),
        (Some(c), _) if c == i32::from(signals::STOPPED_EXIT_CODE) => {
            format!("exited with code {c} (stopped by a signal before it finished)")
        }
        (Some(c), _) => format!("exited with code {c}"),
        _ => status.to_string(),
    }
}

struct Running {
    name: &'static str,
    command: Command,
    child: Child,
    restarts: u32,
    status: Option<ExitStatus>,
    failure: Option<String>,
    /// Ended while the pipeline was stopping.
    stopped_with_pipeline: bool,
}

fn terminate(stages: &mut [Running], grace: Duration) {
    for s in stages.iter_mut().filter(|s| s.status.is_none()) {
        s.stopped_with_pipeline = true;
    }
    for s in stages.iter_mut() {
        if s.status.is_none() && matches!(s.child.try_wait(), Ok(None)) {
            info!(stage = s.name, "sending SIGTERM");
            let _ = kill_process(Pid::from_child(&s.child), Signal::TERM);
        }
    }
    let t = Instant::now();
    while t.elapsed() < grace {
        if stages
            .iter_mut()
            .all(|s| s.status.is_some() || !matches!(s.child.try_wait(), Ok(None)))
        {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    for s in stages.iter_mut() {
        if s.status.is_none() && matches!(s.child.try_wait(), Ok(None)) {
            warn!(stage = s.name, "did not stop within {grace:?}: killing");
            s.failure = Some(format!("did not stop within {grace:?}"));
            let _ = s.child.kill();
        }
        if s.status.is_none() {
            s.status = s.child.wait().ok();
        }
    }
}

fn spawn(name: &str, command: &mut Command) -> anyhow::Result<Child> {
    command
        .env(signals::PARENT_ENV, std::process::id().to_string())
        .spawn()
        .map_err(|e| anyhow::anyhow!("cannot start {name}: {e}"))
}

/// Starts `stages` in order (readers first, so the first scans are not lost), then
/// supervises them until the stage named `finisher` finishes, a stage fails (after
/// `max_restarts` restarts), or SIGINT / SIGTERM / SIGHUP arrives; then the others get
/// SIGTERM and a grace period to leave cleanly.
pub fn run(
    cfg: &ServiceConfig,
    stages: Vec<Stage>,
    finisher: &str,
    max_restarts: u32,
) -> anyhow::Result<Outcome> {
    // A node of its own to learn about signals the iceoryx2 way too (and to sweep up
    // after a stage that died).
    let node = transport::node(cfg, "launcher")?;
    signals::install(&node)?;
    let mut running: Vec<Running> = Vec::new();
    for mut s in stages {
        match spawn(s.name, &mut s.command) {
            Ok(child) => {
                info!(stage = s.name, pid = child.id(), "started");
                running.push(Running {
                    name: s.name,
                    command: s.command,
                    child,
                    restarts: 0,
                    status: None,
                    failure: None,
                    stopped_with_pipeline: false,
                });
                // Give each reader time to attach before the next stage starts.
                signals::sleep(Duration::from_millis(300));
            }
            Err(e) => {
                terminate(&mut running, Duration::from_secs(3));
                return Err(e);
            }
        }
    }
    'supervise: loop {
        if !signals::sleep(Duration::from_millis(100)) {
            info!("stop requested: stopping the pipeline");
            break;
        }
        for s in running.iter_mut().filter(|s| s.status.is_none()) {
            let Ok(Some(status)) = s.child.try_wait() else {
                continue;
            };
            // A signal to the whole group (Ctrl-C in a terminal) reaches the stages too,
            // and one may end before the launcher sees the signal: the stop asked for.
            if signals::stop_requested() {
                info!("stop requested: stopping the pipeline");
                break 'supervise;
            }
            if s.name == finisher && finished(&status) {
                if status.code() == Some(1) {
                    warn!(stage = s.name, "finished with bad input (see its log)");
                }
                s.status = Some(status);
                break 'supervise;
            }
            // Any other stage that ends while the pipeline runs leaves it without that
            // stage, even with exit code 0 (someone sent it SIGTERM): a failure, like a
            // death.
            let why = if finished(&status) {
                format!("{} while the pipeline ran", describe(&status))
            } else {
                describe(&status)
            };
            if s.restarts < max_restarts {
                s.restarts += 1;
                warn!(
                    stage = s.name,
                    restart = s.restarts,
                    of = max_restarts,
                    "{why}: restarting"
                );
                transport::cleanup_dead(&node);
                match spawn(s.name, &mut s.command) {
                    Ok(c) => s.child = c,
                    Err(e) => {
                        error!("{e}");
                        s.status = Some(status);
                        s.failure = Some(format!("{why}; restart failed: {e}"));
                        break 'supervise;
                    }
                }
            } else {
                error!(stage = s.name, "{why}: stopping the pipeline");
                s.status = Some(status);
                s.failure = Some(why);
                break 'supervise;
            }
        }
    }
    terminate(&mut running, Duration::from_secs(5));
    Ok(Outcome {
        stages: running
            .into_iter()
            .map(|s| StageOutcome {
                name: s.name,
                status: s.status,
                stopped_with_pipeline: s.stopped_with_pipeline,
                restarts: s.restarts,
                failure: s.failure,
            })
            .collect(),
    })
}
