//! Recordings (ROS 2 bags in rosbag2's MCAP or SQLite storage): PointCloud2 messages of one
//! topic read as a sequence of scans, streamed (a recording may be far larger than
//! memory), and results written back as PointCloud2 with a `ground_probability` field,
//! which Foxglove and rerun open as they are.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::io::{BufReader, BufWriter};
use std::path::{Path, PathBuf};

use std::io::{Read, Seek};

use mcap::records::op;
use mcap::sans_io::decompressor::{DecompressResult, Decompressor};
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use tracing::warn;
use zstd::zstd_safe::{DStream, InBuffer, OutBuffer, ResetDirective};

use crate::error::FormatError;
use crate::pointcloud2::{self, SCHEMA_NAME, SCHEMA_TEXT};
use crate::rosbag2::Rosbag2Db;
use crate::scan::Scan;
use crate::transform::{
    StaticTransform, TF_SCHEMA_NAME, TF_SCHEMA_TEXT, TF_STATIC_TOPIC, encode_static_transform,
};

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
    /// The message it was decoded from (CDR PointCloud2): a recording written from this
    /// one keeps every field of it.
    pub message: std::sync::Arc<[u8]>,
}

/// A channel as far as the reader needs it.
#[derive(Debug, Clone)]
struct ChannelInfo {
    topic: String,
    encoding: String,
    schema: Option<String>,
    schema_id: u16,
}

/// A schema record: its name, encoding and definition.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SchemaRecord {
    /// `sensor_msgs/msg/PointCloud2`, …
    pub name: String,
    /// `ros2msg`, `protobuf`, … (empty: none).
    pub encoding: String,
    /// The definition.
    pub data: Vec<u8>,
}

/// A message of a recording on a topic other than the scans read: what a recording written
/// from it passes through unchanged.
#[derive(Debug, Clone)]
pub struct OtherMessage {
    /// Its topic.
    pub topic: String,
    /// Its schema (None: schemaless).
    pub schema: Option<SchemaRecord>,
    /// Its channel's message encoding (`cdr`, `json`, …).
    pub encoding: String,
    /// Log time, ns.
    pub log_time_ns: u64,
    /// Publish time, ns.
    pub publish_time_ns: u64,
    /// The message, as recorded.
    pub data: Vec<u8>,
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
    source: Source,
    schemas: BTreeMap<u16, SchemaRecord>,
    channels: BTreeMap<u16, ChannelInfo>,
    topic: Option<String>,
    /// Reading the messages of every other topic instead of the scans of this one.
    others_of: Option<String>,
    /// Counting the scans' messages instead of decoding them.
    counting: bool,
    max_points: usize,
    next_index: usize,
    other_clouds: BTreeSet<String>,
    done: bool,
}

