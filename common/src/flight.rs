//! Flight recorders: each role's own record of what it published (and the plant's of
//! what it received), in fixed-size binary records in the run directory, so that the
//! record of a run survives whatever process the user kills, the monitor included.
//!
//! A recorder is a file `DIR/STREAM.flight`, memory-mapped shared: a 64-byte header, then
//! one slot per tick `k` (`capacity` slots), each an 8-byte tag and the sample. Writing
//! tick `k` stores tag 0, copies the sample, then stores tag `k + 1` (release): the
//! kernel keeps the mapped pages after a `kill -9`, so a killed writer loses at most the
//! record it was writing (its tag is 0, and a reader skips it). A restarted role opens
//! the same file and goes on; a sample published again for the same tick (a restart
//! re-answering, say) replaces the earlier one, as it does in a subscriber's view.
//!
//! **A recorder never stops the loop.** The whole file is reserved with
//! `posix_fallocate` and its pages mapped in up front (`MAP_POPULATE`), so a write is a
//! `memcpy` with no system call, no page fault and no allocation, and it cannot hit a
//! full disk later (a write to a mapped page of a full disk would be SIGBUS). When the
//! file cannot be created or reserved (a disk full from the start, a read-only
//! directory) the recorder is off: the role says so once on stderr, counts what it could
//! not record, and the loop goes on; the run's report then says which record is missing
//! and falls back on the monitor's live view.

use std::marker::PhantomData;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering, fence};

use iceoryx2::prelude::ZeroCopySend;

use crate::wire::{LAYOUT_VERSION, ReferenceSample, StateSample, TorqueSample};

const MAGIC: u64 = 0x7468_6769_6c66_6c72; // "rlflight"
const HEADER: usize = 64;
/// Slots beyond the run's last tick (the reference publishes ahead of the plant).
pub const SPARE_SLOTS: u64 = 64;

/// Where `rotorloop run` stages the records of domain `domain` while the run goes on
/// (tmpfs, moved into `OUT/flight` at the end; `None` without `/dev/shm`).
pub fn staging_dir(domain: &str) -> Option<PathBuf> {
    let shm = Path::new("/dev/shm");
    shm.is_dir().then(|| shm.join(format!("rotorloop-flight-{domain}")))
}

/// The file in a staging directory that names the run directory its records belong to
/// (so that `rotorloop clean` can say where to recover them).
pub const RUN_DIR_FILE: &str = "run-dir";

/// Moves every record file (`*.flight`) of `from` into `to` (created if need be; a rename
/// where both lie on one filesystem, else a copy then a removal, one file at a time, so a
/// move cut short leaves each record whole in one of the two), then removes `from` with
/// its [`RUN_DIR_FILE`]. Returns how many files it moved.
pub fn move_records(from: &Path, to: &Path) -> std::io::Result<usize> {
    std::fs::create_dir_all(to)?;
    let mut moved = 0;
    for entry in std::fs::read_dir(from)? {
        let path = entry?.path();
        if path.extension().is_none_or(|e| e != "flight") {
            continue;
        }
        let Some(name) = path.file_name() else { continue };
        let dest = to.join(name);
        if std::fs::rename(&path, &dest).is_err() {
            let part = to.join(format!(".{}.part", name.to_string_lossy()));
            std::fs::copy(&path, &part)?;
            std::fs::rename(&part, &dest)?;
            std::fs::remove_file(&path)?;
        }
        moved += 1;
    }
    let _ = std::fs::remove_file(from.join(RUN_DIR_FILE));
    std::fs::remove_dir(from)?;
    Ok(moved)
}

/// The streams of a run, one file each.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stream {
    /// Every state sample the plant published (with what took effect in each tick).
    PlantState,
    /// Every torque sample the plant received (what it could apply).
    PlantTorque,
    /// Every torque sample the controller published.
    ControllerTorque,
    /// Every reference sample the reference published.
    Reference,
}

impl Stream {
    /// Every stream.
    pub const ALL: [Stream; 4] =
        [Stream::PlantState, Stream::PlantTorque, Stream::ControllerTorque, Stream::Reference];

