//! `groundwork`: the command line, a thin front end over the library crates. One module
//! per command; this file dispatches.

use std::process::ExitCode;

use anyhow::Result;
use clap::Parser;

mod args;
mod calibrate;
mod common;
mod detect;
mod eval;
mod label;
mod methods;
mod render;
mod segment;
mod sensors;
mod stages;
mod synth;

use args::{Cli, Command};

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
                // The DDS stack's own info is its internals (sockets, discovery).
                .unwrap_or_else(|_| {
                    tracing_subscriber::EnvFilter::new("info,rustdds=warn,ros2_client=error")
                }),
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
        Command::Segment(a) => segment::command(a),
        Command::Detect(a) => detect::command(a),
        Command::Render(a) => render::command(a),
        Command::Label(a) => label::command(a),
        Command::Eval(a) => eval::command(a),
        Command::Calibrate(a) => calibrate::command(a),
        Command::Synth(a) => synth::command(a),
        Command::Sensors => sensors::command(),
        Command::Pipeline(a) => stages::pipeline_command(*a),
        Command::Producer(a) => stages::producer(a),
        Command::Segmenter(a) => stages::segmenter(a),
        Command::Detector(a) => stages::detector(a),
        Command::Consumer(a) => stages::consumer(a),
        Command::Ros2(a) => stages::ros2(a),
        Command::View(a) => stages::view(a),
        Command::ShmSize(a) => stages::shm_size(a),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::args::Common;
    use crate::common::{DEFAULT_SERVICE, load};
    use groundwork_service::ServiceConfig;

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
    }

    #[test]
    fn cli_parses() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
    }
}
