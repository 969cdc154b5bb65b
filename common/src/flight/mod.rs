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
//! **A ring, moved out while the run goes on.** The file holds `capacity` slots, and tick
//! `k` goes to slot `k mod capacity` (its tag says which tick it holds), so a record's RAM
//! on tmpfs is bounded whatever the run's duration: `rotorloop run` sizes it with
//! `--flight-ring-ticks` (default [`DEFAULT_RING_TICKS`], about 80 MB for the four
//! streams), or to the whole run when that is shorter. The launcher, off the hot path,
//! copies each finished half of a ring ([`Mover`]) into a segment file
//! `DIR/STREAM.NNNNNN.flight` of the run directory before the ring comes round to it; a
//! reader ([`FlightLog`]) takes the segments and the ring together, a block at a time. A launcher killed
//! mid-run leaves the ring in place (the roles end with it, so it does not come round),
//! and `rotorloop recover` moves it beside the segments already moved.
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
use std::os::unix::ffi::OsStringExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering, fence};

use iceoryx2::prelude::ZeroCopySend;

use crate::wire::{LAYOUT_VERSION, ReferenceSample, StateSample, TorqueSample};

mod journal;
mod pack;
mod read;
pub use journal::{
    CATCH_UP, DURABLE_BOUND, JOURNAL_PERIOD, journal_path, journals, kept_journal_path,
};
pub use read::{FlightLog, StreamCount};

const MAGIC: u64 = 0x7468_6769_6c66_6c72; // "rlflight"
/// A packed segment's magic ([`pack`]): "rlflpack".
const PACKED_MAGIC: u64 = 0x6b63_6170_6c66_6c72;
/// The magic of a segment whose slots are another stream's segment's, byte for byte
/// ([`Mover`]: the controller's torques as the plant received them): "rlflsame". The
/// file is its 64-byte header alone, [`word::BASE`] naming the other stream.
const SAME_MAGIC: u64 = 0x656d_6173_6c66_6c72;
const HEADER: usize = 64;

/// A record file's header: its bytes and its eight words ([`word`]), or the error of a
/// file shorter than a header.
fn read_header(file: &std::fs::File) -> std::io::Result<([u8; HEADER], [u64; 8])> {
    use std::os::unix::fs::FileExt;
    let mut header = [0u8; HEADER];
    file.read_exact_at(&mut header, 0)?;
    let words = std::array::from_fn(|i| {
        u64::from_ne_bytes(header[8 * i..8 * i + 8].try_into().unwrap_or_default())
    });
    Ok((header, words))
}

/// Slots beyond the run's last tick (the reference publishes ahead of the plant).
pub const SPARE_SLOTS: u64 = 64;
/// The ring's slots per stream unless `--flight-ring-ticks` says otherwise: 65.5 s at
/// 1 kHz, 1224 bytes a tick for the four streams (80 MB).
pub const DEFAULT_RING_TICKS: u64 = 65_536;
/// The smallest ring: a half must hold more than the reference's lead and the spare slots,
/// and in lockstep the plant's wait for the mover ([`free_through`]) must come after the
/// mover's due point (`1.5 H` published) by more than the spare slots: `H/2 > 64 + 1`.
pub const MIN_RING_TICKS: u64 = 512;

/// The slots of a recorder for a run of `ticks` ticks with a ring of `ring` slots: the whole
/// run where that is shorter (nothing to move), else the ring, rounded up to a power of two
/// (two halves, and a slot is a mask, not a division: 6 ns of a 24 ns record).
pub fn ring_capacity(ticks: u64, ring: u64) -> u64 {
    let whole = ticks + 1 + SPARE_SLOTS;
    let ring = ring.max(MIN_RING_TICKS).next_power_of_two();
    whole.min(ring)
}

/// Whether a recorder of `capacity` slots for a run of `ticks` ticks is a ring that comes
/// round (its halves must be moved out while the run goes on).
pub fn ring_wraps(ticks: u64, capacity: u64) -> bool {
    capacity < ticks + 1 + SPARE_SLOTS
}

/// The last tick the plant may publish while the mover has copied `copied` halves of `half`
/// ticks of every stream: publishing the next could let a writer (the reference, up to
/// [`SPARE_SLOTS`] ahead) come round to half `copied` before it is copied. Lockstep waits
/// here; real time never waits (module docs).
pub fn free_through(copied: u64, half: u64) -> u64 {
    (copied + 2) * half - SPARE_SLOTS - 1
}

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
/// its [`RUN_DIR_FILE`]. Returns how many files it moved. Where `packed`, each ring
/// (`STREAM.flight`) is packed as it is moved, as the segments are (`pack.rs`: a quarter of
/// its bytes); one that cannot be is moved raw. Each moved file is made durable
/// (`fdatasync`, then the directory's `fsync`), and then the journals of `to`
/// (`journal`), whose ticks the rings hold, are removed.
pub fn move_records(from: &Path, to: &Path, packed: bool) -> std::io::Result<usize> {
    std::fs::create_dir_all(to)?;
    let mut moved = 0;
    let mut paths: Vec<PathBuf> =
        std::fs::read_dir(from)?.map(|e| e.map(|e| e.path())).collect::<Result<_, _>>()?;
    // The controller's ring last: where its slots are the plant's, byte for byte, it is
    // kept as a header naming the plant's ring (as its segments are: `Mover::pass`), which
    // is then in place.
    let (plant, controller) = (Stream::PlantTorque.path(from), Stream::ControllerTorque.path(from));
    paths.sort_by_key(|p| *p == controller);
    let same = packed && same_slots(&plant, &controller);
    for path in paths {
        if path.extension().is_none_or(|e| e != "flight") {
            continue;
        }
        let Some(name) = path.file_name() else { continue };
        let dest = to.join(name);
        let ring = Stream::ALL.iter().any(|s| s.path(from) == path);
        let base_moved = Stream::PlantTorque.path(to).exists() && !plant.exists();
        let kept_once =
            same && path == controller && base_moved && write_same(&path, &dest).is_ok();
        if kept_once || (packed && ring && pack::pack_file(&path, &dest).is_ok()) {
            std::fs::remove_file(&path)?;
        } else if std::fs::rename(&path, &dest).is_err() {
            let part = to.join(format!(".{}.part", name.to_string_lossy()));
            std::fs::copy(&path, &part)?;
            std::fs::rename(&part, &dest)?;
            std::fs::remove_file(&path)?;
        }
        moved += 1;
        // Durable before the journal of its newest ticks goes (below).
        std::fs::File::open(&dest)?.sync_data()?;
    }
    journal::sync_dir(to)?;
    // The rings moved hold every tick the journals held, and are durable now; a kept journal
    // (`journal::kept_journal_path`) holds ticks no ring or segment does.
    for stream in Stream::ALL {
        for (j, journal) in journals(to, stream) {
            if journal != journal::kept_journal_path(to, stream, j) {
                std::fs::remove_file(journal)?;
            }
        }
    }
    let _ = std::fs::remove_file(from.join(RUN_DIR_FILE));
    std::fs::remove_dir(from)?;
    Ok(moved)
}

