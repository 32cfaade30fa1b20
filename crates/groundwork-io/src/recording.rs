//! MCAP recordings (ROS 2 bags in rosbag2's MCAP storage): PointCloud2 messages of one
//! topic read as a sequence of scans, streamed (a recording may be far larger than
//! memory), and results written back as PointCloud2 with a `ground_probability` field,
//! which Foxglove and rerun open as they are.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::io::{BufReader, BufWriter};
use std::path::{Path, PathBuf};

use std::io::Read;

use mcap::records::op;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use tracing::warn;

use crate::error::FormatError;
use crate::pointcloud2::{self, SCHEMA_NAME, SCHEMA_TEXT};
use crate::scan::Scan;

/// A scan read from a recording.
#[derive(Debug, Clone)]
pub struct RecordedScan {
    /// Place among the topic's messages, from 0 (bad messages count too, so names stay
    /// stable).
    pub index: usize,
    /// The recording's log time of the message, ns.
    pub log_time_ns: u64,
    /// The topic it came from.
    pub topic: String,
    /// The decoded scan.
    pub scan: Scan,
}

/// A channel as far as the reader needs it.
#[derive(Debug, Clone)]
struct ChannelInfo {
    topic: String,
    encoding: String,
    schema: Option<String>,
}

/// Streams the PointCloud2 messages of one topic of an MCAP file.
///
/// The container (chunks, compression, CRCs) is the `mcap` crate's sans-io reader; the
/// three record kinds needed here (schema, channel, message) are parsed here, with every
/// length checked against its record, because the crate's record parser allocates string
/// lengths as claimed (a flipped byte in a topic name would reserve 4 GiB). Reading stops at the data end record: the summary
/// after it repeats what was read.
///
/// Items are `Err` for a message that does not decode (the stream goes on with the next
/// one) and for a broken container (truncated file, bad record: the stream then ends).
pub struct RecordingReader {
    path: PathBuf,
    file: BufReader<fs::File>,
    reader: LinearReader,
    schemas: BTreeMap<u16, String>,
    channels: BTreeMap<u16, ChannelInfo>,
    topic: Option<String>,
    max_points: usize,
    next_index: usize,
    other_clouds: BTreeSet<String>,
    done: bool,
}

impl std::fmt::Debug for RecordingReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RecordingReader")
            .field("path", &self.path)
            .field("topic", &self.topic)
            .field("next_index", &self.next_index)
            .finish_non_exhaustive()
    }
}

/// Little-endian fields of one record, every length checked against what is left.
struct Fields<'a>(&'a [u8]);

impl<'a> Fields<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        if n > self.0.len() {
            return None;
        }
        let (head, rest) = self.0.split_at(n);
        self.0 = rest;
        Some(head)
    }
    fn u16(&mut self) -> Option<u16> {
        self.take(2).map(|b| u16::from_le_bytes([b[0], b[1]]))
    }
    fn u32(&mut self) -> Option<u32> {
        self.take(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&mut self) -> Option<u64> {
        self.take(8)
            .map(|b| u64::from_le_bytes(b.try_into().unwrap_or_default()))
    }
    fn string(&mut self) -> Option<String> {
        let n = self.u32()? as usize;
        String::from_utf8(self.take(n)?.to_vec()).ok()
    }
}

impl RecordingReader {
    /// Opens a recording. With `topic` None, the first PointCloud2 topic met is read (and
    /// any other PointCloud2 topic named in a warning).
    pub fn open(path: &Path, topic: Option<&str>, max_points: usize) -> Result<Self, FormatError> {
        let file = fs::File::open(path).map_err(|e| FormatError::io(path, e))?;
        let options =
            LinearReaderOptions::default().with_record_length_limit(Self::record_limit(max_points));
        Ok(Self {
            path: path.to_path_buf(),
            file: BufReader::new(file),
            reader: LinearReader::new_with_options(options),
            schemas: BTreeMap::new(),
            channels: BTreeMap::new(),
            topic: topic.map(str::to_string),
            max_points,
            next_index: 0,
            other_clouds: BTreeSet::new(),
            done: false,
        })
    }

    /// The longest MCAP record read for scans of at most `max_points` points: a length
    /// field claiming more is refused before anything is allocated for it. (Not the file
    /// size: a compressed chunk legitimately unpacks to more than the file holds; the
    /// reader unpacks it record by record, never whole.)
    pub fn record_limit(max_points: usize) -> usize {
        // 256 bytes is a generous point_step (Ouster's is 48), 1 MiB the rest of a message.
        max_points.saturating_mul(256).saturating_add(1 << 20)
    }