    /// The stream's name (its file is `NAME.flight`).
    pub fn name(self) -> &'static str {
        match self {
            Stream::PlantState => "plant-state",
            Stream::PlantTorque => "plant-torque",
            Stream::ControllerTorque => "controller-torque",
            Stream::Reference => "reference",
        }
    }

    /// The stream's file in `dir`.
    pub fn path(self, dir: &Path) -> PathBuf {
        dir.join(format!("{}.flight", self.name()))
    }
}

/// A sample type a recorder can hold: plain data of a fixed size, with its tick.
pub trait Record: Copy + ZeroCopySend {
    /// The tick the sample belongs to (its slot).
    fn tick(&self) -> u64;
}

impl Record for StateSample {
    fn tick(&self) -> u64 {
        self.tick
    }
}
impl Record for TorqueSample {
    fn tick(&self) -> u64 {
        self.tick
    }
}
impl Record for ReferenceSample {
    fn tick(&self) -> u64 {
        self.tick
    }
}

fn slot_len<T>() -> usize {
    8 + size_of::<T>().next_multiple_of(8)
}

/// The header's words: magic, layout version, sample size, capacity, opens, beyond.
mod word {
    pub const MAGIC: usize = 0;
    pub const VERSION: usize = 1;
    pub const SIZE: usize = 2;
    pub const CAPACITY: usize = 3;
    /// How often the file was opened for writing (1 + the writer's restarts).
    pub const OPENS: usize = 4;
    /// Samples whose tick lay beyond the capacity (not recorded).
    pub const BEYOND: usize = 5;
}

/// One role's recorder of one stream (module docs).
#[derive(Debug)]
pub struct FlightRecorder<T: Record> {
    map: *mut u8,
    len: usize,
    capacity: u64,
    /// Samples not recorded because the recorder is off.
    unrecorded: std::cell::Cell<u64>,
    _t: PhantomData<T>,
}

impl<T: Record> FlightRecorder<T> {
    /// A recorder that records nothing (no `--record` directory).
    pub fn off() -> Self {
        Self {
            map: std::ptr::null_mut(),
            len: 0,
            capacity: 0,
            unrecorded: Default::default(),
            _t: PhantomData,
        }
    }

    /// The recorder of `stream` in `dir` for ticks `0..capacity`, continuing the file a
    /// killed predecessor left there. Never fails: when the file cannot be made, it says
    /// why on stderr (naming `role`) and returns a recorder that is off.
    pub fn open(dir: Option<&Path>, stream: Stream, capacity: u64, role: &str) -> Self {
        let Some(dir) = dir else { return Self::off() };
        match Self::try_open(dir, stream, capacity) {
            Ok(r) => r,
            Err(e) => {
                eprintln!(
                    "{role}: warning: flight recorder {} off: {e}; the loop goes on, the run's \
                     report falls back on the monitor's live view",
                    stream.path(dir).display()
                );
                Self::off()
            }
        }
    }

