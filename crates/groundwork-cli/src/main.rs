//! `groundwork`: thin command-line front end over the core, io and eval crates.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use groundwork_core::{Segmenter, SegmenterConfig};
use groundwork_eval::{Protocol, Sequence, evaluate, median};
use groundwork_io::{load_config, parse_config, read_scan, scan_stem, write_outputs};
use groundwork_service::{
    ServiceConfig, check_shared_memory, consumer, launcher, producer, segmenter,
};
use indicatif::{ProgressBar, ProgressStyle};
use tracing::{error, info};

/// The HDL-64E preset, embedded so the binary works from any directory.
const DEFAULT_PRESET: &str = include_str!("../../../config/sensors/hdl64e.toml");
/// The service defaults, likewise.
const DEFAULT_SERVICE: &str = include_str!("../../../config/service.toml");
/// The bundled sample scans (this checkout's copy).
const BUNDLED_DATA: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../tests/data/semantickitti-00"
);

#[derive(Parser, Debug)]
#[command(name = "groundwork", version, about = "GMM LiDAR ground segmentation")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Args, Debug)]
struct Common {
    /// Sensor/segmenter configuration (TOML). Default: the built-in HDL-64E preset
    /// (config/sensors/hdl64e.toml).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Multi-frame history length N_f (1 = single frame); overrides the config.
    #[arg(long)]
    frames: Option<u32>,
    /// KITTI poses.txt (default: <sequence>/poses.txt if present).
    #[arg(long)]
    poses: Option<PathBuf>,
    /// KITTI calib.txt with Tr (default: <sequence>/calib.txt if present).
    #[arg(long)]
    calib: Option<PathBuf>,
}