/// Whether the rings `a` and `b` hold the same slots, byte for byte (their header words
/// aside but the sample size and the capacity).
fn same_slots(a: &Path, b: &Path) -> bool {
    use std::os::unix::fs::FileExt;
    let (Ok(fa), Ok(fb)) = (std::fs::File::open(a), std::fs::File::open(b)) else {
        return false;
    };
    let (Ok((_, wa)), Ok((_, wb))) = (read_header(&fa), read_header(&fb)) else { return false };
    let (Ok(ma), Ok(mb)) = (fa.metadata(), fb.metadata()) else { return false };
    let geometry = |w: [u64; 8]| (w[word::MAGIC], w[word::SIZE], w[word::CAPACITY]);
    if geometry(wa) != geometry(wb) || wa[word::MAGIC] != MAGIC || ma.len() != mb.len() {
        return false;
    }
    let (mut ba, mut bb) = (vec![0u8; 1 << 20], vec![0u8; 1 << 20]);
    let mut at = HEADER as u64;
    while at < ma.len() {
        let n = (ma.len() - at).min(ba.len() as u64) as usize;
        let read = fa.read_exact_at(&mut ba[..n], at).and(fb.read_exact_at(&mut bb[..n], at));
        if read.is_err() || ba[..n] != bb[..n] {
            return false;
        }
        at += n as u64;
    }
    true
}