    fn try_open(dir: &Path, stream: Stream, capacity: u64) -> std::io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        let path = stream.path(dir);
        let len = HEADER + capacity as usize * slot_len::<T>();
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)?;
        let fresh = file.metadata()?.len() != len as u64;
        if fresh {
            file.set_len(0)?;
        }
        // Reserve every block now: a later write to the mapping cannot meet a full disk.
        // SAFETY: a plain system call on an open descriptor.
        let rc = unsafe { libc::posix_fallocate(file.as_raw_fd(), 0, len as libc::off_t) };
        if rc != 0 {
            let e = std::io::Error::from_raw_os_error(rc);
            let _ = std::fs::remove_file(&path);
            return Err(std::io::Error::new(e.kind(), format!("reserving {len} bytes: {e}")));
        }
        // SAFETY: maps `len` bytes of a file of exactly that size; checked for failure.
        let map = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                len,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_SHARED | libc::MAP_POPULATE,
                file.as_raw_fd(),
                0,
            )
        };
        if map == libc::MAP_FAILED {
            return Err(std::io::Error::last_os_error());
        }
        let r = Self {
            map: map.cast(),
            len,
            capacity,
            unrecorded: Default::default(),
            _t: PhantomData,
        };
        let same = r.word(word::MAGIC).load(Ordering::Acquire) == MAGIC
            && r.word(word::VERSION).load(Ordering::Relaxed) == u64::from(LAYOUT_VERSION)
            && r.word(word::SIZE).load(Ordering::Relaxed) == size_of::<T>() as u64
            && r.word(word::CAPACITY).load(Ordering::Relaxed) == capacity;
        if !fresh && !same {
            // Another run's layout: start empty (a fresh file is all zeros already).
            // SAFETY: the mapping is `len` bytes long and ours.
            unsafe { std::ptr::write_bytes(r.map, 0, len) };
        }
        if fresh || !same {
            r.word(word::VERSION).store(u64::from(LAYOUT_VERSION), Ordering::Relaxed);
            r.word(word::SIZE).store(size_of::<T>() as u64, Ordering::Relaxed);
            r.word(word::CAPACITY).store(capacity, Ordering::Relaxed);
            r.word(word::MAGIC).store(MAGIC, Ordering::Release);
        }
        r.word(word::OPENS).fetch_add(1, Ordering::Release);
        Ok(r)
    }

    fn word(&self, i: usize) -> &AtomicU64 {
        // SAFETY: the header's words lie in the mapping, 8-byte aligned (page-aligned
        // base); the mapping lives as long as self. Only called when mapped.
        unsafe { &*(self.map.add(8 * i) as *const AtomicU64) }
    }

    /// Whether this recorder records.
    pub fn is_on(&self) -> bool {
        !self.map.is_null()
    }

    /// Samples not recorded because the recorder is off.
    pub fn unrecorded(&self) -> u64 {
        self.unrecorded.get()
    }

    /// Records `sample` in its tick's slot: a copy and two atomic stores, no system call,
    /// no allocation.
    #[inline]
    pub fn record(&self, sample: &T) {
        if self.map.is_null() {
            self.unrecorded.set(self.unrecorded.get() + 1);
            return;
        }
        let k = sample.tick();
        if k >= self.capacity {
            self.word(word::BEYOND).fetch_add(1, Ordering::Relaxed);
            return;
        }
        // SAFETY: slot `k` lies in the mapping (k < capacity); only this process writes
        // it; the tag is 8-byte aligned (header and slot lengths are multiples of 8).
        unsafe {
            let slot = self.map.add(HEADER + k as usize * slot_len::<T>());
            let tag = &*(slot as *const AtomicU64);
            tag.store(0, Ordering::Relaxed);
            fence(Ordering::Release);
            std::ptr::write_unaligned(slot.add(8) as *mut T, *sample);
            tag.store(k + 1, Ordering::Release);
        }
    }
}

impl<T: Record> Drop for FlightRecorder<T> {
    fn drop(&mut self) {
        if !self.map.is_null() {
            // SAFETY: unmaps what open() mapped.
            unsafe { libc::munmap(self.map.cast(), self.len) };
        }
    }
}

/// Why a recorder's file cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum FlightError {
    /// No file (the role ran without `--record`, or could not create it).
    #[error("{path}: no flight record ({why})")]
    Missing { path: String, why: String },
    /// A file of another build or another sample type.
    #[error("{path}: {why}")]
    Foreign { path: String, why: String },
}

/// Whether `stream`'s file in `dir` holds a complete record of tick `k` (a read of its
/// tag; false when there is no such file). A role records a sample just after it
/// published it, so a reader that has seen the sample may have to wait for its record.
pub fn has_record<T: Record>(dir: &Path, stream: Stream, k: u64) -> bool {
    use std::os::unix::fs::FileExt;
    let Ok(f) = std::fs::File::open(stream.path(dir)) else { return false };
    let mut tag = [0u8; 8];
    let at = HEADER as u64 + k * slot_len::<T>() as u64;
    f.read_exact_at(&mut tag, at).is_ok() && u64::from_ne_bytes(tag) == k + 1
}

/// What a recorder's file holds, read after the run.
#[derive(Debug, Clone)]
pub struct FlightLog<T> {
    /// The sample of each tick `0..capacity`, `None` where none was (completely) written.
    pub records: Vec<Option<T>>,
    /// How often the file was opened for writing (1 + the writer's restarts).
    pub opens: u64,
    /// Samples whose tick lay beyond the capacity (not recorded).
    pub beyond: u64,
}

