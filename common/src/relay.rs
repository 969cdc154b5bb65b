//! Output that never blocks its process: stdout and stderr through a pipe of the process's
//! own, drained by two threads into a bounded buffer and written from there to where the
//! output really goes.
//!
//! **Why.** A write to a pipe nobody reads blocks once the pipe holds 64 KiB, and a write
//! to a terminal blocks while it is paused (Ctrl-S). The launcher and every role share
//! the launcher's stderr, so one consumer that stopped reading (`| less` left on its first
//! page, a test harness that read the pipes only after the exit) stopped the whole loop
//! mid-run: seen as a split run that never ended, every process of it in
//! `anon_pipe_write` (`ps -o wchan`), states reaching the far host and no torque coming
//! back. A control loop must not depend on whether someone reads its log.
//!
//! **How.** [`Relay::install`] points the descriptor at a pipe (so everything the process
//! writes, its children's inherited output included, goes there); a reader thread moves
//! what arrives into a buffer of at most [`BUFFER_BYTES`], and a writer thread writes the
//! buffer out, a line at a time where it can (lines of several processes stay whole). When
//! the real output does not take it, the buffer fills and further output is dropped and
//! counted: the process goes on, and once the output moves again it says how much it lost.
//! A real output that is gone (`EPIPE`: the reader exited) is not an error either: the
//! output is discarded, never a panic. [`Relay::finish`] waits for the buffer to drain (a
//! bound: it gives up after [`FLUSH_STALL`] without progress), and a panic flushes the
//! same way, so the last message of a process still gets out.
//!
//! Nothing here runs inside a tick: a role's tick logs nothing (only changes of state,
//! which cost one `write` to the pipe, as to a terminal before).

use std::collections::VecDeque;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::sync::{Arc, Condvar, Mutex, OnceLock};
use std::time::{Duration, Instant};

/// Output held at most while the real output does not take it; more is dropped and counted.
pub const BUFFER_BYTES: usize = 1 << 20;
/// How long [`Relay::finish`] waits for output that makes no progress.
pub const FLUSH_STALL: Duration = Duration::from_secs(1);
/// The largest write that stays whole in a pipe shared with other writers (`PIPE_BUF`).
const WHOLE: usize = 4096;

/// One relayed descriptor (module docs).
#[derive(Debug)]
pub struct Relay {
    fd: RawFd,
    real: OwnedFd,
    shared: Arc<Shared>,
}

#[derive(Debug, Default)]
struct Shared {
    state: Mutex<State>,
    changed: Condvar,
    /// The pipe's read end (to ask how much waits in it).
    pipe: OnceLock<RawFd>,
}

#[derive(Debug, Default)]
struct State {
    buffer: VecDeque<u8>,
    /// Bytes dropped since the last notice.
    dropped: u64,
    /// Bytes written to the real output so far.
    written: u64,
    /// The writer holds bytes it took from the buffer and has not written yet.
    writing: bool,
    /// The real output failed (its reader is gone): discard.
    broken: bool,
    /// The rest of a line being dropped is still to come.
    mid_drop: bool,
}

impl State {
    /// Takes `bytes` into the buffer, or drops them, whole lines only: a line is never
    /// cut and joined to another.
    fn accept(&mut self, mut bytes: &[u8]) {
        if self.mid_drop {
            let Some(i) = bytes.iter().position(|b| *b == b'\n') else {
                self.dropped += bytes.len() as u64;
                return;
            };
            self.dropped += i as u64 + 1;
            bytes = &bytes[i + 1..];
            self.mid_drop = false;
        }
        if self.buffer.len() + bytes.len() <= BUFFER_BYTES {
            self.buffer.extend(bytes);
            return;
        }
        // Full: the line begun at the buffer's end goes too, with everything that came.
        let tail = self.buffer.iter().rev().position(|b| *b == b'\n');
        let tail = tail.unwrap_or(self.buffer.len());
        self.buffer.truncate(self.buffer.len() - tail);
        self.dropped += (tail + bytes.len()) as u64;
        self.mid_drop = bytes.last() != Some(&b'\n');
    }
}

/// Every relay of this process, for the panic hook.
static RELAYS: Mutex<Vec<Arc<Shared>>> = Mutex::new(Vec::new());

impl Relay {
    /// Relays stdout and stderr where they are pipes (module docs), and where `terminals`
    /// also where they are terminals; `None` for one that is not, or cannot be relayed (a
    /// closed descriptor, no threads left): it stays as it was. A file is left alone (a
    /// write to it does not wait for a reader).
    pub fn install_stdio(terminals: bool) -> [Option<Relay>; 2] {
        [libc::STDOUT_FILENO, libc::STDERR_FILENO].map(|fd| {
            // SAFETY: isatty on a descriptor number.
            let tty = terminals && unsafe { libc::isatty(fd) } == 1;
            (is_pipe(fd) || tty).then(|| Self::install(fd))?
        })
    }

