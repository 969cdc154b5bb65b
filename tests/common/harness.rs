//! Harness for tests that spawn real processes: a unique domain and temp dir per test,
//! children killed on drop, waits bounded by a deadline, and the check that a run left
//! nothing in shared memory.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::time::{Duration, Instant};

pub const ROTORLOOP: &str = env!("CARGO_BIN_EXE_rotorloop");

/// A 2 MiB tmpfs mounted on a new directory of the harness (mode 0755: a tmpfs's root is
/// 1777 otherwise, an OUT every user could write in, which a run refuses), unmounted when
/// dropped: a disk that fills up a second into a run.
pub struct SmallDisk(PathBuf);

impl SmallDisk {
    /// Mounts it on `h.path(name)`; `None` where `mount` is not allowed (not root, or no
    /// CAP_SYS_ADMIN): the caller skips with a message.
    pub fn mount(h: &Harness, name: &str) -> Option<Self> {
        Self::mount_with(h, name, "")
    }

    /// As [`SmallDisk::mount`], with more of tmpfs's options (`,nr_inodes=64`).
    pub fn mount_with(h: &Harness, name: &str, more: &str) -> Option<Self> {
        let dir = h.path(name);
        std::fs::create_dir_all(&dir).expect("dir");
        let mounted = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size=2m,mode=0755{more}"), "tmpfs"])
            .arg(&dir)
            .output()
            .is_ok_and(|o| o.status.success());
        mounted.then_some(Self(dir))
    }

    pub fn path(&self) -> &Path {
        &self.0
    }

    /// Makes empty files (`.inode-N`) until the disk has no inode left, so that no file can
    /// be made on it any more whatever space is freed (a run's full disk frees some now and
    /// then: a journal's frame that did not fit is cut off again). Returns how many it made.
    pub fn take_every_inode(&self) -> usize {
        for n in 0.. {
            let made = std::fs::File::create_new(self.0.join(format!(".inode-{n}")));
            if let Err(e) = made {
                assert_eq!(e.raw_os_error(), Some(28), "not ENOSPC: {e}");
                return n;
            }
        }
        unreachable!()
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

/// The machine: shared by every harness, or held alone by a test that loads a CPU at a
/// real-time priority on purpose ([`Harness::alone`]). Its 50 ms of SCHED_FIFO spin
/// otherwise landed on the runs beside it (a C controller's run then had 993 of its 2 695
/// answers reproduced, its references late), and their load on its figures.
static MACHINE: (std::sync::Mutex<Machine>, std::sync::Condvar) = (
    std::sync::Mutex::new(Machine { shared: 0, alone: false, waiting: 0 }),
    std::sync::Condvar::new(),
);

/// Who holds [`MACHINE`]. A harness made while another is alive never waits (a test may
/// hold two, or one and start another's thread), so none deadlocks; one waits only while
/// a test runs alone, or when none is alive and one waits to run alone (which then goes
/// first).
struct Machine {
    /// Harnesses alive that share it.
    shared: usize,
    /// Whether a test holds it alone.
    alone: bool,
    /// Tests waiting to hold it alone.
    waiting: usize,
}

fn machine() -> std::sync::MutexGuard<'static, Machine> {
    MACHINE.0.lock().unwrap_or_else(|p| p.into_inner())
}

/// One test's domain, directory and children, and its hold on the machine.
pub struct Harness {
    pub domain: String,
    pub dir: tempfile::TempDir,
    children: Vec<Running>,
    /// Whether it holds the machine alone (else it shares it).
    alone: bool,
}

impl Harness {
    pub fn new(test: &str) -> Self {
        let h = Self::made(test, false);
        let mut m = machine();
        while m.alone || (m.waiting > 0 && m.shared == 0) {
            m = MACHINE.1.wait(m).unwrap_or_else(|p| p.into_inner());
        }
        m.shared += 1;
        h
    }

    /// A harness whose test runs with no other harness beside it.
    pub fn alone(test: &str) -> Self {
        let h = Self::made(test, true);
        let mut m = machine();
        m.waiting += 1;
        while m.alone || m.shared > 0 {
            m = MACHINE.1.wait(m).unwrap_or_else(|p| p.into_inner());
        }
        (m.waiting, m.alone) = (m.waiting - 1, true);
        h
    }

