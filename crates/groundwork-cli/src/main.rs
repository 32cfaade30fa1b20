//! `groundwork`: thin command-line front end over the core, io and eval crates.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use groundwork_core::SegmenterConfig;
use groundwork_eval::{Protocol, Sequence, evaluate};
use groundwork_io::{SENSOR_PRESETS, load_config_over, sensor_preset};
use groundwork_service::{
    ServiceConfig, check_shared_memory, consumer, launcher, producer, segmenter,
};
use indicatif::{ProgressBar, ProgressStyle};
use tracing::{error, info};

mod detect;
mod label;
mod methods;
mod render;
mod segment;
use methods::MethodArg;

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
    /// Sensor preset (`groundwork sensors` lists them). Default: the service
    /// configuration's `sensor`, else hdl64e.
    #[arg(long)]
    sensor: Option<String>,
    /// Configuration file (TOML) laid over the sensor preset: every field it gives
    /// replaces the preset's.
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
    /// PointCloud2 topic of MCAP recordings (default: the first point cloud topic).
    #[arg(long)]
    topic: Option<String>,
}

/// The sensor and configuration alone, for commands that take one scan or scans one at a
/// time (no history, no poses, no recordings).
#[derive(clap::Args, Debug)]
struct SensorArgs {
    /// Sensor preset (`groundwork sensors` lists them). Default: hdl64e.
    #[arg(long)]
    sensor: Option<String>,
    /// Configuration file (TOML) laid over the sensor preset: every field it gives
    /// replaces the preset's.
    #[arg(long)]
    config: Option<PathBuf>,
}

