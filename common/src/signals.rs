//! Termination signals: SIGINT, SIGTERM and SIGHUP set a flag each role's loop reads, so a
//! role stopped by its launcher ends like one that finished (its records closed, its last
//! sample published), and a launcher stopped by one writes a partial report and leaves
//! nothing behind.
//!
//! **SIGHUP is a stop like SIGINT** (docs/running.md): the terminal of the run is gone (an
//! SSH connection dropped, `tmux kill-session`). What the processes still say goes to
//! `/dev/null` where it went to that terminal (the handler of each of the three signals
//! points it there, the roles' too, which learn of the stop by their launcher's SIGTERM: a
//! print that fails with `EIO` would panic), and an output relay (`relay`) discards what its real
//! output refuses. A run's launcher relays its terminal too (`Stdio::relay_terminals_too`),
//! so that no process of a run writes to the terminal itself: the hangup comes before the
//! signal, and a print in between panicked (the launcher, in the suite). A run meant to outlive its terminal is started under
//! `nohup` (a SIGHUP that is ignored when the process starts stays ignored), `setsid` or a
//! terminal multiplexer.

use std::sync::atomic::{AtomicBool, Ordering};

static SHUTDOWN: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_sig: libc::c_int) {
    // Before the flag: another thread that sees it may print its way out at once. And on
    // every signal, not SIGHUP alone: the kernel sends SIGHUP to the session's leader (the
    // launcher), whose roles then learn of the stop by SIGINT, their terminal as gone.
    away_from_a_hung_up_terminal();
    SHUTDOWN.store(true, Ordering::SeqCst);
}

/// Points stdin, stdout and stderr that are a terminal which hung up at `/dev/null`: what
/// the process still says on its way out (a partial report's last lines) would otherwise
/// fail with `EIO`, and a print that fails panics. Only such a terminal: after a hangup
/// the kernel answers every request on it with `EIO` (a live terminal answers `TCGETS`,
/// anything else `ENOTTY`). Called from the SIGHUP handler: `ioctl`, `open`, `dup2` and
/// `close` are plain system calls, safe there.
fn away_from_a_hung_up_terminal() {
    // SAFETY: system calls on this process's own descriptors and a termios of ours.
    unsafe {
        // The interrupted code's errno is its own.
        let saved = *libc::__errno_location();
        let mut null = -1;
        for fd in 0..3 {
            let mut t: libc::termios = std::mem::zeroed();
            if libc::ioctl(fd, libc::TCGETS, &mut t) == 0 || *libc::__errno_location() != libc::EIO
            {
                continue;
            }
            if null < 0 {
                null = libc::open(c"/dev/null".as_ptr(), libc::O_RDWR | libc::O_CLOEXEC);
            }
            if null >= 0 {
                libc::dup2(null, fd);
            }
        }
        if null >= 0 {
            libc::close(null);
        }
        *libc::__errno_location() = saved;
    }
}

/// Installs SIGINT/SIGTERM/SIGHUP handlers that set the flag read by
/// [`shutdown_requested`] (module docs).
pub fn install_signal_handlers() {
    for sig in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP] {
        // SAFETY: the handler stores to an atomic and makes system calls, which are
        // async-signal-safe; the query of the disposition fills a struct of ours.
        unsafe {
            let mut old: libc::sigaction = std::mem::zeroed();
            libc::sigaction(sig, std::ptr::null(), &mut old);
            if sig == libc::SIGHUP && old.sa_sigaction == libc::SIG_IGN {
                continue; // `nohup`: the run outlives its terminal, as asked
            }
            let mut sa: libc::sigaction = std::mem::zeroed();
            sa.sa_sigaction = on_signal as *const () as usize;
            libc::sigemptyset(&mut sa.sa_mask);
            libc::sigaction(sig, &sa, std::ptr::null_mut());
        }
    }
}

/// Whether SIGINT, SIGTERM or SIGHUP arrived.
#[inline]
pub fn shutdown_requested() -> bool {
    SHUTDOWN.load(Ordering::Relaxed)
}

/// Stops this process (SIGSTOP) until someone continues or kills it (the tests' hooks).
pub fn stop_self() {
    // SAFETY: raises a signal in this process.
    unsafe { libc::raise(libc::SIGSTOP) };
}
