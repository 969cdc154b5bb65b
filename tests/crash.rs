//! What survives what: a closed terminal (SIGHUP), a missing or damaged file of the record,
//! and a crash of the whole machine.
//!
//! The machine crash is made without a reboot: the run's `--out` is on an ext4 image,
//! loop-mounted; at a seeded random moment of the run its processes are stopped, the image
//! file is copied (what the block device holds: the filesystem's dirty pages are not in it,
//! as after a power cut), every process of the run is killed (`kill -9`) and its
//! `/dev/shm` entries removed (what a reboot does to tmpfs). The copy is then mounted (the
//! filesystem's journal replayed, as at boot) and `rotorloop recover` writes the report.
//! The image file lies on a tmpfs of its own: a disk whose flush is done at once, so that
//! what is measured is the record's own promise (what it makes durable, and when), not the
//! host disk's `fsync` latency under the other tests' writes (on the host disk, beside the
//! whole suite, one journal and its `fdatasync` took 1.07 s, and a crash lost 2.1 s).
//! Needs root, loop devices and `mkfs.ext4`; skipped with a message without them.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rand::Rng;
use rotorloop_common::flight::{FlightLog, Record, Stream};
use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample};

use crate::common::harness::{Harness, ROTORLOOP, group, json, live_timing_rows, ok, processes_of};

const LIMIT: Duration = Duration::from_secs(180);

fn signal_all(pids: &[u32], sig: libc::c_int) {
    for &pid in pids {
        // SAFETY: a plain system call on processes this test started.
        unsafe { libc::kill(pid as libc::pid_t, sig) };
    }
}

