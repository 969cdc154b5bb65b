//! Termination signals: SIGINT and SIGTERM set a flag each role's loop reads, so a role
//! stopped by its launcher ends like one that finished (its records closed, its last
//! sample published).

use std::sync::atomic::{AtomicBool, Ordering};

static SHUTDOWN: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_: libc::c_int) {
    SHUTDOWN.store(true, Ordering::SeqCst);
}

/// Installs SIGINT/SIGTERM handlers that set the flag read by [`shutdown_requested`].
pub fn install_signal_handlers() {
    for sig in [libc::SIGINT, libc::SIGTERM] {
        // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
        unsafe {
            let mut sa: libc::sigaction = std::mem::zeroed();
            sa.sa_sigaction = on_signal as *const () as usize;
            libc::sigemptyset(&mut sa.sa_mask);
            libc::sigaction(sig, &sa, std::ptr::null_mut());
        }
    }
}

/// Whether SIGINT or SIGTERM arrived.
#[inline]
pub fn shutdown_requested() -> bool {
    SHUTDOWN.load(Ordering::Relaxed)
}

/// Stops this process (SIGSTOP) until someone continues or kills it (the tests' hooks).
pub fn stop_self() {
    // SAFETY: raises a signal in this process.
    unsafe { libc::raise(libc::SIGSTOP) };
}