    /// Relays descriptor `fd` (module docs).
    pub fn install(fd: RawFd) -> Option<Relay> {
        // SAFETY: plain system calls on descriptors this function owns or `fd`; each result
        // is checked before use.
        unsafe {
            let real = libc::fcntl(fd, libc::F_DUPFD_CLOEXEC, 3);
            if real < 0 {
                return None;
            }
            let real = OwnedFd::from_raw_fd(real);
            let mut p = [0; 2];
            if libc::pipe2(p.as_mut_ptr(), libc::O_CLOEXEC) != 0 {
                return None;
            }
            let (read, write) = (OwnedFd::from_raw_fd(p[0]), OwnedFd::from_raw_fd(p[1]));
            let shared = Arc::new(Shared::default());
            let _ = shared.pipe.set(read.as_raw_fd());
            let real_fd = real.as_raw_fd();
            let (s1, s2) = (shared.clone(), shared.clone());
            let reader = std::thread::Builder::new()
                .name(format!("relay-{fd}-in"))
                .spawn(move || read_loop(read, &s1));
            if reader.is_err() {
                return None;
            }
            let writer = std::thread::Builder::new()
                .name(format!("relay-{fd}-out"))
                .spawn(move || write_loop(real_fd, &s2));
            if writer.is_err() {
                // The reader holds the pipe's read end; with nothing in it, it only waits.
                return None;
            }
            // From here on the process (and every child it starts) writes into the pipe.
            if libc::dup2(write.as_raw_fd(), fd) < 0 {
                return None;
            }
            drop(write);
            install_panic_flush();
            if let Ok(mut all) = RELAYS.lock() {
                all.push(shared.clone());
            }
            Some(Relay { fd, real, shared })
        }
    }

    /// Waits until everything written so far is out (at most until [`FLUSH_STALL`] passes
    /// without progress), then writes to the real output directly again.
    pub fn finish(self) {
        flush(&self.shared);
        // SAFETY: `real` is open; dup2 replaces our pipe's write end in `fd` with it.
        unsafe { libc::dup2(self.real.as_raw_fd(), self.fd) };
        // The relay threads end when the process does (children may hold the pipe).
        std::mem::forget(self.real);
    }
}

/// Whether `fd` is a pipe (or a FIFO).
fn is_pipe(fd: RawFd) -> bool {
    // SAFETY: fstat fills the struct for an open descriptor; checked.
    let mut st: libc::stat = unsafe { std::mem::zeroed() };
    (unsafe { libc::fstat(fd, &mut st) }) == 0 && st.st_mode & libc::S_IFMT == libc::S_IFIFO
}

/// Whether stderr was a terminal before [`Stdio::relay_terminals_too`] relayed it (else
/// whether it is one now).
pub fn stderr_was_terminal() -> bool {
    use std::io::IsTerminal;
    STDERR_WAS_TERMINAL.load(std::sync::atomic::Ordering::Relaxed)
        || std::io::stderr().is_terminal()
}

static STDERR_WAS_TERMINAL: std::sync::atomic::AtomicBool =
    std::sync::atomic::AtomicBool::new(false);

/// Stdout and stderr relayed (see [`Relay::install_stdio`]) until [`Stdio::finish`].
#[derive(Debug)]
pub struct Stdio([Option<Relay>; 2]);

impl Stdio {
    /// Relays this process's stdout and stderr where they are pipes.
    pub fn relay() -> Self {
        Self(Relay::install_stdio(false))
    }

    /// Relays this process's stdout and stderr where they are pipes or terminals: a run's
    /// launcher, whose roles inherit its output. Only the relay's thread then writes to a
    /// terminal, and when the terminal hangs up (an SSH connection dropped: every write
    /// then fails with `EIO`) it discards the output; a process that printed to the
    /// terminal itself would panic, and one did: the launcher or the monitor in the window
    /// between the hangup and the stop it signals. Whether stderr was a terminal is kept
    /// ([`stderr_was_terminal`]): the monitor's live status line is for one.
    pub fn relay_terminals_too() -> Self {
        // SAFETY: isatty on a descriptor number.
        let tty = unsafe { libc::isatty(libc::STDERR_FILENO) } == 1;
        STDERR_WAS_TERMINAL.store(tty, std::sync::atomic::Ordering::Relaxed);
        Self(Relay::install_stdio(true))
    }

    /// Nothing relayed (output stays as it is).
    pub fn none() -> Self {
        Self([None, None])
    }