/// A terminal that hangs up in the middle of a run (the SSH connection dropped, `tmux
/// kill-session`: SIGHUP) stops it as SIGINT does: exit 3, a partial report, nothing of
/// the domain left in shared memory. The run's terminal is a real pseudo-terminal whose
/// master is closed (before, the launcher died of the SIGHUP: no `summary.json`, the
/// domain's files left in `/dev/shm`).
#[test]
fn a_closed_terminal_stops_the_run_like_sigint_with_a_partial_report_and_nothing_left() {
    use std::os::unix::process::CommandExt;
    let h = Harness::new("hangup");
    let out = h.path("rt");
    // SAFETY: plain system calls making a pseudo-terminal; checked.
    let (master, slave) = unsafe {
        // Closed on exec from the start: the hangup comes when the last master descriptor
        // closes, so neither the run nor a process another test starts meanwhile (the
        // tests run in threads of one process) may inherit it. With `FD_CLOEXEC` set just
        // after, one did in the suite: the terminal never hung up and the run ended normally
        // 60 s later (exit 0).
        let master = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC);
        assert!(master >= 0, "posix_openpt");
        assert_ne!(libc::fcntl(master, libc::F_GETFD) & libc::FD_CLOEXEC, 0, "close on exec");
        assert_eq!(libc::grantpt(master), 0);
        assert_eq!(libc::unlockpt(master), 0);
        let mut name = [0 as libc::c_char; 128];
        assert_eq!(libc::ptsname_r(master, name.as_mut_ptr(), name.len()), 0);
        (master, std::ffi::CStr::from_ptr(name.as_ptr()).to_owned())
    };
    let slave_name = slave.clone();
    // Each process that ends normally (not by a panic) says so in this file.
    let ends = h.path("ends");
    let mut cmd = Command::new(ROTORLOOP);
    cmd.args(["run", "--scenario", "paper-zero", "--duration", "60", "--mode", "realtime"])
        .args(["--domain", &h.domain, "--out"])
        .arg(&out)
        .env("ROTORLOOP_PEAK_RSS", &ends);
    // SAFETY: between fork and exec only async-signal-safe calls: the child leads a session
    // of its own whose controlling terminal is the pseudo-terminal, its stdio on it.
    unsafe {
        cmd.pre_exec(move || {
            if libc::setsid() < 0 {
                return Err(std::io::Error::last_os_error());
            }
            let fd = libc::open(slave.as_ptr(), libc::O_RDWR);
            if fd < 0 || libc::ioctl(fd, libc::TIOCSCTTY, 0) < 0 {
                return Err(std::io::Error::last_os_error());
            }
            for t in 0..3 {
                libc::dup2(fd, t);
            }
            if fd > 2 {
                libc::close(fd);
            }
            Ok(())
        });
    }
    let mut launcher = cmd.spawn().expect("spawn the run on a terminal");
    let until = Instant::now() + LIMIT;
    while processes_of(&h.domain).len() < 5 || live_timing_rows(&out) < 1000 {
        assert!(Instant::now() < until, "the run did not start");
        assert!(launcher.try_wait().expect("wait").is_none(), "the run ended early");
        std::thread::sleep(Duration::from_millis(50));
    }
    // The terminal goes away: the master closed, and the hangup forced (`TIOCVHANGUP`,
    // what the master's close does to the slave), since a process another test of this
    // one spawned may hold a copy of the master between its fork and its exec: in the
    // suite the terminal then never hung up and the run ended normally after 60 s.
    // SAFETY: closes the master this test opened; opens the slave without making it a
    // controlling terminal, hangs it up and closes it.
    unsafe {
        libc::close(master);
        let fd = libc::open(slave_name.as_ptr(), libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC);
        if fd >= 0 {
            libc::ioctl(fd, libc::TIOCVHANGUP, 0);
            libc::close(fd);
        }
    }
    let status = loop {
        if let Some(s) = launcher.try_wait().expect("wait") {
            break s;
        }
        if Instant::now() > until {
            let _ = launcher.kill();
            signal_all(&processes_of(&h.domain), libc::SIGKILL);
            panic!("the run did not stop after its terminal hung up");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    assert_eq!(status.code(), Some(3), "stopped by a signal: {status:?}");
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], false, "{s}");
    let rows = s["trace_rows"].as_u64().expect("rows");
    assert!(rows >= 1000, "a partial report of what ran: {rows} rows");
    // Every process ended normally, none of a print to the hung-up terminal (which
    // panics: the monitor's last line did, and the launcher assembled the report for it).
    let ends = std::fs::read_to_string(&ends).unwrap_or_default();
    for who in ["run ", "role plant ", "role reference ", "role controller ", "role monitor "] {
        let n = ends.lines().filter(|l| l.starts_with(who)).count();
        assert_eq!(n, 1, "`{who}` ended normally once:\n{ends}");
    }
    while !processes_of(&h.domain).is_empty() {
        assert!(Instant::now() < until, "roles outlived the launcher");
        std::thread::sleep(Duration::from_millis(20));
    }
    h.assert_no_leftovers();
}

/// A finished run's directory, `--flight-ring-ticks 512`: its records are segments and the
/// rings moved in at the end.
fn finished_run(h: &Harness, mode: &str) -> PathBuf {
    let dir = h.path("run");
    let d = dir.display().to_string();
    let args = ["run", "--scenario", "paper-sinusoid", "--duration", "3", "--mode", mode];
    let more = ["--flight-ring-ticks", "512", "--domain", &h.domain, "--out", &d, "--quiet"];
    ok(&h.rotorloop(&[&args[..], &more[..]].concat(), LIMIT));
    dir
}

/// Copies the run directory `from` to `to` (its files and `flight/`).
fn copy_run(from: &Path, to: &Path) {
    let _ = std::fs::remove_dir_all(to);
    let st = Command::new("cp").arg("-a").arg(from).arg(to).status().expect("cp");
    assert!(st.success());
}