/// Writes `to` as the header of the ring `from` that is the plant's torque ring's, byte
/// for byte ([`SAME_MAGIC`]): whole or not at all (a `.part` renamed).
fn write_same(from: &Path, to: &Path) -> std::io::Result<()> {
    let (mut header, _) = read_header(&std::fs::File::open(from)?)?;
    let index = Stream::ALL.iter().position(|s| *s == Stream::PlantTorque).unwrap_or(0);
    header[8 * word::MAGIC..8 * word::MAGIC + 8].copy_from_slice(&SAME_MAGIC.to_ne_bytes());
    header[8 * word::BASE..8 * word::BASE + 8].copy_from_slice(&(index as u64).to_ne_bytes());
    let part = to.with_extension("part");
    std::io::Write::write_all(&mut journal::create_private(&part)?, &header)?;
    std::fs::rename(&part, to)
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

// A reader that looks only at a slot's first two words (`FlightLog::count`) takes the
// second for the sample's tick.
const _: () = assert!(std::mem::offset_of!(StateSample, tick) == 0);
const _: () = assert!(std::mem::offset_of!(TorqueSample, tick) == 0);
const _: () = assert!(std::mem::offset_of!(ReferenceSample, tick) == 0);

/// Bytes a tick takes in the records of the four streams (a slot of each).
pub fn bytes_per_tick() -> u64 {
    (slot_len::<StateSample>() + 2 * slot_len::<TorqueSample>() + slot_len::<ReferenceSample>())
        as u64
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
    /// In a plant state ring: the halves of every stream the launcher's mover has copied.
    pub const MOVED: usize = 6;
    /// In a segment that is another's ([`super::SAME_MAGIC`]): that stream's index in
    /// [`super::Stream::ALL`].
    pub const BASE: usize = 7;
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
        // Owner-only whatever the umask (live data: the staging directory is 0700 too),
        // and never through a link.
        use std::os::unix::fs::OpenOptionsExt;
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .mode(0o600)
            .custom_flags(libc::O_NOFOLLOW)
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
        let map = crate::private::map_shared(&file, len, libc::MAP_POPULATE)?;
        let r = Self { map, len, capacity, unrecorded: Default::default(), _t: PhantomData };
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

    /// The ring's slots (0 when off).
    pub fn capacity(&self) -> u64 {
        self.capacity
    }

    /// Lockstep's wait for the launcher's mover before the plant publishes tick `k` (the
    /// recorder is the plant state ring, a ring that comes round): waits, 1 ms at a time,
    /// until the mover has copied what publishing `k` could overwrite ([`free_through`]),
    /// but at most `limit`. Returns whether it had to give up (the records of that half
    /// may then be lost, and the mover counts them). A load and a compare when nothing
    /// is due.
    pub fn wait_for_mover(&self, k: u64, limit: std::time::Duration) -> bool {
        if self.map.is_null() {
            return false;
        }
        let half = self.capacity / 2;
        let moved = || self.word(word::MOVED).load(Ordering::Acquire);
        if k <= free_through(moved(), half) {
            return false;
        }
        let until = std::time::Instant::now() + limit;
        while k > free_through(moved(), half) {
            if std::time::Instant::now() >= until {
                return true;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        false
    }

    /// Samples not recorded because the recorder is off.
    pub fn unrecorded(&self) -> u64 {
        self.unrecorded.get()
    }

    /// Records `sample` in its tick's slot (tick mod capacity): a copy and two atomic
    /// stores, no system call, no allocation.
    #[inline]
    pub fn record(&self, sample: &T) {
        if self.map.is_null() {
            self.unrecorded.set(self.unrecorded.get() + 1);
            return;
        }
        let k = sample.tick();
        // Within the first round the slot is the tick; after it the capacity is a power of
        // two (`ring_capacity`). A whole-run file is never gone round (the spare slots hold
        // the reference's lead); were it, the masked slot stays in the file, and its tag
        // does not match the slot, so readers skip it.
        let i = if k < self.capacity { k } else { k & (self.capacity - 1) };
        // SAFETY: slot `i` lies in the mapping (i < capacity); only this process writes
        // it; the tag is 8-byte aligned (header and slot lengths are multiples of 8).
        unsafe {
            let slot = self.map.add(HEADER + i as usize * slot_len::<T>());
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
    Missing {
        /// The file.
        path: String,
        /// Why there is none.
        why: String,
    },
    /// A file of another build or another sample type.
    #[error("{path}: {why}")]
    Foreign {
        /// The file.
        path: String,
        /// What does not match.
        why: String,
    },
}

/// Whether `stream`'s file in `dir` holds a complete record of tick `k` (a read of its
/// tag; false when there is no such file). A role records a sample just after it
/// published it, so a reader that has seen the sample may have to wait for its record.
pub fn has_record<T: Record>(dir: &Path, stream: Stream, k: u64) -> bool {
    use std::os::unix::fs::FileExt;
    let Ok(f) = std::fs::File::open(stream.path(dir)) else { return false };
    let (mut tag, mut capacity, mut magic) = ([0u8; 8], [0u8; 8], [0u8; 8]);
    if f.read_exact_at(&mut magic, 0).is_err()
        || u64::from_ne_bytes(magic) != MAGIC
        || f.read_exact_at(&mut capacity, 8 * word::CAPACITY as u64).is_err()
    {
        return false; // no ring being written (a packed one is a finished run's)
    }
    let capacity = u64::from_ne_bytes(capacity).max(1);
    let at = HEADER as u64 + (k % capacity) * slot_len::<T>() as u64;
    f.read_exact_at(&mut tag, at).is_ok() && u64::from_ne_bytes(tag) == k + 1
}

/// The segment files of `stream` for the records in `dir`, in order (module docs): in
/// `dir`, and, for a staging directory, in its run directory's `flight/`, where the
/// launcher moves them during the run.
pub fn segments(dir: &Path, stream: Stream) -> Vec<PathBuf> {
    let prefix = format!("{}.", stream.name());
    let moved_to = std::fs::read(dir.join(RUN_DIR_FILE))
        .ok()
        .map(|p| PathBuf::from(std::ffi::OsString::from_vec(p)).join("flight"));
    let mut out: Vec<(u64, PathBuf)> = std::iter::once(dir.to_path_buf())
        .chain(moved_to)
        .flat_map(std::fs::read_dir)
        .flatten()
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().into_string().ok()?;
            let j = name.strip_prefix(&prefix)?.strip_suffix(".flight")?.parse().ok()?;
            Some((j, e.path()))
        })
        .collect();
    out.sort();
    out.into_iter().map(|(_, p)| p).collect()
}

/// The segment file of half `j` of `stream`'s ring (ticks `j·H … (j+1)·H − 1`).
pub fn segment_path(dir: &Path, stream: Stream, j: u64) -> PathBuf {
    dir.join(format!("{}.{j:06}.flight", stream.name()))
}

/// Copies the finished halves of the rings in `staged` into segment files in `kept` while
/// the run goes on (module docs), off the hot path (the launcher's supervision loop).
///
/// Half `j` of a ring of `C = 2H` slots holds ticks `jH … (j+1)H − 1`; the writers come
/// round to it again at tick `(j+2)H`. It is copied once the plant has published tick
/// `(j+1)H + H/2`: late enough that a sample published again for one of its ticks (a
/// restarted role re-answering) is in the copy, early enough that the reference, at most
/// [`SPARE_SLOTS`] ahead, is `H/2 − SPARE_SLOTS` ticks from overwriting it. A slot already
/// overwritten when it is copied (the launcher stopped for longer than that) is lost, and
/// counted.
#[derive(Debug)]
pub struct Mover {
    staged: PathBuf,
    kept: PathBuf,
    /// The next half to copy, per stream.
    next: [u64; 4],
    /// The streams whose ring was seen (one that never comes holds nobody up).
    rings: [bool; 4],
    /// Records lost because the ring came round before they were copied.
    pub lost: u64,
    /// Segment files written.
    pub segments: u64,
    /// The plant tick before which nothing is due (known once a ring's size is).
    due_at: u64,
    /// The plant state ring's [`word::MOVED`], where the plant reads it (mapped once
    /// that ring exists).
    moved: Option<MovedWord>,
    /// The ticks in a half of the rings, once read.
    pub half: Option<u64>,
    /// Whether segments are packed ([`pack`]; raw only to measure what packing costs).
    packed: bool,
    /// Whether the rings come round and their halves are moved (else the rings are the
    /// whole run's and only journaled).
    halves: bool,
    /// Per stream, the first tick the next journal frame writes (`journal`).
    jnext: [u64; 4],
    /// Per stream, the halves up to the newest whose segment is durable, plus one.
    synced: [u64; 4],
    /// Per stream, the transforms of its last journal frame (`pack::pack_reusing`), and
    /// its frames so far.
    jcodes: [Vec<u8>; 4],
    jframes: [u64; 4],
    /// The journal files open to append to: stream index, half, file, whether written since
    /// they were last made durable.
    jfiles: Vec<(usize, u64, std::fs::File, bool)>,
    /// Segments written since the last time they were made durable: stream index, half,
    /// file, whether the ring had come round over some of the half's ticks before it was
    /// read (its journal is then kept: `kept_journal_path`).
    unsynced: Vec<(usize, u64, std::fs::File, bool)>,
    /// Whether a file was made or renamed in the run directory since its last `fsync`.
    dir_dirty: bool,
    /// Whether the journal's last attempt failed (said once, until it works again).
    journal_failing: bool,
    /// Whether it journals at all (not only to measure what the journal costs).
    journaling: bool,
    /// Journal frames written.
    pub frames: u64,
    /// Bytes of journal frames written.
    pub journal_bytes: u64,
    /// When the newest ticks were last journaled.
    journaled: Option<std::time::Instant>,
    /// When the last journal made durable began: every tick recorded before it is on the
    /// disk (`None` before the first, which begins within a poll of the first tick).
    durable_from: Option<std::time::Instant>,
    /// The longest the newest ticks were from the disk: at each journal made durable, the
    /// time since the one before began. A machine crash at any moment of the run would
    /// have lost at most this much; `None` without a journal (or before the first).
    pub durable_lag_max: Option<std::time::Duration>,
    /// The plant's newest tick, plus one, as the loop goes on ([`Mover::following`]): what
    /// a pass journals between its segments.
    live: Option<std::sync::Arc<std::sync::atomic::AtomicU64>>,
    /// The thread's policy while it journals ([`Mover::in_background`]).
    background: Option<std::sync::Arc<crate::rt::Background>>,
    /// Whether a pass is writing segments (the thread stays ordinary until it ends).
    in_pass: bool,
}

impl Mover {
    /// The mover of the rings in `staged` into `kept`.
    pub fn new(staged: &Path, kept: &Path) -> Self {
        let (staged, kept) = (staged.to_owned(), kept.to_owned());
        Self {
            staged,
            kept,
            next: [0; 4],
            rings: [false; 4],
            lost: 0,
            segments: 0,
            due_at: 0,
            moved: None,
            half: None,
            packed: true,
            halves: true,
            jnext: [0; 4],
            synced: [0; 4],
            jcodes: Default::default(),
            jframes: [0; 4],
            jfiles: Vec::new(),
            unsynced: Vec::new(),
            dir_dirty: false,
            journal_failing: false,
            journaling: true,
            frames: 0,
            journal_bytes: 0,
            journaled: None,
            durable_from: None,
            durable_lag_max: None,
            live: None,
            background: None,
            in_pass: false,
        }
    }

    /// The mover that reads the plant's newest tick, plus one, from `live` while a pass
    /// packs its segments, and journals it between them when [`JOURNAL_PERIOD`] has
    /// passed: packing the halves of a large ring takes longer than the period on a loaded
    /// machine, and a machine crash meanwhile would lose all that time (1.19 s seen).
    pub fn following(self, live: std::sync::Arc<std::sync::atomic::AtomicU64>) -> Self {
        Self { live: Some(live), ..self }
    }

    /// The mover whose thread journals in the background (`SCHED_IDLE`: real time lost
    /// ticks to the journal's packing and syncs on a 2-vCPU machine, docs/flight-recorders.md)
    /// and writes its segments as an ordinary thread; `background` says when the newest
    /// ticks were last made durable, so that the launcher's loop makes the thread ordinary
    /// again once they are [`CATCH_UP`] from the disk (a saturated machine would starve it).
    pub fn in_background(self, background: std::sync::Arc<crate::rt::Background>) -> Self {
        Self { background: Some(background), ..self }
    }

    /// The mover's thread in the background or ordinary ([`Mover::in_background`]).
    fn background(&self, idle: bool) {
        if let Some(b) = &self.background {
            b.set(idle);
        }
    }

    /// Whether [`JOURNAL_PERIOD`] has passed since the newest ticks were last journaled.
    pub fn journal_due(&self) -> bool {
        self.journaled.is_none_or(|t| t.elapsed() >= JOURNAL_PERIOD)
    }

    /// The mover that keeps no journal (`run --no-journal`: to measure what the journal
    /// costs the loop).
    pub fn without_journal(self) -> Self {
        Self { journaling: false, ..self }
    }

    /// The mover of rings that hold the whole run (they never come round): it moves no
    /// half, and only journals the newest ticks ([`Mover::journal`]).
    pub fn whole_run(self) -> Self {
        Self { halves: false, ..self }
    }

    /// The mover that writes raw segments instead of packed ones (`run --raw-segments`:
    /// for `bench --before-after pack`, what packing costs the loop).
    pub fn raw(self) -> Self {
        Self { packed: false, ..self }
    }

    /// The mover of rings whose halves hold `half` ticks, known before their files exist
    /// (the plant's wait for it can be told apart from a hang from the start).
    pub fn with_half(self, half: u64) -> Self {
        Self { half: Some(half), ..self }
    }

    /// The halves of every stream with a ring copied so far.
    pub fn copied(&self) -> u64 {
        let seen = self.next.iter().zip(self.rings).filter(|(_, r)| *r);
        seen.map(|(n, _)| *n).min().unwrap_or(0)
    }

    /// Copies every half that is due now that the plant has published `plant_tick`;
    /// returns what went wrong (a file that cannot be read or written), in words.
    ///
    /// Every due half is read out of its ring (tmpfs: a memcpy) before any is written to
    /// disk, which can wait seconds on writeback: a slow write of one stream's segment
    /// then never leaves another stream's half in its ring until it comes round (seen
    /// under the repeat harness: the reference's, last in order, lost 784 ticks of a
    /// lockstep run). Then it tells the plant how far it got (header word 6 of its state ring).
    pub fn pass(&mut self, plant_tick: u64) -> Vec<String> {
        let mut errors = Vec::new();
        if !self.halves || plant_tick < self.due_at {
            return errors;
        }
        let mut read = Vec::new();
        for (n, stream) in Stream::ALL.into_iter().enumerate() {
            loop {
                match self.read_half(stream, self.next[n], plant_tick) {
                    Ok(Half::Read(bytes, overran)) => {
                        self.rings[n] = true;
                        read.push((stream, self.next[n], bytes, overran));
                        self.next[n] += 1;
                    }
                    Ok(Half::NotDue(h)) => {
                        (self.rings[n], self.half) = (true, Some(h));
                        break;
                    }
                    Ok(Half::NoRing) => break,
                    Err(e) => {
                        errors.push(format!("{}: {e}", stream.path(&self.staged).display()));
                        self.next[n] += 1; // never again: the loop goes on
                        break;
                    }
                }
            }
        }
        // Halves are written as an ordinary thread: in the background on a saturated
        // machine they would wait until their ring came round.
        self.in_pass = !read.is_empty();
        self.background(!self.in_pass);
        let mut written = Vec::with_capacity(read.len());
        for (stream, j, bytes, overran) in &read {
            // The controller's half is the plant's, byte for byte, unless a sample went
            // missing on the way or a restart answered again: then it is packed on its own.
            let same = (*stream == Stream::ControllerTorque && self.packed)
                .then(|| {
                    read.iter().zip(&written).find(|((s, i, b, _), ok)| {
                        **ok && *s == Stream::PlantTorque
                            && i == j
                            && b[HEADER..] == bytes[HEADER..]
                    })
                })
                .flatten()
                .map(|((s, ..), _)| *s);
            // The newest ticks journaled between its chunks too (a large ring's half takes
            // long to pack: 0.15 s for the plant's states, idle, three times that beside a
            // build, and a machine crash meanwhile loses it all).
            let (kept, packed) = (self.kept.clone(), self.packed);
            let between = &mut || self.journal_if_due(&mut errors);
            let done = match write_segment(&kept, packed, (*stream, *j, bytes, same), between) {
                Ok(file) => {
                    // Made durable with the next journal frames (`make_durable`).
                    let n = Stream::ALL.iter().position(|s| s == stream).unwrap_or(0);
                    self.unsynced.push((n, *j, file, *overran));
                    self.dir_dirty = true;
                    true
                }
                Err(e) => {
                    let path = segment_path(&self.kept, *stream, *j);
                    errors.push(format!("{}: {e}", path.display()));
                    false
                }
            };
            self.segments += u64::from(done);
            written.push(done);
            self.journal_if_due(&mut errors);
        }
        self.in_pass = false;
        self.background(true);
        // Nothing is due before the lowest next half is (a ring's size is known once read).
        if let Some(h) = self.half {
            let lowest = self.next.iter().min().copied().unwrap_or(0);
            self.due_at = (lowest + 1) * h + h / 2;
        }
        if self.moved.is_none() {
            self.moved = MovedWord::map(&Stream::PlantState.path(&self.staged));
        }
        if let Some(m) = &self.moved {
            m.store(self.copied());
        }
        // Many small segments (lockstep's small rings): durable now, not hundreds of open
        // files until the next journal frames.
        if self.unsynced.len() > 64
            && let Err(e) = self.make_durable()
        {
            errors.push(format!("{}: making the record durable: {e}", self.kept.display()));
        }
        errors
    }

    /// Reads half `j` of `stream`'s ring, as its segment file's bytes, if it is due.
    fn read_half(&mut self, stream: Stream, j: u64, plant_tick: u64) -> std::io::Result<Half> {
        use std::os::unix::fs::FileExt;
        let ring = stream.path(&self.staged);
        let Ok(f) = std::fs::File::open(&ring) else { return Ok(Half::NoRing) };
        let Ok((header, w)) = read_header(&f) else { return Ok(Half::NoRing) };
        let (capacity, size) = (w[word::CAPACITY], w[word::SIZE] as usize);
        if w[word::MAGIC] != MAGIC || capacity < MIN_RING_TICKS || capacity % 2 != 0 {
            return Ok(Half::NoRing);
        }
        let half = capacity / 2;
        if plant_tick < (j + 1) * half + half / 2 {
            return Ok(Half::NotDue(half));
        }
        let slot = 8 + size.next_multiple_of(8);
        let mut bytes = vec![0u8; HEADER + half as usize * slot];
        let mut overran = false;
        let (seg_header, body) = bytes.split_at_mut(HEADER);
        let first_slot = (j % 2) * half;
        f.read_exact_at(body, (HEADER + first_slot as usize * slot) as u64)?;
        for (i, s) in body.chunks_exact_mut(slot).enumerate() {
            let tag = u64::from_ne_bytes(s[..8].try_into().unwrap_or_default());
            let want = j * half + i as u64 + 1;
            if tag != want {
                // Never written, torn, or already the next round's (lost: counted).
                self.lost += u64::from(tag > want);
                overran |= tag > want;
                s.fill(0);
            }
        }
        seg_header.copy_from_slice(&header);
        seg_header[8 * word::CAPACITY..8 * word::CAPACITY + 8].copy_from_slice(&half.to_ne_bytes());
        seg_header[8 * word::OPENS..8 * word::MOVED + 8].fill(0);
        Ok(Half::Read(bytes, overran))
    }

    /// Journals the newest ticks ([`Mover::journal`]) if [`JOURNAL_PERIOD`] has passed,
    /// where the loop's newest tick is known ([`Mover::following`]): between the segments
    /// of a pass and the chunks of each.
    fn journal_if_due(&mut self, errors: &mut Vec<String>) {
        let live = self.live.as_ref().map(|t| t.load(std::sync::atomic::Ordering::Acquire));
        if let Some(newest) = live.filter(|t| *t > 0 && self.journal_due()) {
            errors.extend(self.journal(newest - 1));
        }
    }

    /// Journals the newest ticks of every stream (those past its last segment, since the
    /// last frame, and the last few of that frame again) and makes what was written since
    /// the last call durable: the frames, the segments the passes wrote (`journal`
    /// module docs). The mover's thread calls it every [`JOURNAL_PERIOD`], `plant_tick`
    /// the plant's newest tick. Returns what went wrong, in words (once, until it works
    /// again).
    pub fn journal(&mut self, plant_tick: u64) -> Vec<String> {
        let mut errors = Vec::new();
        if !self.journaling {
            return errors;
        }
        let began = std::time::Instant::now();
        self.journaled = Some(began);
        if let Err(e) = self.sync_segments() {
            errors.push(format!("{}: making the segments durable: {e}", self.kept.display()));
        }
        for (n, stream) in Stream::ALL.into_iter().enumerate() {
            if let Err(e) = self.journal_stream(n, stream, plant_tick) {
                errors.push(format!("{} (journal): {e}", stream.path(&self.staged).display()));
            }
        }
        if let Err(e) = self.make_durable() {
            errors.push(format!("{}: making the record durable: {e}", self.kept.display()));
        }
        let failing = !errors.is_empty();
        if !failing {
            // Until now, the ticks since the last durable journal began were only in memory.
            let lag = self.durable_from.unwrap_or(began).elapsed();
            self.durable_lag_max = Some(self.durable_lag_max.map_or(lag, |m| m.max(lag)));
            self.durable_from = Some(began);
            if let Some(b) = &self.background {
                b.durable_at(began);
            }
        }
        if !self.in_pass {
            self.background(true);
        }
        if std::mem::replace(&mut self.journal_failing, failing) {
            errors.clear(); // said already
        }
        errors
    }

    /// Appends a frame of `stream`'s newest ticks to its journal (module docs of
    /// `journal`).
    fn journal_stream(&mut self, n: usize, stream: Stream, plant_tick: u64) -> std::io::Result<()> {
        let Ok(ring) = std::fs::File::open(stream.path(&self.staged)) else { return Ok(()) };
        let Ok((header, w)) = read_header(&ring) else { return Ok(()) };
        let (capacity, slot) = (w[word::CAPACITY], journal::slot_of(w[word::SIZE]));
        let whole = HEADER as u128 + u128::from(capacity) * slot as u128;
        if w[word::MAGIC] != MAGIC || capacity < 2 || u128::from(ring.metadata()?.len()) != whole {
            return Ok(()); // no ring being written (yet)
        }
        let half = if self.halves { capacity / 2 } else { u64::MAX };
        // Past the segments made durable, not those only read or written: a half the pass
        // has read is in the journal until its segment is on the disk (else a crash between
        // the frames' sync and the segments' lost the ticks in neither: seen once in 40
        // lockstep crashes, 3 007 ticks).
        let past_segments = if self.halves { self.synced[n].saturating_mul(half) } else { 0 };
        let to = plant_tick.saturating_add(SPARE_SLOTS);
        // Ticks older than a round are the ring's no more.
        let from = self.jnext[n].max(past_segments).max((to + 1).saturating_sub(capacity));
        // Read at once, then framed: a half read after the packing of the one before would
        // hold ticks the plant recorded meanwhile, and a crash then leave a hole at the end
        // of the older half (seen: 10 ticks, twice in 40 lockstep crashes).
        let Some(all) = journal::read_ticks(&ring, (capacity, slot), from, to) else {
            return Err(std::io::Error::other("cannot read the ring"));
        };
        let mut k = from;
        while k <= to {
            // A frame lies in one half's journal, and holds 16 384 slots at most.
            let j = k / half;
            let end = to.min(j.saturating_add(1).saturating_mul(half) - 1).min(k + 16_383);
            let body = &all[(k - from) as usize * slot..(end + 1 - from) as usize * slot];
            let held = body.chunks_exact(slot).rposition(|s| s[..8] != [0; 8]);
            if let Some(last) = held {
                let body = &body[..(last + 1) * slot];
                // The transforms searched for again every `RESEARCH` frames (a stream's
                // columns change their character seldom; the search is most of the cost).
                if self.jframes[n] % journal::RESEARCH == 0 {
                    self.jcodes[n].clear();
                }
                self.jframes[n] += 1;
                let bytes = journal::frame(&header, k, (body, slot), &mut self.jcodes[n])?;
                self.append(n, stream, if self.halves { j } else { 0 }, &bytes)?;
            }
            k = end + 1;
        }
        self.jnext[n] = from.max(plant_tick.saturating_sub(journal::OVERLAP));
        Ok(())
    }

    /// Appends `bytes` to the journal of half `j` of `stream`: whole, or not at all (a
    /// failed write is cut off again, so the frames after it stay readable).
    fn append(&mut self, n: usize, stream: Stream, j: u64, bytes: &[u8]) -> std::io::Result<()> {
        // A stream's frames reach the disk in order: an older half's journal is made durable
        // before a frame goes to a newer one's. Else the kernel's writeback may keep the
        // newer file's frame and a crash lose the older's: a hole before the last tick
        // recorded (seen once in 40 crashes: ten ticks at the end of a half of 2 048).
        for (_, _, file, dirty) in self.jfiles.iter_mut().filter(|f| f.0 == n && f.1 < j && f.3) {
            file.sync_data()?;
            *dirty = false;
        }
        let at = match self.jfiles.iter().position(|(i, h, ..)| (*i, *h) == (n, j)) {
            Some(at) => at,
            None => {
                std::fs::create_dir_all(&self.kept)?;
                let (file, made) =
                    journal::open_private_append(&journal_path(&self.kept, stream, j))?;
                self.dir_dirty |= made;
                self.jfiles.push((n, j, file, false));
                self.jfiles.len() - 1
            }
        };
        let (_, _, file, dirty) = &mut self.jfiles[at];
        let len = file.metadata()?.len();
        if let Err(e) = std::io::Write::write_all(file, bytes) {
            let _ = file.set_len(len);
            return Err(e);
        }
        *dirty = true;
        self.frames += 1;
        self.journal_bytes += bytes.len() as u64;
        Ok(())
    }

    /// Makes durable what was written since the last call: the segments
    /// ([`Mover::sync_segments`]), then the journals' frames.
    fn make_durable(&mut self) -> std::io::Result<()> {
        self.sync_segments()?;
        let dirty: Vec<&std::fs::File> =
            self.jfiles.iter().filter(|f| f.3).map(|(_, _, file, _)| file).collect();
        sync_all_of(&self.kept, &dirty)?;
        self.jfiles.iter_mut().for_each(|f| f.3 = false);
        self.sync_dir_if_changed()
    }

    /// Makes the segments written since the last call durable, then removes the journal of
    /// each of their halves. [`Mover::journal`] calls it before it writes its frames: a
    /// frame skips the ticks of a half whose segment is durable, and the ring may have come
    /// round over a half whose segment is only written, so no frame may reach the disk
    /// before the segments written ahead of it (a crash would leave a hole of the ticks in
    /// neither).
    fn sync_segments(&mut self) -> std::io::Result<()> {
        if self.unsynced.is_empty() {
            return Ok(());
        }
        let files: Vec<&std::fs::File> = self.unsynced.iter().map(|(_, _, file, _)| file).collect();
        sync_all_of(&self.kept, &files)?;
        self.sync_dir_if_changed()?;
        for (n, j, _, overran) in std::mem::take(&mut self.unsynced) {
            self.synced[n] = self.synced[n].max(j + 1);
            self.jfiles.retain(|(i, h, ..)| (*i, *h) != (n, j));
            let path = journal_path(&self.kept, Stream::ALL[n], j);
            // A segment that lacks ticks its journal holds keeps the journal beside it.
            let done = if overran {
                self.dir_dirty = true;
                std::fs::rename(&path, kept_journal_path(&self.kept, Stream::ALL[n], j))
            } else {
                std::fs::remove_file(&path)
            };
            match done {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(e),
                _ => {}
            }
        }
        Ok(())
    }

    /// The `fsync` of the directory where a file was made or renamed in it since the last.
    fn sync_dir_if_changed(&mut self) -> std::io::Result<()> {
        if std::mem::take(&mut self.dir_dirty) {
            journal::sync_dir(&self.kept)?;
            // The run directory's entry of `flight/` itself (made by the first file).
            if let Some(run_dir) = self.kept.parent() {
                journal::sync_dir(run_dir)?;
            }
        }
        Ok(())
    }
}

/// Writes half `j` of `stream` (its segment file's `bytes`) into its segment file in `kept`
/// (whole or not at all): packed ([`pack`]) where `packed`, calling `between` after each
/// chunk, or as the header of a segment that is `same`'s segment `j`.
fn write_segment(
    kept: &Path,
    packed: bool,
    (stream, j, bytes, same): (Stream, u64, &[u8], Option<Stream>),
    between: &mut dyn FnMut(),
) -> std::io::Result<std::fs::File> {
    std::fs::create_dir_all(kept)?;
    let path = segment_path(kept, stream, j);
    let part = path.with_extension("part");
    let (header, body) = bytes.split_at(HEADER);
    let size = u64::from_ne_bytes(
        header[8 * word::SIZE..8 * word::SIZE + 8].try_into().unwrap_or_default(),
    );
    let mut header = header.to_vec();
    let set = |header: &mut [u8], w: usize, v: u64| {
        header[8 * w..8 * w + 8].copy_from_slice(&v.to_ne_bytes());
    };
    let packed = match (same, packed) {
        (Some(base), _) => {
            let index = Stream::ALL.iter().position(|s| *s == base).unwrap_or(0);
            set(&mut header, word::MAGIC, SAME_MAGIC);
            set(&mut header, word::BASE, index as u64);
            Some(header)
        }
        (None, true) => {
            set(&mut header, word::MAGIC, PACKED_MAGIC);
            // A segment that cannot be packed (never seen) is kept raw: readers take both.
            pack::pack_between(&header, body, 8 + (size as usize).next_multiple_of(8), between).ok()
        }
        (None, false) => None,
    };
    let mut file = journal::create_private(&part)?;
    std::io::Write::write_all(&mut file, packed.as_deref().unwrap_or(bytes))?;
    std::fs::rename(&part, &path)?;
    Ok(file)
}

/// `fdatasync` of each of `files` in `dir`, or one `syncfs` where they are more than 16
/// (lockstep's small rings: many segments a period).
fn sync_all_of(dir: &Path, files: &[&std::fs::File]) -> std::io::Result<()> {
    if files.len() > 16 {
        let dir = std::fs::File::open(dir)?;
        // SAFETY: a plain system call on an open descriptor.
        if unsafe { libc::syncfs(dir.as_raw_fd()) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
        return Ok(());
    }
    files.iter().try_for_each(|f| f.sync_data())
}

/// What [`Mover::read_half`] found.
enum Half {
    /// No ring of this stream (yet), or not one that wraps.
    NoRing,
    /// The half is not due yet; the ring's halves hold this many ticks.
    NotDue(u64),
    /// Read: the segment file's bytes, and whether the ring had come round over some of
    /// its ticks.
    Read(Vec<u8>, bool),
}

/// The plant state ring's header, mapped by the mover to store [`word::MOVED`] where the
/// plant's atomic load sees it whole (a `pwrite` may be torn).
#[derive(Debug)]
struct MovedWord {
    map: *mut u8,
}

// SAFETY: the mapping is only written through an atomic store, and unmapped on drop.
unsafe impl Send for MovedWord {}

impl MovedWord {
    fn map(ring: &Path) -> Option<Self> {
        let f = std::fs::OpenOptions::new().read(true).write(true).open(ring).ok()?;
        if f.metadata().ok()?.len() < HEADER as u64 {
            return None;
        }
        // The first page of a file at least HEADER bytes long.
        crate::private::map_shared(&f, HEADER, 0).ok().map(|map| Self { map })
    }

    fn store(&self, copied: u64) {
        // SAFETY: the word lies in the mapped header, 8-byte aligned (page-aligned base).
        let w = unsafe { &*(self.map.add(8 * word::MOVED) as *const AtomicU64) };
        w.store(copied, Ordering::Release);
    }
}

impl Drop for MovedWord {
    fn drop(&mut self) {
        // SAFETY: unmaps what map() mapped.
        unsafe { libc::munmap(self.map.cast(), HEADER) };
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
                FlightRecorder::<TorqueSample>::open(Some(&dir), Stream::ControllerTorque, 16, "t");
            assert!(r.capacity() > 0, "on");
            (0..4).for_each(|k| r.record(&torque(k)));
        }
        {
            let r =
                FlightRecorder::<TorqueSample>::open(Some(&dir), Stream::ControllerTorque, 16, "t");
            r.record(&TorqueSample { rotor_torque_nm: [9.0; 3], ..torque(3) });
            r.record(&torque(5));
            r.record(&torque(18)); // a ring: tick 18 takes tick 2's slot
        }
        let log =
            FlightLog::<TorqueSample>::read(&dir, Stream::ControllerTorque, 1 << 20).expect("read");
        assert_eq!(log.opens, 2);
        assert_eq!(log.beyond, 0);
        assert_eq!(log.get(3).map(|t| t.rotor_torque_nm), Some([9.0; 3]));
        assert_eq!(log.get(1), Some(torque(1)));
        assert_eq!(log.get(18), Some(torque(18)));
        assert_eq!(log.missing(6), vec![[2, 2], [4, 4], [6, 6]]);
        clean(&dir);
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
        let log = FlightLog::<TorqueSample>::read(&dir, Stream::Reference, 1 << 20).expect("read");
        assert_eq!(log.missing(2), vec![[1, 1]]);
        assert_eq!(log.get(2), Some(torque(2)));
        clean(&dir);
    }

    #[test]
    fn a_recorder_that_cannot_create_its_file_is_off_and_counts_what_it_lost() {
        let dir = tempfile_dir("off");
        // A file where the directory should be: the recorder cannot create its own.
        std::fs::create_dir_all(dir.parent().expect("parent")).expect("mkdir");
        std::fs::write(&dir, b"not a directory").expect("write");
        let r = FlightRecorder::<TorqueSample>::open(Some(&dir), Stream::PlantTorque, 4, "t");
        assert_eq!(r.capacity(), 0, "off");
        (0..3).for_each(|k| r.record(&torque(k)));
        assert_eq!(r.unrecorded(), 3);
        assert!(matches!(
            FlightLog::<TorqueSample>::read(&dir, Stream::PlantTorque, 1 << 20),
            Err(FlightError::Missing { .. })
        ));
        clean(&dir);
    }

    /// A ring of 512 slots over 2000 ticks, its halves moved as the writer goes: every
    /// tick is read back from the segments and the ring, and the ring's file stays 512
    /// slots long. A mover that comes too late finds its half overwritten and counts it.
    #[test]
    fn a_ring_moved_in_halves_keeps_every_tick_and_a_late_mover_counts_what_it_lost() {
        let staged = tempfile_dir("ring-staged");
        let kept = staged.with_file_name("kept");
        let _ = std::fs::remove_dir_all(&kept);
        let cap = ring_capacity(2000, 512);
        assert_eq!(cap, 512);
        let r = FlightRecorder::<TorqueSample>::open(Some(&staged), Stream::PlantTorque, cap, "t");
        let mut mover = Mover::new(&staged, &kept);
        for k in 0..2000 {
            r.record(&torque(k));
            assert!(mover.pass(k).is_empty());
        }
        assert_eq!(mover.lost, 0);
        std::fs::copy(Stream::PlantTorque.path(&staged), Stream::PlantTorque.path(&kept))
            .expect("the ring beside its segments");
        let log =
            FlightLog::<TorqueSample>::read(&kept, Stream::PlantTorque, 1 << 20).expect("read");
        assert_eq!(log.missing(1999), Vec::<[u64; 2]>::new());
        assert_eq!(log.get(1000), Some(torque(1000)));
        let len = std::fs::metadata(Stream::PlantTorque.path(&staged)).expect("ring").len();
        assert_eq!(len, (HEADER + 512 * slot_len::<TorqueSample>()) as u64);
        // A mover asleep while the writer went round twice: halves lost, and counted.
        let staged2 = tempfile_dir("ring-late");
        let kept2 = staged2.with_file_name("kept");
        let r = FlightRecorder::<TorqueSample>::open(Some(&staged2), Stream::PlantTorque, cap, "t");
        (0..1200).for_each(|k| r.record(&torque(k)));
        let mut late = Mover::new(&staged2, &kept2);
        late.pass(1199);
        // Halves 0–3 (ticks 0–1023) were due; the ring holds 688–1199 by then.
        assert_eq!(late.lost, 688, "ticks 0–687 were overwritten by 512–1199");
        clean(&staged);
        clean(&staged2);
    }

    /// The plant's lockstep wait: free while the ring has room, held at the tick that
    /// could let the reference come round to an unmoved half until the mover says it
    /// copied it, and given up after its limit when no mover ever does.
    #[test]
    fn the_plant_waits_for_the_mover_only_where_a_ring_would_come_round_unmoved() {
        let staged = tempfile_dir("gate");
        let cap = 512;
        let r = FlightRecorder::<StateSample>::open(Some(&staged), Stream::PlantState, cap, "p");
        let (half, none) = (cap / 2, std::time::Duration::ZERO);
        // 2H − 64 − 1: the reference, 64 ahead at most, stays in half 1.
        assert_eq!(free_through(0, half), 447);
        assert!(!r.wait_for_mover(447, none), "room in the ring: no wait");
        assert!(r.wait_for_mover(448, none), "half 0 unmoved: it would wait");
        let moved = MovedWord::map(&Stream::PlantState.path(&staged)).expect("map");
        moved.store(1);
        assert!(!r.wait_for_mover(448, none), "half 0 moved");
        assert!(!r.wait_for_mover(free_through(1, half), none));
        assert!(r.wait_for_mover(free_through(1, half) + 1, none), "half 1 unmoved");
        let limit = std::time::Duration::from_millis(20);
        let t0 = std::time::Instant::now();
        assert!(r.wait_for_mover(10_000, limit), "no mover: gives up");
        assert!(t0.elapsed() >= limit, "after its limit");
        clean(&staged);
    }

    /// Removes the test's whole directory: the parent of `d` (from [`tempfile_dir`]).
    fn clean(d: &Path) {
        let _ = std::fs::remove_dir_all(d.parent().expect("its base"));
    }

    /// `TMP/rotorloop-flight-PID-NAME/flight`, empty.
    fn tempfile_dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir()
            .join(format!("rotorloop-flight-{}-{name}", std::process::id()))
            .join("flight");
        let _ = std::fs::remove_dir_all(&d);
        d
    }
}
