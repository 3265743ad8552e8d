//! Reads the messages of chosen topics from an MCAP file front to back, a record at a time, so
//! that a bag of any length is read in bounded memory (one record, or one decompressed chunk,
//! at a time; no record may exceed the configured size).

use std::collections::{HashMap, HashSet};
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};

use super::BagError;

/// A channel's schema as the file records it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Schema {
    /// e.g. `sensor_msgs/msg/Image`.
    pub name: String,
    /// e.g. `ros2msg`.
    pub encoding: String,
    /// The definition.
    pub data: Vec<u8>,
}

/// A topic as the file records it.
#[derive(Debug)]
pub struct Topic {
    /// The topic name.
    pub name: String,
    /// Its schema; `None` for a schemaless channel.
    pub schema: Option<Arc<Schema>>,
    /// e.g. `cdr`.
    pub message_encoding: String,
}

/// One message of a chosen topic.
#[derive(Debug, Clone)]
pub struct BagMessage {
    /// The topic it was published on.
    pub topic: Arc<Topic>,
    /// When it was logged, nanoseconds.
    pub log_time: u64,
    /// When it was published, nanoseconds.
    pub publish_time: u64,
    /// The encoded message.
    pub data: Vec<u8>,
}

/// Streams the messages of chosen topics out of an MCAP file.
pub struct BagReader {
    path: PathBuf,
    file: File,
    reader: LinearReader,
    wanted: HashSet<String>,
    schemas: HashMap<u16, Arc<Schema>>,
    topics: HashMap<u16, Arc<Topic>>,
    bytes_read: u64,
    bytes_total: u64,
    done: bool,
}

impl BagReader {
    /// Opens `path` to read the messages of `topics`; a record longer than `max_record_bytes`
    /// (a chunk: compressed or decompressed) is an error.
    pub fn open(
        path: &Path,
        topics: impl IntoIterator<Item = String>,
        max_record_bytes: usize,
    ) -> Result<Self, BagError> {
        let io = |source| BagError::Io {
            path: path.display().to_string(),
            source,
        };
        let file = File::open(path).map_err(io)?;
        let bytes_total = file.metadata().map_err(io)?.len();
        let options = LinearReaderOptions::default()
            .with_validate_chunk_crcs(true)
            .with_record_length_limit(max_record_bytes);
        Ok(Self {
            path: path.to_path_buf(),
            file,
            reader: LinearReader::new_with_options(options),
            wanted: topics.into_iter().collect(),
            schemas: HashMap::new(),
            topics: HashMap::new(),
            bytes_read: 0,
            bytes_total,
            done: false,
        })
    }

    /// Bytes of the file read so far, and its length.
    pub fn progress(&self) -> (u64, u64) {
        (self.bytes_read, self.bytes_total)
    }

    /// The topics whose channel records have been read so far (all of them, chosen or not).
    pub fn topics_seen(&self) -> impl Iterator<Item = &Topic> {
        self.topics.values().map(|t| t.as_ref())
    }

    fn container_error(&self, message: impl std::fmt::Display) -> BagError {
        BagError::Container {
            path: self.path.display().to_string(),
            offset: self.bytes_read,
            message: message.to_string(),
        }
    }

    /// The next message of a chosen topic; `None` after the file's end magic.
    pub fn next_message(&mut self) -> Option<Result<BagMessage, BagError>> {
        if self.done {
            return None;
        }
        let out = self.advance();
        if !matches!(out, Some(Ok(_))) {
            self.done = true;
        }
        out
    }

    fn advance(&mut self) -> Option<Result<BagMessage, BagError>> {
        loop {
            let (opcode, data) = match self.reader.next_event()? {
                Err(mcap::McapError::UnexpectedEof) => {
                    return Some(Err(self.container_error(
                        "the file ends inside a record: it is truncated (a recording that did \
                         not finish?)",
                    )))
                }
                Err(e) => return Some(Err(self.container_error(e))),
                Ok(LinearReadEvent::ReadRequest(need)) => {
                    let buf = self.reader.insert(need);
                    match self.file.read(buf) {
                        Ok(n) => {
                            self.bytes_read += n as u64;
                            self.reader.notify_read(n);
                        }
                        Err(source) => {
                            return Some(Err(BagError::Io {
                                path: self.path.display().to_string(),
                                source,
                            }))
                        }
                    }
                    continue;
                }
                Ok(LinearReadEvent::Record { opcode, data }) => (opcode, data),
            };
            let record = match mcap::parse_record(opcode, data) {
                Ok(r) => r,
                Err(e) => return Some(Err(self.container_error(e))),
            };
            match record {
                Record::Schema { header, data } => {
                    self.schemas.insert(
                        header.id,
                        Arc::new(Schema {
                            name: header.name,
                            encoding: header.encoding,
                            data: data.into_owned(),
                        }),
                    );
                }
                Record::Channel(c) => {
                    let schema = match c.schema_id {
                        0 => None,
                        id => match self.schemas.get(&id) {
                            Some(s) => Some(s.clone()),
                            None => {
                                return Some(Err(self.container_error(format!(
                                    "channel {} ({}) names schema {id}, which precedes no \
                                     channel record",
                                    c.id, c.topic
                                ))))
                            }
                        },
                    };
                    self.topics.insert(
                        c.id,
                        Arc::new(Topic {
                            name: c.topic,
                            schema,
                            message_encoding: c.message_encoding,
                        }),
                    );
                }
                Record::Message { header, data } => {
                    let Some(topic) = self.topics.get(&header.channel_id) else {
                        return Some(Err(self.container_error(format!(
                            "a message on channel {}, which no channel record introduced",
                            header.channel_id
                        ))));
                    };
                    if self.wanted.contains(&topic.name) {
                        return Some(Ok(BagMessage {
                            topic: topic.clone(),
                            log_time: header.log_time,
                            publish_time: header.publish_time,
                            data: data.into_owned(),
                        }));
                    }
                }
                _ => {}
            }
        }
    }
}

impl Iterator for BagReader {
    type Item = Result<BagMessage, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_message()
    }
}
