//! `groundwork segment`: scans through a method into `.prob`/`.ground` files or a recording.
//!
//! Three kinds of thread share the work so that the cores segment while files move: one
//! reads the next scans ahead, the segmenting workers compute (each scan itself on the
//! rayon pool), and the calling thread writes what they finish. The GMM runs as one worker
//! in input order, as the service's segmenter stage (same checks, same counters): its
//! zone-1 height filter carries from scan to scan even without history, so splitting a
//! sequence across workers would make the output depend on the number of cores. The
//! per-scan methods (PseudoLabeler, RANSAC) keep no state between scans and run one worker
//! per core, scans finishing in any order (a recording is written in input order, so there
//! they run as one worker too).

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{Result, anyhow, bail};
use groundwork_core::{GroundMethod, Pose};
use groundwork_eval::median;
use groundwork_io::Sequence;
use groundwork_io::{OutputTarget, ScanItem, write_outputs};
use groundwork_service::segmenter::{SegmenterOptions, SegmenterStage};
use indicatif::ProgressBar;
use tracing::{error, info, warn};

use crate::args::Common;
use crate::common::{load_methods, offline_header, open_inputs, progress};
use crate::methods::{self, MethodArg};

/// One scan to segment: which input it belongs to, its place among all scans, its pose.
struct Job {
    input: usize,
    k: usize,
    pose: Option<Pose>,
    item: ScanItem,
}

/// A segmented scan on its way to the writer.
struct Segmented {
    input: usize,
    k: usize,
    item: ScanItem,
    probs: Vec<f32>,
}

/// What one worker segments with.
enum Engine {
    /// The service's segmenter stage (GMM, history, height filter).
    Gmm(Box<SegmenterStage>),
    /// A per-scan method.
    Method(Box<dyn GroundMethod>),
}

/// One worker's tally.
#[derive(Default)]
struct Tally {
    failed: usize,
    sequence_resets: u64,
    times_ms: Vec<f64>,
}

impl Engine {
    /// Segments one scan into `probs`; points beyond the coordinate bound are returned.
    fn segment(&mut self, job: &Job, probs: &mut Vec<f32>) -> Result<usize> {
        let item = &job.item;
        let scan = item.scan.as_ref().map_err(|e| anyhow!("{e}"))?;
        match self {
            Self::Method(m) => {
                probs.resize(scan.points.len(), 0.0);
                m.segment_scan(&scan.points, job.pose.as_ref(), probs)
                    .map_err(|e| anyhow!("{}: {e}", item.name))?;
                Ok(0)
            }
            Self::Gmm(stage) => {
                let header = offline_header(job.pose.as_ref(), job.input, job.k, scan.points.len());
                probs.resize(stage.mask_len(&header, &scan.points), 0.0);
                let mask = stage.segment(&header, &scan.points, 0, probs);
                if let Some(reason) = stage.last_rejection() {
                    bail!("{}: {reason}", item.name);
                }
                Ok(mask.out_of_bounds_points as usize)
            }
        }
    }

    /// Takes jobs until the reader is done, passing each segmented scan to the writer.
    fn work(
        &mut self,
        jobs: &Mutex<Receiver<Job>>,
        done: &SyncSender<Segmented>,
        pb: &ProgressBar,
    ) -> Tally {
        let mut tally = Tally::default();
        let mut last_input = None;
        loop {
            // The lock is held only to take the next job, never while segmenting.
            let next = jobs
                .lock()
                .map_err(|_| ())
                .and_then(|r| r.recv().map_err(|_| ()));
            let Ok(job) = next else { break };
            if let Self::Gmm(stage) = self {
                // Every input is a sequence of its own: the history of the previous one
                // describes another place (and KITTI sequences all start at the identity
                // pose).
                if last_input.is_some_and(|i| i != job.input) && stage.new_sequence() {
                    tally.sequence_resets += 1;
                }
            }
            last_input = Some(job.input);
            let t = Instant::now();
            let mut probs = Vec::new();
            match self.segment(&job, &mut probs) {
                Ok(out_of_bounds) => {
                    tally.times_ms.push(t.elapsed().as_secs_f64() * 1e3);
                    if out_of_bounds > 0 {
                        pb.suspend(|| {
                            warn!(
                                points = out_of_bounds,
                                "{}: points beyond the coordinate bound (probability 0)",
                                job.item.name
                            )
                        });
                    }
                    let segmented = Segmented {
                        input: job.input,
                        k: job.k,
                        item: job.item,
                        probs,
                    };
                    if done.send(segmented).is_err() {
                        break;
                    }
                }
                Err(e) => {
                    // One bad scan never costs the others.
                    tally.failed += 1;
                    pb.suspend(|| error!("skipped: {e:#}"));
                    pb.inc(1);
                }
            }
        }
        tally
    }
}

