//! Scans held until their mask comes: a stage that needs a scan's points after its mask
//! (the consumer's recording, the detector) copies them here, bounded.

use std::collections::BTreeMap;

use groundwork_core::Point;
use groundwork_msg::ScanPoint;

/// Scans a stage holds waiting for their masks. A mask normally follows its scan within a
/// frame or two; a stalled segmenter must not make a stage hold 256 scans of 200 000 points.
pub const SCAN_WINDOW: usize = 16;

/// The newest [`SCAN_WINDOW`] scans by (producer epoch, sequence).
#[derive(Debug, Default)]
pub struct ScanWindow {
    held: BTreeMap<(u64, u64), Vec<Point>>,
}

impl ScanWindow {
    /// Holds a copy of a scan's points; the oldest scan leaves when the window is full.
    pub fn hold(&mut self, producer_epoch: u64, sequence: u64, points: &[ScanPoint]) {
        self.held.insert(
            (producer_epoch, sequence),
            points.iter().map(Point::from).collect(),
        );
        if self.held.len() > SCAN_WINDOW {
            self.held.pop_first();
        }
    }

    /// The points of a scan, if still held (they leave the window).
    pub fn take(&mut self, producer_epoch: u64, sequence: u64) -> Option<Vec<Point>> {
        self.held.remove(&(producer_epoch, sequence))
    }

    /// Scans held.
    pub fn len(&self) -> usize {
        self.held.len()
    }

    /// Whether no scan is held.
    pub fn is_empty(&self) -> bool {
        self.held.is_empty()
    }
}
