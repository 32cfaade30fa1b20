//! iceoryx2 wiring shared by the stages: every topic is a publish-subscribe service plus an
//! event service of the same name that wakes the readers.

use std::fmt::Debug;

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;

use groundwork_msg::{MaskHeader, ProposalsHeader, ScanHeader, ScanPoint};

use crate::config::{OverflowPolicy, ServiceConfig};

/// The scan topic's service.
pub type ScanService = PortFactory<ipc::Service, [ScanPoint], ScanHeader>;
/// The mask topic's service.
pub type MaskService = PortFactory<ipc::Service, [f32], MaskHeader>;
/// The proposals topic's service.
pub type ProposalsService = PortFactory<ipc::Service, [u32], ProposalsHeader>;
/// A publisher of scans.
pub type ScanPublisher = Publisher<ipc::Service, [ScanPoint], ScanHeader>;
/// The wake-up side of a topic's publisher.
pub type EventNotifier = Notifier<ipc::Service>;
/// The wake-up side of a topic's readers.
pub type EventListener = Listener<ipc::Service>;

/// The iceoryx2 configuration every groundwork process uses: iceoryx2's defaults, set in
/// code rather than looked up in files, so that all stages agree whatever their working
/// directory, and a clean start logs no "No config file was loaded" warning.
pub fn ipc_config() -> &'static iceoryx2::config::Config {
    static CONFIG: std::sync::OnceLock<iceoryx2::config::Config> = std::sync::OnceLock::new();
    CONFIG.get_or_init(|| {
        let config = iceoryx2::config::Config::default();
        install_as_global(&config);
        config
    })
}

/// iceoryx2 falls back to its *global* configuration on paths that take no configuration
/// (cleaning up a dead node whose details are gone), and the first use looks for files and
/// warns "No config file was loaded". Installing ours as the global one first (it can only
/// be set from a file: a private one, removed at once) keeps every path on the same values
/// and the log quiet. Failing that, iceoryx2 looks up its files as it would anyway.
fn install_as_global(config: &iceoryx2::config::Config) {
    let path = std::env::temp_dir().join(format!(
        "groundwork-iceoryx2-{}-{}.toml",
        std::process::id(),
        groundwork_msg::new_epoch()
    ));
    let Ok(text) = toml::to_string(config) else {
        return;
    };
    if std::fs::write(&path, text).is_err() {
        return;
    }
    if let Ok(file) = iceoryx2::prelude::FilePath::new(path.as_os_str().as_encoded_bytes()) {
        let _ = iceoryx2::config::Config::setup_global_config_from_file(&file);
    }
    let _ = std::fs::remove_file(&path);
}

/// The iceoryx2 node name of a pipeline's stage: `<prefix>/<stage>`, so that a node
/// listing tells which pipeline a process (alive or dead) belongs to.
pub fn node_name(cfg: &ServiceConfig, stage: &str) -> String {
    format!("{}/{stage}", cfg.prefix)
}

/// Registered nodes of this pipeline (named `<prefix>/…`): (stage, alive, pid).
pub fn pipeline_nodes(cfg: &ServiceConfig) -> Vec<(String, bool, i32)> {
    use iceoryx2::node::NodeView;
    let own = format!("{}/", cfg.prefix);
    let mut found = Vec::new();
    let _ = Node::<ipc::Service>::list(ipc_config(), |s| {
        let (view_details, id, alive) = match &s {
            NodeState::Alive(v) => (v.details(), v.id(), true),
            NodeState::Dead(v) => (v.details(), v.id(), false),
            _ => return CallbackProgression::Continue,
        };
        if let Some(d) = view_details
            && let Some(stage) = d.name().as_str().strip_prefix(&own)
        {
            let pid = id.pid::<ipc::Service>().map_or(0, |p| p.value());
            found.push((stage.to_string(), alive, pid));
        }
        CallbackProgression::Continue
    });
    found
}

/// Creates this process's node, named after the pipeline and the stage. Creating a node
/// removes the ports and shared memory of processes that died without cleaning up (killed
/// with -9, crashed); we count this pipeline's first so that the log says what was removed.
pub fn node(cfg: &ServiceConfig, stage: &str) -> anyhow::Result<Node<ipc::Service>> {
    create_node(cfg, stage, &pipeline_nodes(cfg))
}

/// [`node`] for a stage that must be unique in its pipeline (the producer, the segmenter):
/// refused while another live process holds that role, since two segmenters would answer
/// every scan twice. (The topics also admit one publisher each, which settles a race of two
/// starts.)
pub fn unique_node(cfg: &ServiceConfig, stage: &str) -> anyhow::Result<Node<ipc::Service>> {
    let before = pipeline_nodes(cfg);
    if let Some((_, _, pid)) = before.iter().find(|(s, alive, _)| s == stage && *alive) {
        anyhow::bail!(
            "another {stage} of pipeline \"{}\" is running (pid {pid}): refusing to start a \
                 second one (use another --prefix to run a second pipeline)",
            cfg.prefix
        );
    }
    create_node(cfg, stage, &before)
}

