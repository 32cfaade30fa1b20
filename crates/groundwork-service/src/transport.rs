//! iceoryx2 wiring shared by the stages: every topic is a publish-subscribe service plus an
//! event service of the same name that wakes the readers.

use std::fmt::Debug;

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;

use groundwork_msg::{MaskHeader, ScanHeader, ScanPoint};

use crate::config::{OverflowPolicy, ServiceConfig};

/// The scan topic's service.
pub type ScanService = PortFactory<ipc::Service, [ScanPoint], ScanHeader>;
/// The mask topic's service.
pub type MaskService = PortFactory<ipc::Service, [f32], MaskHeader>;
/// A publisher of scans.
pub type ScanPublisher = Publisher<ipc::Service, [ScanPoint], ScanHeader>;
/// The wake-up side of a topic's publisher.
pub type EventNotifier = Notifier<ipc::Service>;
/// The wake-up side of a topic's readers.
pub type EventListener = Listener<ipc::Service>;

/// Dead nodes (processes that died without cleaning up) currently registered.
fn dead_nodes(config: &iceoryx2::config::Config) -> u64 {
    let mut dead = 0;
    let _ = Node::<ipc::Service>::list(config, |s| {
        dead += u64::from(matches!(s, NodeState::Dead(_)));
        CallbackProgression::Continue
    });
    dead
}

/// The iceoryx2 node name of a pipeline's stage: `<prefix>/<stage>`, so that a node
/// listing tells which pipeline a process (alive or dead) belongs to.
pub fn node_name(cfg: &ServiceConfig, stage: &str) -> String {
    format!("{}/{stage}", cfg.prefix)
}

/// Creates this process's node, named after the pipeline and the stage. Creating a node
/// removes the ports and shared memory of processes that died without cleaning up (killed
/// with -9, crashed); we count them first so that the log says what was removed.
pub fn node(cfg: &ServiceConfig, stage: &str) -> anyhow::Result<Node<ipc::Service>> {
    let name = node_name(cfg, stage);
    let stale = dead_nodes(iceoryx2::config::Config::global_config());
    let node = NodeBuilder::new()
        .name(&NodeName::new(&name).map_err(|e| anyhow::anyhow!("node name {name}: {e:?}"))?)
        .create::<ipc::Service>()
        .map_err(|e| anyhow::anyhow!("cannot create iceoryx2 node: {e:?}"))?;
    // Whatever creation did not remove (e.g. a configuration that disables it) goes now.
    let c = node.try_cleanup_dead_nodes();
    let left = dead_nodes(node.config());
    if stale > 0 || c.cleanups > 0 {
        tracing::info!(
            dead_processes = stale.max(c.cleanups),
            still_stale = left,
            "removed stale resources of dead processes"
        );
    }
    Ok(node)
}

/// Periodic sweep for processes that died while we run.
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
        .max_publishers(2)
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
        .map_err(|e| anyhow::anyhow!("{what} publisher: {e:?}"))
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
/// process should go on: `Ok(false)` once SIGINT/SIGTERM arrived (iceoryx2 catches them).
/// The bounded wait is what lets an idle stage notice a termination request.
pub fn wait_or_stop(
    node: &Node<ipc::Service>,
    listener: &EventListener,
    timeout: std::time::Duration,
) -> anyhow::Result<bool> {
    let woke = listener
        .timed_wait(|_| {}, timeout)
        .map_err(|e| anyhow::anyhow!("wait for {}: {e:?}", listener.name()));
    if node.wait(std::time::Duration::ZERO).is_err() {
        tracing::info!("termination requested");
        return Ok(false);
    }
    woke.map(|_| true)
}