    /// The harness before its hold on the machine is taken (made first: nothing that can
    /// fail comes between the hold and the harness whose drop gives it back).
    fn made(test: &str, alone: bool) -> Self {
        let domain = format!("t-{test}-{}", std::process::id());
        let dir = tempfile::tempdir().expect("tempdir");
        Self { domain, dir, children: Vec::new(), alone }
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// Runs `rotorloop args…` to completion (at most `limit`), returning its output.
    pub fn rotorloop(&self, args: &[&str], limit: Duration) -> Output {
        let child = group(&mut Command::new(ROTORLOOP))
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn rotorloop");
        wait_output(child, limit)
    }

    /// Starts a process in the background; it is killed when the harness drops.
    pub fn spawn(&mut self, program: &str, args: &[String]) -> usize {
        let child = Command::new(program)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn");
        self.children.push(Running::from(child));
        self.children.len() - 1
    }

    pub fn child(&mut self, i: usize) -> &mut Child {
        &mut self.children[i].child
    }

    /// What background child `i` wrote to stderr (once it has exited: see [`wait_all`]).
    pub fn stderr_of(&mut self, i: usize) -> String {
        let (_, err, _) = self.children[i].collect(Instant::now() + Duration::from_secs(10));
        String::from_utf8_lossy(&err).into_owned()
    }

    /// Waits for every background child to exit, at most `limit`; panics otherwise.
    pub fn wait_all(&mut self, limit: Duration) -> Vec<ExitStatus> {
        let until = Instant::now() + limit;
        let mut out = Vec::new();
        for (i, c) in self.children.iter_mut().enumerate() {
            loop {
                if let Some(st) = c.child.try_wait().expect("try_wait") {
                    out.push(st);
                    break;
                }
                if Instant::now() > until {
                    let _ = c.child.kill();
                    let _ = c.child.wait();
                    let (_, err, _) = c.collect(Instant::now() + Duration::from_secs(5));
                    panic!(
                        "child {i} did not exit within {limit:?}; its stderr:\n{}",
                        String::from_utf8_lossy(&err)
                    );
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        out
    }

    /// Nothing of this domain remains in /dev/shm or iceoryx2's root directory.
    pub fn assert_no_leftovers(&self) {
        self.assert_none_with_prefix(&format!("rl_{}_", self.domain));
        if let Some(staged) = rotorloop_common::flight::staging_dir(&self.domain) {
            assert!(!staged.exists(), "flight records left in {}", staged.display());
        }
    }

    /// Nothing of this test's domain on `host` (a `--split` run's host) is left.
    pub fn assert_no_leftovers_on(&self, host: &str) {
        self.assert_none_with_prefix(&format!("rh_{host}_{}_", self.domain));
    }

    fn assert_none_with_prefix(&self, prefix: &str) {
        let shm: Vec<String> = std::fs::read_dir("/dev/shm")
            .map(|d| {
                d.flatten()
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .filter(|n| n.starts_with(prefix))
                    .collect()
            })
            .unwrap_or_default();
        assert!(shm.is_empty(), "left in /dev/shm: {shm:?}");
        let root =
            PathBuf::from(format!("{}{prefix}", rotorloop_common::ipc::domain::ICEORYX2_ROOT));
        let files = files_under(&root);
        assert!(files.is_empty(), "left under {}: {files:?}", root.display());
    }
}

fn files_under(p: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Ok(d) = std::fs::read_dir(p) {
        for e in d.flatten() {
            let path = e.path();
            if path.is_dir() {
                out.extend(files_under(&path));
            } else {
                out.push(path);
            }
        }
    }
    out
}

impl Drop for Harness {
    fn drop(&mut self) {
        for c in &mut self.children {
            let _ = c.child.kill();
            let _ = c.child.wait();
        }
        let mut m = machine();
        match self.alone {
            true => m.alone = false,
            false => m.shared -= 1,
        }
        drop(m);
        MACHINE.1.notify_all();
    }
}

/// Puts the command's process in a group of its own, which [`wait_output`] kills whole
/// at its time limit.
pub fn group(cmd: &mut Command) -> &mut Command {
    use std::os::unix::process::CommandExt;
    cmd.process_group(0)
}

/// A child whose stdout and stderr are read while it runs. A pipe nobody reads holds
/// 64 KiB; then the writer blocks, and with it the whole run: the launcher and every role
/// sharing its stderr stopped mid-loop that way when a loaded split run wrote its
/// warnings, and the test hung until its time limit.
pub struct Running {
    child: Child,
    stdout: Option<std::thread::JoinHandle<Vec<u8>>>,
    stderr: Option<std::thread::JoinHandle<Vec<u8>>>,
}

impl From<Child> for Running {
    fn from(mut child: Child) -> Self {
        fn drain(
            pipe: Option<impl std::io::Read + Send + 'static>,
        ) -> Option<std::thread::JoinHandle<Vec<u8>>> {
            pipe.map(|mut p| {
                std::thread::spawn(move || {
                    let mut buf = Vec::new();
                    let _ = p.read_to_end(&mut buf);
                    buf
                })
            })
        }
        let stdout = drain(child.stdout.take());
        let stderr = drain(child.stderr.take());
        Self { child, stdout, stderr }
    }
}

impl Running {
    pub fn id(&self) -> u32 {
        self.child.id()
    }

    /// Sends the child SIGTERM (as Ctrl-C does) and waits for it and its output, as
    /// [`wait_output`] does.
    pub fn terminate(self, limit: Duration) -> Output {
        // SAFETY: signals this test's own child, not yet waited for.
        unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM) };
        wait_output(self, limit)
    }

    /// Whether the child has ended, for a failure's message (it is reaped if it has).
    pub fn ended(&mut self) -> Option<std::process::ExitStatus> {
        self.child.try_wait().ok().flatten()
    }

    /// Kills the child's whole process group (see [`group`]).
    fn kill_group(&mut self) {
        // SAFETY: plain syscall; the group is the child's own (see `group`).
        unsafe { libc::kill(-(self.child.id() as libc::pid_t), libc::SIGKILL) };
        let _ = self.child.kill();
    }

    /// What the child wrote, and whether its pipes were held open past `until`. Waits
    /// for the pipes to close until `until`, then kills the group (a grandchild that
    /// outlived the child may hold them) and waits 5 s more; a pipe still open then (held
    /// outside the group) is left to its thread, unread.
    fn collect(&mut self, until: Instant) -> (Vec<u8>, Vec<u8>, bool) {
        type Reader = Option<std::thread::JoinHandle<Vec<u8>>>;
        let done = |h: &Reader| h.as_ref().is_none_or(|h| h.is_finished());
        let mut killed = false;
        while !(done(&self.stdout) && done(&self.stderr)) {
            if !killed && Instant::now() > until {
                self.kill_group();
                killed = true;
            } else if killed && Instant::now() > until + Duration::from_secs(5) {
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let join = |h: Reader| match h {
            Some(h) if h.is_finished() => h.join().expect("reader"),
            Some(_) => b"(not read: a process outside the group holds the pipe)".to_vec(),
            None => Vec::new(),
        };
        (join(self.stdout.take()), join(self.stderr.take()), killed)
    }
}

/// Waits for `child` (started with [`group`], or its grandchildren may survive a
/// timeout) to finish, at most `limit`, reading its output meanwhile; panics with its
/// stderr otherwise.
pub fn wait_output(child: impl Into<Running>, limit: Duration) -> Output {
    let mut r = child.into();
    let until = Instant::now() + limit;
    loop {
        if let Some(status) = r.child.try_wait().expect("try_wait") {
            let (stdout, stderr, held_open) = r.collect(until);
            assert!(
                !held_open,
                "the process exited ({status}) but a process it started held its output open \
                 past {limit:?}; stderr:\n{}",
                String::from_utf8_lossy(&stderr)
            );
            return Output { status, stdout, stderr };
        }
        if Instant::now() > until {
            // The whole group: a grandchild holding the pipes would block the read below.
            r.kill_group();
            let _ = r.child.wait();
            let (_, stderr, _) = r.collect(Instant::now() + Duration::from_secs(5));
            panic!(
                "process did not finish within {limit:?}; stderr:\n{}",
                String::from_utf8_lossy(&stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

pub fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "failed ({}): {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

pub fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).expect("read json")).expect("json")
}

/// One row of the monitor's `timing.csv`.
#[derive(Debug, Clone, Copy)]
pub struct TimingRow {
    pub tick: i64,
    /// The tick whose torque was held over the tick before (−1: none, the rotors coasted).
    pub applied: i64,
    /// The state's flags (`rotorloop_common::wire::FLAG_*`).
    pub flags: u64,
}

/// Complete rows so far in `out/timing.csv` of a run that is still going (0 before the
/// file exists; a row still being written is not counted).
pub fn live_timing_rows(out: &Path) -> usize {
    let text = std::fs::read(out.join("timing.csv")).unwrap_or_default();
    text.iter().filter(|b| **b == b'\n').count().saturating_sub(1)
}

/// The rows of `out/timing.csv`.
pub fn timing_rows(out: &Path) -> Vec<TimingRow> {
    std::fs::read_to_string(out.join("timing.csv"))
        .expect("timing.csv")
        .lines()
        .skip(1)
        .map(|l| {
            let c: Vec<&str> = l.split(',').collect();
            TimingRow {
                tick: c[0].parse().expect("tick"),
                applied: c[2].parse().expect("applied"),
                flags: c[3].parse().expect("flags"),
            }
        })
        .collect()
}

/// Asserts two traces are byte-identical, naming the first differing row and columns.
pub fn assert_same_trace(what: &str, got: &[u8], want: &[u8]) {
    if got == want {
        return;
    }
    let (g, w) = (String::from_utf8_lossy(got), String::from_utf8_lossy(want));
    let header: Vec<&str> = w.lines().next().unwrap_or("").split(',').collect();
    for (i, (a, b)) in g.lines().zip(w.lines()).enumerate() {
        if a != b {
            let cols: Vec<String> = a
                .split(',')
                .zip(b.split(','))
                .enumerate()
                .filter(|(_, (x, y))| x != y)
                .take(6)
                .map(|(j, (x, y))| format!("{}: {x} vs {y}", header.get(j).unwrap_or(&"?")))
                .collect();
            panic!("{what}: row {i} differs from the simulator's: {cols:?}");
        }
    }
    panic!("{what}: {} rows vs the simulator's {}", g.lines().count(), w.lines().count());
}

/// The trace of `rotorloop sim` of `scenario` for `duration` s with `extra` arguments,
/// written under the harness's directory (`sim-<scenario>`), at most 120 s.
pub fn sim_trace(h: &Harness, scenario: &str, duration: &str, extra: &[&str]) -> Vec<u8> {
    let out = h.path(&format!("sim-{scenario}"));
    let mut args = vec!["sim", "--scenario", scenario, "--duration", duration, "--no-figures"];
    args.extend_from_slice(extra);
    args.extend(["--out", out.to_str().expect("utf8")]);
    ok(&h.rotorloop(&args, Duration::from_secs(120)));
    std::fs::read(out.join("trace.csv")).expect("sim trace")
}

/// How a process just sent SIGKILL ended: how long until it was a zombie or gone, and the
/// states (`/proc/PID/stat`) and kernel waits (`wchan`) it went through on the way.
pub fn exit_of(pid: u32) -> String {
    let start = Instant::now();
    let mut seen: Vec<String> = Vec::new();
    while start.elapsed() < Duration::from_secs(10) {
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
        let state = stat.rsplit(')').next().and_then(|r| r.split_whitespace().next());
        let Some(state) = state.filter(|s| *s != "Z" && *s != "X") else {
            return format!("pid {pid} exited {:?} after SIGKILL via {seen:?}", start.elapsed());
        };
        let wchan = std::fs::read_to_string(format!("/proc/{pid}/wchan")).unwrap_or_default();
        let now = format!("{state} {wchan}");
        if seen.last() != Some(&now) {
            seen.push(now);
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    format!("pid {pid} still not exited 10 s after SIGKILL, via {seen:?}")
}

/// The processes of `domain` (by their command line: `--domain DOMAIN`), each with its
/// arguments.
fn domain_processes(domain: &str) -> Vec<(u32, Vec<Vec<u8>>)> {
    let mut out = Vec::new();
    for e in std::fs::read_dir("/proc").expect("/proc").flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else { continue };
        let Ok(cmdline) = std::fs::read(e.path().join("cmdline")) else { continue };
        let args: Vec<Vec<u8>> = cmdline.split(|b| *b == 0).map(<[u8]>::to_vec).collect();
        if args.windows(2).any(|w| w[0] == b"--domain" && w[1] == domain.as_bytes()) {
            out.push((pid, args));
        }
    }
    out
}

/// The pids of the processes of `domain` (by their command line).
pub fn processes_of(domain: &str) -> Vec<u32> {
    domain_processes(domain).into_iter().map(|(pid, _)| pid).collect()
}

/// The pid of the newest `rotorloop role ROLE` process of `domain`.
pub fn pid_of_role(domain: &str, role: &str) -> Option<u32> {
    let is_role =
        |args: &[Vec<u8>]| args.windows(2).any(|w| w[0] == b"role" && w[1] == role.as_bytes());
    domain_processes(domain).into_iter().filter(|(_, a)| is_role(a)).map(|(pid, _)| pid).max()
}

/// The state letter of a process (`/proc/PID/stat`'s third field): `T` when stopped.
pub fn proc_state(pid: u32) -> Option<char> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    stat.rsplit_once(')')?.1.trim_start().chars().next()
}