#[derive(clap::Args, Debug, Clone)]
struct ServiceArgs {
    /// Service configuration (TOML). Default: the built-in config/service.toml.
    #[arg(long)]
    service: Option<PathBuf>,
    /// Service name prefix; overrides the configuration (run pipelines side by side).
    #[arg(long)]
    prefix: Option<String>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run producer, segmenter and consumer as three processes on the bundled scans.
    /// Stops cleanly on Ctrl-C, or after --count scans.
    Pipeline {
        #[command(flatten)]
        common: Common,
        #[command(flatten)]
        service: ServiceArgs,
        /// Scans to replay (looping); default: the bundled KITTI sequence.
        #[arg(long)]
        data: Option<PathBuf>,
        /// Stop after this many scans (default: run until Ctrl-C).
        #[arg(long)]
        count: Option<u64>,
        /// Producer rate, scans per second (0 = as fast as possible).
        #[arg(long)]
        rate: Option<f64>,
        /// Consumer writes .prob/.ground files here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Stage: publish scans from a folder (looping) or synthetic scans.
    Producer {
        #[command(flatten)]
        service: ServiceArgs,
        /// Stop after this many scans.
        #[arg(long)]
        count: Option<u64>,
        /// Scans per second (0 = as fast as possible); overrides the configuration.
        #[arg(long)]
        rate: Option<f64>,
        /// Publish generated scans of this many points instead of files.
        #[arg(long, conflicts_with = "data")]
        synthetic: Option<usize>,
        /// Fault testing: every N-th scan is malformed (NaN, empty, bad schema, bad count).
        #[arg(long)]
        malformed_every: Option<u64>,
        /// Sequence folder to replay; default: the bundled KITTI sequence.
        data: Option<PathBuf>,
    },
    /// Stage: segment scans into masks, keeping the multi-frame history.
    Segmenter {
        #[command(flatten)]
        common: Common,
        #[command(flatten)]
        service: ServiceArgs,
        /// Stop after this many scans.
        #[arg(long)]
        count: Option<u64>,
        /// Transport benchmark: answer with masks of the right size without segmenting.
        #[arg(long)]
        echo: bool,
    },
    /// Stage: read scans and masks, report latency, accuracy and counters.
    Consumer {
        #[command(flatten)]
        service: ServiceArgs,
        /// Stop after this many masks.
        #[arg(long)]
        count: Option<u64>,
        /// Stop when no mask arrived for this many seconds (after the first).
        #[arg(long)]
        idle_timeout: Option<f64>,
        /// Sequence folder with labels/ for live accuracy.
        #[arg(long)]
        labels: Option<PathBuf>,
        /// Write .prob/.ground files here.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Write the final report as JSON here.
        #[arg(long)]
        report_json: Option<PathBuf>,
        /// Fault testing: after this many masks stop reading for --stall-secs.
        #[arg(long)]
        stall_after: Option<u64>,
        /// Seconds to stall.
        #[arg(long, default_value_t = 0.0)]
        stall_secs: f64,
        /// Leave the first N segmented masks out of the latency figures (first touches of
        /// shared memory, cold caches).
        #[arg(long, default_value_t = 0)]
        warmup: u64,
    },
    /// Segment scans: writes <out>/<scan>.prob (f32 per point) and <out>/<scan>.ground (u8).
    Segment {
        #[command(flatten)]
        common: Common,
        /// Output folder (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Scan files, or folders of scans (a sequence folder with velodyne/ works too).
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
    },
    /// Evaluate against SemanticKITTI labels: per scan and pooled metrics, plus speed.
    Eval {
        #[command(flatten)]
        common: Common,
        /// Sequence folder with velodyne/ and labels/ (poses.txt, calib.txt optional).
        sequence: PathBuf,
        /// Label protocol: gmm (vegetation ignored) or terraseg (vegetation is non-ground).
        #[arg(long, value_enum, default_value_t = ProtocolArg::Gmm)]
        protocol: ProtocolArg,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Copy, Clone, Debug, ValueEnum)]
enum ProtocolArg {
    Gmm,
    Terraseg,
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    match run(Cli::parse()) {
        Ok(code) => code,
        Err(e) => {
            error!("{e:#}");
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}

fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Segment {
            common,
            out,
            inputs,
        } => segment(&common, &out, &inputs),
        Command::Eval {
            common,
            sequence,
            protocol,
            json,
        } => eval(&common, &sequence, protocol, json),
        Command::Pipeline {
            common,
            service,
            data,
            count,
            rate,
            out,
        } => pipeline(&common, &service, data, count, rate, out),
        Command::Producer {
            service,
            count,
            rate,
            synthetic,
            malformed_every,
            data,
        } => {
            let cfg = load_service(&service)?;
            let source = match synthetic {
                Some(n) => producer::Source::Synthetic(n),
                None => producer::Source::Sequence(data.unwrap_or_else(|| BUNDLED_DATA.into())),
            };
            producer::run(
                &cfg,
                &producer::ProducerOptions {
                    source,
                    count,
                    rate_hz: rate,
                    malformed_every,
                },
            )?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Segmenter {
            common,
            service,
            count,
            echo,
        } => {
            let cfg = load_service(&service)?;
            segmenter::run(
                &cfg,
                &segmenter::SegmenterOptions {
                    segmenter: load(&common)?,
                    count,
                    echo,
                },
            )?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Consumer {
            service,
            count,
            idle_timeout,
            labels,
            out,
            report_json,
            stall_after,
            stall_secs,
            warmup,
        } => {
            let cfg = load_service(&service)?;
            let secs =
                |s: f64| Duration::try_from_secs_f64(s).context("seconds must be finite and >= 0");
            consumer::run(
                &cfg,
                &consumer::ConsumerOptions {
                    count,
                    idle_timeout: idle_timeout.map(secs).transpose()?,
                    labels,
                    out,
                    report_json,
                    stall_after,
                    stall: secs(stall_secs)?,
                    warmup,
                },
            )?;
            Ok(ExitCode::SUCCESS)
        }
    }
}

fn load_service(args: &ServiceArgs) -> Result<ServiceConfig> {
    let mut cfg = match &args.service {
        Some(p) => ServiceConfig::load(p)?,
        None => toml::from_str(DEFAULT_SERVICE).context("built-in config/service.toml")?,
    };
    if let Some(p) = &args.prefix {
        cfg.prefix = p.clone();
    }
    cfg.validate()?;
    Ok(cfg)
}

fn pipeline(
    common: &Common,
    service: &ServiceArgs,
    data: Option<PathBuf>,
    count: Option<u64>,
    rate: Option<f64>,
    out: Option<PathBuf>,
) -> Result<ExitCode> {
    // Validate everything here, before any process starts.
    let cfg = load_service(service)?;
    load(common)?;
    check_shared_memory(&cfg)?;
    let data = data.unwrap_or_else(|| BUNDLED_DATA.into());
    anyhow::ensure!(data.is_dir(), "{}: no such folder", data.display());
    let exe = std::env::current_exe().context("cannot find this executable")?;
    let stage = |name: &'static str| {
        let mut c = std::process::Command::new(&exe);
        c.arg(name).arg("--prefix").arg(&cfg.prefix);
        if let Some(s) = &service.service {
            c.arg("--service").arg(s);
        }
        c
    };
    let mut seg = stage("segmenter");
    if let Some(c) = &common.config {
        seg.arg("--config").arg(c);
    }
    if let Some(f) = common.frames {
        seg.arg("--frames").arg(f.to_string());
    }
    let mut con = stage("consumer");
    con.arg("--labels").arg(&data);
    if let Some(n) = count {
        con.arg("--count")
            .arg(n.to_string())
            .arg("--idle-timeout")
            .arg("5");
    }
    if let Some(o) = &out {
        con.arg("--out").arg(o);
    }
    let mut prod = stage("producer");
    if let Some(n) = count {
        prod.arg("--count").arg(n.to_string());
    }
    if let Some(r) = rate {
        prod.arg("--rate").arg(r.to_string());
    }
    prod.arg(&data);
    let outcome = launcher::run(
        vec![
            launcher::Stage {
                name: "segmenter",
                command: seg,
            },
            launcher::Stage {
                name: "consumer",
                command: con,
            },
            launcher::Stage {
                name: "producer",
                command: prod,
            },
        ],
        "consumer",
    )?;
    let ok = outcome
        .iter()
        .all(|(_, s)| s.is_some_and(|s| s.success() || s.code().is_none()));
    for (name, s) in &outcome {
        info!(stage = *name, status = ?s, "stage stopped");
    }
    Ok(if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

fn load(common: &Common) -> Result<SegmenterConfig> {
    let mut cfg = match &common.config {
        Some(p) => load_config(p)?,
        None => parse_config(Path::new("<built-in hdl64e preset>"), DEFAULT_PRESET)?,
    };
    if let Some(n) = common.frames {
        cfg.history.frames = n;
        cfg.validate().context("--frames")?;
    }
    Ok(cfg)
}

fn progress(len: usize, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len as u64);
    pb.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} scans, {per_sec}, eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_message(what.to_string());
    pb
}

fn segment(common: &Common, out: &Path, inputs: &[PathBuf]) -> Result<ExitCode> {
    let cfg = load(common)?;
    let thr = cfg.ground.ground_threshold;
    let max = cfg.sensor.max_points;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;

    // Each input is a scan file or a folder; a folder may carry poses for history.
    let mut jobs: Vec<(PathBuf, Option<groundwork_core::Pose>)> = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let seq = Sequence::open(input, common.poses.as_deref(), common.calib.as_deref())?;
            let poses = seq.poses.clone();
            for (i, s) in seq.scans.into_iter().enumerate() {
                jobs.push((s, poses.as_ref().and_then(|p| p.get(i).copied())));
            }
        } else if input.is_file() {
            jobs.push((input.clone(), None));
        } else {
            bail!("{}: no such file or folder", input.display());
        }
    }
    if cfg.history.frames > 1 && jobs.iter().all(|j| j.1.is_none()) {
        info!("no poses found: scans are segmented single-frame");
    }
    let mut seg = Segmenter::new(cfg)?;
    let pb = progress(jobs.len(), "segment");
    let (mut failed, mut times) = (0usize, Vec::with_capacity(jobs.len()));
    let mut probs = Vec::new();
    for (path, pose) in &jobs {
        let result = (|| -> Result<()> {
            let points = read_scan(path, max)?;
            probs.resize(points.len(), 0.0);
            let t = Instant::now();
            seg.segment(&points, pose.as_ref(), &mut probs)
                .with_context(|| path.display().to_string())?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
            write_outputs(out, &scan_stem(path), &probs, thr)?;
            Ok(())
        })();
        if let Err(e) = result {
            // One bad scan never costs the others.
            failed += 1;
            pb.suspend(|| error!("skipped: {e:#}"));
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    seg.log_state();
    info!(
        scans = jobs.len(),
        failed,
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

fn eval(common: &Common, dir: &Path, protocol: ProtocolArg, json: bool) -> Result<ExitCode> {
    let cfg = load(common)?;
    let seq = Sequence::open(dir, common.poses.as_deref(), common.calib.as_deref())?;
    if cfg.history.frames > 1 && seq.poses.is_none() {
        info!("no poses.txt + calib.txt: multi-frame history is not used");
    }
    let mut seg = Segmenter::new(cfg)?;
    let protocol = match protocol {
        ProtocolArg::Gmm => Protocol::Gmm,
        ProtocolArg::Terraseg => Protocol::Terraseg,
    };
    let pb = progress(seq.scans.len(), "eval");
    let report = evaluate(&seq, &mut seg, protocol, |_| pb.inc(1))?;
    pb.finish_and_clear();
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", report.to_table());
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_service_config_is_valid() {
        let c: ServiceConfig = toml::from_str(DEFAULT_SERVICE).unwrap();
        c.validate().unwrap();
        assert_eq!(c, ServiceConfig::default());
    }

    #[test]
    fn embedded_preset_is_valid() {
        let c = parse_config(Path::new("preset"), DEFAULT_PRESET).unwrap();
        assert_eq!(c.sensor.name, "hdl64e");
        assert!((c.sensor.mount.height - 1.73).abs() < 1e-12);
    }

    #[test]
    fn cli_parses() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
    }
}