    /// Flushes both and writes directly again (before the process exits).
    pub fn finish(self) {
        use std::io::Write;
        let _ = std::io::stdout().flush();
        self.0.into_iter().flatten().for_each(Relay::finish);
    }
}

/// Pipe → buffer; drops what does not fit. Bytes leave the pipe only while the lock is
/// held, so [`flush`] never sees them in neither place (a read outside the lock once lost
/// a process's last line: out of the pipe, not yet in the buffer, the process gone).
fn read_loop(pipe: OwnedFd, shared: &Shared) {
    let fd = pipe.as_raw_fd();
    let mut chunk = vec![0u8; 64 * 1024];
    loop {
        let mut p = libc::pollfd { fd, events: libc::POLLIN, revents: 0 };
        // SAFETY: polls one descriptor of ours.
        let rc = unsafe { libc::poll(&mut p, 1, -1) };
        if rc < 0 {
            if std::io::Error::last_os_error().kind() == std::io::ErrorKind::Interrupted {
                continue;
            }
            return;
        }
        let Ok(mut st) = shared.state.lock() else { return };
        let ready = in_pipe(shared).min(chunk.len());
        if ready == 0 {
            if p.revents & (libc::POLLHUP | libc::POLLERR) != 0 {
                return; // every writer is gone
            }
            continue;
        }
        // SAFETY: reads at most what the pipe holds (no wait) into our own buffer.
        let n = unsafe { libc::read(fd, chunk.as_mut_ptr().cast(), ready) };
        if n <= 0 {
            continue;
        }
        let n = n as usize;
        if st.broken {
            st.written += n as u64;
        } else {
            st.accept(&chunk[..n]);
        }
        drop(st);
        shared.changed.notify_all();
    }
}

/// Buffer → the real output, whole lines where it can; blocks only itself.
fn write_loop(real: RawFd, shared: &Shared) {
    loop {
        let out: Vec<u8> = {
            let Ok(mut st) = shared.state.lock() else { return };
            while st.buffer.is_empty() && st.dropped == 0 {
                st.writing = false;
                shared.changed.notify_all();
                st = match shared.changed.wait(st) {
                    Ok(st) => st,
                    Err(_) => return,
                };
            }
            st.writing = true;
            if st.buffer.is_empty() {
                let lost = std::mem::take(&mut st.dropped);
                format!("[{lost} bytes of output dropped: it was not being read]\n").into_bytes()
            } else {
                let head = st.buffer.len().min(WHOLE);
                let line_end = st.buffer.range(..head).rposition(|b| *b == b'\n');
                let take = line_end.map_or(head, |i| i + 1);
                st.buffer.drain(..take).collect()
            }
        };
        let ok = write_all(real, &out);
        let Ok(mut st) = shared.state.lock() else { return };
        st.written += out.len() as u64;
        if !ok {
            st.broken = true;
            st.buffer.clear();
            st.dropped = 0;
        }
    }
}

/// Writes all of `bytes` to `fd`; false when the output is gone.
fn write_all(fd: RawFd, mut bytes: &[u8]) -> bool {
    while !bytes.is_empty() {
        // SAFETY: writes from our own buffer to an open descriptor.
        let n = unsafe { libc::write(fd, bytes.as_ptr().cast(), bytes.len()) };
        if n < 0 {
            if std::io::Error::last_os_error().kind() == std::io::ErrorKind::Interrupted {
                continue;
            }
            return false;
        }
        bytes = &bytes[n as usize..];
    }
    true
}

/// Bytes still in the pipe.
fn in_pipe(shared: &Shared) -> usize {
    let Some(&fd) = shared.pipe.get() else { return 0 };
    let mut n: libc::c_int = 0;
    // SAFETY: FIONREAD writes one int.
    let rc = unsafe { libc::ioctl(fd, libc::FIONREAD, &mut n) };
    if rc == 0 { n.max(0) as usize } else { 0 }
}

