//! A rosbag2 recording read message by message: an MCAP file (the `mcap`
//! crate), a sqlite3 `.db3` file (rosbag2's older default storage, read
//! with `rusqlite`), or a bag directory holding either (its split files in
//! name order). Only what the importer needs: topic, type, receive time and
//! the serialized bytes.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use omniscan_core::CoreError;

use crate::RosError;

/// One serialized message.
#[derive(Debug, Clone, Copy)]
pub struct BagMessage<'a> {
    pub topic: &'a str,
    /// The ROS type, e.g. `sensor_msgs/msg/Image`.
    pub type_name: &'a str,
    /// When the recorder received it, nanoseconds (rosbag2's timestamp,
    /// MCAP's `log_time`).
    pub log_time_ns: i64,
    pub data: &'a [u8],
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Storage {
    Mcap,
    Sqlite,
}

/// A recording's storage files.
#[derive(Debug, Clone)]
pub struct Bag {
    pub path: PathBuf,
    files: Vec<(PathBuf, Storage)>,
}

fn storage_of(path: &Path) -> Option<Storage> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("mcap") => Some(Storage::Mcap),
        Some("db3") => Some(Storage::Sqlite),
        _ => None,
    }
}

impl Bag {
    /// The bag at `path`: a `.mcap` or `.db3` file, or a directory with them.
    pub fn open(path: &Path) -> Result<Bag, RosError> {
        let meta = std::fs::metadata(path).map_err(|e| CoreError::io(path, e))?;
        let files = if meta.is_dir() {
            let mut files: Vec<(PathBuf, Storage)> = std::fs::read_dir(path)
                .map_err(|e| CoreError::io(path, e))?
                .filter_map(|entry| entry.ok().map(|e| e.path()))
                .filter_map(|p| storage_of(&p).map(|s| (p, s)))
                .collect();
            files.sort_by(|a, b| a.0.cmp(&b.0));
            files
        } else {
            let storage = storage_of(path).ok_or_else(|| {
                RosError::bag(
                    path,
                    "is neither an .mcap nor a .db3 file, nor a bag directory",
                )
            })?;
            vec![(path.to_path_buf(), storage)]
        };
        if files.is_empty() {
            return Err(RosError::bag(
                path,
                "holds no .mcap or .db3 file; is it a rosbag2 directory?",
            ));
        }
        Ok(Bag {
            path: path.to_path_buf(),
            files,
        })
    }

    /// Calls `visit` with every message whose topic `wanted` accepts, file
    /// by file in the order stored; returns every topic of the bag with its
    /// type (for errors that say what the bag has instead).
    pub fn for_each(
        &self,
        wanted: &dyn Fn(&str) -> bool,
        visit: &mut dyn FnMut(BagMessage) -> Result<(), RosError>,
    ) -> Result<BTreeMap<String, String>, RosError> {
        let mut topics = BTreeMap::new();
        for (file, storage) in &self.files {
            match storage {
                Storage::Mcap => read_mcap(file, wanted, visit, &mut topics)?,
                Storage::Sqlite => read_sqlite(file, wanted, visit, &mut topics)?,
            }
        }
        Ok(topics)
    }
}

fn read_mcap(
    path: &Path,
    wanted: &dyn Fn(&str) -> bool,
    visit: &mut dyn FnMut(BagMessage) -> Result<(), RosError>,
    topics: &mut BTreeMap<String, String>,
) -> Result<(), RosError> {
    let file = std::fs::File::open(path).map_err(|e| CoreError::io(path, e))?;
    for message in mcap::io::MessageReader::new(std::io::BufReader::new(file)) {
        let message =
            message.map_err(|e| RosError::bag(path, format!("not a readable MCAP file: {e}")))?;
        let channel = &message.channel;
        let type_name = channel
            .schema
            .as_ref()
            .map(|s| s.name.clone())
            .unwrap_or_default();
        topics
            .entry(channel.topic.clone())
            .or_insert_with(|| type_name.clone());
        if !wanted(&channel.topic) {
            continue;
        }
        if channel.message_encoding != "cdr" {
            return Err(RosError::bag(
                path,
                format!(
                    "topic {} is encoded as `{}`; ROS 2 bags store CDR",
                    channel.topic, channel.message_encoding
                ),
            ));
        }
        visit(BagMessage {
            topic: &channel.topic,
            type_name: &type_name,
            log_time_ns: i64::try_from(message.log_time).unwrap_or(i64::MAX),
            data: &message.data,
        })?;
    }
    Ok(())
}

fn read_sqlite(
    path: &Path,
    wanted: &dyn Fn(&str) -> bool,
    visit: &mut dyn FnMut(BagMessage) -> Result<(), RosError>,
    topics: &mut BTreeMap<String, String>,
) -> Result<(), RosError> {
    let sql = |e: rusqlite::Error| RosError::bag(path, format!("not a rosbag2 sqlite3 file: {e}"));
    let db =
        rusqlite::Connection::open_with_flags(path, rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY)
            .map_err(sql)?;
    let mut by_id: BTreeMap<i64, (String, String)> = BTreeMap::new();
    {
        let mut statement = db
            .prepare("SELECT id, name, type, serialization_format FROM topics")
            .map_err(sql)?;
        let mut rows = statement.query([]).map_err(sql)?;
        while let Some(row) = rows.next().map_err(sql)? {
            let (id, name, type_name, format): (i64, String, String, String) = (
                row.get(0).map_err(sql)?,
                row.get(1).map_err(sql)?,
                row.get(2).map_err(sql)?,
                row.get(3).map_err(sql)?,
            );
            if format != "cdr" && wanted(&name) {
                return Err(RosError::bag(
                    path,
                    format!("topic {name} is serialized as `{format}`; ROS 2 bags store CDR"),
                ));
            }
            topics
                .entry(name.clone())
                .or_insert_with(|| type_name.clone());
            by_id.insert(id, (name, type_name));
        }
    }
    let mut statement = db
        .prepare("SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp, id")
        .map_err(sql)?;
    let mut rows = statement.query([]).map_err(sql)?;
    while let Some(row) = rows.next().map_err(sql)? {
        let topic_id: i64 = row.get(0).map_err(sql)?;
        let Some((topic, type_name)) = by_id.get(&topic_id) else {
            return Err(RosError::bag(
                path,
                format!("a message names topic id {topic_id}, which the topics table lacks"),
            ));
        };
        if !wanted(topic) {
            continue;
        }
        let log_time_ns: i64 = row.get(1).map_err(sql)?;
        let data = row.get_ref(2).map_err(sql)?.as_blob().map_err(|e| {
            RosError::bag(path, format!("a message on {topic} has no data blob: {e}"))
        })?;
        visit(BagMessage {
            topic,
            type_name,
            log_time_ns,
            data,
        })?;
    }
    Ok(())
}