    /// The topic being read, once known.
    pub fn topic(&self) -> Option<&str> {
        self.topic.as_deref()
    }

    fn broken(&mut self, what: impl std::fmt::Display) -> FormatError {
        self.done = true;
        FormatError::malformed(&self.path, format!("MCAP: {what}"))
    }

    fn end_of_data(&mut self) -> Option<Result<RecordedScan, FormatError>> {
        self.done = true;
        if self.next_index > 0 {
            return None;
        }
        let mut topics: Vec<&str> = self.channels.values().map(|c| c.topic.as_str()).collect();
        topics.dedup();
        let message = match &self.topic {
            Some(t) => format!("no messages on topic {t} (topics: {})", topics.join(", ")),
            None => format!("no {SCHEMA_NAME} messages (topics: {})", topics.join(", ")),
        };
        Some(Err(FormatError::malformed(&self.path, message)))
    }
}

/// What one record meant to the reader.
enum Step {
    Continue,
    EndOfData,
    Broken(String),
    Scan(Result<RecordedScan, FormatError>),
}

impl RecordingReader {
    fn record(&mut self, opcode: u8, data: &[u8]) -> Step {
        let mut f = Fields(data);
        match opcode {
            op::SCHEMA => {
                let (Some(id), Some(name)) = (f.u16(), f.string()) else {
                    return Step::Broken("malformed schema record".into());
                };
                self.schemas.insert(id, name);
            }
            op::CHANNEL => {
                let parsed = (|| {
                    let id = f.u16()?;
                    let schema = f.u16()?;
                    Some((id, schema, f.string()?, f.string()?))
                })();
                let Some((id, schema, topic, encoding)) = parsed else {
                    return Step::Broken("malformed channel record".into());
                };
                let schema = self.schemas.get(&schema).cloned();
                self.channels.insert(
                    id,
                    ChannelInfo {
                        topic,
                        encoding,
                        schema,
                    },
                );
            }
            op::MESSAGE => {
                let (Some(channel), Some(_sequence), Some(log_time), Some(_publish)) =
                    (f.u16(), f.u32(), f.u64(), f.u64())
                else {
                    return Step::Broken("malformed message record".into());
                };
                let Some(ch) = self.channels.get(&channel) else {
                    return Step::Broken(format!("message on unknown channel {channel}"));
                };
                let is_cloud = ch.schema.as_deref() == Some(SCHEMA_NAME);
                let chosen = match &self.topic {
                    Some(t) => *t == ch.topic,
                    None => is_cloud,
                };
                if !chosen {
                    if is_cloud && self.other_clouds.insert(ch.topic.clone()) {
                        warn!(
                            "{}: also holds PointCloud2 topic {} (not read; choose with --topic)",
                            self.path.display(),
                            ch.topic
                        );
                    }
                    return Step::Continue;
                }
                let ch = ch.clone();
                self.topic.get_or_insert_with(|| ch.topic.clone());
                let index = self.next_index;
                self.next_index += 1;
                let label = PathBuf::from(format!(
                    "{} (message {index} on {})",
                    self.path.display(),
                    ch.topic
                ));
                if !is_cloud || ch.encoding != "cdr" {
                    return Step::Scan(Err(FormatError::malformed(
                        &label,
                        format!(
                            "not a CDR {SCHEMA_NAME} (schema {:?}, encoding {:?})",
                            ch.schema, ch.encoding
                        ),
                    )));
                }
                return Step::Scan(
                    pointcloud2::decode(&label, f.0, self.max_points).map(|scan| RecordedScan {
                        index,
                        log_time_ns: log_time,
                        topic: ch.topic,
                        scan,
                    }),
                );
            }
            op::DATA_END => return Step::EndOfData,
            // Header, indexes, attachments, metadata, statistics: not needed.
            _ => {}
        }
        Step::Continue
    }
}