fn create_node(
    cfg: &ServiceConfig,
    stage: &str,
    before: &[(String, bool, i32)],
) -> anyhow::Result<Node<ipc::Service>> {
    let name = node_name(cfg, stage);
    let stale = before.iter().filter(|(_, alive, _)| !alive).count();
    let node = NodeBuilder::new()
        .config(ipc_config())
        .name(&NodeName::new(&name).map_err(|e| anyhow::anyhow!("node name {name}: {e:?}"))?)
        .create::<ipc::Service>()
        .map_err(|e| {
            let root = ipc_config().global.root_path().to_string();
            match std::fs::read_dir(&root) {
                Err(io) if io.kind() == std::io::ErrorKind::PermissionDenied => anyhow::anyhow!(
                    "cannot create iceoryx2 node ({e:?}): {root}: permission denied. The \
                     pipeline's shared memory and sockets belong to the user who started it \
                     (created 0600 under a 0750 root): run every stage as that user"
                ),
                _ => anyhow::anyhow!("cannot create iceoryx2 node: {e:?}"),
            }
        })?;
    // Whatever creation did not remove (e.g. a configuration that disables it) goes now.
    let c = node.try_cleanup_dead_nodes();
    let left = pipeline_nodes(cfg).iter().filter(|n| !n.1).count();
    if stale > 0 {
        tracing::info!(
            dead_processes = stale,
            still_stale = left,
            "removed stale resources of dead processes of this pipeline"
        );
    }
    if c.failed_cleanups > 0 {
        tracing::warn!(
            failed = c.failed_cleanups,
            "stale resources of dead processes could not be removed (another user's?)"
        );
    }
    Ok(node)
}

/// Periodic sweep for processes that died while we run (any pipeline's: iceoryx2 cleans
/// them all); the log counts what was removed.
pub fn cleanup_dead(node: &Node<ipc::Service>) {
    let c = node.try_cleanup_dead_nodes();
    if c.cleanups > 0 || c.failed_cleanups > 0 {
        tracing::info!(
            cleaned = c.cleanups,
            failed = c.failed_cleanups,
            "removed stale resources of dead processes"
        );
    }
}

fn service_name(cfg: &ServiceConfig, topic: &str) -> anyhow::Result<ServiceName> {
    let s = format!("{}/{}", cfg.prefix, topic);
    ServiceName::new(&s).map_err(|e| anyhow::anyhow!("service name {s}: {e:?}"))
}

/// Opens (or creates) a topic whose payload is a slice of `P` with header `H`, sized by the
/// configuration: `queue` samples per subscriber, safe overflow per the overflow policy.
fn topic<P, H>(
    node: &Node<ipc::Service>,
    cfg: &ServiceConfig,
    name: &str,
    queue: usize,
) -> anyhow::Result<PortFactory<ipc::Service, [P], H>>
where
    P: Debug + ZeroCopySend + 'static,
    H: Debug + ZeroCopySend + 'static,
{
    node.service_builder(&service_name(cfg, name)?)
        .publish_subscribe::<[P]>()
        .user_header::<H>()
        .subscriber_max_buffer_size(queue)
        .subscriber_max_borrowed_samples(cfg.max_borrowed)
        .max_subscribers(cfg.max_subscribers)
        // One producer, one segmenter: a second publisher is refused.
        .max_publishers(1)
        .history_size(0)
        .enable_safe_overflow(cfg.overflow == OverflowPolicy::DropOldest)
        .open_or_create()
        .map_err(|e| anyhow::anyhow!("{}/{name}: {e:?}", cfg.prefix))
}

/// Opens (or creates) the scan topic.
pub fn scan_service(node: &Node<ipc::Service>, cfg: &ServiceConfig) -> anyhow::Result<ScanService> {
    topic(node, cfg, "scans", cfg.scan_queue)
}

/// Opens (or creates) the mask topic.
pub fn mask_service(node: &Node<ipc::Service>, cfg: &ServiceConfig) -> anyhow::Result<MaskService> {
    topic(node, cfg, "masks", cfg.mask_queue)
}

/// Opens (or creates) the proposals topic.
pub fn proposals_service(
    node: &Node<ipc::Service>,
    cfg: &ServiceConfig,
) -> anyhow::Result<ProposalsService> {
    topic(node, cfg, "proposals", cfg.mask_queue)
}

/// Opens (or creates) a topic's event service.
fn event_service(
    node: &Node<ipc::Service>,
    cfg: &ServiceConfig,
    topic: &str,
) -> anyhow::Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>> {
    node.service_builder(&service_name(cfg, topic)?)
        .event()
        .max_notifiers(4)
        .max_listeners(cfg.max_subscribers + 2)
        .open_or_create()
        .map_err(|e| anyhow::anyhow!("{}/{topic} (event): {e:?}", cfg.prefix))
}

