//! The recorder's writer thread: MCAP files, channels, rotation, chunk flushing.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant, SystemTime};

use bytes::Bytes;
use mcap::records::{MessageHeader, Metadata};
use prost::Message;

use super::{Exchange, Payload, REQUESTS, RESPONSES, RecordConfig, RecordError, SURFACE, Stats, TIMING, nanos};
use crate::mesh::TetMesh;
use crate::proto::foxglove;
use crate::proto::v1 as pb;
use crate::wire::{f32_bytes, response_rows};

/// A chunk is finished at least this often, bounding what a hard kill can lose.
const FLUSH_EVERY: Duration = Duration::from_secs(1);

struct OpenFile {
    path: PathBuf,
    mcap: mcap::Writer<BufWriter<File>>,
    opened: Instant,
    channels: Channels,
}

#[derive(Clone, Copy)]
struct Channels {
    requests: u16,
    responses: u16,
    timing: u16,
    surface: u16,
}

pub(super) struct Writer {
    config: RecordConfig,
    mesh: Arc<TetMesh>,
    metadata: BTreeMap<String, String>,
    stats: Arc<Stats>,
    file: Option<OpenFile>,
    sequence: u32,
    files_opened: u64,
    last_flush: Instant,
    last_scene: Option<Instant>,
}

impl Writer {
    pub(super) fn new(
        config: RecordConfig,
        mesh: Arc<TetMesh>,
        metadata: BTreeMap<String, String>,
        stats: Arc<Stats>,
    ) -> Self {
        Self {
            config,
            mesh,
            metadata,
            stats,
            file: None,
            sequence: 0,
            files_opened: 0,
            last_flush: Instant::now(),
            last_scene: None,
        }
    }

