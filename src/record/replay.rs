//! Reading recordings back: the exchanges of an MCAP file, complete or cut short by a hard kill.

use std::collections::BTreeMap;
use std::path::Path;

use mcap::read::Options;
use prost::Message;

use super::{REQUESTS, RESPONSES};
use crate::proto::v1 as pb;
use crate::serve::response_rows;

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
    let stream = mcap::MessageStream::new_with_options(&bytes, Options::IgnoreEndMagic.into()).map_err(|source| {
        ReadError::Mcap {
            path: origin.clone(),
            source,
        }
    })?;
    let mut exchanges: BTreeMap<u32, Recorded> = BTreeMap::new();
    let mut truncated = None;
    for message in stream {
        let message = match message {
            Ok(m) => m,
            Err(e) => {
                truncated = Some(e.to_string());
                break;
            }
        };
        let decode_error = |source| ReadError::Decode {
            path: origin.clone(),
            sequence: message.sequence,
            topic: message.channel.topic.clone(),
            source,
        };
        match message.channel.topic.as_str() {
            REQUESTS => {
                let request = pb::PredictRequest::decode(&message.data[..]).map_err(decode_error)?;
                exchanges.insert(
                    message.sequence,
                    Recorded {
                        log_time: message.log_time,
                        request,
                        response: None,
                    },
                );
            }
            RESPONSES => {
                let response = pb::PredictResponse::decode(&message.data[..]).map_err(decode_error)?;
                if let Some(e) = exchanges.get_mut(&message.sequence) {
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
