//! iceoryx2's global configuration is ours from the first use of the transport: a path
//! that falls back to it (cleaning up a dead node whose details are gone) neither looks
//! up files nor warns "No config file was loaded". A test binary of its own: the global
//! configuration is set once per process.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use std::io::Write;
use std::sync::Mutex;

static LOG: Mutex<Vec<u8>> = Mutex::new(Vec::new());

struct Capture;

impl Write for Capture {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        LOG.lock().unwrap().extend_from_slice(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[test]
fn the_global_configuration_is_ours_and_loads_no_file() {
    let subscriber = tracing_subscriber::fmt()
        .with_writer(|| Capture)
        .with_max_level(tracing::Level::DEBUG)
        .finish();
    tracing::subscriber::with_default(subscriber, || {
        let ours = groundwork_service::transport::ipc_config();
        assert_eq!(iceoryx2::config::Config::global_config(), ours);
    });
    let log = String::from_utf8(LOG.lock().unwrap().clone()).unwrap();
    assert!(!log.contains("No config file"), "{log}");
}