impl<T: Record> FlightLog<T> {
    /// Reads `stream`'s file in `dir`.
    pub fn read(dir: &Path, stream: Stream) -> Result<Self, FlightError> {
        let path = stream.path(dir);
        let shown = path.display().to_string();
        let bytes = std::fs::read(&path)
            .map_err(|e| FlightError::Missing { path: shown.clone(), why: e.to_string() })?;
        let foreign = |why: String| FlightError::Foreign { path: shown.clone(), why };
        let w = |i: usize| -> u64 {
            bytes
                .get(8 * i..8 * i + 8)
                .map_or(0, |b| u64::from_ne_bytes(b.try_into().unwrap_or_default()))
        };
        if bytes.len() < HEADER || w(word::MAGIC) != MAGIC {
            return Err(foreign("not a flight record (or never written)".into()));
        }
        if w(word::VERSION) != u64::from(LAYOUT_VERSION) || w(word::SIZE) != size_of::<T>() as u64 {
            return Err(foreign(format!(
                "written by layout v{} with {}-byte samples; this build reads layout v{} with \
                 {}-byte samples",
                w(word::VERSION),
                w(word::SIZE),
                LAYOUT_VERSION,
                size_of::<T>()
            )));
        }
        let capacity = w(word::CAPACITY);
        if bytes.len() != HEADER + capacity as usize * slot_len::<T>() {
            return Err(foreign(format!("{} bytes, not {capacity} slots", bytes.len())));
        }
        let records = bytes[HEADER..]
            .chunks_exact(slot_len::<T>())
            .enumerate()
            .map(|(k, slot)| {
                let tag = u64::from_ne_bytes(slot[..8].try_into().unwrap_or_default());
                // SAFETY: the slot holds `size_of::<T>()` bytes after its tag; T is plain
                // old data (f64/u64 fields), valid for any bit pattern.
                (tag == k as u64 + 1)
                    .then(|| unsafe { std::ptr::read_unaligned(slot[8..].as_ptr() as *const T) })
            })
            .collect();
        Ok(Self { records, opens: w(word::OPENS), beyond: w(word::BEYOND) })
    }

    /// The sample of tick `k`, if recorded.
    pub fn get(&self, k: u64) -> Option<&T> {
        self.records.get(k as usize).and_then(Option::as_ref)
    }