/// Where a recording's records come from.
enum Source {
    Mcap {
        file: BufReader<fs::File>,
        reader: LinearReader,
        /// Bytes of the file handed to the reader so far: where an error was met.
        offset: u64,
    },
    /// rosbag2's SQLite storage: its topics are the channels, each with its type as the
    /// schema.
    Rosbag2(Rosbag2Db),
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
        let (mut file, _) = crate::file::open_regular(path)?;
        let mut head = [0u8; 16];
        let n = crate::file::read_head(path, &mut file, &mut head)?;
        let (mut schemas, mut channels) = (BTreeMap::new(), BTreeMap::new());
        let source = if head[..n] == *crate::rosbag2::MAGIC {
            let (db, topics) = Rosbag2Db::open(path)?;
            for t in topics {
                channels.insert(
                    t.id,
                    ChannelInfo {
                        topic: t.name,
                        encoding: t.serialization,
                        schema: Some(t.type_name.clone()),
                        schema_id: t.id,
                    },
                );
                schemas.insert(
                    t.id,
                    SchemaRecord {
                        name: t.type_name,
                        encoding: "ros2msg".into(),
                        data: t.definition,
                    },
                );
            }
            Source::Rosbag2(db)
        } else {
            file.seek(std::io::SeekFrom::Start(0))
                .map_err(|e| FormatError::io(path, e))?;
            let options = LinearReaderOptions::default()
                .with_record_length_limit(Self::record_limit(max_points));
            let mut reader = LinearReader::new_with_options(options);
            reader
                .add_decompressor(BoundedZstd::new(Self::chunk_limit(max_points)))
                .map_err(|e| FormatError::malformed(path, format!("MCAP: {e}")))?;
            Source::Mcap {
                file: BufReader::new(file),
                reader,
                offset: 0,
            }
        };
        Ok(Self {
            path: path.to_path_buf(),
            source,
            schemas,
            channels,
            topic: topic.map(str::to_string),
            max_points,
            others_of: None,
            counting: false,
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

    /// The most a zstd chunk may unpack to for scans of at most `max_points` points (a
    /// chunk holds one scan or more; recorders close a chunk at 1 to 4 MiB): whatever a
    /// chunk's header declares, unpacking stops there with an error. Together with the
    /// ratio bound of [`MAX_ZSTD_RATIO`] it bounds the work a file can ask for by its size.
    pub fn chunk_limit(max_points: usize) -> usize {
        Self::record_limit(max_points)
            .saturating_mul(2)
            .saturating_add(64 << 20)
    }

    /// The topic being read, once known.
    pub fn topic(&self) -> Option<&str> {
        self.topic.as_deref()
    }

    fn broken(&mut self, what: impl std::fmt::Display) -> FormatError {
        self.done = true;
        let what = match &self.source {
            Source::Mcap { offset, .. } => {
                format!("MCAP: {what} (in the record read up to byte {offset})")
            }
            Source::Rosbag2(_) => format!("rosbag2 SQLite: {what}"),
        };
        FormatError::malformed(&self.path, what)
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

/// The most output a zstd chunk may produce per byte of its input (beyond a first MiB):
/// point clouds compress 2 to 10 times, a chunk of identical tiny messages a few hundred
/// times; a chunk claiming more is a decompression bomb (zstd turns 4 bytes into a 128 KiB
/// block of zeros), refused before it costs minutes of CPU. lz4 needs no such bound: its
/// format cannot expand more than 255 times.
pub const MAX_ZSTD_RATIO: u64 = 1024;

/// The zstd chunk decoder, with the work per chunk bounded: at most `limit` bytes out, and
/// at most [`MAX_ZSTD_RATIO`] bytes out per byte in. (The `mcap` reader already stops at
/// the chunk's declared uncompressed size; the declared size itself is what a bomb lies
/// about.)
struct BoundedZstd {
    stream: Option<DStream<'static>>,
    need: usize,
    limit: u64,
    consumed: u64,
    wrote: u64,
}

impl BoundedZstd {
    fn new(limit: usize) -> Self {
        Self {
            stream: None,
            need: 0,
            limit: limit as u64,
            consumed: 0,
            wrote: 0,
        }
    }
}

fn zstd_error(code: usize) -> mcap::McapError {
    mcap::McapError::DecompressionError(zstd::zstd_safe::get_error_name(code).into())
}

impl Decompressor for BoundedZstd {
    fn next_read_size(&self) -> usize {
        self.need
    }

    fn decompress(&mut self, src: &[u8], dst: &mut [u8]) -> mcap::McapResult<DecompressResult> {
        let stream = match &mut self.stream {
            Some(s) => s,
            None => {
                let mut s = DStream::create();
                s.init().map_err(zstd_error)?;
                self.stream.insert(s)
            }
        };
        let mut input = InBuffer::around(src);
        let mut output = OutBuffer::around(dst);
        self.need = stream
            .decompress_stream(&mut output, &mut input)
            .map_err(zstd_error)?;
        self.consumed += input.pos as u64;
        self.wrote += output.pos() as u64;
        if self.wrote > self.limit {
            return Err(mcap::McapError::DecompressionError(format!(
                "a zstd chunk unpacks to more than {} bytes, the limit for scans of this size (a decompression bomb, or sensor.max_points too small)",
                self.limit
            )));
        }
        if self.wrote > self.consumed.saturating_mul(MAX_ZSTD_RATIO) + (1 << 20) {
            return Err(mcap::McapError::DecompressionError(format!(
                "a zstd chunk unpacks {} bytes from {} (more than {MAX_ZSTD_RATIO}:1: a decompression bomb)",
                self.wrote, self.consumed
            )));
        }
        Ok(DecompressResult {
            consumed: input.pos,
            wrote: output.pos(),
        })
    }

    fn reset(&mut self) -> mcap::McapResult<()> {
        self.need = 0;
        self.consumed = 0;
        self.wrote = 0;
        if let Some(stream) = self.stream.as_mut() {
            stream
                .reset(ResetDirective::SessionOnly)
                .map_err(zstd_error)?;
        }
        Ok(())
    }

    fn name(&self) -> &'static str {
        "zstd"
    }
}

/// An MCAP error with its cause (the crate's I/O error says only "I/O error from
/// writing"; the disk being full is in its source).
fn mcap_error(path: &Path, e: &mcap::McapError) -> FormatError {
    use std::error::Error;
    match e.source() {
        Some(cause) => FormatError::malformed(path, format!("MCAP: {e}: {cause}")),
        None => FormatError::malformed(path, format!("MCAP: {e}")),
    }
}

/// What one record meant to the reader.
enum Step {
    Continue,
    EndOfData,
    Broken(String),
    Scan(Result<RecordedScan, FormatError>),
    Other(OtherMessage),
}

impl RecordingReader {
    fn record(&mut self, opcode: u8, data: &[u8]) -> Step {
        let mut f = Fields(data);
        match opcode {
            op::SCHEMA => {
                let parsed = (|| {
                    let id = f.u16()?;
                    let (name, encoding) = (f.string()?, f.string()?);
                    let n = f.u32()? as usize;
                    Some((id, name, encoding, f.take(n)?.to_vec()))
                })();
                let Some((id, name, encoding, data)) = parsed else {
                    return Step::Broken("malformed schema record".into());
                };
                self.schemas.insert(
                    id,
                    SchemaRecord {
                        name,
                        encoding,
                        data,
                    },
                );
            }
            op::CHANNEL => {
                let parsed = (|| {
                    let id = f.u16()?;
                    let schema = f.u16()?;
                    Some((id, schema, f.string()?, f.string()?))
                })();
                let Some((id, schema_id, topic, encoding)) = parsed else {
                    return Step::Broken("malformed channel record".into());
                };
                let schema = self.schemas.get(&schema_id).map(|s| s.name.clone());
                self.channels.insert(
                    id,
                    ChannelInfo {
                        topic,
                        encoding,
                        schema,
                        schema_id,
                    },
                );
            }
            op::MESSAGE => {
                let (Some(channel), Some(_sequence), Some(log_time), Some(publish)) =
                    (f.u16(), f.u32(), f.u64(), f.u64())
                else {
                    return Step::Broken("malformed message record".into());
                };
                return self.message(channel, log_time, publish, f.0);
            }
            op::DATA_END => return Step::EndOfData,
            // Header, indexes, attachments, metadata, statistics: not needed.
            _ => {}
        }
        Step::Continue
    }
}

impl RecordingReader {
    /// A message on `channel`: a scan of the topic read, another topic's message when
    /// those are wanted, or nothing.
    fn message(&mut self, channel: u16, log_time: u64, publish: u64, data: &[u8]) -> Step {
        let Some(ch) = self.channels.get(&channel) else {
            return Step::Broken(format!("message on unknown channel {channel}"));
        };
        if let Some(skip) = &self.others_of {
            if ch.topic == *skip {
                return Step::Continue;
            }
            return Step::Other(OtherMessage {
                topic: ch.topic.clone(),
                schema: self.schemas.get(&ch.schema_id).cloned(),
                encoding: ch.encoding.clone(),
                log_time_ns: log_time,
                publish_time_ns: publish,
                data: data.to_vec(),
            });
        }
        let is_cloud = ch.schema.as_deref() == Some(SCHEMA_NAME);
        let chosen = match &self.topic {
            Some(t) => *t == ch.topic,
            None => is_cloud,
        };
        if !chosen {
            if is_cloud && !self.counting && self.other_clouds.insert(ch.topic.clone()) {
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
        if self.counting {
            return Step::Continue;
        }
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
        Step::Scan(
            pointcloud2::decode(&label, data, self.max_points).map(|scan| RecordedScan {
                index,
                log_time_ns: log_time,
                topic: ch.topic,
                scan,
                message: data.into(),
            }),
        )
    }

    /// The next record that is not [`Step::Continue`]; an I/O error ends the stream.
    fn step(&mut self) -> Result<Step, FormatError> {
        loop {
            let step = match &mut self.source {
                Source::Rosbag2(db) => {
                    let limit = Self::record_limit(self.max_points);
                    match db.next(&self.path, limit) {
                        Err(e) => {
                            self.done = true;
                            return Err(e);
                        }
                        Ok(None) => Step::EndOfData,
                        Ok(Some(m)) => match m.data {
                            Ok(data) => {
                                self.message(m.topic_id, m.timestamp_ns, m.timestamp_ns, &data)
                            }
                            // Too large to fetch: a bad scan if it is one of the topic's.
                            Err(e) => {
                                match self.message(m.topic_id, m.timestamp_ns, m.timestamp_ns, &[])
                                {
                                    Step::Scan(_) => Step::Scan(Err(e)),
                                    other => other,
                                }
                            }
                        },
                    }
                }
                Source::Mcap {
                    file,
                    reader,
                    offset,
                } => match reader.next_event() {
                    None => Step::EndOfData,
                    Some(Err(e)) => Step::Broken(e.to_string()),
                    Some(Ok(LinearReadEvent::ReadRequest(need))) => {
                        let read = loop {
                            match file.read(reader.insert(need)) {
                                Ok(n) => break n,
                                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                                Err(e) => {
                                    self.done = true;
                                    return Err(FormatError::io(&self.path, e));
                                }
                            }
                        };
                        *offset += read as u64;
                        reader.notify_read(read);
                        continue;
                    }
                    Some(Ok(LinearReadEvent::Record { opcode, data })) => {
                        // The record borrows the reader's buffer: copy out what outlives it.
                        let data = data.to_vec();
                        self.record(opcode, &data)
                    }
                },
            };
            if !matches!(step, Step::Continue) {
                return Ok(step);
            }
        }
    }

    /// How many messages the scans' reader would give (the topic's, or the first
    /// PointCloud2 topic's), counted without decoding them: one pass over the file, so
    /// that a recording can be sampled over its whole length as a folder is.
    pub fn count(
        path: &Path,
        topic: Option<&str>,
        max_points: usize,
    ) -> Result<usize, FormatError> {
        let mut reader = Self::open(path, topic, max_points)?;
        reader.counting = true;
        while !reader.done {
            match reader.step()? {
                Step::EndOfData => reader.done = true,
                Step::Broken(what) => return Err(reader.broken(what)),
                Step::Continue | Step::Scan(_) | Step::Other(_) => {}
            }
        }
        Ok(reader.next_index)
    }

    /// The messages of `path` on every topic but `topic`, in the order recorded (with the
    /// same bounds as the scans' reader): what a recording written from this one passes
    /// through.
    pub fn others(
        path: &Path,
        topic: &str,
        max_points: usize,
    ) -> Result<OtherMessages, FormatError> {
        let mut reader = Self::open(path, Some(topic), max_points)?;
        reader.others_of = Some(topic.to_string());
        Ok(OtherMessages(reader))
    }
}

impl Iterator for RecordingReader {
    type Item = Result<RecordedScan, FormatError>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.done {
            match self.step() {
                Err(e) => return Some(Err(e)),
                Ok(Step::Continue | Step::Other(_)) => {}
                Ok(Step::EndOfData) => return self.end_of_data(),
                Ok(Step::Broken(what)) => return Some(Err(self.broken(what))),
                Ok(Step::Scan(item)) => return Some(item),
            }
        }
        None
    }
}

/// The messages of a recording on every topic but the scans' ([`RecordingReader::others`]).
#[derive(Debug)]
pub struct OtherMessages(RecordingReader);

impl Iterator for OtherMessages {
    type Item = Result<OtherMessage, FormatError>;

    fn next(&mut self) -> Option<Self::Item> {
        let r = &mut self.0;
        while !r.done {
            match r.step() {
                Err(e) => return Some(Err(e)),
                Ok(Step::Continue | Step::Scan(_)) => {}
                Ok(Step::EndOfData) => r.done = true,
                Ok(Step::Broken(what)) => return Some(Err(r.broken(what))),
                Ok(Step::Other(m)) => return Some(Ok(m)),
            }
        }
        None
    }
}

/// Writes scans with their ground probabilities as PointCloud2 messages.
///
/// The recording is written to `<path>.partial` and renamed to `path` by
/// [`RecordingWriter::finish`]: a run that fails (a full disk) or is dropped unfinished
/// removes the partial file and never leaves an unreadable recording under the final name.
pub struct RecordingWriter {
    path: PathBuf,
    partial: PathBuf,
    writer: Option<mcap::Writer<BufWriter<fs::File>>>,
    schema: u16,
    channels: BTreeMap<String, u16>,
    sequence: u32,
    /// The sensor's mount, written once per scan frame on `/tf_static`.
    mount: Option<StaticTransform>,
    /// Frames whose transform is written.
    placed: BTreeSet<String>,
    /// Scans written.
    scans: u64,
    /// Channels of messages passed through, by (topic, schema name, encoding).
    passed: BTreeMap<(String, String, String), u16>,
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
    /// Starts an MCAP file (zstd-compressed chunks) at `<path>.partial`; `path` itself is
    /// replaced only when [`RecordingWriter::finish`] succeeds.
    pub fn create(path: &Path) -> Result<Self, FormatError> {
        let partial = crate::file::partial_name(path);
        let file = fs::File::create(&partial).map_err(|e| FormatError::io(&partial, e))?;
        let err = |e: mcap::McapError| mcap_error(path, &e);
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
            partial,
            writer: Some(writer),
            schema,
            channels: BTreeMap::new(),
            sequence: 0,
            mount: None,
            placed: BTreeSet::new(),
            scans: 0,
            passed: BTreeMap::new(),
        })
    }

    /// Places every scan frame in `mount.parent` by the sensor's mount: a static transform
    /// on `/tf_static` before the first scan of each frame, so that viewers put the cloud
    /// on the ground frame without being told.
    pub fn set_mount(&mut self, mount: StaticTransform) {
        self.mount = Some(mount);
    }

    /// The channel of `topic` with schema `schema` (registered on first use).
    fn channel(&mut self, topic: &str, schema: u16) -> Result<u16, FormatError> {
        self.channel_encoded(topic, "cdr", |_| Ok(schema))
    }

    /// The channel of `topic` whose messages are in `encoding`, with the schema `schema`
    /// registers (asked only on first use).
    fn channel_encoded(
        &mut self,
        topic: &str,
        encoding: &str,
        schema: impl FnOnce(&mut mcap::Writer<BufWriter<fs::File>>) -> Result<u16, FormatError>,
    ) -> Result<u16, FormatError> {
        if let Some(&c) = self.channels.get(topic) {
            return Ok(c);
        }
        let Some(writer) = self.writer.as_mut() else {
            return Err(FormatError::malformed(&self.path, "MCAP: already finished"));
        };
        let schema = schema(writer)?;
        let c = writer
            .add_channel(schema, topic, encoding, &BTreeMap::new())
            .map_err(|e| mcap_error(&self.path, &e))?;
        self.channels.insert(topic.to_string(), c);
        Ok(c)
    }

    /// Appends one message of Foxglove's own schemas (`foxglove.SceneUpdate`, ...: protobuf)
    /// on `topic` at `log_time_ns`.
    pub fn write_foxglove<M: foxglove::Encode>(
        &mut self,
        topic: &str,
        message: &M,
        log_time_ns: u64,
    ) -> Result<(), FormatError> {
        let path = self.path.clone();
        let encoding = M::get_message_encoding();
        let channel = self.channel_encoded(topic, &encoding, |writer| {
            let schema = M::get_schema().ok_or_else(|| {
                FormatError::malformed(&path, format!("MCAP: {topic}: a message without a schema"))
            })?;
            writer
                .add_schema(&schema.name, &schema.encoding, &schema.data)
                .map_err(|e| mcap_error(&path, &e))
        })?;
        let mut data = Vec::with_capacity(message.encoded_len().unwrap_or(256));
        message.encode(&mut data).map_err(|e| {
            FormatError::malformed(&self.path, format!("MCAP: {topic}: cannot encode: {e}"))
        })?;
        self.write_message(channel, log_time_ns, &data)
    }

    /// A message of ours: published when logged.
    fn write_message(
        &mut self,
        channel: u16,
        log_time_ns: u64,
        data: &[u8],
    ) -> Result<(), FormatError> {
        self.write_record(channel, log_time_ns, log_time_ns, data)
    }

    fn write_record(
        &mut self,
        channel: u16,
        log_time_ns: u64,
        publish_time_ns: u64,
        data: &[u8],
    ) -> Result<(), FormatError> {
        let Some(writer) = self.writer.as_mut() else {
            return Err(FormatError::malformed(&self.path, "MCAP: already finished"));
        };
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: self.sequence,
            log_time: log_time_ns,
            publish_time: publish_time_ns,
        };
        self.sequence = self.sequence.wrapping_add(1);
        writer
            .write_to_known_channel(&header, data)
            .map_err(|e| mcap_error(&self.path, &e))
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
        let frame = scan
            .frame_id
            .as_deref()
            .unwrap_or(crate::transform::SENSOR_FRAME);
        let stamp = scan.stamp_ns.unwrap_or(log_time_ns);
        self.place(frame, stamp, log_time_ns)?;
        let channel = self.channel(topic, self.schema)?;
        let data = pointcloud2::encode(scan, probabilities, stamp, frame);
        self.write_message(channel, log_time_ns, &data)?;
        self.scans += 1;
        Ok(())
    }

    /// [`Self::write`] for a scan decoded from the PointCloud2 `message` (CDR): the cloud
    /// written is that message with every record and field as it was (rings, times, an
    /// organized layout, its byte order) and `ground_probability` appended. `label` names
    /// the message in errors.
    pub fn write_over(
        &mut self,
        topic: &str,
        label: &Path,
        message: &[u8],
        scan: &Scan,
        probabilities: &[f32],
        log_time_ns: u64,
    ) -> Result<(), FormatError> {
        let parsed = pointcloud2::parse(label, message)?;
        let cloud = parsed.cloud();
        let per_record = scan.expand(probabilities, 0.0);
        let out = pointcloud2::with_probability(label, &cloud, &per_record, per_record.len())?;
        let frame = cloud.frame_id;
        self.place(frame, cloud.stamp_ns().unwrap_or(log_time_ns), log_time_ns)?;
        let channel = self.channel(topic, self.schema)?;
        let data = pointcloud2::encode_data(&cloud, &out);
        self.write_message(channel, log_time_ns, &data)?;
        self.scans += 1;
        Ok(())
    }

    /// Passes a message of another recording through unchanged (its topic, schema and
    /// encoding; its own channel, apart from the scans' and the transforms' here).
    pub fn write_other(&mut self, m: &OtherMessage) -> Result<(), FormatError> {
        let key = (
            m.topic.clone(),
            m.schema
                .as_ref()
                .map(|s| s.name.clone())
                .unwrap_or_default(),
            m.encoding.clone(),
        );
        let channel = match self.passed.get(&key) {
            Some(&c) => c,
            None => {
                let path = self.path.clone();
                let Some(writer) = self.writer.as_mut() else {
                    return Err(FormatError::malformed(&path, "MCAP: already finished"));
                };
                let err = |e: mcap::McapError| mcap_error(&path, &e);
                let schema = match &m.schema {
                    Some(s) => writer
                        .add_schema(&s.name, &s.encoding, &s.data)
                        .map_err(err)?,
                    None => 0,
                };
                let c = writer
                    .add_channel(schema, &m.topic, &m.encoding, &BTreeMap::new())
                    .map_err(err)?;
                self.passed.insert(key, c);
                c
            }
        };
        self.write_record(channel, m.log_time_ns, m.publish_time_ns, &m.data)
    }

    /// Writes the mount's transform for `frame` before its first scan.
    fn place(&mut self, frame: &str, stamp_ns: u64, log_time_ns: u64) -> Result<(), FormatError> {
        if let Some(mount) = &self.mount
            && !self.placed.contains(frame)
        {
            let data = encode_static_transform(mount, frame, stamp_ns);
            let schema = self.tf_schema()?;
            let channel = self.channel(TF_STATIC_TOPIC, schema)?;
            self.write_message(channel, log_time_ns, &data)?;
            self.placed.insert(frame.to_string());
        }
        Ok(())
    }

    /// The TFMessage schema's id (registered on first use).
    fn tf_schema(&mut self) -> Result<u16, FormatError> {
        let Some(writer) = self.writer.as_mut() else {
            return Err(FormatError::malformed(&self.path, "MCAP: already finished"));
        };
        writer
            .add_schema(TF_SCHEMA_NAME, "ros2msg", TF_SCHEMA_TEXT.as_bytes())
            .map_err(|e| mcap_error(&self.path, &e))
    }

    /// [`Self::finish`] when at least one scan was written; otherwise the partial file is
    /// removed and whatever `path` held before (an earlier run's recording) is left as it
    /// was. Whether the recording was written.
    pub fn finish_unless_empty(self) -> Result<bool, FormatError> {
        if self.scans == 0 {
            return Ok(false);
        }
        self.finish().map(|()| true)
    }

    /// Writes the summary, flushes, and renames the file to its final name.
    pub fn finish(mut self) -> Result<(), FormatError> {
        let Some(mut writer) = self.writer.take() else {
            return Err(FormatError::malformed(&self.path, "MCAP: already finished"));
        };
        writer.finish().map_err(|e| mcap_error(&self.path, &e))?;
        let file = writer
            .into_inner()
            .into_inner()
            .map_err(|e| FormatError::io(&self.partial, e.into_error()))?;
        file.sync_all()
            .map_err(|e| FormatError::io(&self.partial, e))?;
        drop(file);
        fs::rename(&self.partial, &self.path).map_err(|e| FormatError::io(&self.path, e))
    }
}

impl Drop for RecordingWriter {
    fn drop(&mut self) {
        // Unfinished (an error, a panic): the partial recording is not a result.
        if let Some(writer) = self.writer.take() {
            drop(writer);
        }
        if fs::exists(&self.partial).unwrap_or(false) {
            let _ = fs::remove_file(&self.partial);
        }
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

        assert_eq!(RecordingReader::count(&p, None, 100).unwrap(), 3);
        assert_eq!(RecordingReader::count(&p, Some("/nope"), 100).unwrap(), 0);
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
