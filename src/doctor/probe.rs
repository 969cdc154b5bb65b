//! What only a system call can say about this process and machine: its CPU set, whether a
//! `SCHED_FIFO` priority is granted (tried in a child, so this process keeps its policy),
//! the limits, whether `/dev/cpu_dma_latency` can be held, `/dev/shm`'s free space and a
//! run's need of it. A plain struct: tests fill it with refusals of their own.

/// What the system calls said.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Probe {
    /// The CPUs a run would use (the process's CPU set, or `--cpus`).
    pub cpus: Vec<usize>,
    /// `sched_setscheduler(SCHED_FIFO, 1)` in a child: granted, or its errno.
    pub fifo: Result<(), i32>,
    /// `RLIMIT_RTPRIO`'s soft limit (`None`: unlimited).
    pub rtprio_limit: Option<u64>,
    /// `RLIMIT_MEMLOCK`'s soft limit in bytes (`None`: unlimited).
    pub memlock_limit: Option<u64>,
    /// The effective user id.
    pub euid: u32,
    /// `/dev/cpu_dma_latency` opened for writing: granted, or its errno.
    pub dma_latency: Result<(), i32>,
    /// `/dev/shm`'s free bytes, if it can be asked.
    pub shm_free: Option<u64>,
    /// What a run of the rate and length asked keeps in `/dev/shm` (its flight rings).
    pub shm_need: u64,
}

impl Probe {
    /// This process, for a run at `rate_hz` of `seconds` on `cpus` (its CPU set when
    /// `None`).
    pub fn this_process(rate_hz: f64, seconds: f64, cpus: Option<&[usize]>) -> Self {
        let ticks = (rate_hz * seconds).ceil().max(1.0) as u64;
        let ring = rotorloop_common::flight::ring_capacity(
            ticks,
            rotorloop_common::flight::DEFAULT_RING_TICKS,
        );
        Self {
            cpus: cpus.map_or_else(crate::cpus::allowed_now, <[usize]>::to_vec),
            fifo: fifo_in_child(),
            rtprio_limit: limit(libc::RLIMIT_RTPRIO),
            memlock_limit: limit(libc::RLIMIT_MEMLOCK),
            // SAFETY: geteuid reads this process's effective user id.
            euid: unsafe { libc::geteuid() },
            dma_latency: std::fs::OpenOptions::new()
                .write(true)
                .open("/dev/cpu_dma_latency")
                .map(drop)
                .map_err(|e| e.raw_os_error().unwrap_or(0)),
            shm_free: free_bytes(std::path::Path::new("/dev/shm")),
            shm_need: ring.saturating_mul(rotorloop_common::flight::bytes_per_tick()),
        }
    }
}

/// A soft resource limit; `None` when unlimited or unknown.
fn limit(resource: libc::__rlimit_resource_t) -> Option<u64> {
    // SAFETY: getrlimit fills the struct it is given.
    let mut r: libc::rlimit = unsafe { std::mem::zeroed() };
    let ok = unsafe { libc::getrlimit(resource, &mut r) } == 0;
    (ok && r.rlim_cur != libc::RLIM_INFINITY).then_some(r.rlim_cur)
}

/// Forks a child that asks for `SCHED_FIFO` priority 1 and exits with 0 when granted, or
/// with the errno (this process keeps its policy; the child's RT time is nil).
fn fifo_in_child() -> Result<(), i32> {
    // SAFETY: the child calls only async-signal-safe functions (sched_setscheduler,
    // _exit) before it exits; the parent waits for it.
    unsafe {
        let pid = libc::fork();
        if pid == 0 {
            let param = libc::sched_param { sched_priority: 1 };
            let code = match libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) {
                0 => 0,
                _ => *libc::__errno_location(),
            };
            libc::_exit(code);
        }
        if pid < 0 {
            return Err(*libc::__errno_location());
        }
        let mut status = 0;
        if libc::waitpid(pid, &mut status, 0) != pid || !libc::WIFEXITED(status) {
            return Err(libc::ECHILD);
        }
        match libc::WEXITSTATUS(status) {
            0 => Ok(()),
            e => Err(e),
        }
    }
}

/// Free bytes of the filesystem that holds `path` (or would: its nearest existing
/// ancestor), if it can be asked.
pub fn free_bytes(path: &std::path::Path) -> Option<u64> {
    let mut at =
        if path.is_absolute() { path.to_owned() } else { std::path::Path::new(".").join(path) };
    while !at.exists() {
        at = at.parent()?.to_owned();
    }
    let c = std::ffi::CString::new(at.as_os_str().as_encoded_bytes()).ok()?;
    // SAFETY: statvfs fills the struct from a NUL-terminated path; checked for failure.
    let st = unsafe {
        let mut st: libc::statvfs = std::mem::zeroed();
        (libc::statvfs(c.as_ptr(), &mut st) == 0).then_some(st)
    }?;
    Some(st.f_bavail.saturating_mul(st.f_frsize))
}