/// Every reader reads what is sound: a run whose record lacks a ring, has a torn ring, a
/// torn segment and a missing one is recovered, explained, exported and replayed (exit 0),
/// each missing or damaged file named in `summary.json` with the reason "record damaged"
/// and its ticks missing, every other tick read; only a record with nothing sound left is
/// refused (exit 2, naming the directory). Before, one torn ring made each of them refuse
/// the whole run.
#[test]
fn readers_read_around_a_missing_or_damaged_ring_or_segment() {
    let h = Harness::new("damaged-ring");
    let run = finished_run(&h, "lockstep");
    let good = json(&run.join("summary.json"));
    let ticks = good["trace_rows"].as_u64().expect("rows");
    assert_eq!(ticks, 3001, "{good}");
    // The run says how far its newest ticks ever were from the disk (its crash bound).
    let lag = good["flight"]["durable_lag_max_s"].as_f64();
    assert!(lag.is_some_and(|l| l > 0.0 && l.is_finite()), "{good}");
    let flight = |d: &Path| d.join("flight");
    let tear = |p: PathBuf, len: u64| {
        std::fs::OpenOptions::new().write(true).open(&p).expect("open").set_len(len).expect("tear")
    };
    type Damage = fn(&Path, &dyn Fn(PathBuf, u64));
    let cases: [(&str, Damage, &str); 3] = [
        (
            "the reference ring missing",
            |f, _| std::fs::remove_file(f.join("reference.flight")).expect("rm"),
            "reference.flight",
        ),
        (
            "the plant state ring torn",
            |f, tear| tear(f.join("plant-state.flight"), 100),
            "plant-state.flight",
        ),
        (
            "a state segment torn, a torque segment missing",
            |f, tear| {
                let seg = f.join("plant-state.000003.flight");
                let len = std::fs::metadata(&seg).expect("segment 3").len();
                tear(seg, len / 2);
                std::fs::remove_file(f.join("plant-torque.000001.flight")).expect("rm");
            },
            "plant-state.000003.flight",
        ),
    ];
    for (what, damage, named) in cases {
        let copy = h.path("damaged");
        copy_run(&run, &copy);
        damage(&flight(&copy), &tear);
        let d = copy.display().to_string();
        let replay = h.path("replay").display().to_string();
        for args in [
            vec!["recover", &d],
            vec!["explain", &d],
            vec!["export", &d, "--mcap"],
            vec!["sim", "--replay", &d, "--out", &replay],
        ] {
            let o = h.rotorloop(&args, LIMIT);
            assert!(
                o.status.success(),
                "{what}: {args:?}: {:?}\n{}",
                o.status,
                String::from_utf8_lossy(&o.stderr)
            );
        }
        let s = json(&copy.join("summary.json"));
        assert_eq!(s["flight"]["lost"]["reason"], "record damaged", "{what}: {s}");
        let problems = s["flight"]["streams"].to_string();
        assert!(problems.contains(named), "{what}: {problems}");
        let rows = s["trace_rows"].as_u64().expect("rows");
        assert!(rows > 0 && rows < ticks, "{what}: {rows} rows of {ticks}");
        assert!(copy.join("run.mcap").exists() && copy.join("incidents.md").exists(), "{what}");
    }
    // The torn segment's ticks (768–1023) are missing; every other state is read.
    let s = json(&h.path("damaged").join("summary.json"));
    let streams = s["flight"]["streams"].as_array().expect("streams");
    let state = streams.iter().find(|x| x["stream"] == "plant-state").expect("plant-state");
    assert_eq!(state["missing"], serde_json::json!([[768, 1023]]), "{s}");
    assert_eq!(s["flight"]["lost"]["ticks"], serde_json::json!([[768, 1023]]), "{s}");
    // Nothing sound: refused, exit 2, naming the directory. The run itself (a copy's
    // summary names the run's own records, read where the copy has none), without its
    // records or the CSVs made from them (`export` reads `trace.csv` where nothing else is).
    for e in std::fs::read_dir(flight(&run)).expect("flight").flatten() {
        std::fs::remove_file(e.path()).expect("rm");
    }
    for csv in ["trace.csv", "timing.csv"] {
        std::fs::remove_file(run.join(csv)).expect("rm");
    }
    let d = run.display().to_string();
    for args in [vec!["recover", &d], vec!["explain", &d], vec!["export", &d, "--mcap"]] {
        let o = h.rotorloop(&args, LIMIT);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(&d), "{args:?}: {err}");
    }
}

