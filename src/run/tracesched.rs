//! `run --trace-sched`: the kernel's scheduler and IRQ events during the run, so that an
//! incident names what ran instead of the late process (`crate::pipeline::incidents`).
//!
//! A tracefs instance of the run's own (`instances/rotorloop-DOMAIN`: other tracers on
//! the machine are not touched) with the `mono` clock (`CLOCK_MONOTONIC`, the clock of
//! the loop's stamps), `sched_switch`, `sched_wakeup`, `irq_handler_entry` and
//! `irq_handler_exit` enabled on every CPU. A thread of the launcher reads its
//! `trace_pipe` while the run goes on (so the buffer never overflows) into
//! `OUT/sched-trace.txt`, the kernel's text lines as they are. tracefs is mounted at
//! `/sys/kernel/tracing` when it is mounted nowhere; whatever happens to the run, the
//! instance is removed and only what was mounted here is unmounted ([`Drop`]). A launcher
//! killed with `SIGKILL` leaves its instance; the next `--trace-sched` run removes
//! instances whose launcher is gone.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use rotorloop_common::role::UsageError;

/// Where tracefs is mounted when it is mounted nowhere.
const MOUNT_AT: &str = "/sys/kernel/tracing";
/// The events recorded.
const EVENTS: [&str; 4] =
    ["sched/sched_switch", "sched/sched_wakeup", "irq/irq_handler_entry", "irq/irq_handler_exit"];

/// A tracefs instance recording the run, torn down when dropped.
#[derive(Debug)]
pub(crate) struct TraceSched {
    instance: PathBuf,
    mounted: Option<PathBuf>,
    stop: Arc<AtomicBool>,
    reader: Option<std::thread::JoinHandle<()>>,
}

/// Where tracefs is mounted, if it is.
fn tracefs_mount() -> Option<PathBuf> {
    let mounts = std::fs::read_to_string("/proc/mounts").ok()?;
    mounts.lines().find_map(|l| {
        let f: Vec<&str> = l.split_whitespace().collect();
        (f.get(2) == Some(&"tracefs")).then(|| PathBuf::from(f[1]))
    })
}

fn write(path: &Path, value: &str) -> anyhow::Result<()> {
    std::fs::write(path, value)
        .with_context(|| format!("--trace-sched: cannot write {value:?} to {}", path.display()))
}

fn mount(at: &str) -> anyhow::Result<()> {
    let c = |s: &str| std::ffi::CString::new(s).expect("no NUL");
    let (src, dst, fs) = (c("tracefs"), c(at), c("tracefs"));
    // SAFETY: mount(2) with NUL-terminated strings that outlive the call and no data.
    let rc = unsafe { libc::mount(src.as_ptr(), dst.as_ptr(), fs.as_ptr(), 0, std::ptr::null()) };
    if rc != 0 {
        let e = std::io::Error::last_os_error();
        return Err(UsageError(format!(
            "--trace-sched: tracefs is not mounted and mounting it at {at} failed: {e}"
        ))
        .into());
    }
    Ok(())
}

/// Removes instances `rotorloop-PID-DOMAIN` whose launcher `PID` is gone (one killed by
/// `SIGKILL` could not remove its own).
fn remove_stale(root: &Path) {
    let Ok(dir) = std::fs::read_dir(root.join("instances")) else { return };
    for e in dir.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let pid = name
            .strip_prefix("rotorloop-")
            .and_then(|r| r.split_once('-'))
            .and_then(|(p, _)| p.parse::<u32>().ok());
        if pid.is_some_and(|p| !Path::new(&format!("/proc/{p}")).exists()) {
            let _ = std::fs::remove_dir(e.path());
        }
    }
}