    /// Ticks of `0..=last` with no record, as `[first, last]` ranges.
    pub fn missing(&self, last: u64) -> Vec<[u64; 2]> {
        let mut out: Vec<[u64; 2]> = Vec::new();
        for k in (0..=last).filter(|k| self.get(*k).is_none()) {
            match out.last_mut() {
                Some(r) if r[1] + 1 == k => r[1] = k,
                _ => out.push([k, k]),
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn torque(k: u64) -> TorqueSample {
        TorqueSample { tick: k, rotor_torque_nm: [k as f64, 1.0, 2.0], ..Default::default() }
    }

    #[test]
    fn a_reopened_recorder_continues_the_file_and_a_rewrite_replaces_its_tick() {
        let dir = tempfile_dir("reopen");
        {
            let r =
                FlightRecorder::<TorqueSample>::open(Some(&dir), Stream::ControllerTorque, 10, "t");
            assert!(r.is_on());
            (0..4).for_each(|k| r.record(&torque(k)));
        }
        {
            let r =
                FlightRecorder::<TorqueSample>::open(Some(&dir), Stream::ControllerTorque, 10, "t");
            r.record(&TorqueSample { rotor_torque_nm: [9.0; 3], ..torque(3) });
            r.record(&torque(5));
            r.record(&torque(12)); // beyond the capacity: counted, not recorded
        }
        let log = FlightLog::<TorqueSample>::read(&dir, Stream::ControllerTorque).expect("read");
        assert_eq!(log.opens, 2);
        assert_eq!(log.beyond, 1);
        assert_eq!(log.get(3).map(|t| t.rotor_torque_nm), Some([9.0; 3]));
        assert_eq!(log.get(2), Some(&torque(2)));
        assert_eq!(log.missing(6), vec![[4, 4], [6, 6]]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_record_torn_by_a_kill_is_skipped_not_misread() {
        let dir = tempfile_dir("torn");
        {
            let r = FlightRecorder::<TorqueSample>::open(Some(&dir), Stream::Reference, 4, "t");
            (0..3).for_each(|k| r.record(&torque(k)));
        }
        // What a writer killed inside `record` of tick 1 leaves: tag 0, half a sample.
        let path = Stream::Reference.path(&dir);
        let mut bytes = std::fs::read(&path).expect("read");
        let slot = HEADER + slot_len::<TorqueSample>();
        bytes[slot..slot + 8].fill(0);
        bytes[slot + 16..slot + 40].fill(0xff);
        std::fs::write(&path, bytes).expect("write");
        let log = FlightLog::<TorqueSample>::read(&dir, Stream::Reference).expect("read");
        assert_eq!(log.missing(2), vec![[1, 1]]);
        assert_eq!(log.get(2), Some(&torque(2)));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_recorder_that_cannot_create_its_file_is_off_and_counts_what_it_lost() {
        let dir = tempfile_dir("off");
        // A file where the directory should be: the recorder cannot create its own.
        std::fs::create_dir_all(dir.parent().expect("parent")).expect("mkdir");
        std::fs::write(&dir, b"not a directory").expect("write");
        let r = FlightRecorder::<TorqueSample>::open(Some(&dir), Stream::PlantTorque, 4, "t");
        assert!(!r.is_on());
        (0..3).for_each(|k| r.record(&torque(k)));
        assert_eq!(r.unrecorded(), 3);
        assert!(matches!(
            FlightLog::<TorqueSample>::read(&dir, Stream::PlantTorque),
            Err(FlightError::Missing { .. })
        ));
        let _ = std::fs::remove_file(&dir);
    }

    fn tempfile_dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir()
            .join(format!("rotorloop-flight-{}-{name}", std::process::id()))
            .join("flight");
        let _ = std::fs::remove_dir_all(&d);
        d
    }
}

#[cfg(test)]
mod cost {
    use super::*;

    /// What one record costs on the disk of `dir` (not a test of behaviour: run with
    /// `cargo test -p rotorloop-common --release flight::cost -- --ignored --nocapture`).
    fn measure(dir: &Path) {
        let n = 60_000u64;
        let r = FlightRecorder::<StateSample>::open(Some(dir), Stream::PlantState, n, "cost");
        let x = crate::RotorBodyState {
            r: glam::DMat3::IDENTITY,
            omega: glam::DVec3::ZERO,
            omega_r: glam::DVec3::ZERO,
            theta: glam::DVec3::ZERO,
        };
        let mut s = StateSample::of(0, 0.0, &x);
        let faults = || {
            let mut u: libc::rusage = unsafe { std::mem::zeroed() };
            // SAFETY: getrusage fills the struct.
            unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
            u.ru_minflt + u.ru_majflt
        };
        let f0 = faults();
        let mut ns = Vec::with_capacity(n as usize);
        for k in 0..n {
            if k == n / 2 {
                // What the kernel's writeback does to a dirty page: clean, write-protected.
                // SAFETY: syncs the recorder's own mapping.
                unsafe { libc::msync(r.map.cast(), r.len, libc::MS_SYNC) };
            }
            s.tick = k;
            let t = crate::ipc::now_ns();
            r.record(&s);
            ns.push(crate::ipc::now_ns() - t);
        }
        ns.sort_unstable();
        let q = |p: f64| ns[((ns.len() - 1) as f64 * p) as usize];
        eprintln!(
            "{}: p50 {} ns, p99 {} ns, p99.9 {} ns, max {} ns, faults {}",
            dir.display(),
            q(0.5),
            q(0.99),
            q(0.999),
            q(1.0),
            faults() - f0
        );
    }

    #[test]
    #[ignore]
    fn record_cost_on_disk_and_tmpfs() {
        for base in [std::env::temp_dir(), PathBuf::from("/dev/shm")] {
            let dir = base.join(format!("rotorloop-flight-cost-{}", std::process::id()));
            measure(&dir);
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
}
