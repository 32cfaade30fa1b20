//! rosbag2's SQLite storage (`.db3`, the default before ROS 2 Jazzy): its `topics` and
//! `messages` tables read as the channels and messages of a recording, one message at a
//! time, each checked against a size limit before its bytes are fetched.

use std::path::Path;

use rusqlite::{Connection, OpenFlags, OptionalExtension};

use crate::error::FormatError;

/// The first bytes of every SQLite 3 database.
pub const MAGIC: &[u8] = b"SQLite format 3\0";

/// A topic of the bag.
#[derive(Debug, Clone)]
pub struct Topic {
    /// rosbag2's id for it.
    pub id: u16,
    /// `/points`, …
    pub name: String,
    /// `sensor_msgs/msg/PointCloud2`, …
    pub type_name: String,
    /// `cdr` for ROS 2's own.
    pub serialization: String,
    /// The message definition, where the bag keeps one (rosbag2 from Iron on); empty else.
    pub definition: Vec<u8>,
}

/// A message row.
#[derive(Debug)]
pub struct Message {
    /// Its topic's id.
    pub topic_id: u16,
    /// Receive time, ns.
    pub timestamp_ns: u64,
    /// The serialized message, or why it was not fetched (too large).
    pub data: Result<Vec<u8>, FormatError>,
}

/// An open bag file, read in the order messages were stored.
pub struct Rosbag2Db {
    db: Connection,
    /// The last message row read.
    last_id: i64,
}

impl std::fmt::Debug for Rosbag2Db {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Rosbag2Db")
            .field("last_id", &self.last_id)
            .finish_non_exhaustive()
    }
}

fn malformed(path: &Path, what: impl std::fmt::Display) -> FormatError {
    FormatError::malformed(path, format!("rosbag2 SQLite: {what}"))
}

impl Rosbag2Db {
    /// Opens `path` read-only and lists its topics.
    pub fn open(path: &Path) -> Result<(Self, Vec<Topic>), FormatError> {
        let db = Connection::open_with_flags(
            path,
            OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .map_err(|e| malformed(path, e))?;
        let definitions = Self::definitions(&db).map_err(|e| malformed(path, e))?;
        let mut topics = Vec::new();
        {
            let mut query = db
                .prepare("SELECT id, name, type, serialization_format FROM topics ORDER BY id")
                .map_err(|e| malformed(path, format!("no topics table ({e})")))?;
            let rows = query
                .query_map([], |r| {
                    Ok((
                        r.get::<_, i64>(0)?,
                        r.get::<_, String>(1)?,
                        r.get::<_, String>(2)?,
                        r.get::<_, String>(3)?,
                    ))
                })
                .map_err(|e| malformed(path, e))?;
            for row in rows {
                let (id, name, type_name, serialization) = row.map_err(|e| malformed(path, e))?;
                let id = u16::try_from(id)
                    .map_err(|_| malformed(path, format!("topic {name} has id {id}")))?;
                let definition = definitions
                    .iter()
                    .find(|(t, _)| *t == type_name)
                    .map(|(_, d)| d.clone().into_bytes())
                    .unwrap_or_default();
                topics.push(Topic {
                    id,
                    name,
                    type_name,
                    serialization,
                    definition,
                });
            }
        }
        Ok((
            Self {
                db,
                last_id: i64::MIN,
            },
            topics,
        ))
    }

    /// The message definitions the bag keeps (rosbag2 from Iron on), by type.
    fn definitions(db: &Connection) -> rusqlite::Result<Vec<(String, String)>> {
        let has: bool = db.query_row(
            "SELECT count(*) > 0 FROM sqlite_master WHERE type = 'table' AND name = 'message_definitions'",
            [],
            |r| r.get(0),
        )?;
        if !has {
            return Ok(Vec::new());
        }
        let mut query =
            db.prepare("SELECT topic_type, encoded_message_definition FROM message_definitions")?;
        let rows = query.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?;
        rows.collect()
    }

    /// The next message in the order stored (which is the order received), its size
    /// checked against `limit` before its bytes are fetched.
    pub fn next(&mut self, path: &Path, limit: usize) -> Result<Option<Message>, FormatError> {
        let row = self
            .db
            .query_row(
                "SELECT id, topic_id, timestamp, length(data) FROM messages WHERE id > ?1 ORDER BY id LIMIT 1",
                [self.last_id],
                |r| Ok((r.get::<_, i64>(0)?, r.get::<_, i64>(1)?, r.get::<_, i64>(2)?, r.get::<_, i64>(3)?)),
            )
            .optional()
            .map_err(|e| malformed(path, e))?;
        let Some((id, topic_id, timestamp, len)) = row else {
            return Ok(None);
        };
        self.last_id = id;
        let at = |what: String| malformed(path, format!("message {id}: {what}"));
        let topic_id = u16::try_from(topic_id).map_err(|_| at(format!("topic id {topic_id}")))?;
        let timestamp_ns =
            u64::try_from(timestamp).map_err(|_| at(format!("timestamp {timestamp}")))?;
        let data = if usize::try_from(len).map_or(true, |n| n > limit) {
            Err(at(format!(
                "{len} bytes, more than the {limit} allowed for this max_points"
            )))
        } else {
            Ok(self
                .db
                .query_row("SELECT data FROM messages WHERE id = ?1", [id], |r| {
                    r.get(0)
                })
                .map_err(|e| at(e.to_string()))?)
        };
        Ok(Some(Message {
            topic_id,
            timestamp_ns,
            data,
        }))
    }
}
