//! Who gets a core first when the cores are saturated: the async runtime, which reads requests,
//! refuses what admission control turns away and answers health checks, before the compute pool,
//! whose work is already admitted. Without it a refusal waits behind computations (milliseconds at
//! overload; docs/reports/reliability.md measures both).

/// The compute threads' default niceness: enough that the kernel's scheduler runs the async runtime
/// first whenever both want a core.
pub const DEFAULT_COMPUTE_NICENESS: i32 = 5;

/// The time slice the runtime's threads ask for: the shortest Linux grants (0.1 ms).
#[cfg(target_os = "linux")]
const RUNTIME_SLICE_NS: u64 = 100_000;

/// Starts rayon's global pool, the compute pool, with its threads `niceness` below where the process
/// runs. Call it before anything uses rayon.
pub fn start_compute_pool(niceness: i32) -> Result<(), rayon::ThreadPoolBuildError> {
    let builder = rayon::ThreadPoolBuilder::new().thread_name(|i| format!("nak-compute-{i}"));
    if niceness == 0 {
        return builder.build_global();
    }
    builder.start_handler(move |_| lower_priority(niceness)).build_global()
}

/// For the runtime's threads (tokio's `on_thread_start`): asks for a short time slice. Linux's EEVDF
/// scheduler (6.12 and later) lets a waking thread with a shorter slice than the running one preempt
/// it, so a runtime thread woken by a request runs at once instead of after the compute thread's slice
/// (up to a few milliseconds). Older kernels ignore the request.
pub fn favour_runtime_thread() {
    #[cfg(target_os = "linux")]
    if let Err(e) = shorten_slice(RUNTIME_SLICE_NS) {
        tracing::debug!("runtime thread keeps the default time slice: {e}");
    }
}

/// `struct sched_attr` of sched_setattr(2), its first version (48 bytes).
#[cfg(target_os = "linux")]
#[repr(C)]
struct SchedAttr {
    size: u32,
    policy: u32,
    flags: u64,
    nice: i32,
    priority: u32,
    runtime_ns: u64,
    deadline_ns: u64,
    period_ns: u64,
}

#[cfg(target_os = "linux")]
fn shorten_slice(slice_ns: u64) -> std::io::Result<()> {
    // sched_setattr sets the niceness too: keep the thread's own.
    let nice = this_threads_niceness()?;
    let attr = SchedAttr {
        size: std::mem::size_of::<SchedAttr>() as u32,
        policy: libc::SCHED_OTHER as u32,
        flags: 0,
        nice,
        priority: 0,
        runtime_ns: slice_ns,
        deadline_ns: 0,
        period_ns: 0,
    };
    // SAFETY: `attr` is a valid sched_attr of the size it declares, read by the kernel for the
    // calling thread (pid 0) only.
    let outcome = unsafe { libc::syscall(libc::SYS_sched_setattr, 0, &attr as *const SchedAttr, 0) };
    if outcome == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// The calling thread's niceness (on Linux, PRIO_PROCESS with id 0 is the calling thread).
#[cfg(target_os = "linux")]
fn this_threads_niceness() -> std::io::Result<i32> {
    // SAFETY: reads the calling thread's own priority.
    checked_by_errno(|| unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) })
}

#[cfg(target_os = "linux")]
fn lower_priority(niceness: i32) {
    // On Linux nice() changes the calling thread only, and relative to where it is, so a server
    // started nice stays below its runtime.
    // SAFETY: changes the calling thread's own priority.
    if let Err(e) = checked_by_errno(|| unsafe { libc::nice(niceness) }) {
        tracing::warn!("compute thread keeps its priority: {e}");
    }
}

/// Runs a libc call for which -1 is also a valid answer (nice, getpriority): only errno tells failure.
#[cfg(target_os = "linux")]
fn checked_by_errno(call: impl FnOnce() -> libc::c_int) -> std::io::Result<libc::c_int> {
    // SAFETY: errno is the calling thread's own.
    unsafe { *libc::__errno_location() = 0 };
    let value = call();
    let error = std::io::Error::last_os_error();
    if value == -1 && error.raw_os_error() != Some(0) {
        Err(error)
    } else {
        Ok(value)
    }
}

#[cfg(not(target_os = "linux"))]
fn lower_priority(_niceness: i32) {}
