//! Recording what the server answered to MCAP, off the hot path.
//!
//! The service hands each exchange (request, answer, times) to [`Recorder::record`], which never
//! blocks: a bounded queue feeds a writer thread, and when the queue is full the exchange is dropped
//! and counted. The writer encodes protobuf messages with their schemas embedded, compresses chunks
//! with LZ4, finishes a chunk at least every second (so a hard kill loses at most that second),
//! rotates files by size and age, and writes the summary and indexes when closed.
//!
//! LZ4 rather than zstd: displacement fields are f32 noise to a compressor (zstd saved 12 %), and at
//! 1,000 requests/s zstd's cost on a 2-core machine tripled the server's p99 (0.69 → 3.2 ms) where LZ4
//! adds 0.2 ms.
//!
//! Channels: `/nak/requests` (nak.v1.PredictRequest), `/nak/responses` (nak.v1.PredictResponse, with
//! the displacement payload configured by [`Payload`]), `/nak/timing` (nak.v1.RecordedTiming) and
//! `/nak/surface` (foxglove.PointCloud: the deformed surface coloured by |u|, rate-limited). Log time
//! is the time the request was received; publish time, the time it was answered.

pub mod replay;
mod writer;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{SyncSender, TrySendError};
use std::sync::{Arc, Mutex, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime};

use crate::mesh::TetMesh;
use crate::proto::v1 as pb;

pub const REQUESTS: &str = "/nak/requests";
pub const RESPONSES: &str = "/nak/responses";
pub const TIMING: &str = "/nak/timing";
pub const SURFACE: &str = "/nak/surface";

/// How much of each answer's displacement field is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Payload {
    /// Every row the client received.
    Full,
    /// The surface nodes' rows only (with their ids), enough to replay and to render.
    #[default]
    Surface,
    /// No displacements: requests, timing and status only.
    None,
}

#[derive(Debug, Clone, PartialEq)]
pub struct RecordConfig {
    pub directory: PathBuf,
    pub payload: Payload,
    /// Start a new file after this many bytes.
    pub rotate_bytes: u64,
    /// Start a new file after this long.
    pub rotate_after: Duration,
    /// Exchanges waiting for the writer; beyond this they are dropped.
    pub queue: usize,
    /// Most point clouds per second on the Foxglove channel (0: none).
    pub scene_hz: f64,
}

impl RecordConfig {
    pub fn new(directory: PathBuf) -> Self {
        Self {
            directory,
            payload: Payload::Surface,
            rotate_bytes: 1 << 30,
            rotate_after: Duration::from_secs(3600),
            queue: 4096,
            scene_hz: 30.0,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: MCAP: {}", with_causes(source))]
    Mcap {
        path: String,
        #[source]
        source: mcap::McapError,
    },
    #[error("the recorder's writer thread panicked")]
    WriterPanicked,
}

/// An error and its causes, outermost first: mcap's I/O error alone says only "I/O error from
/// writing", not "No space left on device".
fn with_causes(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut cause = error.source();
    while let Some(e) = cause {
        text.push_str(&format!(": {e}"));
        cause = e.source();
    }
    text
}

/// One answered request.
#[derive(Debug, Clone)]
pub struct Exchange {
    pub received: SystemTime,
    pub answered: SystemTime,
    pub request: pb::PredictRequest,
    /// The answer, or the gRPC code and message it was refused with.
    pub response: Result<pb::PredictResponse, (i32, String)>,
}

/// Counters, shared with the writer thread.
#[derive(Debug, Default)]
pub struct Stats {
    pub recorded: AtomicU64,
    pub dropped: AtomicU64,
    pub files: AtomicU64,
    pub bytes: AtomicU64,
    /// Exchanges waiting in the queue for the writer.
    pub queued: AtomicU64,
    /// Why the writer stopped, once it has.
    pub stopped: OnceLock<String>,
}

pub struct Recorder {
    config: RecordConfig,
    queue: Mutex<Option<SyncSender<Exchange>>>,
    stats: Arc<Stats>,
    writer: Mutex<Option<JoinHandle<()>>>,
}

impl Recorder {
    /// Starts the writer thread; `metadata` goes into every file's metadata record `nak.server`.
    pub fn start(
        config: RecordConfig,
        mesh: Arc<TetMesh>,
        metadata: BTreeMap<String, String>,
    ) -> Result<Self, RecordError> {
        std::fs::create_dir_all(&config.directory).map_err(|source| RecordError::Io {
            path: config.directory.display().to_string(),
            source,
        })?;
        let (tx, rx) = std::sync::mpsc::sync_channel(config.queue);
        let stats = Arc::new(Stats::default());
        let mut writer = writer::Writer::new(config.clone(), mesh, metadata, stats.clone());
        // Open the first file now, so that a bad directory fails at start, not at the first request.
        writer.open()?;
        let handle = std::thread::Builder::new()
            .name("nak-recorder".into())
            .spawn(move || writer.run(rx))
            .map_err(|source| RecordError::Io {
                path: "recorder thread".into(),
                source,
            })?;
        Ok(Self {
            config,
            queue: Mutex::new(Some(tx)),
            stats,
            writer: Mutex::new(Some(handle)),
        })
    }

    /// Queues an exchange for writing; never blocks. A full queue drops it and counts the drop.
    pub fn record(&self, exchange: Exchange) {
        let Ok(queue) = self.queue.lock() else { return };
        let Some(tx) = queue.as_ref() else { return };
        // Counted before sending: the writer may take it (and count it off) before try_send returns.
        self.stats.queued.fetch_add(1, Ordering::Relaxed);
        match tx.try_send(exchange) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                self.stats.queued.fetch_sub(1, Ordering::Relaxed);
                self.stats.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    pub fn status(&self) -> pb::RecorderStatus {
        pb::RecorderStatus {
            enabled: true,
            directory: self.config.directory.display().to_string(),
            recorded: self.stats.recorded.load(Ordering::Relaxed),
            dropped: self.stats.dropped.load(Ordering::Relaxed),
            files: self.stats.files.load(Ordering::Relaxed),
            bytes: self.stats.bytes.load(Ordering::Relaxed),
            error: self.stats.stopped.get().cloned().unwrap_or_default(),
        }
    }

    pub fn dropped(&self) -> u64 {
        self.stats.dropped.load(Ordering::Relaxed)
    }

    /// Exchanges waiting for the writer now.
    pub fn queued(&self) -> u64 {
        self.stats.queued.load(Ordering::Relaxed)
    }

    /// The most exchanges the queue holds.
    pub fn capacity(&self) -> usize {
        self.config.queue
    }

    /// Stops accepting exchanges, writes what is queued, and finishes the file (summary, indexes). A
    /// write failure is not returned here: it stopped the recording when it happened, was logged then,
    /// and shows in [`Self::status`].
    pub fn close(&self) -> Result<(), RecordError> {
        if let Ok(mut queue) = self.queue.lock() {
            queue.take();
        }
        let handle = self.writer.lock().ok().and_then(|mut w| w.take());
        match handle {
            Some(h) => h.join().map_err(|_| RecordError::WriterPanicked),
            None => Ok(()),
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        if let Err(e) = self.close() {
            tracing::error!(error = %e, "recording not finished cleanly");
        }
    }
}

/// Nanoseconds since the Unix epoch, as MCAP log times are.
pub fn nanos(t: SystemTime) -> u64 {
    t.duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}
