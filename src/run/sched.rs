//! The kernel's view of each role while the run goes on, without privileges: a thread of
//! the launcher (off the hot path, like the monitor, and never killed by a fault) reads
//! each role's `/proc/PID/schedstat` (time on a CPU, time runnable but waiting for one),
//! its state and last CPU in `/proc/PID/stat` (`R` running or runnable, `S` sleeping, `T`
//! stopped, …) and the machine's steal time in `/proc/stat` every [`PERIOD_NS`], into
//! `OUT/sched.csv`. The incidents of the run (`crate::pipeline::incidents`) read it to say
//! "runnable, not running for 29 ms", "stopped", or "the host took the vCPU".
//!
//! The files are opened once per life of a role and read with `pread` at offset 0 (a
//! `/proc` file is generated on each read), so a sample is three system calls per role and
//! no allocation. A role that has died is skipped until its next life is tracked.

use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use rotorloop_common::clock::now_ns;

use crate::pipeline::sched_csv::{self, HEADER, PERIOD_NS};

/// One role's life: its pid and its open `/proc` files.
struct Life {
    role: String,
    pid: u32,
    schedstat: std::fs::File,
    stat: std::fs::File,
    /// The last row written: (t, state, CPU, on CPU, waiting).
    written: Option<(u64, char, u32, u64, u64)>,
}

/// Whether a sample is worth a row: the first of a life, a change of state or CPU, 100 µs
/// more waiting or 1 ms more on a CPU since the last row, or 50 ms since it. Between two
/// rows a role waited less than 100 µs and ran less than 1 ms more than the first says,
/// so a window's figures are that close, and the file is several times smaller than one
/// row a millisecond (a sixth, measured on a loaded 2-vCPU machine).
fn worth_a_row(last: Option<(u64, char, u32, u64, u64)>, now: (u64, char, u32, u64, u64)) -> bool {
    let Some((t, state, cpu, on, wait)) = last else { return true };
    state != now.1
        || cpu != now.2
        || now.3 >= on + 1_000_000
        || now.4 >= wait + 100_000
        || now.0 >= t + 50_000_000
}

/// The sampler thread and the roles it looks at.
pub(crate) struct SchedSampler {
    lives: Arc<Mutex<Vec<Life>>>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl SchedSampler {
    /// Starts sampling into `out/sched.csv`, or `out/sched.csv.zst` where `compressed`
    /// (`run --no-csv`: zstd, about a quarter of the bytes, read with `zstdcat` or pandas);
    /// `None` (with a warning) where the file cannot be written: the kernel's view is an
    /// observer's, never a reason to stop the run.
    pub(crate) fn start(out: &Path, compressed: bool) -> Option<Self> {
        let path = out.join(if compressed { sched_csv::ZST } else { sched_csv::FILE });
        let file = rotorloop_common::outdir::create_file(&path)
            .map_err(|e| eprintln!("warning: cannot write {}: {e}", path.display()))
            .ok()?;
        let file: Box<dyn Write + Send> = match compressed {
            // Finished when the sampler drops it; a launcher killed mid-run leaves a frame
            // cut short, which the readers read as far as it goes.
            true => Box::new(
                zstd::stream::write::Encoder::new(file, 3)
                    .map_err(|e| eprintln!("warning: cannot write {}: {e}", path.display()))
                    .ok()?
                    .auto_finish(),
            ),
            false => Box::new(file),
        };
        let lives: Arc<Mutex<Vec<Life>>> = Arc::default();
        let stop = Arc::new(AtomicBool::new(false));
        let (l, s) = (lives.clone(), stop.clone());
        let thread = std::thread::Builder::new()
            .name("sched-sampler".into())
            .spawn(move || sample_until(&l, &s, std::io::BufWriter::new(file)))
            .map_err(|e| eprintln!("warning: no scheduler sampling: {e}"))
            .ok()?;
        Some(Self { lives, stop, thread: Some(thread) })
    }

    /// A new life of `role` (pid `pid`): it replaces the role's earlier one.
    pub(crate) fn track(&self, role: &str, pid: u32) {
        let open = |what: &str| std::fs::File::open(format!("/proc/{pid}/{what}"));
        let (Ok(schedstat), Ok(stat)) = (open("schedstat"), open("stat")) else {
            return;
        };
        let mut lives = self.lives.lock().unwrap_or_else(|e| e.into_inner());
        lives.retain(|l| l.role != role);
        lives.push(Life { role: role.to_owned(), pid, schedstat, stat, written: None });
    }
}

impl Drop for SchedSampler {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn sample_until(lives: &Mutex<Vec<Life>>, stop: &AtomicBool, mut out: impl Write) {
    let mut buf = [0u8; 1024];
    let mut text = String::with_capacity(4096);
    let stat = std::fs::File::open("/proc/stat").ok();
    let ns_per_clock = 1e9 / clock_ticks_per_second();
    let _ = writeln!(out, "{HEADER}");
    let mut next = now_ns();
    while !stop.load(Ordering::Relaxed) {
        next += PERIOD_NS;
        rotorloop_common::clock::sleep_until_ns(next, 0);
        let t = now_ns();
        let steal = stat.as_ref().and_then(|f| read(f, &mut buf)).and_then(steal_clocks);
        let steal_ns = steal.map_or(0, |c| (c as f64 * ns_per_clock) as u64);
        text.clear();
        for life in lives.lock().unwrap_or_else(|e| e.into_inner()).iter_mut() {
            let Some((on, wait)) = read(&life.schedstat, &mut buf).and_then(schedstat) else {
                continue;
            };
            let Some((state, cpu)) = read(&life.stat, &mut buf).and_then(state_and_cpu) else {
                continue;
            };
            let now = (t, state, cpu, on, wait);
            if !worth_a_row(life.written, now) {
                continue;
            }
            life.written = Some(now);
            use std::fmt::Write as _;
            let _ = writeln!(
                text,
                "{t},{},{},{state},{cpu},{on},{wait},{steal_ns}",
                life.role, life.pid
            );
        }
        if out.write_all(text.as_bytes()).is_err() {
            eprintln!("warning: cannot write sched.csv any more; scheduler sampling ends");
            return;
        }
    }
    let _ = out.flush();
}

/// A `/proc` file's text now, or `None` where its process is gone.
fn read<'a>(f: &std::fs::File, buf: &'a mut [u8]) -> Option<&'a str> {
    let n = f.read_at(buf, 0).ok().filter(|n| *n > 0)?;
    std::str::from_utf8(&buf[..n]).ok()
}