impl From<SensorArgs> for Common {
    fn from(s: SensorArgs) -> Self {
        Self {
            sensor: s.sensor,
            config: s.config,
            frames: None,
            poses: None,
            calib: None,
            topic: None,
        }
    }
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
    /// Run producer, segmenter, detector and consumer as four processes (three with
    /// --no-detector) on the bundled scans or --data.
    /// Stops cleanly on Ctrl-C, or after --count scans.
    Pipeline {
        #[command(flatten)]
        common: Common,
        #[command(flatten)]
        service: ServiceArgs,
        /// Scans to replay (looping): a folder of scans or an MCAP recording; default: the
        /// bundled KITTI sequence.
        #[arg(long)]
        data: Option<PathBuf>,
        /// Stop after this many scans (default: run until Ctrl-C).
        #[arg(long)]
        count: Option<u64>,
        /// Producer rate, scans per second (0 = as fast as possible).
        #[arg(long)]
        rate: Option<f64>,
        /// Consumer writes .prob/.ground files into this folder, or one recording
        /// (PointCloud2 with ground_probability) to a path ending in .mcap.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Start a stage that dies (killed, crashed) again, up to this many times per
        /// stage; each restart is logged and counted. Default 0: a dead stage stops the
        /// pipeline, which then exits non-zero.
        #[arg(long, default_value_t = 0)]
        restart: u32,
        /// Leave out the detector stage (object proposals on <prefix>/proposals).
        #[arg(long)]
        no_detector: bool,
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
        /// After --count scans, stay this many seconds (`inf`: until stopped) so that
        /// subscribers can still read the last ones (a leaving publisher takes its queued
        /// scans with it).
        #[arg(long, default_value_t = 0.0)]
        linger: f64,
        /// PointCloud2 topic of a recording (default: its first point cloud topic).
        #[arg(long)]
        topic: Option<String>,
        /// Folder of scans or MCAP recording to replay (a recording at its recorded rate
        /// unless --rate is given); default: the bundled KITTI sequence.
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
    /// Stage: turn scans and masks into object proposals on <prefix>/proposals.
    Detector {
        #[command(flatten)]
        common: Common,
        #[command(flatten)]
        service: ServiceArgs,
        /// Stop after this many masks.
        #[arg(long)]
        count: Option<u64>,
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
        /// Write .prob/.ground files into this folder, or one recording (PointCloud2 with
        /// ground_probability, topic /points) to a path ending in .mcap.
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
    /// List the sensor presets (`--sensor NAME`): mount, ranges, limits.
    Sensors,
    /// Generate a labeled synthetic sequence in the KITTI layout (velodyne/*.bin,
    /// labels/*.label with class and instance ids, poses.txt, calib.txt), which segment
    /// and eval read like the bundled one.
    Synth {
        /// Sensor preset whose beam pattern and mount the scans are taken with.
        #[arg(long, default_value = "hdl64e")]
        sensor: String,
        /// Configuration laid over the preset: its sensor.mount is the mount the scans are
        /// taken with (a tilted or low sensor).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Scene: urban, offroad or parking.
        #[arg(long, default_value = "urban")]
        scene: String,
        /// Frames to generate.
        #[arg(long, default_value_t = 10)]
        frames: usize,
        /// Seed of the layout and the sensor noise.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Output folder (created if missing).
        #[arg(long)]
        out: PathBuf,
    },
    /// Print the shared memory (MiB) one pipeline with this service configuration may need
    /// at worst: the `/dev/shm` size a container must get (`docker run --shm-size`).
    ShmSize {
        #[command(flatten)]
        service: ServiceArgs,
    },
    /// Segment scans: writes <out>/<scan>.prob (f32 per point) and <out>/<scan>.ground (u8).
    Segment {
        #[command(flatten)]
        common: Common,
        /// Method: gmm (online, history), pseudolabeler (offline, slow, accurate) or ransac.
        #[arg(long, value_enum, default_value_t = MethodArg::Gmm)]
        method: MethodArg,
        /// Output folder (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Scan files, or folders of scans (a sequence folder with velodyne/ works too).
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
    },
    /// Object proposals (the fallback detector): segments each scan, removes the ground,
    /// clusters the rest. Writes <out>/<scan>.proposals.json and <out>/<scan>.clusters (u32
    /// proposal id per point, 0 = none); with instance labels beside the scans, reports the
    /// labeled objects found.
    Detect {
        #[command(flatten)]
        common: Common,
        /// Ground segmentation method.
        #[arg(long, value_enum, default_value_t = MethodArg::Gmm)]
        method: MethodArg,
        /// Output folder (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Scan files, or folders of scans (a sequence folder with velodyne/ works too).
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
    },
    /// A bird's-eye PNG of one scan: ground by height or probability (or errors against
    /// labels with --compare), non-ground grey, proposals as boxes with ids, scale bar,
    /// sensor.
    Render {
        #[command(flatten)]
        sensor: SensorArgs,
        /// The scan.
        scan: PathBuf,
        /// Its .prob file (default: segment it with --method).
        #[arg(long)]
        mask: Option<PathBuf>,
        /// Method when no mask is given.
        #[arg(long, value_enum, default_value_t = MethodArg::Gmm)]
        method: MethodArg,
        /// Its .proposals.json, drawn as boxes.
        #[arg(long, conflicts_with = "detect")]
        proposals: Option<PathBuf>,
        /// Run the detector and draw its proposals.
        #[arg(long)]
        detect: bool,
        /// Colour true/false ground and missed ground against labels (gmm protocol).
        #[arg(long)]
        compare: bool,
        /// Label file for --compare (default: labels/<stem>.label beside velodyne/).
        #[arg(long)]
        labels: Option<PathBuf>,
        /// Ground colouring.
        #[arg(long, value_enum, default_value_t = render::ColourArg::Height)]
        colour: render::ColourArg,
        /// Half the picture's side, metres.
        #[arg(long, default_value_t = 40.0)]
        range: f32,
        /// Metres per pixel.
        #[arg(long, default_value_t = 0.08)]
        resolution: f32,
        /// The PNG to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Evaluate against SemanticKITTI labels: per scan and pooled metrics, plus speed.
    Eval {
        #[command(flatten)]
        common: Common,
        /// Methods to score on the same scans (comma-separated or repeated): gmm,
        /// pseudolabeler, ransac; several are printed side by side.
        #[arg(long, value_enum, value_delimiter = ',', default_value = "gmm")]
        method: Vec<MethodArg>,
        /// Sequence folder with velodyne/ and labels/ (poses.txt, calib.txt optional), a
        /// folder of scans, or an MCAP recording.
        sequence: PathBuf,
        /// Folder of .label files (default: <sequence>/labels). For a recording, the
        /// index-th message's labels are <index:06>.label.
        #[arg(long)]
        labels: Option<PathBuf>,
        /// Label layout and ground classes: semantickitti, nuscenes, rellis (built-in maps,
        /// config/labels/) or the path of a map file for another dataset.
        #[arg(long, default_value = "semantickitti")]
        labels_format: String,
        /// Label protocol: gmm (vegetation ignored) or terraseg (vegetation is non-ground).
        #[arg(long, value_enum, default_value_t = ProtocolArg::Gmm)]
        protocol: ProtocolArg,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Label a whole dataset offline (PseudoLabeler by default): <out>/<scan>.prob and
    /// .ground per scan, in parallel across scans, resumable, shardable across machines
    /// (`--shard i/n`), with a summary JSON.
    Label {
        #[command(flatten)]
        sensor: SensorArgs,
        /// Per-scan method (the GMM keeps a history over scans in order: use `segment`).
        #[arg(long, value_enum, default_value_t = label::LabelMethod::Pseudolabeler)]
        method: label::LabelMethod,
        /// Output folder (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Label only shard i of n (0-based): scans whose place in the sorted list is i
        /// modulo n. Every scan is in exactly one shard.
        #[arg(long, value_parser = label::parse_shard)]
        shard: Option<label::Shard>,
        /// Label again even scans whose outputs are complete.
        #[arg(long)]
        overwrite: bool,
        /// Scan files or folders of scans (a sequence folder with velodyne/ works too).
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
    },
}

#[derive(Copy, Clone, Debug, ValueEnum)]
enum ProtocolArg {
    Gmm,
    Terraseg,
}

/// Exit codes: 0 done; 1 done, but some input was bad (reported and counted); 2 error;
/// 3 this CPU cannot run this build.
fn main() -> ExitCode {
    // First of all: on a CPU below the build's target (x86-64-v3) the first vector
    // instruction would kill the process with SIGILL and no word of why.
    if let Err(e) = groundwork_core::cpu::check() {
        eprintln!("error: {e}");
        return ExitCode::from(3);
    }
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
            // Once, on stderr (a log line as well would print it twice).
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}

fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Segment {
            common,
            method,
            out,
            inputs,
        } => segment::run(&common, method, &out, &inputs),
        Command::Detect {
            common,
            method,
            out,
            inputs,
        } => detect::run(&detect::DetectJob {
            config: &load_methods(&common, None)?,
            method,
            out: &out,
            inputs: &inputs,
            poses: common.poses.as_deref(),
            calib: common.calib.as_deref(),
            topic: common.topic.clone(),
        }),
        Command::Render {
            sensor,
            scan,
            mask,
            method,
            proposals,
            detect,
            compare,
            labels,
            colour,
            range,
            resolution,
            out,
        } => {
            render::run(&render::RenderJob {
                config: &load_methods(&sensor.into(), None)?,
                scan: &scan,
                mask: mask.as_deref(),
                method,
                proposals: proposals.as_deref(),
                detect,
                compare,
                labels: labels.as_deref(),
                colour,
                view: groundwork_viz::View { range, resolution },
                out: &out,
            })?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Label {
            sensor,
            method,
            out,
            shard,
            overwrite,
            inputs,
        } => label::run(
            &load_methods(&sensor.into(), None)?,
            method,
            &out,
            shard.unwrap_or_default(),
            overwrite,
            &inputs,
        ),
        Command::Eval {
            common,
            method,
            sequence,
            labels,
            labels_format,
            protocol,
            json,
        } => eval(
            &common,
            &method,
            &sequence,
            labels.as_deref(),
            &labels_format,
            protocol,
            json,
        ),
        Command::Pipeline {
            common,
            service,
            data,
            count,
            rate,
            out,
            restart,
            no_detector,
        } => pipeline(
            &common,
            &service,
            &PipelineRun {
                data,
                count,
                rate,
                out,
                restart,
                detector: !no_detector,
            },
        ),
        Command::Producer {
            service,
            count,
            rate,
            synthetic,
            malformed_every,
            linger,
            topic,
            data,
        } => {
            let cfg = load_service(&service)?;
            anyhow::ensure!(
                linger >= 0.0,
                "--linger {linger}: must be ≥ 0 seconds or inf"
            );
            let linger = Duration::try_from_secs_f64(linger).unwrap_or(Duration::MAX);
            let source = match synthetic {
                Some(n) => producer::Source::Synthetic(n),
                None => {
                    producer::Source::from_path(data.unwrap_or_else(|| BUNDLED_DATA.into()), topic)
                }
            };
            let r = producer::run(
                &cfg,
                &producer::ProducerOptions {
                    source,
                    count,
                    rate_hz: rate,
                    malformed_every,
                    linger,
                },
            )?;
            // Report, count, go on, and say so at the end.
            Ok(if r.skipped_files.is_empty() {
                ExitCode::SUCCESS
            } else {
                ExitCode::from(1)
            })
        }
        Command::Sensors => {
            print!("{}", sensors_table()?);
            Ok(ExitCode::SUCCESS)
        }
        Command::Synth {
            sensor,
            config,
            scene,
            frames,
            seed,
            out,
        } => {
            synth(&sensor, config.as_deref(), &scene, frames, seed, &out)?;
            Ok(ExitCode::SUCCESS)
        }
        Command::ShmSize { service } => {
            let cfg = load_service(&service)?;
            // Round up, and leave room for iceoryx2's management segments.
            println!("{}m", (cfg.shared_memory_estimate() >> 20) + 1 + 16);
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
                    segmenter: load(&common, cfg.sensor.as_deref())?,
                    count,
                    echo,
                },
            )?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Detector {
            common,
            service,
            count,
        } => {
            let cfg = load_service(&service)?;
            let methods = load_methods(&common, cfg.sensor.as_deref())?;
            groundwork_service::detector::run(
                &cfg,
                &groundwork_service::detector::DetectorOptions {
                    segmenter: methods.segmenter,
                    detector: methods.detector,
                    count,
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
            let report = consumer::run(
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
            // Asked to write and could not: the run did not do what it was asked.
            Ok(if report.write_failures > 0 {
                ExitCode::from(1)
            } else {
                ExitCode::SUCCESS
            })
        }
    }
}

/// The presets as a table a person reads at a glance.
fn sensors_table() -> Result<String> {
    use std::fmt::Write;
    let mut s = format!(
        "{:<10} {:>7} {:>7} {:>7} {:>7} {:>6} {:>10} {:>9}  {}\n",
        "sensor", "height", "roll°", "pitch°", "yaw°", "ego m", "range m", "max pts", "about"
    );
    for (name, text) in SENSOR_PRESETS {
        let c = sensor_preset(name)?;
        let m = &c.sensor.mount;
        // The preset's first comment line says what the sensor is.
        let about = text
            .lines()
            .next()
            .and_then(|l| l.strip_prefix("# "))
            .unwrap_or("")
            .split(':')
            .next()
            .unwrap_or("");
        let _ = writeln!(
            s,
            "{:<10} {:>7.2} {:>7.1} {:>7.1} {:>7.1} {:>6.1} {:>10} {:>9}  {}",
            name,
            m.height,
            m.roll.to_degrees(),
            m.pitch.to_degrees(),
            m.yaw.to_degrees(),
            c.sensor.ego_radius,
            format!("{}–{}", c.zones.min_range, c.zones.max_range),
            c.sensor.max_points,
            about
        );
    }
    Ok(s)
}

/// Writes a synthetic sequence in the KITTI layout.
fn synth(
    sensor: &str,
    config: Option<&Path>,
    scene: &str,
    frames: usize,
    seed: u64,
    out: &Path,
) -> Result<()> {
    use groundwork_synth::{Generator, SceneKind, SynthConfig};
    let kind = SceneKind::from_name(scene).with_context(|| {
        let known: Vec<_> = SceneKind::ALL.iter().map(|k| k.name()).collect();
        format!("unknown scene {scene:?} (known: {})", known.join(", "))
    })?;
    let cfg = load_config_over(Some(sensor), config)?;
    let generator = Generator::new(
        SynthConfig::new(sensor, cfg.sensor.mount, kind, seed)?,
        frames,
    )?;
    let (velodyne, labels) = (out.join("velodyne"), out.join("labels"));
    for dir in [&velodyne, &labels] {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    info!(sensor, scene, frames, seed, out = %out.display(), "generating a synthetic sequence");
    let pb = progress(frames, "synth");
    let mut poses = Vec::with_capacity(frames);
    let mut points = 0;
    for i in 0..frames {
        let scan = generator.scan(i);
        let stem = format!("{i:06}");
        groundwork_io::write_kitti_bin(&velodyne.join(format!("{stem}.bin")), &scan.points)?;
        groundwork_io::write_labels(&labels.join(format!("{stem}.label")), &scan.labels)?;
        poses.push(scan.pose_matrix());
        points += scan.points.len();
        pb.inc(1);
    }
    pb.finish_and_clear();
    groundwork_io::write_poses(&out.join("poses.txt"), &poses)?;
    // The poses are the LiDAR's own: Tr is the identity.
    let identity = std::array::from_fn(|r| std::array::from_fn(|c| f64::from(u8::from(r == c))));
    groundwork_io::write_calib_tr(&out.join("calib.txt"), &identity)?;
    info!(frames, points, "synthetic sequence written");
    Ok(())
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

/// What `pipeline` runs, beyond the common and service options.
#[derive(Debug)]
struct PipelineRun {
    data: Option<PathBuf>,
    count: Option<u64>,
    rate: Option<f64>,
    out: Option<PathBuf>,
    restart: u32,
    /// Start the detector stage too.
    detector: bool,
}

fn pipeline(common: &Common, service: &ServiceArgs, run: &PipelineRun) -> Result<ExitCode> {
    let PipelineRun {
        data,
        count,
        rate,
        out,
        restart,
        detector,
    } = run;
    let (count, rate, restart) = (*count, *rate, *restart);
    // Validate everything here, before any process starts.
    let cfg = load_service(service)?;
    let seg_cfg = load(common, cfg.sensor.as_deref())?;
    anyhow::ensure!(
        seg_cfg.sensor.max_points <= cfg.max_points,
        "sensor {} takes scans of up to {} points, but the service's shared memory is sized for {} (raise max_points in the service configuration)",
        seg_cfg.sensor.name,
        seg_cfg.sensor.max_points,
        cfg.max_points
    );
    check_shared_memory(&cfg)?;
    if let Some(r) = rate {
        groundwork_service::config::check_rate("--rate", r)?;
    }
    let data = data.clone().unwrap_or_else(|| BUNDLED_DATA.into());
    anyhow::ensure!(
        data.exists(),
        "{}: no such folder or recording",
        data.display()
    );
    if let Some(o) = &out {
        groundwork_io::check_not_an_input(o, std::slice::from_ref(&data))?;
    }
    let exe = std::env::current_exe().context("cannot find this executable")?;
    let stage = |name: &'static str| {
        let mut c = std::process::Command::new(&exe);
        c.arg(name).arg("--prefix").arg(&cfg.prefix);
        if let Some(s) = &service.service {
            c.arg("--service").arg(s);
        }
        c
    };
    // The segmenter and the detector read the same sensor and configuration.
    let configured = |name: &'static str| {
        let mut c = stage(name);
        if let Some(s) = &common.sensor {
            c.arg("--sensor").arg(s);
        }
        if let Some(f) = &common.config {
            c.arg("--config").arg(f);
        }
        c
    };
    let mut seg = configured("segmenter");
    if let Some(f) = common.frames {
        seg.arg("--frames").arg(f.to_string());
    }
    let mut con = stage("consumer");
    if data.is_dir() {
        con.arg("--labels").arg(&data);
    }
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
        // The producer stays until the pipeline stops: the consumer reads the last scans
        // (and counts them) after the producer has published them all.
        prod.arg("--count")
            .arg(n.to_string())
            .arg("--linger")
            .arg("inf");
    }
    if let Some(r) = rate {
        prod.arg("--rate").arg(r.to_string());
    }
    if let Some(t) = &common.topic {
        prod.arg("--topic").arg(t);
    }
    prod.arg(&data);
    let mut stages = vec![launcher::Stage {
        name: "segmenter",
        command: seg,
    }];
    if *detector {
        stages.push(launcher::Stage {
            name: "detector",
            command: configured("detector"),
        });
    }
    stages.push(launcher::Stage {
        name: "consumer",
        command: con,
    });
    stages.push(launcher::Stage {
        name: "producer",
        command: prod,
    });
    let outcome = launcher::run(&cfg, stages, "consumer", restart)?;
    for s in &outcome.stages {
        match &s.failure {
            Some(f) => error!(stage = s.name, restarts = s.restarts, "failed: {f}"),
            None => info!(
                stage = s.name,
                restarts = s.restarts,
                "stage stopped: {}",
                s.status
                    .as_ref()
                    .map_or("status unknown".into(), launcher::describe)
            ),
        }
    }
    Ok(if outcome.success() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// The segmenter configuration: the named preset (`--sensor`, else the service's, else
/// hdl64e), the `--config` file over it, then `--frames`.
fn load(common: &Common, service_sensor: Option<&str>) -> Result<SegmenterConfig> {
    Ok(load_methods(common, service_sensor)?.segmenter)
}

/// The whole configuration (segmenter and method sections) the common options describe.
fn load_methods(
    common: &Common,
    service_sensor: Option<&str>,
) -> Result<groundwork_io::MethodsConfig> {
    let sensor = common.sensor.as_deref().or(service_sensor);
    let mut cfg = groundwork_io::load_methods_config_over(sensor, common.config.as_deref())?;
    if let Some(n) = common.frames {
        cfg.segmenter.history.frames = n;
        cfg.segmenter.validate().context("--frames")?;
    }
    Ok(cfg)
}

/// Opens each input (a scan file, a folder or a recording; a folder may carry poses for
/// history) as a sequence. An input that cannot be used is reported and counted, and the
/// others still run: the sequences, and how many inputs were skipped.
fn open_inputs(
    inputs: &[PathBuf],
    poses: Option<&Path>,
    calib: Option<&Path>,
    topic: Option<&str>,
) -> (Vec<Sequence>, usize) {
    let mut skipped = 0;
    let mut sequences = Vec::new();
    for path in inputs {
        match Sequence::open(path, poses, calib) {
            Ok(seq) => sequences.push(seq.with_topic(topic.map(str::to_owned))),
            Err(e) => {
                skipped += 1;
                error!("skipped: {e}");
            }
        }
    }
    (sequences, skipped)
}

/// The output of an offline run, refused before anything is written where it would destroy
/// an input (`--out rec.mcap rec.mcap`) or where two inputs' scans would write the same
/// files of a folder (`000000.bin` in two folders): outputs are never overwritten in
/// silence.
fn create_output(
    out: &Path,
    inputs: &[PathBuf],
    sequences: &[Sequence],
) -> Result<groundwork_io::OutputTarget> {
    let is_recording = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("mcap"));
    if !is_recording {
        let sources: Vec<_> = sequences.iter().map(|s| &s.source).collect();
        groundwork_io::check_output_names(&sources)?;
    }
    let mut files: Vec<PathBuf> = inputs.to_vec();
    for s in sequences {
        if let groundwork_io::ScanSource::Files(f) = &s.source {
            files.extend(f.iter().cloned());
        }
    }
    Ok(groundwork_io::OutputTarget::create(out, &files)?)
}

fn progress(len: usize, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len as u64);
    pb.set_style(progress_style(
        "{msg} [{bar:30}] {pos}/{len} scans, {rate}, eta {eta}",
    ));
    pb.set_message(what.to_string());
    pb
}

/// A progress bar style whose `{rate}` is scans per second to one decimal (indicatif's
/// `{per_sec}` prints four).
fn progress_style(template: &str) -> ProgressStyle {
    ProgressStyle::with_template(template)
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .with_key(
            "rate",
            |s: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                let _ = write!(w, "{:.1} scans/s", s.per_sec());
            },
        )
        .progress_chars("=> ")
}

/// The header a scan read from a file would carry in the service: its input is its
/// producer run, its place among all scans its sequence number.
fn offline_header(
    pose: Option<&groundwork_core::Pose>,
    input: usize,
    k: usize,
    points: usize,
) -> groundwork_msg::ScanHeader {
    let mut h = groundwork_msg::ScanHeader {
        point_count: u32::try_from(points).unwrap_or(u32::MAX),
        sequence: k as u64,
        producer_epoch: input as u64 + 1,
        source_index: k as u64,
        ..Default::default()
    };
    if let Some(p) = pose {
        h.has_pose = 1;
        h.pose = producer::pose_matrix(p);
    }
    h
}

fn eval(
    common: &Common,
    methods: &[MethodArg],
    dir: &Path,
    labels: Option<&Path>,
    labels_format: &str,
    protocol: ProtocolArg,
    json: bool,
) -> Result<ExitCode> {
    let all = load_methods(common, None)?;
    let cfg = &all.segmenter;
    let mut seq = Sequence::open(dir, common.poses.as_deref(), common.calib.as_deref())?
        .with_topic(common.topic.clone())
        .with_label_map(groundwork_io::LabelMap::load(labels_format)?);
    if let Some(l) = labels {
        anyhow::ensure!(l.is_dir(), "{}: no such folder", l.display());
        seq = seq.with_labels(l.to_path_buf());
    }
    if cfg.history.frames > 1 && seq.poses.is_none() {
        info!("no poses.txt + calib.txt: multi-frame history is not used");
    }
    let protocol = match protocol {
        ProtocolArg::Gmm => Protocol::Gmm,
        ProtocolArg::Terraseg => Protocol::Terraseg,
    };
    // Every method on the same scans, through the same evaluator.
    let mut reports = Vec::new();
    for &m in methods {
        let mut method = methods::build(m, &all)?;
        let known = seq.len_hint();
        let pb = progress(known.unwrap_or(0), method.name());
        let report = evaluate(&seq, method.as_mut(), protocol, |_| {
            if known.is_none() {
                pb.inc_length(1);
            }
            pb.inc(1)
        })?;
        pb.finish_and_clear();
        reports.push(report);
    }
    match (json, reports.as_slice()) {
        (true, [one]) => println!("{}", serde_json::to_string_pretty(one)?),
        (true, _) => println!("{}", serde_json::to_string_pretty(&reports)?),
        (false, [one]) => print!("{}", one.to_table()),
        (false, _) => print!("{}", groundwork_eval::side_by_side(&reports)),
    }
    // Scores of the readable scans are printed; a run that skipped any is incomplete.
    Ok(if reports.iter().any(|r| !r.skipped.is_empty()) {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
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
    fn the_default_preset_is_the_kitti_hdl64e() {
        let common = Common {
            sensor: None,
            config: None,
            frames: None,
            poses: None,
            calib: None,
            topic: None,
        };
        let c = load(&common, None).unwrap();
        assert_eq!(c.sensor.name, "hdl64e");
        assert!((c.sensor.mount.height - 1.73).abs() < 1e-12);
        assert_eq!(load(&common, Some("vlp16")).unwrap().sensor.name, "vlp16");
        let table = sensors_table().unwrap();
        assert_eq!(table.lines().count(), SENSOR_PRESETS.len() + 1);
        assert!(table.contains("livox") && table.contains("1.10"), "{table}");
    }

    #[test]
    fn cli_parses() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
    }
}