impl TraceSched {
    /// Starts recording into `out/sched-trace.txt` (root only: a named error otherwise).
    pub(crate) fn start(out: &Path, domain: &str) -> anyhow::Result<Self> {
        // SAFETY: geteuid reads this process's effective user id.
        if unsafe { libc::geteuid() } != 0 {
            return Err(UsageError(
                "--trace-sched needs root (a tracefs instance); without it the incidents still \
                 have each role's schedstat (sched.csv)"
                    .into(),
            )
            .into());
        }
        let (root, mounted) = match tracefs_mount() {
            Some(root) => (root, None),
            None => {
                mount(MOUNT_AT)?;
                (PathBuf::from(MOUNT_AT), Some(PathBuf::from(MOUNT_AT)))
            }
        };
        remove_stale(&root);
        let name = format!("rotorloop-{}-{domain}", std::process::id());
        let instance = root.join("instances").join(name);
        let _ = std::fs::remove_dir(&instance);
        let mut me = Self { instance, mounted, stop: Arc::default(), reader: None };
        std::fs::create_dir(&me.instance).with_context(|| {
            format!("--trace-sched: cannot create the instance {}", me.instance.display())
        })?;
        write(&me.instance.join("trace_clock"), "mono")?;
        write(&me.instance.join("buffer_size_kb"), "8192")?;
        for e in EVENTS {
            write(&me.instance.join("events").join(e).join("enable"), "1")?;
        }
        let path = out.join("sched-trace.txt");
        let file = rotorloop_common::outdir::create_file(&path)
            .with_context(|| format!("cannot write {}", path.display()))?;
        let pipe = std::fs::File::open(me.instance.join("trace_pipe"))
            .context("--trace-sched: cannot open trace_pipe")?;
        set_nonblocking(&pipe);
        write(&me.instance.join("tracing_on"), "1")?;
        let stop = me.stop.clone();
        me.reader = Some(
            std::thread::Builder::new()
                .name("trace-sched".into())
                .spawn(move || copy_until(pipe, std::io::BufWriter::new(file), &stop))
                .context("--trace-sched: no reader thread")?,
        );
        Ok(me)
    }
}

fn set_nonblocking(f: &std::fs::File) {
    use std::os::fd::AsRawFd;
    // SAFETY: fcntl on a descriptor we own.
    unsafe {
        let flags = libc::fcntl(f.as_raw_fd(), libc::F_GETFL);
        libc::fcntl(f.as_raw_fd(), libc::F_SETFL, flags | libc::O_NONBLOCK);
    }
}

/// Copies `pipe` into `out` until `stop`, then what is left in it.
fn copy_until(mut pipe: std::fs::File, mut out: impl Write, stop: &AtomicBool) {
    let mut buf = vec![0u8; 1 << 16];
    let mut stopping = false;
    loop {
        match pipe.read(&mut buf) {
            Ok(n) if n > 0 => {
                if out.write_all(&buf[..n]).is_err() {
                    eprintln!("warning: cannot write sched-trace.txt any more");
                    return;
                }
            }
            _ if stopping => break,
            _ => {
                stopping = stop.load(Ordering::Relaxed);
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
        }
    }
    let _ = out.flush();
}

impl Drop for TraceSched {
    fn drop(&mut self) {
        let _ = std::fs::write(self.instance.join("tracing_on"), "0");
        self.stop.store(true, Ordering::Relaxed);
        if let Some(r) = self.reader.take() {
            let _ = r.join();
        }
        for e in EVENTS {
            let _ = std::fs::write(self.instance.join("events").join(e).join("enable"), "0");
        }
        if let Err(e) = std::fs::remove_dir(&self.instance) {
            eprintln!("warning: --trace-sched: cannot remove {}: {e}", self.instance.display());
        }
        if let Some(at) = self.mounted.take() {
            let c = std::ffi::CString::new(at.to_string_lossy().as_bytes()).expect("no NUL");
            // SAFETY: umount2(2) of the tracefs this launcher mounted.
            if unsafe { libc::umount2(c.as_ptr(), 0) } != 0 {
                let e = std::io::Error::last_os_error();
                eprintln!("warning: --trace-sched: cannot unmount {}: {e}", at.display());
            }
        }
    }
}