/// A loop-mounted ext4 image for a run's `--out` (module docs), removed on drop.
struct Image {
    dir: tempfile::TempDir,
    mounted: Vec<PathBuf>,
}

/// Runs `cmd`; its error output where it fails.
fn sh(cmd: &mut Command) -> Result<(), String> {
    let o = cmd.stdin(Stdio::null()).output().map_err(|e| format!("{cmd:?}: {e}"))?;
    if o.status.success() {
        Ok(())
    } else {
        Err(format!("{cmd:?}: {}", String::from_utf8_lossy(&o.stderr).trim()))
    }
}

impl Image {
    /// A fresh 384 MiB ext4 image mounted at `DIR/mnt`, or why there cannot be one here.
    fn new() -> Result<Self, String> {
        // SAFETY: a plain getter.
        if unsafe { libc::geteuid() } != 0 {
            return Err("not root".into());
        }
        if !Path::new("/dev/loop-control").exists() {
            return Err("no loop devices (/dev/loop-control)".into());
        }
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        // The "disk" in memory: the image's flush (the run's `fdatasync`) reaches it at once.
        let disk = dir.path().join("disk");
        std::fs::create_dir(&disk).map_err(|e| e.to_string())?;
        sh(Command::new("mount")
            .args(["-t", "tmpfs", "-o", "size=1g,mode=0700", "tmpfs"])
            .arg(&disk))?;
        let mut image = Self { dir, mounted: vec![disk] };
        let img = image.path("disk.img");
        std::fs::File::create(&img)
            .and_then(|f| f.set_len(384 << 20))
            .map_err(|e| e.to_string())?;
        sh(Command::new("mkfs.ext4").args(["-q", "-F"]).arg(&img))?;
        image.mount(&img, "mnt")?;
        Ok(image)
    }

    /// `name` in the image's directory; the image files (`*.img`) on its tmpfs "disk".
    fn path(&self, name: &str) -> PathBuf {
        match name.ends_with(".img") {
            true => self.dir.path().join("disk").join(name),
            false => self.dir.path().join(name),
        }
    }

    fn mount(&mut self, img: &Path, at: &str) -> Result<PathBuf, String> {
        let mnt = self.path(at);
        std::fs::create_dir_all(&mnt).map_err(|e| e.to_string())?;
        sh(Command::new("mount").args(["-t", "ext4", "-o", "loop"]).arg(img).arg(&mnt))?;
        self.mounted.push(mnt.clone());
        Ok(mnt)
    }

    /// The block device's content now: the image file copied (sparse), not the
    /// filesystem's dirty pages.
    fn snapshot(&self) -> PathBuf {
        let snap = self.path("snap.img");
        let st = Command::new("cp")
            .arg("--sparse=always")
            .arg(self.path("disk.img"))
            .arg(&snap)
            .status()
            .expect("cp");
        assert!(st.success(), "snapshot");
        snap
    }

    /// Unmounts the filesystems on the image and its snapshot; the tmpfs "disk" under
    /// them last, on drop.
    fn unmount_all(&mut self) {
        for m in self.mounted.drain(1..).rev() {
            let _ = Command::new("umount").arg("-l").arg(&m).status();
        }
    }
}

impl Drop for Image {
    fn drop(&mut self) {
        self.unmount_all();
        for m in self.mounted.drain(..) {
            let _ = Command::new("umount").arg("-l").arg(&m).status();
        }
    }
}

