//! Real-time set-up of a process: core pinning, SCHED_FIFO, mlock and timer slack; and
//! background threads ([`Background`]).

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

/// A thread that runs in the background (`SCHED_IDLE`: only where a CPU has nothing else
/// to run, giving the CPU up at once to any thread that wakes) while it keeps up with its
/// work, and is an ordinary thread again (`SCHED_OTHER`, its nice value kept) while it has
/// fallen behind: on a saturated machine a background thread gets next to no CPU.
///
/// The thread names itself ([`Background::here`]); then it, or another thread that sees it
/// fall behind, sets its policy ([`Background::set`]). Since [`Background::durable_at`]
/// the thread has had nothing outstanding; [`Background::catch_up`] makes it ordinary
/// once that is longer ago than a bound. A thread of another policy (real time, given by
/// the user) is left as it is.
#[derive(Debug)]
pub struct Background {
    /// The thread's id (0: not named yet).
    tid: std::sync::atomic::AtomicI32,
    /// Whether it is `SCHED_IDLE` now.
    idle: std::sync::Mutex<bool>,
    /// When it last had nothing outstanding: ns since `base`.
    done_ns: std::sync::atomic::AtomicU64,
    base: std::time::Instant,
}

impl Default for Background {
    fn default() -> Self {
        Self {
            tid: Default::default(),
            idle: Default::default(),
            done_ns: Default::default(),
            base: std::time::Instant::now(),
        }
    }
}

impl Background {
    /// The calling thread is the one this handle sets, if it could be made ordinary again
    /// once in the background: Linux lets a thread leave `SCHED_IDLE` only with
    /// `CAP_SYS_NICE` or an `RLIMIT_NICE` that allows its nice value (the default, 0, does
    /// not), and a thread that cannot stays ordinary.
    pub fn here(&self) {
        // SAFETY: plain system calls; `getrlimit` fills a struct of ours.
        let (tid, nice, limit) = unsafe {
            let nice = libc::getpriority(libc::PRIO_PROCESS, 0);
            let mut limit = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
            libc::getrlimit(libc::RLIMIT_NICE, &mut limit);
            (libc::gettid(), nice, limit.rlim_cur)
        };
        if limit >= (20 - nice) as u64 || has_cap_sys_nice() {
            self.tid.store(tid, std::sync::atomic::Ordering::Release);
        }
    }

    /// The thread in the background (`idle`) or ordinary; from any thread.
    pub fn set(&self, idle: bool) {
        let tid = self.tid.load(std::sync::atomic::Ordering::Acquire);
        let Ok(mut now) = self.idle.lock() else { return };
        if tid == 0 || *now == idle {
            return;
        }
        let want = if idle { libc::SCHED_IDLE } else { libc::SCHED_OTHER };
        // SAFETY: plain system calls on a thread of this process, with a valid param.
        let set = unsafe {
            let policy = libc::sched_getscheduler(tid);
            (policy == libc::SCHED_OTHER || policy == libc::SCHED_IDLE)
                && libc::sched_setscheduler(tid, want, &libc::sched_param { sched_priority: 0 })
                    == 0
        };
        if set {
            *now = idle;
        }
    }

    /// The thread had nothing outstanding at `at`.
    pub fn durable_at(&self, at: std::time::Instant) {
        let ns = at.saturating_duration_since(self.base).as_nanos() as u64;
        self.done_ns.fetch_max(ns, std::sync::atomic::Ordering::Release);
    }

    /// Makes the thread ordinary if it last had nothing outstanding more than `bound` ago.
    pub fn catch_up(&self, bound: std::time::Duration) {
        let done = self.done_ns.load(std::sync::atomic::Ordering::Acquire);
        let since = self.base.elapsed().saturating_sub(std::time::Duration::from_nanos(done));
        if since > bound {
            self.set(false);
        }
    }
}

/// Whether the calling thread has `CAP_SYS_NICE` (bit 23 of `CapEff` in its status).
fn has_cap_sys_nice() -> bool {
    let status = std::fs::read_to_string("/proc/thread-self/status").unwrap_or_default();
    let eff = status.lines().find_map(|l| l.strip_prefix("CapEff:"));
    eff.and_then(|v| u64::from_str_radix(v.trim(), 16).ok()).is_some_and(|c| c & (1 << 23) != 0)
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

    /// A thread in the background is `SCHED_IDLE`; another thread makes it ordinary again
    /// once it last had nothing outstanding longer ago than the bound, not before. Needs
    /// the right to leave `SCHED_IDLE` (root); skipped with a message otherwise.
    #[test]
    fn a_background_thread_fallen_behind_is_made_ordinary_by_another() {
        let b = std::sync::Arc::new(Background::default());
        let (tx, rx) = std::sync::mpsc::channel();
        let (go_tx, go_rx) = std::sync::mpsc::channel::<()>();
        let t = {
            let b = b.clone();
            std::thread::spawn(move || {
                b.here();
                b.set(true);
                // SAFETY: plain system calls.
                tx.send(unsafe { (libc::gettid(), libc::sched_getscheduler(0)) }).expect("send");
                let _ = go_rx.recv();
            })
        };
        let (tid, policy) = rx.recv().expect("the thread's policy");
        if b.tid.load(std::sync::atomic::Ordering::Acquire) == 0 {
            eprintln!("skipped: this thread could not leave SCHED_IDLE (no CAP_SYS_NICE)");
            return;
        }
        assert_eq!(policy, libc::SCHED_IDLE);
        // SAFETY: plain system calls on the thread, alive until `go`.
        let policy = || unsafe { libc::sched_getscheduler(tid) };
        b.durable_at(std::time::Instant::now());
        b.catch_up(std::time::Duration::from_secs(3600));
        assert_eq!(policy(), libc::SCHED_IDLE, "it kept up: still in the background");
        std::thread::sleep(std::time::Duration::from_millis(20));
        b.catch_up(std::time::Duration::from_millis(10));
        assert_eq!(policy(), libc::SCHED_OTHER, "fallen behind: ordinary");
        go_tx.send(()).expect("go");
        t.join().expect("thread");
    }

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