/// Reads every scan of every input in order and hands them out; stops early if the
/// workers are gone.
fn read_all(sequences: &[Sequence], max_points: usize, jobs: &SyncSender<Job>, pb: &ProgressBar) {
    let known = sequences.iter().all(|s| s.len_hint().is_some());
    let mut k = 0;
    for (input, seq) in sequences.iter().enumerate() {
        for item in seq.scans(max_points) {
            if !known {
                pb.inc_length(1);
            }
            let pose = seq.pose(item.index).copied();
            if jobs
                .send(Job {
                    input,
                    k,
                    pose,
                    item,
                })
                .is_err()
            {
                return;
            }
            k += 1;
        }
    }
}

/// Copies every message of the recording inputs on topics other than their scans' into the
/// output recording, unchanged (a `/chatter`, the vehicle's `/tf`, camera images): a
/// recording written from a recording loses nothing. Says what it passed, and what it could
/// not (a message past a broken part of the input is named in a warning).
fn pass_through(
    w: &mut groundwork_io::RecordingWriter,
    sequences: &[Sequence],
    scan_topics: &std::collections::BTreeMap<usize, String>,
    max_points: usize,
) {
    for (input, topic) in scan_topics {
        let Some(groundwork_io::ScanSource::Recording { path, .. }) =
            sequences.get(*input).map(|s| &s.source)
        else {
            continue;
        };
        let (mut passed, mut topics) = (0usize, std::collections::BTreeSet::new());
        let result =
            groundwork_io::RecordingReader::others(path, topic, max_points).and_then(|it| {
                for m in it {
                    let m = m?;
                    w.write_other(&m)?;
                    passed += 1;
                    topics.insert(m.topic);
                }
                Ok(())
            });
        if let Err(e) = result {
            warn!("{e}: other topics passed through up to here ({passed} messages)");
        }
        if passed > 0 {
            let topics: Vec<String> = topics.into_iter().collect();
            info!(
                from = %path.display(),
                messages = passed,
                topics = %topics.join(", "),
                "other topics passed through"
            );
        }
    }
}

/// Writes one segmented scan: one value per record of the input (placeholders get 0).
fn write_one(output: &mut OutputTarget, s: &Segmented, threshold: f32) -> Result<usize> {
    let scan = s.item.scan.as_ref().map_err(|e| anyhow!("{e}"))?;
    match output {
        OutputTarget::Files(dir) => {
            write_outputs(dir, &s.item.name, &scan.expand(&s.probs, 0.0), threshold)?
        }
        OutputTarget::Recording(w) => {
            let topic = s.item.topic.as_deref().unwrap_or("/points");
            // Scans without a time (no recording, no times.txt): 10 Hz from 0, in
            // processing order (the documentation says so).
            let t = s.item.log_time_ns.unwrap_or(s.k as u64 * 100_000_000);
            match &s.item.message {
                // From a recording: its cloud as it was, every field kept.
                Some(m) => w.write_over(topic, Path::new(&s.item.name), m, scan, &s.probs, t)?,
                None => w.write(topic, scan, &s.probs, t)?,
            }
        }
    }
    Ok(scan.skipped())
}

