//! What each role's process costs in memory: resident memory sampled once a second into
//! `rss.csv`, and the figures `summary.json` and the console get after the run.

use std::collections::BTreeMap;

use rotorloop_common::clock::now_ns;

/// Resident memory of one role over a run, from `/proc/<pid>/status`, sampled once a
/// second by the launcher: `VmRSS` and its parts `RssAnon` (heap and stacks: what a leak
/// grows), `RssFile` (code and libraries, paged in as code paths first run) and
/// `RssShmem` (the iceoryx2 segments' pages touched so far). A restarted role starts a new
/// life: the figures are of its last life.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct RssTrack {
    /// The process's pid (last life).
    pub pid: u32,
    /// First sample taken at least [`RSS_SETTLE_S`] after the start, or the first at all
    /// for a shorter life (KiB).
    pub start_kib: u64,
    /// Seconds after the start of that sample.
    pub start_at_s: f64,
    /// Last sample before the process ended (KiB).
    pub end_kib: u64,
    /// Seconds after the start of that sample.
    pub end_at_s: f64,
    /// Largest sample (KiB).
    pub max_kib: u64,
    /// `(RssAnon, RssFile, RssShmem)` of the start sample (KiB).
    pub start_parts_kib: [u64; 3],
    /// The same of the end sample (KiB).
    pub end_parts_kib: [u64; 3],
    /// Samples taken.
    pub samples: u64,
    #[serde(skip)]
    spawned_ns: u64,
    #[serde(skip)]
    settled: bool,
}

/// Seconds a process may allocate its set-up before its "start" memory is taken.
pub const RSS_SETTLE_S: f64 = 3.0;

/// `VmRSS` and `(RssAnon, RssFile, RssShmem)` of a process (KiB), if it is alive.
pub fn rss_kib(pid: u32) -> Option<(u64, [u64; 3])> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| -> Option<u64> {
        let line = status.lines().find(|l| l.starts_with(name))?;
        line.split_whitespace().nth(1)?.parse().ok()
    };
    Some((field("VmRSS:")?, [field("RssAnon:")?, field("RssFile:")?, field("RssShmem:")?]))
}

impl RssTrack {
    fn new(pid: u32) -> Self {
        Self { pid, spawned_ns: now_ns(), ..Self::default() }
    }

    fn sample(&mut self) -> Option<(u64, [u64; 3])> {
        let (kib, parts) = rss_kib(self.pid)?;
        let at = (now_ns() - self.spawned_ns) as f64 / 1e9;
        if self.samples == 0 || (!self.settled && at >= RSS_SETTLE_S) {
            self.start_kib = kib;
            self.start_parts_kib = parts;
            self.start_at_s = at;
            self.settled = at >= RSS_SETTLE_S;
        }
        self.end_kib = kib;
        self.end_parts_kib = parts;
        self.end_at_s = at;
        self.max_kib = self.max_kib.max(kib);
        self.samples += 1;
        Some((kib, parts))
    }
}

/// Each role's resident memory, sampled once a second into `rss.csv`. A file that cannot
/// be written (a full disk) is given up with a warning: memory figures are an observer's,
/// never a reason to stop the loop.
pub(crate) struct RssLog {
    pub(crate) tracks: BTreeMap<String, RssTrack>,
    pub(crate) csv: Option<std::io::BufWriter<std::fs::File>>,
    t0: u64,
    pub(crate) next_ns: u64,
    /// Each role's scheduling, sampled by a thread of its own (`sched.csv`).
    pub(crate) sched: Option<crate::run::sched::SchedSampler>,
}

impl RssLog {
    /// The log of `out`, with the roles' scheduling sampled too where `sched` says so
    /// (into `sched.csv.zst` where `compressed`).
    pub(crate) fn create(out: &std::path::Path, sched: bool, compressed: bool) -> Self {
        use std::io::Write;
        let path = out.join("rss.csv");
        let csv = rotorloop_common::outdir::create_file(&path)
            .map(std::io::BufWriter::new)
            .and_then(|mut f| {
                writeln!(f, "t_s,role,pid,rss_kib,anon_kib,file_kib,shmem_kib")?;
                Ok(f)
            });
        let csv = csv.map_err(|e| eprintln!("warning: cannot write {}: {e}", path.display())).ok();
        let sched =
            sched.then(|| crate::run::sched::SchedSampler::start(out, compressed)).flatten();
        Self { tracks: BTreeMap::new(), csv, t0: now_ns(), next_ns: now_ns(), sched }
    }

    /// A new life of `role` (its figures are of its last life).
    pub(crate) fn track(&mut self, role: &str, pid: u32) {
        self.tracks.insert(role.to_owned(), RssTrack::new(pid));
        if let Some(s) = &self.sched {
            s.track(role, pid);
        }
    }

    pub(crate) fn sample_if_due(&mut self) {
        use std::io::Write;
        if now_ns() < self.next_ns {
            return;
        }
        self.next_ns += 1_000_000_000;
        let t = (now_ns() - self.t0) as f64 / 1e9;
        let mut rows = String::new();
        for (role, track) in self.tracks.iter_mut() {
            if let Some((kib, [anon, file, shmem])) = track.sample() {
                rows += &format!("{t:.1},{role},{},{kib},{anon},{file},{shmem}\n", track.pid);
            }
        }
        if let Some(csv) = &mut self.csv {
            if let Err(e) = csv.write_all(rows.as_bytes()).and_then(|()| csv.flush()) {
                eprintln!(
                    "warning: cannot write rss.csv any more ({e}); memory figures go on in memory"
                );
                self.csv = None;
            }
        }
    }
}

/// Adds the per-role memory figures to `out/summary.json` as `resources`.
pub(crate) fn add_resources(
    out: &std::path::Path,
    rss: &BTreeMap<String, RssTrack>,
) -> anyhow::Result<()> {
    rotorloop_monitor::summary::patch(out, |j| {
        j["resources"] = serde_json::json!({ "rss": rss, "rss_csv": "rss.csv" })
    })
}