/// The wake-up side of a topic's publisher. Every listener of the topic costs each
/// notification a datagram, so a process creates only the side it uses.
pub fn event_notifier(
    node: &Node<ipc::Service>,
    cfg: &ServiceConfig,
    topic: &str,
) -> anyhow::Result<EventNotifier> {
    event_service(node, cfg, topic)?
        .notifier_builder()
        .create()
        .map_err(|e| anyhow::anyhow!("{topic} notifier: {e:?}"))
}

/// The wake-up side of a topic's readers.
pub fn event_listener(
    node: &Node<ipc::Service>,
    cfg: &ServiceConfig,
    topic: &str,
) -> anyhow::Result<EventListener> {
    event_service(node, cfg, topic)?
        .listener_builder()
        .create()
        .map_err(|e| anyhow::anyhow!("{topic} listener: {e:?}"))
}

/// A publisher whose memory is sized once for `max_points` values (no growth at run time)
/// and that never blocks on a full subscriber queue.
fn publisher<P, H>(
    svc: &PortFactory<ipc::Service, [P], H>,
    cfg: &ServiceConfig,
    what: &str,
) -> anyhow::Result<Publisher<ipc::Service, [P], H>>
where
    P: Debug + ZeroCopySend + 'static,
    H: Debug + ZeroCopySend + 'static,
{
    svc.publisher_builder()
        .initial_max_slice_len(cfg.max_points)
        .allocation_strategy(AllocationStrategy::Static)
        .backpressure_strategy(BackpressureStrategy::DiscardData)
        .max_loaned_samples(2)
        .create()
        .map_err(|e| match e {
            iceoryx2::port::publisher::PublisherCreateError::ExceedsMaxSupportedPublishers => {
                anyhow::anyhow!(
                    "{what} topic already has its publisher: another process of this pipeline \
                     publishes {what}s (use another --prefix)"
                )
            }
            e => anyhow::anyhow!("{what} publisher: {e:?}"),
        })
}

fn subscriber<P, H>(
    svc: &PortFactory<ipc::Service, [P], H>,
    queue: usize,
    what: &str,
) -> anyhow::Result<Subscriber<ipc::Service, [P], H>>
where
    P: Debug + ZeroCopySend + 'static,
    H: Debug + ZeroCopySend + 'static,
{
    svc.subscriber_builder()
        .buffer_size(queue)
        .create()
        .map_err(|e| anyhow::anyhow!("{what} subscriber: {e:?}"))
}

/// The scan publisher.
pub fn scan_publisher(svc: &ScanService, cfg: &ServiceConfig) -> anyhow::Result<ScanPublisher> {
    publisher(svc, cfg, "scan")
}

/// The mask publisher.
pub fn mask_publisher(
    svc: &MaskService,
    cfg: &ServiceConfig,
) -> anyhow::Result<Publisher<ipc::Service, [f32], MaskHeader>> {
    publisher(svc, cfg, "mask")
}

/// The proposals publisher.
pub fn proposals_publisher(
    svc: &ProposalsService,
    cfg: &ServiceConfig,
) -> anyhow::Result<Publisher<ipc::Service, [u32], ProposalsHeader>> {
    publisher(svc, cfg, "proposal")
}

/// A proposals subscriber.
pub fn proposals_subscriber(
    svc: &ProposalsService,
    cfg: &ServiceConfig,
) -> anyhow::Result<Subscriber<ipc::Service, [u32], ProposalsHeader>> {
    subscriber(svc, cfg.mask_queue, "proposal")
}

/// A scan subscriber.
pub fn scan_subscriber(
    svc: &ScanService,
    cfg: &ServiceConfig,
) -> anyhow::Result<Subscriber<ipc::Service, [ScanPoint], ScanHeader>> {
    subscriber(svc, cfg.scan_queue, "scan")
}

/// A mask subscriber.
pub fn mask_subscriber(
    svc: &MaskService,
    cfg: &ServiceConfig,
) -> anyhow::Result<Subscriber<ipc::Service, [f32], MaskHeader>> {
    subscriber(svc, cfg.mask_queue, "mask")
}

/// Blocks on `listener` for at most `timeout` (no busy spinning), then reports whether the
/// process should go on: `Ok(false)` once SIGINT, SIGTERM or SIGHUP arrived. Any other
/// signal (SIGCONT after a SIGSTOP) merely ends the wait early. The bounded wait is what
/// lets an idle stage notice a termination request.
pub fn wait_or_stop(
    listener: &EventListener,
    timeout: std::time::Duration,
) -> anyhow::Result<bool> {
    use iceoryx2::port::listener::ListenerWaitError;
    if crate::signals::stop_requested() {
        return Ok(false);
    }
    if timeout.is_zero() {
        return Ok(true); // nothing to wait for (and a zero wait must not mean "forever")
    }
    let woke = listener.timed_wait(|_| {}, timeout);
    if crate::signals::stop_requested() {
        tracing::info!("termination requested");
        return Ok(false);
    }
    match woke {
        Ok(_) | Err(ListenerWaitError::InterruptSignal) => Ok(true),
        Err(e) => Err(anyhow::anyhow!("wait for {}: {e:?}", listener.name())),
    }
}
