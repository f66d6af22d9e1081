//! What the machine and this process spent while a load test measured.
//!
//! Steal time: the share of the machine's CPU time that the hypervisor gave to other guests. On a
//! shared cloud host it can double a latency figure while nothing changed in the server or the client.
//! And the load generator's own CPU time per request, user and system: on a machine it shares with the
//! server, that much is taken from the server, and it shows what each call costs a client (a unary call
//! opens an HTTP/2 stream of its own, a stream's message does not).

use std::time::Duration;

/// Both readings at one moment.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Usage {
    machine: Option<CpuTimes>,
    process: Option<Duration>,
}

impl Usage {
    pub fn now() -> Self {
        Self {
            machine: CpuTimes::now(),
            process: process_cpu_time(),
        }
    }

    /// The steal percentage from `self` to `later` (see [`CpuTimes::steal_percent_until`]).
    pub fn steal_percent_until(&self, later: &Self) -> Option<f64> {
        self.machine?.steal_percent_until(&later.machine?)
    }

    /// This process's CPU time from `self` to `later`.
    pub fn process_time_until(&self, later: &Self) -> Option<Duration> {
        later.process?.checked_sub(self.process?)
    }
}

/// CPU time this process has used so far, all its threads, user and system.
fn process_cpu_time() -> Option<Duration> {
    #[cfg(target_os = "linux")]
    {
        let t = rustix::time::clock_gettime(rustix::time::ClockId::ProcessCPUTime);
        Some(Duration::new(
            u64::try_from(t.tv_sec).ok()?,
            u32::try_from(t.tv_nsec).ok()?,
        ))
    }
    #[cfg(not(target_os = "linux"))]
    None
}

/// CPU time since boot, summed over CPUs, from the first line of `/proc/stat` (Linux), in clock ticks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CpuTimes {
    total: u64,
    steal: u64,
}

impl CpuTimes {
    /// Now; `None` where `/proc/stat` cannot be read (not Linux) or has no steal field.
    pub fn now() -> Option<Self> {
        parse(&std::fs::read_to_string("/proc/stat").ok()?)
    }

    /// The percentage of the CPU time from `self` to `later` that was stolen; `None` when no time
    /// passed (or `later` is earlier).
    pub fn steal_percent_until(&self, later: &Self) -> Option<f64> {
        let total = later.total.checked_sub(self.total).filter(|&t| t > 0)?;
        let steal = later.steal.checked_sub(self.steal)?;
        Some(100.0 * steal as f64 / total as f64)
    }
}

/// `cpu  user nice system idle iowait irq softirq steal guest guest_nice`: the first eight fields are
/// all the time there is (guest time is counted in user time already).
fn parse(stat: &str) -> Option<CpuTimes> {
    let fields = stat.lines().next()?.strip_prefix("cpu ")?.split_whitespace();
    let ticks: Vec<u64> = fields.take(8).map(|f| f.parse().ok()).collect::<Option<_>>()?;
    Some(CpuTimes {
        total: ticks.iter().sum(),
        steal: *ticks.get(7)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steal_is_the_eighth_field_over_the_first_eight() {
        let before = parse("cpu  100 0 50 800 10 0 10 30 5 0\ncpu0 1 2 3\n").unwrap();
        let after = parse("cpu  200 0 70 1500 10 0 20 100 9 0\n").unwrap();
        // 100 + 20 + 700 + 10 + 70 = 900 ticks passed, 70 of them stolen.
        let percent = before.steal_percent_until(&after).unwrap();
        assert!((percent - 100.0 * 70.0 / 900.0).abs() < 1e-12, "{percent}");
        assert_eq!(after.steal_percent_until(&before), None);
        assert_eq!(before.steal_percent_until(&before), None);
    }

    #[test]
    fn a_stat_without_a_steal_field_is_none() {
        assert_eq!(parse("cpu  100 0 50 800\n"), None);
        assert_eq!(parse("intr 5\n"), None);
        assert_eq!(parse(""), None);
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn this_machine_reports_its_cpu_times_and_this_process_its_own() {
        let first = Usage::now();
        // Work for this thread; other tests' threads may add theirs, so only a lower bound holds.
        let mut spent = Duration::ZERO;
        while spent < Duration::from_millis(20) {
            std::hint::spin_loop();
            spent = first
                .process_time_until(&Usage::now())
                .expect("CLOCK_PROCESS_CPUTIME_ID");
        }
        let percent = first.steal_percent_until(&Usage::now()).expect("/proc/stat");
        assert!((0.0..=100.0).contains(&percent), "{percent}");
    }

    #[test]
    fn process_time_is_the_difference_and_none_when_unknown() {
        let at = |ms| Usage {
            machine: None,
            process: Some(Duration::from_millis(ms)),
        };
        assert_eq!(at(10).process_time_until(&at(25)), Some(Duration::from_millis(15)));
        assert_eq!(at(25).process_time_until(&at(10)), None);
        let unknown = Usage {
            machine: None,
            process: None,
        };
        assert_eq!(unknown.process_time_until(&at(10)), None);
        assert_eq!(at(10).steal_percent_until(&at(20)), None);
    }
}
