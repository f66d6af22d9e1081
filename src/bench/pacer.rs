//! Waking when an open-loop request is due, to within microseconds, on the load generator's own
//! thread.
//!
//! tokio's timers tick in whole milliseconds, which would add up to 1 ms of the generator's own
//! lateness to every open-loop latency. A thread sleeping with `nanosleep` is late by the kernel's
//! timer slack (50 µs by default) and must then wake the runtime's thread, another 15–40 µs on a
//! small virtual machine. On Linux a `timerfd` in the runtime's own epoll set has neither delay: the
//! hrtimer behind it fires without slack on the thread that sends. Waking that thread from an idle
//! virtual CPU still takes tens of µs, so the timer fires a little early and the rest is spun.

use std::io;
use std::time::Duration;

use tokio::time::Instant;

pub struct Pacer {
    #[cfg(target_os = "linux")]
    timer: tokio::io::unix::AsyncFd<std::os::fd::OwnedFd>,
}

#[cfg(target_os = "linux")]
impl Pacer {
    pub fn new() -> io::Result<Self> {
        use rustix::time::{TimerfdClockId, TimerfdFlags, timerfd_create};
        let fd = timerfd_create(
            TimerfdClockId::Monotonic,
            TimerfdFlags::NONBLOCK | TimerfdFlags::CLOEXEC,
        )?;
        // SAFETY: `fd` is an open timerfd that the AsyncFd owns from here on, so it stays open and
        // the same descriptor until the AsyncFd is dropped.
        let timer = unsafe { tokio::io::unix::AsyncFd::register_with_interest(fd, tokio::io::Interest::READABLE) }
            .map_err(io::Error::from)?;
        Ok(Self { timer })
    }

    /// Returns at `due`, or at once if it has passed: the timer fires `early` before, and the rest
    /// is spun on this thread.
    pub async fn until(&mut self, due: Instant, early: Duration) -> io::Result<()> {
        self.sleep_until(due.checked_sub(early).unwrap_or(due)).await?;
        while Instant::now() < due {
            std::hint::spin_loop();
        }
        Ok(())
    }

    async fn sleep_until(&mut self, due: Instant) -> io::Result<()> {
        use rustix::time::{Itimerspec, TimerfdTimerFlags, Timespec, timerfd_settime};
        let Some(wait) = due.checked_duration_since(Instant::now()).filter(|w| !w.is_zero()) else {
            return Ok(());
        };
        let once = Itimerspec {
            it_interval: Timespec { tv_sec: 0, tv_nsec: 0 },
            it_value: Timespec {
                tv_sec: wait.as_secs() as i64,
                tv_nsec: i64::from(wait.subsec_nanos()),
            },
        };
        timerfd_settime(self.timer.get_ref(), TimerfdTimerFlags::empty(), &once)?;
        loop {
            let mut ready = self.timer.readable().await?;
            // The timer holds an 8-byte expiry count; reading it re-arms readiness.
            match ready.try_io(|fd| rustix::io::read(fd.get_ref(), &mut [0u8; 8]).map_err(io::Error::from)) {
                Ok(result) => return result.map(|_| ()),
                Err(_would_block) => continue,
            }
        }
    }
}

#[cfg(not(target_os = "linux"))]
impl Pacer {
    pub fn new() -> io::Result<Self> {
        Ok(Self {})
    }

    /// Returns at `due` (to tokio's millisecond), or at once if it has passed.
    pub async fn until(&mut self, due: Instant, _early: Duration) -> io::Result<()> {
        tokio::time::sleep_until(due).await;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Never early, whether the due time is ahead, just past or long past.
    #[tokio::test]
    async fn returns_no_earlier_than_the_due_time() {
        let mut pacer = Pacer::new().unwrap();
        let now = Instant::now();
        for offset_us in [300i64, 2_000, 0, -500, 1_200] {
            let due = if offset_us >= 0 {
                now + Duration::from_micros(offset_us as u64)
            } else {
                now - Duration::from_micros(offset_us.unsigned_abs())
            };
            pacer.until(due, Duration::from_micros(100)).await.unwrap();
            assert!(
                Instant::now() >= due,
                "returned before a due time {offset_us} µs from the start"
            );
        }
    }
}