    fn mcap_error(path: &std::path::Path) -> impl Fn(mcap::McapError) -> RecordError + '_ {
        move |source| RecordError::Mcap {
            path: path.display().to_string(),
            source,
        }
    }

    /// Opens the next file: `nak-<unix ms>-<n>.mcap`, with schemas, channels and the metadata record.
    pub(super) fn open(&mut self) -> Result<(), RecordError> {
        let millis = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis());
        let path = self
            .config
            .directory
            .join(format!("nak-{millis}-{:04}.mcap", self.files_opened));
        let file = File::create(&path).map_err(|source| RecordError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let origin = path.clone();
        let error = Self::mcap_error(&origin);
        let mut mcap = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Lz4))
            .profile("")
            .library(format!("nak {}", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))
            .map_err(&error)?;
        let nak = crate::proto::v1::FILE_DESCRIPTOR_SET;
        let schema = |mcap: &mut mcap::Writer<_>, name: &str, fds: &[u8]| mcap.add_schema(name, "protobuf", fds);
        let request_schema = schema(&mut mcap, "nak.v1.PredictRequest", nak).map_err(&error)?;
        let response_schema = schema(&mut mcap, "nak.v1.PredictResponse", nak).map_err(&error)?;
        let timing_schema = schema(&mut mcap, "nak.v1.RecordedTiming", nak).map_err(&error)?;
        let cloud_schema = schema(&mut mcap, "foxglove.PointCloud", foxglove::FILE_DESCRIPTOR_SET).map_err(&error)?;
        let payload = format!("{:?}", self.config.payload).to_lowercase();
        let none = BTreeMap::new();
        let channels = Channels {
            requests: mcap
                .add_channel(request_schema, REQUESTS, "protobuf", &none)
                .map_err(&error)?,
            responses: mcap
                .add_channel(
                    response_schema,
                    RESPONSES,
                    "protobuf",
                    &BTreeMap::from([("payload".to_owned(), payload)]),
                )
                .map_err(&error)?,
            timing: mcap
                .add_channel(timing_schema, TIMING, "protobuf", &none)
                .map_err(&error)?,
            surface: mcap
                .add_channel(cloud_schema, SURFACE, "protobuf", &none)
                .map_err(&error)?,
        };
        mcap.write_metadata(&Metadata {
            name: "nak.server".into(),
            metadata: self.metadata.clone(),
        })
        .map_err(&error)?;
        tracing::info!(file = %path.display(), "recording");
        self.files_opened += 1;
        self.stats.files.store(self.files_opened, Ordering::Relaxed);
        self.file = Some(OpenFile {
            path,
            mcap,
            opened: Instant::now(),
            channels,
        });
        Ok(())
    }

    fn close_file(&mut self) -> Result<(), RecordError> {
        if let Some(mut file) = self.file.take() {
            file.mcap.finish().map_err(Self::mcap_error(&file.path))?;
        }
        Ok(())
    }

    /// Drains the queue until every sender is gone, then finishes the file. A failure (disk full,
    /// directory gone) stops recording, never serving: it is logged here, once, and kept for
    /// `GetStatus`; the exchanges queued after it are counted as dropped.
    pub(super) fn run(mut self, rx: Receiver<Exchange>) {
        if let Err(e) = self.drain(&rx) {
            tracing::error!(error = %e, "recording stopped; serving continues without it");
            let _ = self.stats.stopped.set(e.to_string());
            // What was queued is lost too; later exchanges find the queue closed and count themselves.
            let queued = rx.try_iter().count() as u64;
            self.stats.queued.fetch_sub(queued, Ordering::Relaxed);
            self.stats.dropped.fetch_add(queued, Ordering::Relaxed);
        }
    }

    fn drain(&mut self, rx: &Receiver<Exchange>) -> Result<(), RecordError> {
        let mut finished_bytes = 0u64;
        loop {
            match rx.recv_timeout(FLUSH_EVERY) {
                Ok(exchange) => {
                    self.stats.queued.fetch_sub(1, Ordering::Relaxed);
                    self.write(&exchange).inspect_err(|_| {
                        self.stats.dropped.fetch_add(1, Ordering::Relaxed);
                    })?
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
            if self.last_flush.elapsed() >= FLUSH_EVERY {
                self.last_flush = Instant::now();
                if let Some(file) = &mut self.file {
                    file.mcap.flush().map_err(Self::mcap_error(&file.path))?;
                    let len = std::fs::metadata(&file.path).map_or(0, |m| m.len());
                    self.stats.bytes.store(finished_bytes + len, Ordering::Relaxed);
                    let too_big = len >= self.config.rotate_bytes;
                    let too_old = file.opened.elapsed() >= self.config.rotate_after;
                    if too_big || too_old {
                        self.close_file()?;
                        finished_bytes += len;
                        self.open()?;
                    }
                }
            }
        }
        let current = self.file.as_ref().map(|f| f.path.clone());
        self.close_file()?;
        if let Some(path) = current {
            let len = std::fs::metadata(&path).map_or(0, |m| m.len());
            self.stats.bytes.store(finished_bytes + len, Ordering::Relaxed);
            tracing::info!(file = %path.display(), "recording finished");
        }
        Ok(())
    }

    fn write(&mut self, exchange: &Exchange) -> Result<(), RecordError> {
        if self.file.is_none() {
            self.open()?;
        }
        let sequence = self.sequence;
        self.sequence = self.sequence.wrapping_add(1);
        let log_time = nanos(exchange.received);
        let publish_time = nanos(exchange.answered);
        let scene_due = self.config.scene_hz > 0.0
            && self
                .last_scene
                .is_none_or(|t| t.elapsed().as_secs_f64() >= 1.0 / self.config.scene_hz);
        let mut messages: Vec<(u16, Vec<u8>)> = Vec::with_capacity(4);
        let Some(file) = &self.file else { return Ok(()) };
        let channels = file.channels;
        messages.push((channels.requests, exchange.request.encode_to_vec()));
        let timing = match &exchange.response {
            Ok(response) => {
                messages.push((channels.responses, self.trimmed(response).encode_to_vec()));
                if scene_due && let Some(cloud) = self.point_cloud(response, exchange.answered) {
                    messages.push((channels.surface, cloud.encode_to_vec()));
                    self.last_scene = Some(Instant::now());
                }
                pb::RecordedTiming {
                    sequence: response.sequence,
                    model: response.model.clone(),
                    timing: response.timing,
                    interaction_points: response.interaction_points,
                    status_code: response.error.as_ref().map_or(0, |e| e.code),
                    status_message: response.error.as_ref().map(|e| e.message.clone()).unwrap_or_default(),
                    node_count: response.node_count,
                }
            }
            Err((code, message)) => pb::RecordedTiming {
                sequence: exchange.request.sequence,
                model: exchange.request.model.clone(),
                status_code: *code,
                status_message: message.clone(),
                ..Default::default()
            },
        };
        messages.push((channels.timing, timing.encode_to_vec()));
        let Some(file) = &mut self.file else { return Ok(()) };
        let error = Self::mcap_error(&file.path);
        for (channel_id, data) in messages {
            let header = MessageHeader {
                channel_id,
                sequence,
                log_time,
                publish_time,
            };
            file.mcap.write_to_known_channel(&header, &data).map_err(&error)?;
        }
        self.stats.recorded.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }

    /// The response as recorded: whole, reduced to its surface rows, or without displacements.
    fn trimmed(&self, response: &pb::PredictResponse) -> pb::PredictResponse {
        let mut r = response.clone();
        match self.config.payload {
            Payload::Full => {}
            Payload::None => {
                r.displacements = Bytes::new();
                r.node_ids.clear();
                r.node_count = 0;
            }
            Payload::Surface => {
                let rows: Vec<(u32, [f32; 3])> = response_rows(response)
                    .filter(|(n, _)| self.mesh.is_surface[*n as usize])
                    .collect();
                r.node_ids = rows.iter().map(|(n, _)| *n).collect();
                r.node_count = rows.len() as u32;
                r.displacements = f32_bytes(rows.iter().flat_map(|(_, u)| *u).collect());
            }
        }
        r
    }

    /// The deformed surface as points (x, y, z, |u| in mm), for Foxglove's 3D panel.
    fn point_cloud(&self, response: &pb::PredictResponse, answered: SystemTime) -> Option<foxglove::PointCloud> {
        let mut data = Vec::new();
        for (n, u) in response_rows(response).filter(|(n, _)| self.mesh.is_surface[*n as usize]) {
            let p = self.mesh.positions[n as usize];
            for k in 0..3 {
                data.extend_from_slice(&(p[k] as f32 + u[k]).to_le_bytes());
            }
            let magnitude_mm = 1e3 * (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
            data.extend_from_slice(&magnitude_mm.to_le_bytes());
        }
        if data.is_empty() {
            return None;
        }
        let since_epoch = answered.duration_since(SystemTime::UNIX_EPOCH).unwrap_or_default();
        let field = |name: &str, offset: u32| foxglove::PackedElementField {
            name: name.into(),
            offset,
            r#type: foxglove::packed_element_field::NumericType::Float32 as i32,
        };
        Some(foxglove::PointCloud {
            timestamp: Some(prost_types::Timestamp {
                seconds: since_epoch.as_secs() as i64,
                nanos: since_epoch.subsec_nanos() as i32,
            }),
            frame_id: self.mesh.config.name.clone(),
            pose: Some(foxglove::Pose {
                position: Some(foxglove::Vector3::default()),
                orientation: Some(foxglove::Quaternion {
                    w: 1.0,
                    ..Default::default()
                }),
            }),
            point_stride: 16,
            fields: vec![
                field("x", 0),
                field("y", 4),
                field("z", 8),
                field("displacement_mm", 12),
            ],
            data: Bytes::from(data),
        })
    }
}