impl Iterator for RecordingReader {
    type Item = Result<RecordedScan, FormatError>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.done {
            let step = match self.reader.next_event() {
                None => Step::EndOfData,
                Some(Err(e)) => Step::Broken(e.to_string()),
                Some(Ok(LinearReadEvent::ReadRequest(need))) => {
                    let read = loop {
                        match self.file.read(self.reader.insert(need)) {
                            Ok(n) => break n,
                            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                            Err(e) => {
                                self.done = true;
                                return Some(Err(FormatError::io(&self.path, e)));
                            }
                        }
                    };
                    self.reader.notify_read(read);
                    continue;
                }
                Some(Ok(LinearReadEvent::Record { opcode, data })) => {
                    // The record borrows the reader's buffer: copy out what outlives it.
                    let data = data.to_vec();
                    self.record(opcode, &data)
                }
            };
            match step {
                Step::Continue => {}
                Step::EndOfData => return self.end_of_data(),
                Step::Broken(what) => return Some(Err(self.broken(what))),
                Step::Scan(item) => return Some(item),
            }
        }
        None
    }
}

/// Writes scans with their ground probabilities as PointCloud2 messages.
pub struct RecordingWriter {
    path: PathBuf,
    writer: mcap::Writer<BufWriter<fs::File>>,
    schema: u16,
    channels: BTreeMap<String, u16>,
    sequence: u32,
}

impl std::fmt::Debug for RecordingWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RecordingWriter")
            .field("path", &self.path)
            .field("sequence", &self.sequence)
            .finish_non_exhaustive()
    }
}

impl RecordingWriter {
    /// Creates (or truncates) an MCAP file, zstd-compressed chunks.
    pub fn create(path: &Path) -> Result<Self, FormatError> {
        let file = fs::File::create(path).map_err(|e| FormatError::io(path, e))?;
        let err = |e: mcap::McapError| FormatError::malformed(path, format!("MCAP: {e}"));
        let mut writer = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("groundwork ", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))
            .map_err(err)?;
        let schema = writer
            .add_schema(SCHEMA_NAME, "ros2msg", SCHEMA_TEXT.as_bytes())
            .map_err(err)?;
        Ok(Self {
            path: path.to_path_buf(),
            writer,
            schema,
            channels: BTreeMap::new(),
            sequence: 0,
        })
    }

    /// Appends one scan on `topic` at `log_time_ns` (also its header stamp unless the scan
    /// carries one), `probabilities` one per point of `scan.points`.
    pub fn write(
        &mut self,
        topic: &str,
        scan: &Scan,
        probabilities: &[f32],
        log_time_ns: u64,
    ) -> Result<(), FormatError> {
        let err = |e: mcap::McapError| FormatError::malformed(&self.path, format!("MCAP: {e}"));
        let channel = match self.channels.get(topic) {
            Some(&c) => c,
            None => {
                let c = self
                    .writer
                    .add_channel(self.schema, topic, "cdr", &BTreeMap::new())
                    .map_err(err)?;
                self.channels.insert(topic.to_string(), c);
                c
            }
        };
        let frame = scan.frame_id.as_deref().unwrap_or("lidar");
        let data = pointcloud2::encode(
            scan,
            probabilities,
            scan.stamp_ns.unwrap_or(log_time_ns),
            frame,
        );
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: self.sequence,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        self.sequence = self.sequence.wrapping_add(1);
        self.writer
            .write_to_known_channel(&header, &data)
            .map_err(|e| FormatError::malformed(&self.path, format!("MCAP: {e}")))
    }

    /// Writes the summary and closes the file.
    pub fn finish(mut self) -> Result<(), FormatError> {
        self.writer
            .finish()
            .map_err(|e| FormatError::malformed(&self.path, format!("MCAP: {e}")))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use groundwork_core::Point;

    #[test]
    fn written_recordings_read_back_with_probabilities() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("out.mcap");
        let mut w = RecordingWriter::create(&p).unwrap();
        for k in 0..3u64 {
            let scan = Scan::dense(vec![Point::new(k as f32, 1.0, -1.0); 5]);
            w.write("/points/ground", &scan, &[0.25; 5], 1_000 + k)
                .unwrap();
        }
        w.finish().unwrap();
        let scans: Vec<_> = RecordingReader::open(&p, None, 100)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(scans.len(), 3);
        assert_eq!(scans[2].scan.points[0].x, 2.0);
        assert_eq!(scans[2].log_time_ns, 1_002);
        assert_eq!(scans[1].topic, "/points/ground");

        let e = RecordingReader::open(&p, Some("/nope"), 100)
            .unwrap()
            .find_map(Result::err)
            .unwrap()
            .to_string();
        assert!(
            e.contains("out.mcap") && e.contains("/points/ground"),
            "{e}"
        );
    }
}
