//! Real-time set-up of a process: core pinning, SCHED_FIFO, mlock and timer slack.

/// Real-time set-up of a process. Each step that the OS refuses gives a one-line warning
/// and the process runs on.
#[derive(Debug, Clone, Copy, Default)]
pub struct RtSetup {
    /// Pin to this core.
    pub core: Option<usize>,
    /// SCHED_FIFO priority (1–99).
    pub rt_priority: Option<i32>,
    /// Lock all memory (mlockall).
    pub mlock: bool,
}

impl RtSetup {
    /// Applies the set-up; returns the warnings.
    pub fn apply(&self, role: &str) -> Vec<String> {
        let mut warnings = Vec::new();
        // Timer slack (50 µs by default) delays every timed wake-up; ask for 1 ns.
        // SAFETY: plain prctl on the calling thread.
        unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0) };
        if let Some(core) = self.core {
            let ids = core_affinity::get_core_ids().unwrap_or_default();
            match ids.into_iter().find(|c| c.id == core) {
                Some(id) if core_affinity::set_for_current(id) => {}
                _ => warnings.push(format!("{role}: cannot pin to core {core}; running unpinned")),
            }
        }
        if let Some(p) = self.rt_priority {
            let param = libc::sched_param { sched_priority: p };
            // SAFETY: plain syscall on the calling thread with a valid param.
            if unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) } != 0 {
                warnings.push(format!(
                    "{role}: SCHED_FIFO priority {p} not permitted ({}); running with the default policy",
                    std::io::Error::last_os_error()
                ));
            }
        }
        if self.mlock {
            // SAFETY: plain syscall.
            if unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) } != 0 {
                warnings.push(format!(
                    "{role}: mlockall failed ({}); memory may be paged",
                    std::io::Error::last_os_error()
                ));
            }
        }
        warnings
    }
}

/// A PM QoS request on `/dev/cpu_dma_latency`: while it is held, no CPU enters an idle
/// state whose exit latency is above `us` microseconds. With 0 an idle CPU polls instead
/// of halting (what cyclictest asks for by default). On a VM with the `haltpoll` cpuidle
/// driver a halted vCPU leaves the guest, and its timer wake-up comes about 20 µs later
/// (measured: docs/measurements.md). The request ends when the guard is dropped, or when
/// the process holding it dies: the kernel drops it with the file.
#[derive(Debug)]
pub struct CpuDmaLatency {
    _file: std::fs::File,
    us: u32,
}

impl CpuDmaLatency {
    /// The device the kernel takes the request on.
    pub const PATH: &'static str = "/dev/cpu_dma_latency";

    /// Asks for at most `us` µs of idle exit latency on every CPU, or says why not.
    pub fn hold(us: u32) -> Result<Self, String> {
        use std::io::Write;
        let value = i32::try_from(us)
            .map_err(|_| format!("--cpu-dma-latency {us} is not allowed: 0 to {}", i32::MAX))?;
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .open(Self::PATH)
            .map_err(|e| format!("cannot open {} ({e}); idle states unchanged", Self::PATH))?;
        file.write_all(&value.to_ne_bytes())
            .map_err(|e| format!("cannot write {} ({e}); idle states unchanged", Self::PATH))?;
        Ok(Self { _file: file, us })
    }

    /// [`hold`](Self::hold)s `us` where it is given; where the kernel refuses, prints a
    /// warning and goes on without it.
    pub fn hold_or_warn(us: Option<u32>) -> Option<Self> {
        us.and_then(|us| Self::hold(us).map_err(|w| eprintln!("warning: {w}")).ok())
    }

    /// The latency asked for (µs).
    pub fn us(&self) -> u32 {
        self.us
    }
}

/// The limit the kernel applies now (µs): the smallest request held by anyone.
pub fn cpu_dma_latency_now() -> Option<u32> {
    use std::io::Read;
    let mut b = [0u8; 4];
    std::fs::File::open(CpuDmaLatency::PATH).ok()?.read_exact(&mut b).ok()?;
    u32::try_from(i32::from_ne_bytes(b)).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The request is in force while held and gone when dropped. Needs root (the device
    /// is root's); skipped with a message otherwise.
    #[test]
    fn a_held_request_is_in_force_until_dropped() {
        let before = match cpu_dma_latency_now() {
            Some(v) => v,
            None => {
                eprintln!("skipped: {} is not readable here", CpuDmaLatency::PATH);
                return;
            }
        };
        let held = match CpuDmaLatency::hold(0) {
            Ok(h) => h,
            Err(e) => {
                eprintln!("skipped: {e}");
                return;
            }
        };
        assert_eq!(cpu_dma_latency_now(), Some(0));
        drop(held);
        // Another process may hold a request of its own; ours is gone.
        let after = cpu_dma_latency_now().expect("readable");
        assert!(after == before || before == 0, "before {before}, after {after}");
    }
}