/// Waits until the pipe and the buffer are empty and the writer idle, or until the output
/// has made no progress for [`FLUSH_STALL`].
fn flush(shared: &Shared) {
    let mut last = (u64::MAX, usize::MAX);
    let mut since = Instant::now();
    loop {
        let Ok(st) = shared.state.lock() else { return };
        let pending = in_pipe(shared); // under the lock: the reader moves bytes only under it
        if pending == 0 && st.buffer.is_empty() && st.dropped == 0 && !st.writing {
            return;
        }
        let now = (st.written, pending + st.buffer.len());
        drop(st);
        if now != last {
            (last, since) = (now, Instant::now());
        } else if since.elapsed() > FLUSH_STALL {
            return;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// A panic's message goes out before the process ends.
fn install_panic_flush() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            previous(info);
            let all = RELAYS.lock().map(|v| v.clone()).unwrap_or_default();
            all.iter().for_each(|s| flush(s));
        }));
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pipe whose read end nobody reads yet, filled to the brim.
    fn full_pipe() -> (OwnedFd, OwnedFd) {
        let mut p = [0; 2];
        // SAFETY: plain system calls on descriptors this test owns.
        unsafe {
            assert_eq!(libc::pipe2(p.as_mut_ptr(), libc::O_CLOEXEC | libc::O_NONBLOCK), 0);
            let chunk = [b'x'; 4096];
            while libc::write(p[1], chunk.as_ptr().cast(), chunk.len()) > 0 {}
            let flags = libc::fcntl(p[1], libc::F_GETFL);
            libc::fcntl(p[1], libc::F_SETFL, flags & !libc::O_NONBLOCK);
            (OwnedFd::from_raw_fd(p[0]), OwnedFd::from_raw_fd(p[1]))
        }
    }

    /// Reads what `fd` holds now, without blocking.
    fn drain(fd: &OwnedFd) -> Vec<u8> {
        // SAFETY: plain system calls on a descriptor this test owns.
        unsafe {
            let flags = libc::fcntl(fd.as_raw_fd(), libc::F_GETFL);
            libc::fcntl(fd.as_raw_fd(), libc::F_SETFL, flags | libc::O_NONBLOCK);
        }
        let mut out = Vec::new();
        let mut chunk = [0u8; 65536];
        loop {
            // SAFETY: as above.
            let n = unsafe { libc::read(fd.as_raw_fd(), chunk.as_mut_ptr().cast(), chunk.len()) };
            if n <= 0 {
                return out;
            }
            out.extend_from_slice(&chunk[..n as usize]);
        }
    }

    /// A process whose output nobody reads is never blocked by it: 4 MiB written to a
    /// relayed descriptor whose real output is a full pipe return at once; what did not fit
    /// is dropped and said so once the output is read again; the rest arrives in order.
    #[test]
    fn writes_never_block_on_an_output_nobody_reads_and_drops_are_reported() {
        let (read, write) = full_pipe();
        // A descriptor of our own to relay (not the test's real stdout or stderr).
        // SAFETY: dup of a descriptor this test owns.
        let fd = unsafe { libc::fcntl(write.as_raw_fd(), libc::F_DUPFD_CLOEXEC, 100) };
        assert!(fd >= 0);
        let relay = Relay::install(fd).expect("relay");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let line = [b'y'; 1023];
            for _ in 0..4096 {
                assert!(write_all(fd, &line) && write_all(fd, b"\n"));
            }
            assert!(write_all(fd, b"last line\n"));
            let _ = tx.send(());
        });
        // Would block for ever without the relay: nobody reads `read` until the writes return.
        rx.recv_timeout(Duration::from_secs(60)).expect("the writes returned");
        let mut got = Vec::new();
        let reader = std::thread::spawn(move || {
            let deadline = Instant::now() + Duration::from_secs(60);
            loop {
                got.extend(drain(&read));
                let text = String::from_utf8_lossy(&got).into_owned();
                if text.contains("bytes of output dropped") || Instant::now() > deadline {
                    return text;
                }
                std::thread::sleep(Duration::from_millis(5));
            }
        });
        let text = reader.join().expect("reader");
        assert!(text.contains("bytes of output dropped: it was not being read"), "{}", text.len());
        // Whole lines only, in order: every relayed line is 1023 y's (or the last one).
        // (The last line can be read before the drop notice: it is relayed like any other.)
        let lines: Vec<&str> =
            text.lines().filter(|l| !l.starts_with('x') && !l.starts_with('[')).collect();
        for (i, line) in lines.iter().enumerate() {
            let last = *line == "last line" && i + 1 == lines.len();
            assert!(last || (line.len() == 1023 && line.bytes().all(|b| b == b'y')), "{line:?}");
        }
        relay.finish();
        // SAFETY: closes our own descriptor.
        unsafe { libc::close(fd) };
        drop(write);
    }

    /// A real output that is gone (its reader exited) is no error: writes go on.
    #[test]
    fn an_output_whose_reader_is_gone_is_discarded_without_an_error() {
        let (read, write) = full_pipe();
        drop(read);
        // SAFETY: dup of a descriptor this test owns.
        let fd = unsafe { libc::fcntl(write.as_raw_fd(), libc::F_DUPFD_CLOEXEC, 100) };
        let relay = Relay::install(fd).expect("relay");
        for _ in 0..1000 {
            assert!(write_all(fd, b"into the void\n"));
        }
        relay.finish();
        // SAFETY: closes our own descriptor.
        unsafe { libc::close(fd) };
    }
}