/// `/proc/PID/schedstat`: time on a CPU and time runnable but waiting (ns).
fn schedstat(s: &str) -> Option<(u64, u64)> {
    let mut w = s.split_ascii_whitespace().map(|x| x.parse::<u64>().ok());
    Some((w.next()??, w.next()??))
}

/// `/proc/PID/stat`: the state letter (field 3) and the CPU it last ran on (field 39). The
/// command name (field 2) may hold spaces and parentheses: the fields after it are
/// counted from its last `)`.
pub fn state_and_cpu(s: &str) -> Option<(char, u32)> {
    let after = &s[s.rfind(')')? + 1..];
    let mut w = after.split_ascii_whitespace();
    let state = w.next()?.chars().next()?;
    let cpu = w.nth(35)?.parse().ok()?;
    Some((state, cpu))
}

/// The machine's steal time in `/proc/stat` (clock ticks): the eighth number of its `cpu`
/// line (0 where the kernel does not count it).
fn steal_clocks(s: &str) -> Option<u64> {
    let line = s.lines().next().filter(|l| l.starts_with("cpu "))?;
    Some(line.split_ascii_whitespace().nth(8).and_then(|x| x.parse().ok()).unwrap_or(0))
}

fn clock_ticks_per_second() -> f64 {
    // SAFETY: sysconf reads a constant of the system.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    if hz > 0 { hz as f64 } else { 100.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn proc_fields_are_read_past_a_command_name_with_spaces_and_parentheses() {
        let stat = "4242 (a (b) c) T 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19 20 21 22 \
                    23 24 25 26 27 28 29 30 31 32 33 34 35 1 0 0";
        assert_eq!(state_and_cpu(stat), Some(('T', 1)));
        assert_eq!(schedstat("123 456 7\n"), Some((123, 456)));
        let proc_stat = "cpu  10 0 20 30 0 0 1 17 0 0\ncpu0 5 0 10 15 0 0 1 9 0 0\n";
        assert_eq!(steal_clocks(proc_stat), Some(17));
    }

    /// Plain and compressed (`run --no-csv`), the file holds the rows of a busy process,
    /// whole once the sampler ends.
    #[test]
    fn a_running_process_is_sampled_with_its_time_on_cpu() {
        for compressed in [false, true] {
            let dir =
                std::env::temp_dir().join(format!("rl-sched-{}-{compressed}", std::process::id()));
            std::fs::create_dir_all(&dir).expect("temp dir");
            let sampler = SchedSampler::start(&dir, compressed).expect("sched.csv");
            let mut busy = std::process::Command::new("yes")
                .stdout(std::process::Stdio::null())
                .spawn()
                .expect("yes");
            sampler.track("busy", busy.id());
            std::thread::sleep(std::time::Duration::from_millis(40));
            busy.kill().expect("kill");
            busy.wait().expect("wait");
            std::thread::sleep(std::time::Duration::from_millis(5));
            drop(sampler);
            let text = match compressed {
                false => std::fs::read_to_string(dir.join("sched.csv")).expect("sched.csv"),
                true => {
                    let bytes = std::fs::read(dir.join("sched.csv.zst")).expect("sched.csv.zst");
                    let text = zstd::decode_all(&bytes[..]).expect("a whole frame");
                    String::from_utf8(text).expect("text")
                }
            };
            assert!(text.starts_with(HEADER), "{text}");
            let rows: Vec<Vec<&str>> =
                text.lines().skip(1).map(|l| l.split(',').collect()).collect();
            assert!(rows.len() >= 5, "{} rows in 30 ms:\n{text}", rows.len());
            let on = |r: &Vec<&str>| r[5].parse::<u64>().expect("on_cpu_ns");
            assert!(on(rows.last().expect("rows")) > on(&rows[0]), "time on CPU grows:\n{text}");
            assert!(rows.iter().all(|r| r[1] == "busy" && r[2] == busy.id().to_string()));
            std::fs::remove_dir_all(&dir).expect("clean up");
        }
    }
}
