//! Reading recordings back: the exchanges of an MCAP file, complete or cut short by a hard kill.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use mcap::McapResult;
use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
use prost::Message as _;

use super::{REQUESTS, RESPONSES};
use crate::proto::v1 as pb;
use crate::wire::response_rows;

/// One recorded exchange: what was asked, when, and what was answered (if the answer was recorded).
#[derive(Debug, Clone, PartialEq)]
pub struct Recorded {
    pub log_time: u64,
    pub request: pb::PredictRequest,
    pub response: Option<pb::PredictResponse>,
}

/// What was read, and whether the file ended cleanly.
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    pub exchanges: Vec<Recorded>,
    /// Set when the file ends mid-record (a hard kill): what was read stops at the last complete chunk.
    pub truncated: Option<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: not an MCAP recording: {source}")]
    Mcap {
        path: String,
        #[source]
        source: mcap::McapError,
    },
    #[error("{path}: corrupt: {message}")]
    Corrupt { path: String, message: String },
    #[error("{path}: message {sequence} on {topic} does not decode: {source}")]
    Decode {
        path: String,
        sequence: u32,
        topic: String,
        #[source]
        source: prost::DecodeError,
    },
}

/// Reads every complete exchange of `path`, tolerating a file that a hard kill left without its
/// summary and footer.
pub fn read(path: &Path) -> Result<Recording, ReadError> {
    let origin = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| ReadError::Io {
        path: origin.clone(),
        source,
    })?;
    read_bytes(&bytes, &origin)
}

/// The longest record read, 256 MiB: far beyond any exchange nak records (a full answer on a
/// million-node mesh is 12 MB), and a bound that mcap's own message stream lacks: inside a chunk it
/// reserves whatever length a record claims, so a corrupt length aborted the process on allocation
/// (found by fuzzing: 261 GB).
const MAX_RECORD_BYTES: usize = 1 << 28;

/// The records of an MCAP file, chunks unpacked, each at most [`MAX_RECORD_BYTES`] long.
struct Records<'a> {
    reader: LinearReader,
    rest: &'a [u8],
}

impl<'a> Records<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        let options = LinearReaderOptions::default()
            .with_skip_end_magic(true)
            .with_record_length_limit(MAX_RECORD_BYTES);
        Self {
            reader: LinearReader::new_with_options(options),
            rest: bytes,
        }
    }
}

impl Iterator for Records<'_> {
    type Item = McapResult<Record<'static>>;

    fn next(&mut self) -> Option<Self::Item> {
        while let Some(event) = self.reader.next_event() {
            match event {
                Ok(LinearReadEvent::ReadRequest(wanted)) => {
                    let n = wanted.min(self.rest.len());
                    self.reader.insert(n).copy_from_slice(&self.rest[..n]);
                    self.reader.notify_read(n);
                    self.rest = &self.rest[n..];
                }
                Ok(LinearReadEvent::Record { data, opcode }) => {
                    return Some(mcap::parse_record(opcode, data).map(Record::into_owned));
                }
                Err(e) => return Some(Err(e)),
            }
        }
        None
    }
}

/// [`read`] for a recording already in memory; `origin` names it in errors.
pub fn read_bytes(bytes: &[u8], origin: &str) -> Result<Recording, ReadError> {
    let origin = origin.to_owned();
    // mcap's reader panics on some malformed files (found by fuzzing: a record that runs past the
    // end of an uncompressed chunk overflows a subtraction; a record shorter than its fields indexes
    // past its end): such a file is refused here rather than taking the process down.
    std::panic::catch_unwind(|| read_records(bytes, &origin)).unwrap_or_else(|_| {
        Err(ReadError::Corrupt {
            path: origin.clone(),
            message: "malformed records (the MCAP reader gave up on them)".into(),
        })
    })
}

fn read_records(bytes: &[u8], origin: &str) -> Result<Recording, ReadError> {
    let origin = origin.to_owned();
    let mut topics: HashMap<u16, String> = HashMap::new();
    let mut exchanges: BTreeMap<u32, Recorded> = BTreeMap::new();
    let mut truncated = None;
    for (index, record) in Records::new(bytes).enumerate() {
        let record = match record {
            Ok(r) => r,
            // Not even a header: this is not a recording.
            Err(source) if index == 0 => {
                return Err(ReadError::Mcap {
                    path: origin.clone(),
                    source,
                });
            }
            Err(e) => {
                truncated = Some(e.to_string());
                break;
            }
        };
        let (header, data) = match record {
            Record::Channel(channel) => {
                topics.insert(channel.id, channel.topic);
                continue;
            }
            Record::Message { header, data } => (header, data),
            // The summary after it repeats what was read; a file cut short has none.
            Record::DataEnd(_) => break,
            _ => continue,
        };
        let topic = topics.get(&header.channel_id).map_or("", String::as_str);
        let decode_error = |source| ReadError::Decode {
            path: origin.clone(),
            sequence: header.sequence,
            topic: topic.to_owned(),
            source,
        };
        match topic {
            REQUESTS => {
                let request = pb::PredictRequest::decode(&data[..]).map_err(decode_error)?;
                exchanges.insert(
                    header.sequence,
                    Recorded {
                        log_time: header.log_time,
                        request,
                        response: None,
                    },
                );
            }
            RESPONSES => {
                let response = pb::PredictResponse::decode(&data[..]).map_err(decode_error)?;
                if let Some(e) = exchanges.get_mut(&header.sequence) {
                    e.response = Some(response);
                }
            }
            _ => {}
        }
    }
    let mut exchanges: Vec<Recorded> = exchanges.into_values().collect();
    exchanges.sort_by_key(|e| e.log_time);
    Ok(Recording { exchanges, truncated })
}

/// Largest difference between two answers over the rows the recorded one holds (metres).
pub fn largest_difference(recorded: &pb::PredictResponse, replayed: &pb::PredictResponse) -> Option<f32> {
    let new: BTreeMap<u32, [f32; 3]> = response_rows(replayed).collect();
    let old: Vec<(u32, [f32; 3])> = response_rows(recorded).collect();
    if old.is_empty() {
        return None;
    }
    let mut largest = 0.0f32;
    for (n, a) in &old {
        let b = new.get(n)?;
        for k in 0..3 {
            largest = largest.max((a[k] - b[k]).abs());
        }
    }
    Some(largest)
}
