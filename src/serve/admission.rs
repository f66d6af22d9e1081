//! Admission control and deadlines: a bound on the requests being answered (from their arrival,
//! [`super::arrival`], until their answer, whether computed on the thread that read them or on the
//! compute pool), so that a burst is refused at once instead of growing everyone's latency, and the
//! gRPC deadline of each call, so that no core computes an answer nobody will read.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use tonic::Status;
use tonic::metadata::MetadataMap;

/// Requests admitted per compute thread by default. Each waits behind at most this many others per
/// core: the Kelvinlet prior on the phantom costs ~0.2 ms, so an admitted request waits ~1 ms at
/// most (docs/operations.md, admission control).
pub const PER_THREAD: usize = 4;

/// How much before a call's deadline nak gives up on it, at most (see [`deadline`]).
/// 10 ms: with 5, tonic's own timer still won now and then on a busy two-core virtual machine
/// (tests/admission.rs, 1 run in 10, debug build).
pub const DEADLINE_MARGIN: Duration = Duration::from_millis(10);

/// Counts what admission control did since start.
#[derive(Debug, Default)]
pub struct Admission {
    limit: usize,
    admitted: AtomicUsize,
    refused: AtomicU64,
    expired: AtomicU64,
    abandoned: AtomicU64,
}

/// A place in the compute pool; dropping it frees the place.
#[derive(Debug)]
pub struct Permit(Arc<Admission>);

impl Drop for Permit {
    fn drop(&mut self) {
        self.0.admitted.fetch_sub(1, Ordering::AcqRel);
    }
}

impl Admission {
    /// At most `limit` requests admitted at once (at least one).
    pub fn new(limit: usize) -> Arc<Self> {
        Arc::new(Self {
            limit: limit.max(1),
            ..Self::default()
        })
    }

    /// Requests holding a place now.
    pub fn in_flight(&self) -> usize {
        self.admitted.load(Ordering::Acquire)
    }

    pub fn limit(&self) -> usize {
        self.limit
    }

    /// A place for one more request, or `None` (counted) when every place is taken.
    pub fn try_admit(self: &Arc<Self>) -> Option<Permit> {
        let taken = self.admitted.fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
            (n < self.limit).then_some(n + 1)
        });
        match taken {
            Ok(_) => Some(Permit(self.clone())),
            Err(_) => {
                self.refused.fetch_add(1, Ordering::Relaxed);
                None
            }
        }
    }

    /// The refusal of a request beyond the bound.
    pub fn at_capacity(&self) -> Status {
        Status::resource_exhausted(format!(
            "the server is at capacity: {} requests are being computed or waiting (--max-in-flight); retry shortly",
            self.limit
        ))
    }

    /// A request answered DEADLINE_EXCEEDED.
    pub fn count_expired(&self) {
        self.expired.fetch_add(1, Ordering::Relaxed);
    }

    /// A request the compute pool reached after its caller had gone (cancelled or timed out) or its
    /// deadline had passed, and did not compute.
    pub fn count_abandoned(&self) {
        self.abandoned.fetch_add(1, Ordering::Relaxed);
    }

    pub fn status(&self) -> crate::proto::v1::AdmissionStatus {
        crate::proto::v1::AdmissionStatus {
            max_in_flight: self.limit as u64,
            in_flight: self.admitted.load(Ordering::Acquire) as u64,
            refused: self.refused.load(Ordering::Relaxed),
            expired: self.expired.load(Ordering::Relaxed),
            abandoned: self.abandoned.load(Ordering::Relaxed),
        }
    }
}

/// When to give up on a call with a `grpc-timeout` header, measured from `received`.
///
/// The client times the call too, from before it was sent, and so does tonic's server layer, which
/// answers CANCELLED when its timer fires first (timers tick in whole milliseconds). nak gives up a
/// little earlier, a quarter of the timeout and at most [`DEADLINE_MARGIN`], so that its
/// DEADLINE_EXCEEDED reaches the client before either: an answer that late would be useless anyway.
pub fn deadline(metadata: &MetadataMap, received: Instant) -> Option<Instant> {
    let timeout = parse_grpc_timeout(metadata.get("grpc-timeout")?.to_str().ok()?)?;
    let margin = (timeout / 4).min(DEADLINE_MARGIN);
    Some(received + (timeout - margin))
}

/// `grpc-timeout`: at most 8 digits and a unit (H, M, S, m, u, n), per the gRPC HTTP/2 protocol.
fn parse_grpc_timeout(value: &str) -> Option<Duration> {
    let (digits, unit) = value.split_at(value.len().checked_sub(1)?);
    if digits.is_empty() || digits.len() > 8 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n * 3600),
        "M" => Duration::from_secs(n * 60),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn places_are_taken_refused_and_freed() {
        let admission = Admission::new(2);
        let (a, b) = (admission.try_admit(), admission.try_admit());
        assert!(a.is_some() && b.is_some());
        assert!(admission.try_admit().is_none());
        drop(a);
        let c = admission.try_admit();
        assert!(c.is_some());
        let status = admission.status();
        assert_eq!((status.in_flight, status.refused, status.max_in_flight), (2, 1, 2));
        drop((b, c));
        assert_eq!(admission.status().in_flight, 0);
    }

    #[test]
    fn grpc_timeouts_parse_as_the_protocol_writes_them() {
        assert_eq!(parse_grpc_timeout("5m"), Some(Duration::from_millis(5)));
        assert_eq!(parse_grpc_timeout("2S"), Some(Duration::from_secs(2)));
        assert_eq!(parse_grpc_timeout("1H"), Some(Duration::from_secs(3600)));
        assert_eq!(parse_grpc_timeout("250u"), Some(Duration::from_micros(250)));
        assert_eq!(parse_grpc_timeout("99999999n"), Some(Duration::from_nanos(99_999_999)));
        for bad in ["", "m", "123456789m", "5x", "-5m", "5 m"] {
            assert_eq!(parse_grpc_timeout(bad), None, "{bad:?}");
        }
        let mut metadata = MetadataMap::new();
        let now = Instant::now();
        assert_eq!(deadline(&metadata, now), None);
        metadata.insert("grpc-timeout", "100m".parse().unwrap());
        assert_eq!(deadline(&metadata, now), Some(now + Duration::from_millis(90)));
        metadata.insert("grpc-timeout", "2m".parse().unwrap());
        assert_eq!(deadline(&metadata, now), Some(now + Duration::from_micros(1500)));
    }
}