/// What one crash left.
#[derive(Debug)]
struct Crash {
    /// Seconds of wall time between the newest state on disk and the snapshot.
    loss_s: f64,
    /// The newest tick on disk (`None`: nothing reached it).
    last: Option<u64>,
}

/// When a tick was published ([`Rings::published`]).
enum Published {
    At(u64),
    /// Never: the stream's newest tick is older.
    Never,
    /// Not known: neither its ring (come round) nor what was written of it holds it.
    Unknown,
}

/// What a crashed run had recorded, read before the reboot clears it: its rings on tmpfs,
/// and what the mover had written into `OUT/flight` (its segments and journals, made
/// durable or not: the page cache of the image the run wrote).
struct Rings {
    states: [Option<FlightLog<StateSample>>; 2],
    /// The plant's record of the torques it took, and the controller's.
    torques: [[Option<FlightLog<TorqueSample>>; 2]; 2],
    references: [Option<FlightLog<ReferenceSample>>; 2],
}

impl Rings {
    fn read(domain: &str, written: &Path) -> Self {
        fn both<T: Record>(dirs: [&Path; 2], s: Stream) -> [Option<FlightLog<T>>; 2] {
            dirs.map(|dir| FlightLog::read(dir, s, u64::MAX).ok())
        }
        let staged = rotorloop_common::flight::staging_dir(domain).expect("/dev/shm");
        let dirs = [staged.as_path(), written];
        Self {
            states: both(dirs, Stream::PlantState),
            torques: [both(dirs, Stream::PlantTorque), both(dirs, Stream::ControllerTorque)],
            references: both(dirs, Stream::Reference),
        }
    }

    /// When `stream`'s tick `k` was published.
    fn published(&self, stream: Stream, k: u64) -> Published {
        fn of<T: Record>(logs: &[Option<FlightLog<T>>], k: u64, ns: fn(&T) -> u64) -> Published {
            let logs = || logs.iter().flatten();
            if let Some(s) = logs().find_map(|l| l.get(k)) {
                return Published::At(ns(&s));
            }
            match logs().filter_map(FlightLog::last).max() {
                Some(newest) if newest >= k => Published::Unknown,
                _ => Published::Never,
            }
        }
        match stream {
            Stream::PlantState => of(&self.states, k, |s| s.publish_ns),
            Stream::Reference => of(&self.references, k, |r| r.publish_ns),
            Stream::PlantTorque => of(&self.torques[0], k, |t| t.publish_ns),
            Stream::ControllerTorque => of(&self.torques[1], k, |t| t.publish_ns),
        }
    }
}

/// Removes what the run of `domain` has in `/dev/shm` (what a reboot does).
fn clear_shm(domain: &str) {
    for e in std::fs::read_dir("/dev/shm").expect("/dev/shm").flatten() {
        if e.file_name().to_string_lossy().contains(domain) {
            let p = e.path();
            let _ = if p.is_dir() { std::fs::remove_dir_all(&p) } else { std::fs::remove_file(&p) };
        }
    }
}

