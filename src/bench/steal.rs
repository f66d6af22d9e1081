//! Steal time: the share of this machine's CPU time that the hypervisor gave to other guests. On a
//! shared cloud host it can double a latency figure while nothing changed in the server or the client,
//! so a load test says how much of it there was while it measured.

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
    fn this_machine_reports_its_cpu_times() {
        let first = CpuTimes::now().expect("/proc/stat");
        std::thread::sleep(std::time::Duration::from_millis(50));
        let percent = first.steal_percent_until(&CpuTimes::now().unwrap()).unwrap();
        assert!((0.0..=100.0).contains(&percent), "{percent}");
    }
}