pub fn run(common: &Common, method: MethodArg, out: &Path, inputs: &[PathBuf]) -> Result<ExitCode> {
    let methods_cfg = load_methods(common, None)?;
    let cfg = methods_cfg.segmenter.clone();
    let max = cfg.sensor.max_points;
    let (sequences, skipped_inputs) = open_inputs(
        inputs,
        common.poses.as_deref(),
        common.calib.as_deref(),
        common.topic.as_deref(),
    )?;
    let mut output = crate::common::create_output(out, inputs, &sequences, &[".prob", ".ground"])?;
    crate::common::place_scans_by_mount(&mut output, &cfg.sensor.mount)?;
    let (mut engines, threshold) = match method {
        MethodArg::Gmm => {
            if cfg.history.frames > 1 && sequences.iter().all(|s| s.poses.is_none()) {
                info!("no poses found: scans are segmented single-frame");
            }
            let threshold = cfg.decision_threshold();
            let opts = SegmenterOptions {
                segmenter: cfg,
                count: None,
                echo: false,
            };
            (
                vec![Engine::Gmm(Box::new(SegmenterStage::new(&opts, max)?))],
                threshold,
            )
        }
        m => {
            let in_order = matches!(output, OutputTarget::Recording(_));
            let workers = if in_order {
                1
            } else {
                rayon::current_num_threads()
            };
            let engines = (0..workers)
                .map(|_| methods::build(m, &methods_cfg).map(Engine::Method))
                .collect::<Result<Vec<_>>>()?;
            let threshold = match &engines[..] {
                [Engine::Method(m), ..] => m.threshold(),
                _ => cfg.decision_threshold(),
            };
            (engines, threshold)
        }
    };
    let known: Option<usize> = sequences.iter().map(Sequence::len_hint).sum();
    let pb = progress(known.unwrap_or(0), "segment");
    // Two scans read ahead per worker at most, two segmented ones waiting for the writer:
    // enough to keep every thread busy, little memory.
    let (job_tx, job_rx) = sync_channel::<Job>(2 * engines.len());
    let (done_tx, done_rx) = sync_channel::<Segmented>(2);
    let jobs = Arc::new(Mutex::new(job_rx));
    let (mut scans, mut failed_writes, mut placeholders) = (0usize, 0usize, 0usize);
    // The topic each recording input's scans came from: its other topics pass through.
    let mut scan_topics: std::collections::BTreeMap<usize, String> = Default::default();
    let tallies = std::thread::scope(|s| {
        // The reader owns the jobs' sender: when it is done, the workers' channel closes.
        let (seqs, reader_pb) = (&sequences, pb.clone());
        let reader = s.spawn(move || read_all(seqs, max, &job_tx, &reader_pb));
        let workers: Vec<_> = engines
            .iter_mut()
            .map(|engine| {
                let (jobs, done, pb) = (Arc::clone(&jobs), done_tx.clone(), pb.clone());
                s.spawn(move || engine.work(&jobs, &done, &pb))
            })
            .collect();
        // The writer's channel closes when the last worker drops its sender.
        drop(done_tx);
        for segmented in done_rx {
            scans += 1;
            if let Some(t) = &segmented.item.topic {
                scan_topics
                    .entry(segmented.input)
                    .or_insert_with(|| t.clone());
            }
            match write_one(&mut output, &segmented, threshold) {
                Ok(p) => placeholders += p,
                Err(e) => {
                    failed_writes += 1;
                    pb.suspend(|| error!("skipped: {e:#}"));
                }
            }
            pb.inc(1);
        }
        let tallies: Vec<Tally> = workers
            .into_iter()
            .map(|w| {
                w.join()
                    .map_err(|_| anyhow!("a segmenting thread panicked"))
            })
            .collect::<Result<_>>()?;
        reader
            .join()
            .map_err(|_| anyhow!("the reading thread panicked"))?;
        Ok::<_, anyhow::Error>(tallies)
    })?;
    pb.finish_and_clear();
    if let OutputTarget::Recording(w) = &mut output {
        pass_through(w, &sequences, &scan_topics, max);
    }
    if let OutputTarget::Recording(w) = output
        && !w.finish_unless_empty()?
    {
        // Nothing segmented: an earlier recording at --out is worth more than an empty one.
        error!(
            "{}: no scan could be segmented, so no recording was written (a file there is \
             left as it was)",
            out.display()
        );
    }
    let failed = skipped_inputs + failed_writes + tallies.iter().map(|t| t.failed).sum::<usize>();
    scans += tallies.iter().map(|t| t.failed).sum::<usize>();
    let times: Vec<f64> = tallies
        .iter()
        .flat_map(|t| t.times_ms.iter().copied())
        .collect();
    let (mut history_resets, mut out_of_bounds_points) = (0, 0);
    for engine in &engines {
        if let Engine::Gmm(stage) = engine {
            stage.segmenter().log_state();
            let c = stage.segmenter().counters();
            history_resets += c.history_resets;
            out_of_bounds_points += c.out_of_bounds_points;
        }
    }
    info!(
        method = method.name(),
        scans,
        failed,
        sequence_resets = tallies.iter().map(|t| t.sequence_resets).sum::<u64>(),
        placeholders,
        history_resets,
        out_of_bounds_points,
        workers = engines.len(),
        median_ms = median(times),
        out = %out.display(),
        "segmentation done"
    );
    Ok(if failed > 0 {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}
/// `groundwork segment`.
pub fn command(a: crate::args::SegmentArgs) -> Result<ExitCode> {
    run(&a.common, a.method, &a.out, &a.inputs)
}