/// One machine crash (module docs) of a run in `mode` with rings of `ring` ticks
/// (`None`: the default), `at_s` seconds after its roles started; checks the recovered
/// report and returns the loss. `None` where the machine cannot make the image (said).
fn crash(h: &Harness, n: usize, mode: &str, ring: Option<u64>, at_s: f64) -> Option<Crash> {
    let mut image = match Image::new() {
        Ok(i) => i,
        Err(why) => {
            eprintln!("crash harness skipped: {why} (needs root, loop devices and mkfs.ext4)");
            return None;
        }
    };
    let domain = format!("{}-{n}", h.domain);
    let out = image.path("mnt").join("out");
    // Lockstep runs as fast as it can: its scenario is long enough to be going at any moment
    // (`--force`: the image is smaller than such a run's whole output, which the crash
    // never lets it reach).
    let duration = if mode == "lockstep" { "1200" } else { "60" };
    let ring = ring.map(|r| r.to_string());
    let mut args = vec!["run", "--scenario", "paper-sinusoid", "--mode", mode, "--force"];
    args.extend(["--duration", duration, "--no-csv", "--no-mcap", "--quiet"]);
    if let Some(r) = &ring {
        args.extend(["--flight-ring-ticks", r]);
    }
    let mut launcher = group(&mut Command::new(ROTORLOOP))
        .args(&args)
        .args(["--domain", &domain, "--out"])
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(h.path(&format!("launcher-{n}.err"))).expect("err file"))
        .spawn()
        .expect("spawn the run");
    let said = || std::fs::read_to_string(h.path(&format!("launcher-{n}.err"))).unwrap_or_default();
    let until = Instant::now() + LIMIT;
    while processes_of(&domain).len() < 5 {
        assert!(Instant::now() < until, "the run did not start: {}", said());
        assert!(launcher.try_wait().expect("wait").is_none(), "the run ended early: {}", said());
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_secs_f64(at_s));
    assert!(launcher.try_wait().expect("wait").is_none(), "ended before its crash: {}", said());
    // The crash: everything stops now; the disk is what the block device holds.
    let pids: Vec<u32> = processes_of(&domain);
    let snap_ns = rotorloop_common::clock::now_ns();
    signal_all(&pids, libc::SIGSTOP);
    let snap = image.snapshot();
    signal_all(&pids, libc::SIGKILL);
    let _ = launcher.wait();
    if let Some(dir) = std::env::var_os("ROTORLOOP_CRASH_KEEP") {
        let to = Path::new(&dir).join(format!("launcher-{n}.err"));
        let _ = std::fs::copy(h.path(&format!("launcher-{n}.err")), to);
    }
    while !processes_of(&domain).is_empty() {
        assert!(Instant::now() < until, "the run's processes did not die");
        std::thread::sleep(Duration::from_millis(10));
    }
    // When each tick was published, from what the run had recorded (read before the reboot
    // clears it): the age of the oldest tick lost is the loss.
    let rings = Rings::read(&domain, &out.join("flight"));
    clear_shm(&domain);
    image.unmount_all();
    // The reboot: the copy mounted (ext4 replays its journal), then one command.
    let mnt = image.mount(&snap, "after").expect("mount the snapshot");
    Some(recover(h, (n, mode), &mnt.join("out"), &rings, snap_ns))
}

