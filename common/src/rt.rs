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
