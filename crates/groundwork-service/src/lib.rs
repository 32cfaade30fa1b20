//! groundwork-service: the zero-copy shared-memory service. Four stages — producer,
//! segmenter, detector, consumer — each its own process, exchanging scans, masks and
//! proposals over iceoryx2 publish-subscribe topics (see `groundwork-msg`), woken by
//! iceoryx2 events.

pub mod awake;
pub mod config;
pub mod consumer;
pub mod cpu;
pub mod detector;
pub mod launcher;
pub mod packets;
pub mod producer;
pub mod scene;
pub mod segmenter;
pub mod signals;
pub mod stage;
pub mod stats;
pub mod synthetic;
pub mod transport;
pub mod window;

pub use config::{OverflowPolicy, ServiceConfig, check_shared_memory};
