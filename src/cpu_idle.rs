//! Keeping idle CPUs polling instead of halting, for as long as a [`PollingIdle`] is held.
//!
//! An answer crosses CPUs twice: the request wakes a server thread, the answer wakes the client.
//! When the CPU it wakes on has halted, the wake-up costs what halting costs to leave: in a virtual
//! machine with guest halt-polling off, an exit to the hypervisor and back, tens of microseconds
//! (docs/reports/latency.md measures it with a pipe round trip across CPUs and on one). Linux's CPU latency QoS lets a process ask that no CPU take longer than a bound to
//! wake; a bound of 0 leaves the cpuidle governors only their polling state, so an idle CPU spins
//! and a wake-up costs what a context switch does. The price is an idle CPU at full power: opt in
//! (`nak serve --poll-idle-cpus`) on machines that serve latency-critical clients.
//!
//! The request lasts as long as the file stays open; the kernel drops it when the process exits.

use std::fs::File;
use std::path::Path;

/// The kernel's interface to CPU latency QoS requests (Documentation/power/pm_qos_interface.rst).
pub const CPU_LATENCY_DEVICE: &str = "/dev/cpu_dma_latency";

#[derive(Debug, thiserror::Error)]
#[error(
    "cannot ask the kernel to keep idle CPUs polling through {device}: {source} \
     (it needs root or write access to that device; in a container, pass the device in)"
)]
pub struct PollingIdleError {
    device: String,
    #[source]
    source: std::io::Error,
}

/// A CPU latency QoS request of 0 µs, held until dropped.
#[derive(Debug)]
pub struct PollingIdle {
    _request: File,
}

impl PollingIdle {
    /// Asks, through [`CPU_LATENCY_DEVICE`], that idle CPUs wake at once.
    pub fn request() -> Result<Self, PollingIdleError> {
        Self::request_through(Path::new(CPU_LATENCY_DEVICE))
    }

    fn request_through(device: &Path) -> Result<Self, PollingIdleError> {
        use std::io::Write;
        let fail = |source| PollingIdleError {
            device: device.display().to_string(),
            source,
        };
        let mut request = std::fs::OpenOptions::new().write(true).open(device).map_err(fail)?;
        // The kernel reads a binary s32 in microseconds.
        request.write_all(&0i32.to_ne_bytes()).map_err(fail)?;
        Ok(Self { _request: request })
    }
}

/// The latency bound now in force over all requests, in µs (reading the device reports it).
pub fn current_bound_us() -> std::io::Result<i32> {
    let bytes = std::fs::read(CPU_LATENCY_DEVICE)?;
    let word: [u8; 4] = bytes
        .get(..4)
        .and_then(|b| b.try_into().ok())
        .ok_or_else(|| std::io::Error::other(format!("{CPU_LATENCY_DEVICE} answered {} bytes", bytes.len())))?;
    Ok(i32::from_ne_bytes(word))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_device_is_named_in_the_error() {
        let error = PollingIdle::request_through(Path::new("/nonexistent/cpu_dma_latency")).unwrap_err();
        let message = error.to_string();
        assert!(message.contains("/nonexistent/cpu_dma_latency"), "{message}");
        assert!(message.contains("root"), "{message}");
    }

    /// Where this process may make the request (root, as in CI), the bound in force is 0 µs while
    /// it is held; elsewhere the request must fail with the device named.
    #[test]
    fn the_request_sets_a_zero_bound_while_held() {
        match PollingIdle::request() {
            Ok(held) => {
                assert_eq!(current_bound_us().expect("readable"), 0);
                drop(held);
            }
            Err(error) => assert!(error.to_string().contains(CPU_LATENCY_DEVICE), "{error}"),
        }
    }
}
