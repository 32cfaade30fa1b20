//! The service commands: `pipeline` (all stages, supervised), the four stages one by one,
//! and `shm-size`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context, Result};
use groundwork_packets::Model;
use groundwork_service::packets::{PacketInput, PacketSensor, PacketSource};
use groundwork_service::{check_shared_memory, consumer, launcher, producer, segmenter, signals};
use tracing::{error, info, warn};

use crate::args::{
    Common, ConsumerArgs, DetectorArgs, PacketArgs, PipelineArgs, ProducerArgs, Rate, Ros2Args,
    Ros2CmdArgs, SegmenterArgs, ServiceArgs, ShmSizeArgs, ViewCmdArgs,
};
use crate::common::{load, load_methods, load_service, sample_data};

/// `groundwork pipeline`.
pub fn pipeline_command(a: PipelineArgs) -> Result<ExitCode> {
    pipeline(
        &a.common,
        &a.service,
        &PipelineRun {
            data: a.data,
            count: a.count,
            rate: a.rate.and_then(Rate::hz),
            out: a.out,
            restart: a.restart,
            detector: !a.no_detector,
            ros2: a.ros2.then_some(a.ros2_args),
            packets: a.packets,
            view: a.view.view,
        },
    )
}

/// `groundwork ros2`.
pub fn ros2(a: Ros2CmdArgs) -> Result<ExitCode> {
    let cfg = load_service(&a.service)?;
    let seg = load(&a.sensor.into(), cfg.sensor.as_deref())?;
    let r = &a.ros2;
    let domain_id = match r.domain_id {
        Some(d) => d,
        None => match std::env::var("ROS_DOMAIN_ID") {
            Ok(v) if !v.trim().is_empty() => v
                .trim()
                .parse()
                .with_context(|| format!("ROS_DOMAIN_ID={v:?}: not a domain id"))?,
            _ => 0,
        },
    };
    let mount = groundwork_io::transform::StaticTransform::of_mount(&seg.sensor.mount)?;
    // The live view, as a thread of this process: it stops when the bridge has.
    let stop_view = Arc::new(AtomicBool::new(false));
    let view = a
        .view
        .view
        .map(|addr| {
            let opts = groundwork_view::ViewOptions {
                addr,
                mount: Some(mount.clone()),
                ground_threshold: seg.decision_threshold(),
                backlog: DEFAULT_VIEW_BACKLOG,
                stop: Some(Arc::clone(&stop_view)),
            };
            let cfg = cfg.clone();
            std::thread::Builder::new()
                .name("view".into())
                .spawn(move || groundwork_view::run(&cfg, opts))
                .context("start the view thread")
        })
        .transpose()?;
    let bridged = groundwork_ros2::run(
        &cfg,
        &groundwork_ros2::BridgeOptions {
            domain_id,
            input_topic: r.input_topic.clone(),
            qos: if r.reliable {
                groundwork_ros2::Qos::Reliable
            } else {
                groundwork_ros2::Qos::SensorData
            },
            namespace: r.namespace.clone(),
            node: r.node.clone(),
            publish_ground: r.publish_ground,
            ground_threshold: seg.decision_threshold(),
            count: a.count,
            mount: Some(mount),
            odometry_topic: r.odom_topic.clone(),
            tf_fixed_frame: r.tf.clone(),
        },
    );
    stop_view.store(true, Ordering::Relaxed);
    if let Some(v) = view {
        v.join()
            .map_err(|_| anyhow::anyhow!("the view thread panicked"))??;
    }
    let report = bridged?;
    // Bad clouds were skipped and counted: done, but not all input was good.
    Ok(if report.rejected == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// The bridge's command line, as `pipeline` starts it.
fn ros2_stage_args(c: &mut std::process::Command, r: &Ros2Args) {
    c.arg("--input-topic")
        .arg(&r.input_topic)
        .arg("--node")
        .arg(&r.node)
        .arg("--namespace")
        .arg(&r.namespace);
    if let Some(d) = r.domain_id {
        c.arg("--domain-id").arg(d.to_string());
    }
    if r.reliable {
        c.arg("--reliable");
    }
    if r.publish_ground {
        c.arg("--publish-ground");
    }
    if let Some(t) = &r.odom_topic {
        c.arg("--odom-topic").arg(t);
    }
    if let Some(f) = &r.tf {
        c.arg(format!("--tf={f}"));
    }
}

/// Messages a viewer may have queued before its oldest are dropped: a few scans.
const DEFAULT_VIEW_BACKLOG: usize = 8;

/// `groundwork view`.
pub fn view(a: ViewCmdArgs) -> Result<ExitCode> {
    let cfg = load_service(&a.service)?;
    let seg = load(&a.sensor.into(), cfg.sensor.as_deref())?;
    groundwork_view::run(
        &cfg,
        groundwork_view::ViewOptions {
            addr: a.addr,
            mount: Some(groundwork_io::transform::StaticTransform::of_mount(
                &seg.sensor.mount,
            )?),
            ground_threshold: seg.decision_threshold(),
            backlog: a.backlog,
            stop: None,
        },
    )?;
    Ok(ExitCode::SUCCESS)
}

/// `groundwork producer`.
pub fn producer(a: ProducerArgs) -> Result<ExitCode> {
    let cfg = load_service(&a.service)?;
    anyhow::ensure!(
        a.linger >= 0.0,
        "--linger {}: must be ≥ 0 seconds or inf",
        a.linger
    );
    let linger = Duration::try_from_secs_f64(a.linger).unwrap_or(Duration::MAX);
    let rate = a.rate.and_then(Rate::hz);
    let packets = packet_source(&a.packets, cfg.sensor.as_deref(), rate)?;
    let source = match (a.synthetic, packets) {
        (_, Some(p)) => producer::Source::Packets(p),
        (Some(n), None) => producer::Source::Synthetic(n),
        (None, None) => producer::Source::from_path(
            match a.data {
                Some(d) => d,
                None => sample_data()?,
            },
            a.topic,
        ),
    };
    let r = producer::run(
        &cfg,
        &producer::ProducerOptions {
            source,
            count: a.count,
            rate_hz: rate.filter(|_| a.packets.packets.is_none()),
            malformed_every: a.malformed_every,
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

/// The packet source the options ask for (None: scans come from elsewhere). The model is
/// `--model`, else the sensor preset's name (`vlp16`, `vlp32c`, `hdl32e`, `hdl64e`).
pub fn packet_source(
    a: &PacketArgs,
    sensor: Option<&str>,
    rate: Option<f64>,
) -> Result<Option<PacketSource>> {
    let Some(family) = &a.packets else {
        return Ok(None);
    };
    let (sensor, port) = match family.as_str() {
        "velodyne" => (
            PacketSensor::Velodyne(velodyne_model(a, sensor)?, a.sensor_config.clone()),
            groundwork_packets::velodyne::DATA_PORT,
        ),
        "ouster" => {
            anyhow::ensure!(
                a.model.is_none(),
                "--model names a Velodyne model; an Ouster's packets are described by its metadata (--sensor-config)"
            );
            let metadata = a.sensor_config.clone().context(
                "--packets ouster needs the sensor's metadata JSON: --sensor-config FILE.json (from http://SENSOR/api/v1/sensor/metadata)",
            )?;
            (
                PacketSensor::Ouster(metadata),
                groundwork_packets::ouster::LIDAR_PORT,
            )
        }
        other => anyhow::bail!("--packets {other}: the families read are velodyne and ouster"),
    };
    let input = match (&a.pcap, &a.udp) {
        (Some(p), None) => PacketInput::Pcap(p.clone()),
        (None, Some(addr)) => PacketInput::Udp(
            addr.parse()
                .with_context(|| format!("--udp {addr}: not an address such as 0.0.0.0:2368"))?,
        ),
        _ => anyhow::bail!("--packets needs where they come from: --pcap FILE or --udp ADDR"),
    };
    let recorded_rate = match rate {
        None => true,
        Some(0.0) => false,
        Some(r) => anyhow::bail!(
            "--rate {r}: packets set their own pace; a capture replays at its recorded rate, or as fast as scans are taken with --rate 0"
        ),
    };
    Ok(Some(PacketSource {
        sensor,
        input,
        port: match a.port {
            Some(0) => None,
            Some(p) => Some(p),
            None => Some(port),
        },
        recorded_rate,
    }))
}

/// The Velodyne model: `--model`, else the sensor preset's name.
fn velodyne_model(a: &PacketArgs, sensor: Option<&str>) -> Result<Model> {
    let names: Vec<&str> = Model::ALL.iter().map(|m| m.name()).collect();
    Ok(match (&a.model, sensor) {
        (Some(m), _) => Model::from_name(m)
            .with_context(|| format!("--model {m}: Velodyne models are {}", names.join(", ")))?,
        (None, Some(s)) => Model::from_name(s).with_context(|| {
            format!(
                "the sensor preset {s} is not a Velodyne model; say which with --model ({})",
                names.join(", ")
            )
        })?,
        (None, None) => anyhow::bail!(
            "--packets velodyne: which sensor? --sensor vlp16|vlp32c|hdl32e|hdl64e (the preset) or --model"
        ),
    })
}

/// `groundwork segmenter`.
pub fn segmenter(a: SegmenterArgs) -> Result<ExitCode> {
    let cfg = load_service(&a.service)?;
    segmenter::run(
        &cfg,
        &segmenter::SegmenterOptions {
            segmenter: load(&a.common, cfg.sensor.as_deref())?,
            count: a.count,
            echo: a.echo,
        },
    )?;
    Ok(ExitCode::SUCCESS)
}

/// `groundwork detector`.
pub fn detector(a: DetectorArgs) -> Result<ExitCode> {
    let cfg = load_service(&a.service)?;
    let methods = load_methods(&a.common, cfg.sensor.as_deref())?;
    groundwork_service::detector::run(
        &cfg,
        &groundwork_service::detector::DetectorOptions {
            segmenter: methods.segmenter,
            detector: methods.detector,
            count: a.count,
        },
    )?;
    Ok(ExitCode::SUCCESS)
}

/// `groundwork consumer`.
pub fn consumer(a: ConsumerArgs) -> Result<ExitCode> {
    let cfg = load_service(&a.service)?;
    let mount = load(&a.sensor.into(), cfg.sensor.as_deref())?.sensor.mount;
    let secs = |s: f64| Duration::try_from_secs_f64(s).context("seconds must be finite and >= 0");
    let report = consumer::run(
        &cfg,
        &consumer::ConsumerOptions {
            count: a.count,
            idle_timeout: a.idle_timeout.map(secs).transpose()?,
            labels: a.labels,
            out: a.out,
            report_json: a.report_json,
            stall_after: a.stall_after,
            stall: secs(a.stall_secs)?,
            warmup: a.warmup,
            mount: Some(mount),
        },
    )?;
    // Stopped by a signal before its end (its count, or the pipeline's own stop): it did
    // not finish, and a launcher must not take it for finished.
    let short = a.count.is_some_and(|n| report.masks < n);
    if signals::stop_requested() && (short || signals::under_launcher()) {
        warn!(
            masks = report.masks,
            count = ?a.count,
            "stopped by a signal before the end: exit {}",
            signals::STOPPED_EXIT_CODE
        );
        return Ok(ExitCode::from(signals::STOPPED_EXIT_CODE));
    }
    // Asked to write and could not: the run did not do what it was asked.
    Ok(if report.write_failures > 0 {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}

/// `groundwork shm-size`.
pub fn shm_size(a: ShmSizeArgs) -> Result<ExitCode> {
    let cfg = load_service(&a.service)?;
    // Round up, and leave room for iceoryx2's management segments.
    println!("{}m", (cfg.shared_memory_estimate() >> 20) + 1 + 16);
    Ok(ExitCode::SUCCESS)
}

/// What `pipeline` runs, beyond the common and service options.
#[derive(Debug)]
pub struct PipelineRun {
    data: Option<PathBuf>,
    count: Option<u64>,
    rate: Option<f64>,
    out: Option<PathBuf>,
    restart: u32,
    /// Start the detector stage too.
    detector: bool,
    /// Scans from ROS 2: the bridge instead of the producer.
    ros2: Option<Ros2Args>,
    /// Scans from a sensor's packets.
    packets: PacketArgs,
    /// Serve a live view on this address.
    view: Option<String>,
}

pub fn pipeline(common: &Common, service: &ServiceArgs, run: &PipelineRun) -> Result<ExitCode> {
    let PipelineRun {
        data,
        count,
        rate,
        out,
        restart,
        detector,
        ros2,
        packets,
        view,
    } = run;
    let (mut count, rate, restart) = (*count, *rate, *restart);
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
    if let Some(addr) = view {
        groundwork_view::parse_addr(addr)?;
    }
    // The scans' source: files (a folder or a recording), a sensor's packets, or the ROS 2
    // bridge.
    let mut what_ran = "clouds from ROS 2".to_string();
    let sensor = common.sensor.as_deref().or(cfg.sensor.as_deref());
    let packet_source = packet_source(packets, sensor, rate)?;
    let data = match (ros2, data) {
        (Some(_), _) => None,
        _ if packet_source.is_some() => None,
        (None, Some(d)) => Some(d.clone()),
        (None, None) => Some(sample_data()?),
    };
    if let Some(p) = &packet_source {
        // A capture is replayed once: the pipeline ends with its last scan.
        what_ran = match (&p.input, p.count_scans(cfg.max_points)?) {
            (PacketInput::Pcap(path), Some(n)) => {
                anyhow::ensure!(n > 0, "{}: no scan in the capture", path.display());
                if count.is_some_and(|c| c > n) {
                    warn!("--count: the capture holds {n} scans; the pipeline stops there");
                }
                count = Some(count.map_or(n, |c| c.min(n)));
                format!(
                    "{} scans of {} packets from {}",
                    count.unwrap_or(n),
                    p.sensor.name(),
                    path.display()
                )
            }
            (input, _) => format!("{} packets from {input:?}", p.sensor.name()),
        };
    }
    if let Some(data) = &data {
        anyhow::ensure!(
            data.exists(),
            "{}: no such folder or recording",
            data.display()
        );
        // Something to replay, checked before any stage starts (an empty folder would
        // otherwise be found by the producer after the others are up).
        let source = groundwork_io::ScanSource::open(data, None)?;
        what_ran = match (source.len_hint(), count) {
            (Some(n), Some(c)) => format!(
                "{n} scans of {} replayed {} time(s) ({c} scans)",
                data.display(),
                c.div_ceil(n as u64)
            ),
            (Some(n), None) => format!("{n} scans of {} replayed until stopped", data.display()),
            (None, _) => format!("the recording {}", data.display()),
        };
        if let Some(o) = &out {
            groundwork_io::check_not_an_input(o, std::slice::from_ref(data))?;
        }
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
    // The consumer reads the mount from the same configuration, for recordings.
    let mut con = configured("consumer");
    if let Some(d) = data.as_ref().filter(|d| d.is_dir()) {
        con.arg("--labels").arg(d);
    }
    if let Some(n) = count {
        con.arg("--count").arg(n.to_string());
        // Replayed files that stop coming mean a stage is stuck; a ROS 2 driver or a live
        // sensor may pause for as long as it likes.
        let live = packets.udp.is_some();
        if ros2.is_none() && !live {
            con.arg("--idle-timeout").arg("5");
        }
    }
    if let Some(o) = &out {
        con.arg("--out").arg(o);
    }
    let producer_with_count = |prod: &mut std::process::Command| {
        if let Some(n) = count {
            // The producer stays until the pipeline stops: the consumer reads the last
            // scans (and counts them) after the producer has published them all.
            prod.arg("--count")
                .arg(n.to_string())
                .arg("--linger")
                .arg("inf");
        }
    };
    let source = match (&data, ros2) {
        _ if packet_source.is_some() => {
            let mut prod = stage("producer");
            producer_with_count(&mut prod);
            prod.arg("--packets")
                .arg(packets.packets.as_deref().unwrap_or("velodyne"));
            if let Some(PacketSource {
                sensor: PacketSensor::Velodyne(model, _),
                ..
            }) = &packet_source
            {
                prod.arg("--model").arg(model.name());
            }
            if let Some(port) = packets.port {
                prod.arg("--port").arg(port.to_string());
            }
            if let Some(f) = &packets.pcap {
                prod.arg("--pcap").arg(f);
            }
            if let Some(a) = &packets.udp {
                prod.arg("--udp").arg(a);
            }
            if let Some(f) = &packets.sensor_config {
                prod.arg("--sensor-config").arg(f);
            }
            if let Some(r) = rate {
                prod.arg("--rate").arg(r.to_string());
            }
            launcher::Stage {
                name: "producer",
                command: prod,
            }
        }
        (Some(data), _) => {
            let mut prod = stage("producer");
            producer_with_count(&mut prod);
            if let Some(r) = rate {
                prod.arg("--rate").arg(r.to_string());
            }
            if let Some(t) = &common.topic {
                prod.arg("--topic").arg(t);
            }
            prod.arg(data);
            launcher::Stage {
                name: "producer",
                command: prod,
            }
        }
        (None, Some(r)) => {
            // No --count: the bridge answers until the consumer has counted the masks
            // and the pipeline stops it.
            let mut bridge = configured("ros2");
            ros2_stage_args(&mut bridge, r);
            launcher::Stage {
                name: "ros2",
                command: bridge,
            }
        }
        (None, None) => anyhow::bail!("no source of scans"),
    };
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
    if let Some(addr) = view {
        let mut v = configured("view");
        v.arg("--addr").arg(addr);
        stages.push(launcher::Stage {
            name: "view",
            command: v,
        });
    }
    stages.push(source);
    // What runs, in one line before the stages' own output (the consumer's verdict ends it).
    let names: Vec<&str> = stages.iter().map(|s| s.name).collect();
    println!(
        "pipeline: {what_ran}, through {} processes ({}) over shared memory",
        names.len(),
        names.join(", ")
    );
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
