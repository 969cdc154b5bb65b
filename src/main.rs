//! The `rotorloop` binary: a thin shell over the library (see `rotorloop::cli`).

fn main() -> std::process::ExitCode {
    // A fixed threshold above which the allocator maps a block of its own and unmaps it
    // when freed. glibc's default raises the threshold to the size of every large block
    // freed (up to 32 MiB), after which blocks that size stay in the heap once freed: the
    // launcher's record mover, which reads halves of the rings of tens of MB, then kept
    // their peak for the rest of the run, and the phases after the last tick added theirs.
    // SAFETY: mallopt before any thread exists.
    unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 20) };
    let code = rotorloop::cli::main();
    peak_rss_report();
    code
}

/// `ROTORLOOP_PEAK_RSS=FILE`: each `rotorloop` process (the launcher, every role, every
/// command) appends one line to FILE as it ends normally: its arguments after the
/// program's name, a tab, and its peak resident memory in KiB (`VmHWM` of
/// `/proc/self/status`). How the memory of every phase of a run is measured
/// (docs/measurements.md, `tests/memory.rs`); a process killed by a signal writes nothing.
///
/// Not `getrusage`'s `ru_maxrss`: Linux keeps that across `execve`, so a process started
/// by a `fork` (a `Command` with a `pre_exec` hook) reports at least its parent's memory
/// at the fork: a command spawned by a test process holding 23 MB of traces said 23 MB.
fn peak_rss_report() {
    use std::io::Write;
    let Some(path) = std::env::var_os("ROTORLOOP_PEAK_RSS") else { return };
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let Some(peak_kib) = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
    else {
        return;
    };
    let args: Vec<String> = std::env::args().skip(1).collect();
    let line = format!("{}\t{peak_kib}\n", args.join(" "));
    // One write of a short line to a file opened for appending: lines of processes
    // ending at once do not interleave.
    let file = std::fs::OpenOptions::new().create(true).append(true).open(path);
    if let Ok(mut f) = file {
        let _ = f.write_all(line.as_bytes());
    }
}