/// `rotorloop recover` of the run `run` the crash `n` in `mode` left (its `rings`, the
/// snapshot at `snap_ns`); checks the report and the replay of the record, and returns the
/// loss (module docs).
fn recover(
    h: &Harness,
    (n, mode): (usize, &str),
    run: &Path,
    rings: &Rings,
    snap_ns: u64,
) -> Crash {
    let d = run.display().to_string();
    let recovered = h.rotorloop(&["recover", &d], LIMIT);
    let err = String::from_utf8_lossy(&recovered.stderr);
    if recovered.status.code() == Some(2) && err.contains("nothing to recover") {
        // Nothing durable yet (a crash before the first journal's sync): every tick lost,
        // the first among them tick 0.
        let loss_s = match rings.published(Stream::PlantState, 0) {
            Published::At(ns) => snap_ns.saturating_sub(ns) as f64 / 1e9,
            Published::Never => 0.0,
            Published::Unknown => panic!("nothing recovered, and tick 0 is gone: {err}"),
        };
        return Crash { loss_s, last: None };
    }
    let said = ok(&recovered);
    assert!(said.contains("recovered:"), "{said}");
    let s = json(&run.join("summary.json"));
    assert_eq!(s["recovered"]["machine_crash"], true, "{s}");
    let lost = &s["flight"]["lost"];
    assert_eq!(lost["reason"], "machine crash", "{s}");
    if lost["ticks"] != serde_json::json!([]) {
        keep(run, n, "a tick is missing before the last");
    }
    assert_eq!(lost["ticks"], serde_json::json!([]), "no tick missing before the last: {s}");
    let last = lost["last_tick_recorded"].as_u64().expect("the last tick recorded");
    assert_eq!(lost["after_last"][0].as_u64(), Some(last + 1), "{s}");
    assert!(run.join("incidents.md").exists() && run.join("run.mcap").exists(), "{said}");
    assert!(run.join("sense_to_actuate.hgrm").exists(), "the histograms: {said}");
    // The loss: the age at the snapshot of the oldest tick published and not on the disk.
    // That is the first state after the newest on disk, and each other stream's first
    // missing tick (a journal frame the crash cut short). A tick nothing holds any more (a
    // small ring come round over it before it was written) is timed, conservatively, by
    // the state on disk before it.
    // In real time a tick without a torque is also one the loop missed (the torque came
    // late or never): only the states and references are whole there.
    let states = FlightLog::<StateSample>::read(&run.join("flight"), Stream::PlantState, u64::MAX)
        .expect("states");
    assert_eq!(states.last(), Some(last));
    let lost_since = |stream: Stream, k: u64| {
        let published = match rings.published(stream, k) {
            Published::At(ns) => ns,
            Published::Never => return 0.0,
            Published::Unknown => {
                states.get(k.saturating_sub(1).min(last)).expect("a state before").publish_ns
            }
        };
        snap_ns.saturating_sub(published) as f64 / 1e9
    };
    let (mut loss_s, mut first_hole) = (lost_since(Stream::PlantState, last + 1), last + 1);
    for stream in s["flight"]["streams"].as_array().expect("streams") {
        let name = stream["stream"].as_str().expect("a stream's name");
        let of = Stream::ALL.into_iter().find(|s| s.name() == name).expect("a stream");
        if mode == "realtime" && name.ends_with("torque") {
            continue;
        }
        for r in stream["missing"].as_array().expect("missing") {
            let first = r[0].as_u64().expect("first");
            loss_s = loss_s.max(lost_since(of, first));
            first_hole = first_hole.min(first);
        }
    }
    // Replay of what the record holds: byte for byte. A record with no whole tick (a
    // stream's first frame cut short by the crash, counted above) has nothing to replay.
    let replay = h.path(&format!("replay-{n}"));
    let replayed =
        h.rotorloop(&["sim", "--replay", &d, "--out", &replay.display().to_string()], LIMIT);
    let err = String::from_utf8_lossy(&replayed.stderr);
    if first_hole == 0 && replayed.status.code() == Some(2) && err.contains("no row for tick 1") {
        return Crash { loss_s, last: Some(last) };
    }
    if !replayed.status.success() {
        keep(run, n, "its replay failed");
    }
    let said = ok(&replayed);
    let r = json(&replay.join("replay.json"));
    assert_eq!(r["identical"], true, "{said} {r}");
    // Replayed to the last row the record explains: the row before a hole (a torque that
    // took effect in the tick after it and was lost, timed by that tick's state), or the
    // row before the newest state on disk, whose effects only the next state (lost or
    // never published) would say.
    if let Some(after) = r.get("stopped").map(|st| st["after_tick"].as_u64().expect("tick")) {
        let why = r["stopped"]["why"].as_str().unwrap_or_default();
        assert!(after + 2 >= first_hole || why.contains("lost"), "{r}");
        let next_state = why.contains("no timing row after tick");
        loss_s = loss_s.max(lost_since(Stream::PlantState, after + 1 + u64::from(next_state)));
    }
    if loss_s > 1.0 {
        keep(run, n, &format!("lost {loss_s:.3} s"));
    }
    Crash { loss_s, last: Some(last) }
}

/// `ROTORLOOP_CRASH_KEEP=DIR`: the recovered run `run` of crash `n` (over the bound, or
/// whose replay failed) is kept there (`DIR/crash-N`), to be read after the harness has
/// gone.
fn keep(run: &Path, n: usize, why: &str) {
    let Some(dir) = std::env::var_os("ROTORLOOP_CRASH_KEEP") else { return };
    let to = Path::new(&dir).join(format!("crash-{n}"));
    let _ = Command::new("cp").arg("-a").arg(run).arg(&to).status();
    eprintln!("crash {n}: {why}; its recovered run is in {}", to.display());
}

/// What a crash may lose here, in the whole suite: the bound the record promises (1 s,
/// measured by [`bound`] on an idle machine: 40 of 40 crashes within it) plus the image's
/// sync path when the suite saturates both vCPUs (seen up to 2.1 s: the loop device's and
/// ext4's kernel threads wait for a CPU). A wall-clock figure under load is a measurement,
/// not behaviour; this limit still catches a record that loses what it had made durable
/// (the bug of 71e951f lost ticks 0-211 of a run crashed seconds later) or a whole half
/// left unsynced (32 768 ticks: 32 s at 1 kHz).
const SUITE_LOSS_S: f64 = 5.0;

/// A crash of the whole machine at seeded random moments of runs in both modes, with the
/// default ring and a small one, is recovered with a bounded loss: the record on the disk
/// image holds every tick up to a few moments before the snapshot (at most 1 s on an idle
/// machine: [`bound`]; here at most [`SUITE_LOSS_S`]), `rotorloop recover` writes the
/// report from it (summary, incidents, `run.mcap`) naming the loss ("machine crash", the
/// last tick recorded), and the replay of what it holds is the run's, byte for byte.
#[test]
fn a_machine_crash_at_any_moment_is_recovered_with_a_bounded_loss() {
    let h = Harness::new("crash");
    let mut rng = crate::common::rng(63);
    let mut n = 0;
    for mode in ["realtime", "lockstep"] {
        for ring in [None, Some(4096)] {
            let at_s = rng.random_range(0.5..4.0);
            let Some(c) = crash(&h, n, mode, ring, at_s) else { return };
            eprintln!("crash {n}: {mode}, ring {ring:?}, at {at_s:.2} s: {c:?}");
            let lost = format!("{mode}, ring {ring:?}, at {at_s:.2} s: lost {c:?}");
            assert!(c.loss_s <= SUITE_LOSS_S, "{lost}");
            n += 1;
        }
    }
}

/// The measurement of the bound (not a test of behaviour: run by hand, `cargo test --test
/// tests crash::bound -- --ignored --nocapture`): 20 seeded crash moments per mode, the
/// largest loss printed (with `ROTORLOOP_CRASH_KEEP=DIR`, each run over the bound or whose
/// replay failed kept, and every launcher's stderr; with `ROTORLOOP_CRASH_MODE=MODE`, only
/// that mode's moments).
#[test]
#[ignore = "a measurement: several minutes"]
fn bound() {
    let h = Harness::new("bound");
    let mut rng = crate::common::rng(6363);
    let only = std::env::var("ROTORLOOP_CRASH_MODE").ok();
    let mut n = 0;
    for mode in ["realtime", "lockstep"] {
        let mut losses = Vec::new();
        for i in 0..20 {
            let ring = if i % 2 == 0 { None } else { Some(4096) };
            let at_s = rng.random_range(0.5..8.0);
            if only.as_ref().is_some_and(|m| m != mode) {
                continue;
            }
            let Some(c) = crash(&h, n, mode, ring, at_s) else { return };
            println!(
                "{mode} crash {i}: ring {ring:?}, at {at_s:.2} s: loss {:.3} s, last tick {:?}",
                c.loss_s, c.last
            );
            losses.push(c.loss_s);
            n += 1;
        }
        if losses.is_empty() {
            continue;
        }
        losses.sort_by(f64::total_cmp);
        println!(
            "{mode}: {} crashes, loss median {:.3} s, largest {:.3} s",
            losses.len(),
            losses[losses.len() / 2],
            losses[losses.len() - 1]
        );
    }
}
