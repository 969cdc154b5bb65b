//! Reading a stream's record after the run in bounded memory, whatever the run's length.
//!
//! A [`FlightLog`] holds no samples: it knows the stream's files (the ring and the
//! segments moved out of it, module docs of [`super`]) and reads a block of slots at a time
//! with `pread`, keeping the last [`BLOCKS`] blocks within [`BYTES_KEPT`]: [`BLOCK_SLOTS`]
//! slots of a raw file, or a chunk of a packed file (a segment, or a ring packed as it was
//! moved in at the end) unpacked whole ([`CHUNK_SLOTS`], [`super::pack`]); a segment that
//! is another stream's (`rlflsame`) is read from that one. A count of the records unpacks
//! each slot's first two words alone. Reading ticks in order (the report, the export, the
//! replay) reads each block once; looking back a few thousand ticks (the incidents) stays
//! in the kept blocks. Its memory is a few MB (6.4 MB of plant states in chunks), the same
//! for a minute's run as for a day's.
//!
//! **It trusts nothing in the files.** Every header is checked against its file's length
//! before anything is read, a tick is only ever looked up, never used as an index of
//! memory, and ticks beyond the run's last (`limit`) are not the run's: a far-future tick
//! written into a record (damage, or a writer that went wrong) is counted and ignored. A
//! segment that is torn, foreign or of another size is skipped, named in
//! [`FlightLog::problems`], and its ticks read as missing: the rest of the stream is read;
//! a packed chunk that does not unpack (its checksum, its table) reads as missing ticks.

use std::cell::RefCell;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::rc::Rc;

use super::journal::{journals, read_frames};
use super::pack::{CHUNK_SLOTS, chunk_table, unpack};
use super::{
    FlightError, HEADER, MAGIC, PACKED_MAGIC, Record, SAME_MAGIC, SPARE_SLOTS, Stream, read_header,
    segment_path, segments, slot_len, word,
};
use crate::wire::LAYOUT_VERSION;

/// Slots read from a file at once.
const BLOCK_SLOTS: u64 = 512;
/// Blocks kept at most (about 1.6 MB of raw state samples).
const BLOCKS: usize = 6;
/// Bytes the kept blocks may hold, beyond the newest two: a packed chunk of plant states is
/// 2.1 MB unpacked, so three of them, where six would be 13 MB a reader.
const BYTES_KEPT: usize = 8 << 20;
/// Problems kept in words; the rest are counted.
const MAX_PROBLEMS: usize = 16;

/// One file of a stream: the ring (slot `k mod capacity`) or a segment (half `j`: ticks
/// `j·H … (j+1)·H − 1`, slot `k − j·H`).
#[derive(Debug, Clone)]
struct Source {
    path: PathBuf,
    capacity: u64,
    /// A packed segment's chunks (offset and length in the file; [`super::pack`]).
    chunks: Option<Vec<(u64, u64)>>,
    /// A segment whose slots are this stream's segment of the same half (`rlflsame`).
    same_as: Option<Stream>,
}

impl Source {
    /// Slots read at once: a block of a raw file, a chunk of a packed one.
    fn block_slots(&self) -> u64 {
        if self.chunks.is_some() { CHUNK_SLOTS } else { BLOCK_SLOTS }
    }
}

/// Slots of one source read at once.
#[derive(Debug)]
struct Block {
    /// 0: the ring; `i + 1`: segment `i` of the list.
    source: usize,
    index: u64,
    /// Whether it holds the slots' first two words only ([`FlightLog::has`]).
    ticks: bool,
    bytes: Vec<u8>,
    used: u64,
}

#[derive(Debug)]
struct Cache {
    blocks: Vec<Block>,
    clock: u64,
    /// At most this many blocks ([`BLOCKS`] unless told, [`FlightLog::keeping`]).
    most_blocks: usize,
    /// Within this many bytes beyond the newest two ([`BYTES_KEPT`] unless told).
    most_bytes: usize,
}

impl Default for Cache {
    fn default() -> Self {
        Self { blocks: Vec::new(), clock: 0, most_blocks: BLOCKS, most_bytes: BYTES_KEPT }
    }
}

impl Cache {
    /// The bytes the kept blocks hold (their buffers' capacity).
    fn held(&self) -> usize {
        self.blocks.iter().map(|b| b.bytes.capacity()).sum()
    }
}

/// What a stream's record holds, read after the run (module docs). Memory: a few blocks,
/// never the stream.
#[derive(Debug)]
pub struct FlightLog<T: Record> {
    ring: Option<Source>,
    /// The segments that are sound, by half index, in order.
    segments: Vec<(u64, Source)>,
    /// The journal's frames that are sound, by first tick, in the order written
    /// (`super::journal`): the newest ticks of a run whose ring is gone.
    frames: Vec<(u64, Source)>,
    /// Ticks per segment.
    half: u64,
    /// Samples held in memory instead of files ([`FlightLog::of`]).
    memory: Vec<Option<T>>,
    /// The last tick the run could hold; later ones are not the run's.
    limit: u64,
    last: Option<u64>,
    /// The oldest tick of the run in the ring (an older one is looked up in its segment
    /// alone).
    ring_first: u64,
    /// How often the ring was opened for writing (1 + the writer's restarts).
    pub opens: u64,
    /// Samples whose tick lay beyond the ring's capacity (not recorded).
    pub beyond: u64,
    /// What in the files could not be read, in words (the first 16).
    pub problems: Vec<String>,
    /// Problems beyond those.
    pub more_problems: u64,
    /// Whether the ring was missing (a machine crash takes tmpfs with it).
    pub no_ring: bool,
    /// Whether a file of the record was skipped, or read only in part, as damaged (but
    /// for [`Self::torn_last`]).
    pub damaged: bool,
    /// Whether the newest segments were skipped as torn or empty (each unsound one after
    /// the last sound one): what a crash of the machine leaves of the segments being
    /// written (their data not yet durable; the mover syncs several at once), damage
    /// otherwise.
    pub torn_last: bool,
    /// The blocks kept: shared with the readers made by [`FlightLog::shared`].
    cache: Rc<RefCell<Cache>>,
}

/// A stream's records counted over ticks `0..=last`.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct StreamCount {
    /// Ticks with a record.
    pub records: u64,
    /// The first ranges of ticks without one, `[first, last]` (at most 16).
    pub missing: Vec<[u64; 2]>,
    /// How many such ranges there are in all.
    pub missing_ranges: u64,
}

/// A file's header words, checked against its length for samples of type `T`: its
/// capacity and, for a packed file, its chunks, or the stream whose segment it is; or why
/// it is not a record of this build.
fn check_header<T>(path: &Path) -> Result<([u64; 8], Source), FlightError> {
    let shown = path.display().to_string();
    let file = std::fs::File::open(path)
        .map_err(|e| FlightError::Missing { path: shown.clone(), why: e.to_string() })?;
    let foreign = |why: String| FlightError::Foreign { path: shown.clone(), why };
    let len = file.metadata().map_err(|e| foreign(e.to_string()))?.len();
    let w = match read_header(&file) {
        Ok((_, w)) if len >= HEADER as u64 => w,
        _ => return Err(foreign(format!("{len} bytes: not a flight record (or never written)"))),
    };
    let is_packed = w[word::MAGIC] == PACKED_MAGIC;
    let is_same = w[word::MAGIC] == SAME_MAGIC;
    if w[word::MAGIC] != MAGIC && !is_packed && !is_same {
        return Err(foreign("not a flight record (or never written)".into()));
    }
    if w[word::VERSION] != u64::from(LAYOUT_VERSION) || w[word::SIZE] != size_of::<T>() as u64 {
        return Err(foreign(format!(
            "written by layout v{} with {}-byte samples; this build reads layout v{} with \
             {}-byte samples",
            w[word::VERSION],
            w[word::SIZE],
            LAYOUT_VERSION,
            size_of::<T>()
        )));
    }
    let capacity = w[word::CAPACITY];
    let source = |chunks| Source { path: path.to_owned(), capacity, chunks, same_as: None };
    if is_same {
        let base = usize::try_from(w[word::BASE]).ok().and_then(|i| Stream::ALL.get(i));
        return match base {
            Some(&base) if len == HEADER as u64 && capacity > 0 => {
                Ok((w, Source { same_as: Some(base), ..source(None) }))
            }
            _ => Err(foreign(format!(
                "{len} bytes, naming stream {}: not a segment that is another's (damaged)",
                w[word::BASE]
            ))),
        };
    }
    if is_packed {
        let damaged = |e: String| foreign(format!("a packed segment: {e} (torn or damaged)"));
        let short =
            || damaged(format!("{len} bytes, too short for the chunks of {capacity} slots"));
        // The table's length is checked against the file's before it is read.
        let table = 16 * u128::from(capacity.div_ceil(CHUNK_SLOTS));
        if capacity == 0 || table > u128::from(len) {
            return Err(short());
        }
        let mut bytes = vec![0u8; table as usize];
        file.read_exact_at(&mut bytes, HEADER as u64).map_err(|_| short())?;
        let chunks = chunk_table(&bytes, (capacity, slot_len::<T>()), len).map_err(damaged)?;
        return Ok((w, source(Some(chunks))));
    }
    let expected = (capacity as u128) * slot_len::<T>() as u128 + HEADER as u128;
    if capacity == 0 || expected != u128::from(len) {
        return Err(foreign(format!(
            "{len} bytes, not a file of {capacity} slots (torn or damaged)"
        )));
    }
    Ok((w, source(None)))
}

impl<T: Record> FlightLog<T> {
    /// A second reader of the same record that shares this one's kept blocks: two readers
    /// of one stream going through it together (a derivation of the rows, and an export
    /// beside it) unpack each block once, within one reader's memory.
    pub fn shared(&self) -> Self {
        Self {
            ring: self.ring.clone(),
            segments: self.segments.clone(),
            frames: self.frames.clone(),
            half: self.half,
            memory: self.memory.clone(),
            limit: self.limit,
            last: self.last,
            ring_first: self.ring_first,
            opens: self.opens,
            beyond: self.beyond,
            problems: self.problems.clone(),
            more_problems: self.more_problems,
            no_ring: self.no_ring,
            damaged: self.damaged,
            torn_last: self.torn_last,
            cache: Rc::clone(&self.cache),
        }
    }

    /// Opens `stream`'s record in `dir` (the ring, the segments the launcher moved there
    /// during the run, and the journal of the newest ticks) for a run whose ticks end at
    /// `limit` (the scenario's last tick and the spare slots: a later tick is not the
    /// run's). Whatever of it is sound is read: a ring, a segment or a journal frame that is
    /// missing, torn or foreign is skipped and named in [`Self::problems`], its ticks read
    /// as missing. An error only where nothing of the stream is sound (the ring's error).
    pub fn read(dir: &Path, stream: Stream, limit: u64) -> Result<Self, FlightError> {
        let mut log = Self::empty();
        log.limit = limit;
        // A ring that is another's (the controller's torques, moved in at the end): that
        // stream's ring, with this one's header words.
        let ring = check_header::<T>(&stream.path(dir))
            .and_then(|(w, ring)| Ok((w, same::<T>(ring, |dir, base| base.path(dir))?)));
        let ring_error = match ring {
            Ok((w, ring)) => {
                (log.opens, log.beyond) = (w[word::OPENS], w[word::BEYOND]);
                log.half = if ring.capacity % 2 == 0 { ring.capacity / 2 } else { 0 };
                log.ring = Some(ring);
                None
            }
            Err(e) => Some(e),
        };
        log.open_segments(dir, stream);
        log.open_journal(dir, stream);
        let Some(e) = ring_error else {
            log.bound_and_find_last();
            return Ok(log);
        };
        if log.segments.is_empty() && log.frames.is_empty() {
            return Err(e);
        }
        log.no_ring = matches!(e, FlightError::Missing { .. });
        log.damaged |= !log.no_ring;
        log.problem(format!(
            "{e}: skipped; the stream is read from its segments and its journal, the ticks \
             they do not hold read as missing"
        ));
        log.bound_and_find_last();
        Ok(log)
    }

    /// Bounds the run's ticks by the record's own geometry, then finds its newest tick.
    fn bound_and_find_last(&mut self) {
        // Whatever a run's files claim, its ring holds no tick beyond two rounds past the
        // last segment moved out of it (the writers end with the mover): a bound that
        // needs no file but the records themselves.
        let capacity = self.ring.as_ref().map_or(2 * self.half, |r| r.capacity);
        if capacity > 0 {
            let after = self.segments.last().map_or(0, |(j, _)| j + 1);
            let rounds = after.saturating_add(2).saturating_mul(capacity);
            self.limit = self.limit.min(rounds.saturating_add(SPARE_SLOTS));
        }
        self.last = self.find_last();
    }

    /// The same reader keeping up to `blocks` blocks within `bytes` (at least the
    /// defaults, 6 blocks within 8 MB): for a reader that walks ahead of where it
    /// comes back to, further than the default keeps (the incidents' counterfactuals,
    /// each going up to a minute past its incident: with three chunks of states kept,
    /// each one unpacked again every chunk the one before had unpacked). Still a bound of
    /// its own, the same for a day's run as for a minute's.
    pub fn keeping(self, blocks: usize, bytes: usize) -> Self {
        {
            let mut cache = self.cache.borrow_mut();
            cache.most_blocks = blocks.max(BLOCKS);
            cache.most_bytes = bytes.max(BYTES_KEPT);
        }
        self
    }

    /// A stream with no record at all (a role that ran without one).
    pub fn empty() -> Self {
        Self {
            ring: None,
            segments: Vec::new(),
            frames: Vec::new(),
            half: 0,
            memory: Vec::new(),
            limit: u64::MAX,
            last: None,
            ring_first: 0,
            opens: 0,
            beyond: 0,
            problems: Vec::new(),
            more_problems: 0,
            no_ring: false,
            damaged: false,
            torn_last: false,
            cache: Rc::default(),
        }
    }

    /// A stream whose record could not be read at all (`e` says why): no sample, the
    /// problem named.
    pub fn unreadable(e: &FlightError) -> Self {
        let mut log = Self::empty();
        log.no_ring = matches!(e, FlightError::Missing { .. });
        log.damaged = !log.no_ring;
        log.problem(format!("{e}: nothing of this stream is read"));
        log
    }

    /// Whether any sample of the stream could be read (a ring, a segment or a frame).
    pub fn is_sound(&self) -> bool {
        self.ring.is_some()
            || !self.segments.is_empty()
            || !self.frames.is_empty()
            || !self.memory.is_empty()
    }

    /// A stream of the samples `records`, tick `k` at index `k`, held in memory (tests;
    /// in-process runs).
    pub fn of(records: Vec<T>) -> Self {
        Self::in_memory(records.into_iter().map(Some).collect())
    }

    /// A stream of the samples `records`, each at its own tick (ticks without one have
    /// none), held in memory (tests of streams with gaps): a slot for every tick up to the
    /// highest.
    pub fn of_ticks(records: Vec<T>) -> Self {
        let len = records.iter().map(|r| r.tick().saturating_add(1)).max().unwrap_or(0);
        let mut memory = vec![None; usize::try_from(len).unwrap_or(0)];
        for r in records {
            if let Some(slot) = usize::try_from(r.tick()).ok().and_then(|k| memory.get_mut(k)) {
                *slot = Some(r);
            }
        }
        Self::in_memory(memory)
    }

    /// A stream held in memory, tick `k`'s sample (or none) at index `k`.
    fn in_memory(memory: Vec<Option<T>>) -> Self {
        let last = memory.len().checked_sub(1).map(|l| l as u64);
        Self { memory, last, opens: 1, ..Self::empty() }
    }

    fn problem(&mut self, what: String) {
        if self.problems.len() < MAX_PROBLEMS {
            self.problems.push(what);
        } else {
            self.more_problems += 1;
        }
    }

    /// Checks each segment's header against its length and the ring's halves: the sound
    /// ones are kept, the others named.
    fn open_segments(&mut self, dir: &Path, stream: Stream) {
        let prefix = format!("{}.", stream.name());
        // Unsound segments since the last sound one: those the crash interrupted (the
        // mover writes several before it syncs them; the journal holds their ticks) if no
        // sound one follows, else a hole.
        let mut trailing = false;
        for path in segments(dir, stream) {
            let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
            let Some(j) = name.as_deref().and_then(|n| {
                n.strip_prefix(&prefix)?.strip_suffix(".flight")?.parse::<u64>().ok()
            }) else {
                continue;
            };
            let of = |dir: &Path, base: Stream| segment_path(dir, base, j);
            let source = match check_header::<T>(&path).and_then(|(_, s)| same::<T>(s, of)) {
                Ok(source) => source,
                Err(e) => {
                    trailing = true;
                    self.problem(format!("{e}: skipped, its ticks read as missing"));
                    continue;
                }
            };
            self.damaged |= std::mem::take(&mut trailing);
            let capacity = source.capacity;
            if self.half == 0 {
                self.half = capacity;
            }
            if capacity != self.half {
                self.damaged = true;
                self.problem(format!(
                    "{}: segment of {capacity} ticks where the ring's halves hold {}: skipped",
                    path.display(),
                    self.half
                ));
                continue;
            }
            if j.checked_mul(capacity).is_none_or(|first| first > self.limit) {
                self.problem(format!(
                    "{}: segment {j} lies beyond the run's last tick {}: skipped",
                    path.display(),
                    self.limit
                ));
                continue;
            }
            if self.segments.last().is_some_and(|(i, _)| *i == j) {
                continue; // the same half in the staging directory and the run directory
            }
            self.segments.push((j, source));
        }
        self.torn_last |= trailing;
    }

    /// Reads the frames of the stream's journal files (`super::journal`): each file is
    /// read up to its first frame that does not fit (a crash while it was appended), named.
    fn open_journal(&mut self, dir: &Path, stream: Stream) {
        for (_, path) in journals(dir, stream) {
            let (frames, stop) = read_frames(&path, size_of::<T>() as u64);
            for f in frames {
                let source = Source {
                    path: path.clone(),
                    capacity: f.slots,
                    chunks: Some(f.chunks),
                    same_as: None,
                };
                if self.ring.is_none() && self.frames.is_empty() && self.segments.is_empty() {
                    (self.opens, self.beyond) = (f.words[word::OPENS], f.words[word::BEYOND]);
                }
                if self.ring.is_none() {
                    self.opens = self.opens.max(f.words[word::OPENS]);
                }
                self.frames.push((f.first, source));
            }
            if let Some(why) = stop {
                self.problem(why);
            }
        }
    }

    /// The newest tick recorded within the run (the ring's newest, or the newest of the
    /// last segments), counting the ring's samples for ticks beyond the run.
    fn find_last(&mut self) -> Option<u64> {
        let mut last = None;
        let mut beyond_run = 0u64;
        let mut first = u64::MAX;
        if let Some(ring) = &self.ring {
            scan::<T>(ring, |slot, k| {
                if k % ring.capacity != slot {
                    return;
                }
                if k > self.limit {
                    beyond_run += 1;
                } else {
                    last = last.max(Some(k));
                    first = first.min(k);
                }
            });
        }
        self.ring_first = first;
        if beyond_run > 0 {
            self.problem(format!(
                "{}: {beyond_run} samples for ticks beyond the run's last tick {}: ignored",
                self.ring.as_ref().map_or(String::new(), |r| r.path.display().to_string()),
                self.limit
            ));
        }
        for (j, seg) in self.segments.iter().rev() {
            let mut newest = None;
            scan::<T>(seg, |slot, k| {
                if k == j * seg.capacity + slot {
                    newest = newest.max(Some(k));
                }
            });
            if newest.is_some() {
                last = last.max(newest);
                break;
            }
        }
        if self.ring.is_some() {
            return last; // the journal holds nothing newer than the ring
        }
        // The journal's frames, newest first: the first that holds a tick holds the newest.
        for (first, frame) in self.frames.iter().rev() {
            let mut newest = None;
            scan::<T>(frame, |slot, k| {
                if k == first + slot && k <= self.limit {
                    newest = newest.max(Some(k));
                }
            });
            if newest.is_some() {
                return last.max(newest);
            }
        }
        last
    }

    /// The newest tick recorded within the run.
    pub fn last(&self) -> Option<u64> {
        self.last
    }

    /// The sample of tick `k`, if recorded: the ring's copy (the newer), else its
    /// segment's.
    pub fn get(&self, k: u64) -> Option<T> {
        self.find(k, |s| s, |id, source, slot| self.lookup(id, source, slot, k))
    }

    /// Tick `k`'s slot looked for where it can be: `in_memory` of the sample kept in
    /// memory ([`FlightLog::of`]), else `probe` of the ring's slot (the newer copy), then,
    /// where that finds nothing, of its segment's.
    fn find<R>(
        &self,
        k: u64,
        in_memory: impl FnOnce(Option<T>) -> Option<R>,
        probe: impl Fn(usize, &Source, u64) -> Option<R>,
    ) -> Option<R> {
        if k > self.limit || self.last.is_none_or(|l| k > l) {
            return None;
        }
        if self.ring.is_none() && self.segments.is_empty() && self.frames.is_empty() {
            return in_memory(self.memory.get(usize::try_from(k).ok()?).copied().flatten());
        }
        if let Some(ring) = &self.ring
            && k >= self.ring_first
            && let Some(r) = probe(0, ring, k % ring.capacity)
        {
            return Some(r);
        }
        if let Some(j) = k.checked_div(self.half)
            && let Ok(i) = self.segments.binary_search_by_key(&j, |(j, _)| *j)
            && let Some(r) = probe(i + 1, &self.segments[i].1, k % self.half)
        {
            return Some(r);
        }
        // The journal's newest frame that holds the tick (frames are few: a second's each).
        let base = 1 + self.segments.len();
        self.frames.iter().enumerate().rev().find_map(|(i, (first, frame))| {
            let slot = k.checked_sub(*first).filter(|s| *s < frame.capacity)?;
            probe(base + i, frame, slot)
        })
    }

    /// The sample in `slot` of `source` if it is tick `k`'s.
    fn lookup(&self, id: usize, source: &Source, slot: u64, k: u64) -> Option<T> {
        let len = slot_len::<T>();
        self.with_slot(id, source, (slot, len), |bytes| {
            let tag = u64::from_ne_bytes(bytes[..8].try_into().unwrap_or_default());
            if tag != k.wrapping_add(1) {
                return None;
            }
            // SAFETY: the slot holds `size_of::<T>()` bytes after its tag; T is plain old
            // data (f64/u64 fields), valid for any bit pattern.
            let sample = unsafe { std::ptr::read_unaligned(bytes[8..].as_ptr() as *const T) };
            (sample.tick() == k).then_some(sample)
        })
        .flatten()
    }

    /// Whether the slot in `source` holds tick `k`'s sample, as [`Self::lookup`] finds it,
    /// from the slot's first two words alone ([`tick_of`]).
    fn holds(&self, id: usize, source: &Source, slot: u64, k: u64) -> bool {
        self.with_slot(id, source, (slot, 16), |bytes| tick_of(bytes) == Some(k)).unwrap_or(false)
    }

    /// `f` of the bytes of `slot` of `source` (its first `len` bytes: a whole slot, or its
    /// two words where `len` is 16), from the kept blocks or a block read now.
    fn with_slot<R>(
        &self,
        id: usize,
        source: &Source,
        (slot, len): (u64, usize),
        f: impl FnOnce(&[u8]) -> R,
    ) -> Option<R> {
        let mut cache = self.cache.borrow_mut();
        let block_slots = source.block_slots();
        let index = slot / block_slots;
        let ticks = len < slot_len::<T>();
        cache.clock += 1;
        let clock = cache.clock;
        let found =
            cache.blocks.iter().position(|b| (b.source, b.index, b.ticks) == (id, index, ticks));
        let at = match found {
            Some(at) => at,
            None => {
                // The least recently used blocks go until the new one fits; the last to go
                // lends its buffer (no fresh pages to fault in).
                let want = block_slots as usize * len;
                let mut bytes = Vec::new();
                while cache.blocks.len() >= cache.most_blocks
                    || (cache.blocks.len() >= 2 && cache.held() + want > cache.most_bytes)
                {
                    let oldest =
                        (0..cache.blocks.len()).min_by_key(|i| cache.blocks[*i].used).unwrap_or(0);
                    bytes = cache.blocks.swap_remove(oldest).bytes;
                }
                read_block::<T>(source, (index, ticks), &mut bytes);
                cache.blocks.push(Block { source: id, index, ticks, bytes, used: clock });
                cache.blocks.len() - 1
            }
        };
        let block = &mut cache.blocks[at];
        block.used = clock;
        let off = (slot - index * block_slots) as usize * len;
        block.bytes.get(off..off + len).map(f)
    }

    /// Whether tick `k` has a record: as `get(k).is_some()`, reading the slots' first two
    /// words only (a chunk's other columns are not decoded).
    fn has(&self, k: u64) -> bool {
        let probe = |id, source: &Source, slot| self.holds(id, source, slot, k).then_some(());
        self.find(k, |s| s.map(|_| ()), probe).is_some()
    }

    /// Every sample recorded, in tick order.
    pub fn iter(&self) -> impl Iterator<Item = T> + '_ {
        let end = self.last.map_or(0, |l| l + 1);
        (0..end).filter_map(|k| self.get(k))
    }

    /// The records of ticks `0..=last` counted, with the ranges of ticks that have none.
    pub fn count(&self, last: u64) -> StreamCount {
        let mut c = StreamCount::default();
        let mut open: Option<[u64; 2]> = None;
        let close = |c: &mut StreamCount, r: [u64; 2]| {
            c.missing_ranges += 1;
            if c.missing.len() < 16 {
                c.missing.push(r);
            }
        };
        for k in 0..=last {
            if self.has(k) {
                c.records += 1;
                if let Some(r) = open.take() {
                    close(&mut c, r);
                }
            } else {
                match &mut open {
                    Some(r) => r[1] = k,
                    None => open = Some([k, k]),
                }
            }
        }
        if let Some(r) = open {
            close(&mut c, r);
        }
        c
    }

    /// Ticks of `0..=last` with no record, as `[first, last]` ranges (the first 16).
    pub fn missing(&self, last: u64) -> Vec<[u64; 2]> {
        self.count(last).missing
    }
}

/// The source of a ring or segment whose header is `source`: itself, or the file `of` the
/// stream it names when it is another's (its ring, or its segment of the same half, in the
/// same directory), which must be a file of its own, of as many slots.
fn same<T>(
    source: Source,
    of: impl FnOnce(&Path, Stream) -> PathBuf,
) -> Result<Source, FlightError> {
    let Some(base) = source.same_as else { return Ok(source) };
    // Beside it: the segments may lie elsewhere than the ring (`OUT/flight` and tmpfs).
    let dir = source.path.parent().unwrap_or(Path::new(""));
    let (_, of) = check_header::<T>(&of(dir, base)).map_err(|e| FlightError::Foreign {
        path: source.path.display().to_string(),
        why: format!("the same as {}, which cannot be read: {e}", base.name()),
    })?;
    if of.same_as.is_some() || of.capacity != source.capacity {
        return Err(FlightError::Foreign {
            path: source.path.display().to_string(),
            why: format!(
                "the same as {}, which is not a record of {} slots of its own",
                of.path.display(),
                source.capacity
            ),
        });
    }
    Ok(of)
}

/// Block `index` of `source`'s slots, as read into `bytes` (its allocation reused; left
/// shorter, or empty, where the file was cut since it was checked or a packed chunk does
/// not unpack: those slots read as missing).
fn read_block<T>(source: &Source, (index, ticks): (u64, bool), bytes: &mut Vec<u8>) {
    let len = slot_len::<T>();
    bytes.clear();
    let Ok(f) = std::fs::File::open(&source.path) else { return };
    if let Some(chunks) = &source.chunks {
        let Some(&(at, l)) = chunks.get(index as usize) else { return };
        let mut packed = vec![0u8; l as usize]; // within the file's length: checked
        if f.read_exact_at(&mut packed, at).is_err()
            || unpack(&packed, (index, source.capacity, len), ticks, bytes).is_err()
        {
            bytes.clear();
        }
        return;
    }
    let first = index * BLOCK_SLOTS;
    let n = BLOCK_SLOTS.min(source.capacity.saturating_sub(first));
    bytes.resize(n as usize * len, 0);
    if f.read_exact_at(bytes, HEADER as u64 + first * len as u64).is_err() {
        bytes.clear();
    }
    if ticks {
        // The first two words of each slot, as a packed chunk's are given.
        let slots = bytes.len() / len;
        for i in 0..slots {
            bytes.copy_within(i * len..i * len + 16, i * 16);
        }
        bytes.truncate(slots * 16);
    }
}

/// The tick a slot holds, from its first two words (its tag, the tick + 1, and its
/// sample's tick: every [`Record`]'s first field), where they agree.
fn tick_of(slot: &[u8]) -> Option<u64> {
    let word = |i: usize| u64::from_ne_bytes(slot[8 * i..8 * i + 8].try_into().unwrap_or_default());
    word(0).checked_sub(1).filter(|k| word(1) == *k)
}

/// Calls `f(slot, tick)` for each slot of `source` whose tag and sample agree on a tick,
/// from those two words alone (a packed chunk decodes two columns of its dozens; one
/// block in memory at a time).
fn scan<T: Record>(source: &Source, mut f: impl FnMut(u64, u64)) {
    let block_slots = source.block_slots();
    let mut bytes = Vec::new();
    for index in 0..source.capacity.div_ceil(block_slots) {
        read_block::<T>(source, (index, true), &mut bytes);
        for (i, s) in bytes.chunks_exact(16).enumerate() {
            if let Some(k) = tick_of(s) {
                f(index * block_slots + i as u64, k);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{FlightRecorder, Mover, ring_capacity, segment_path};
    use super::*;
    use crate::wire::TorqueSample;

    fn torque(k: u64) -> TorqueSample {
        TorqueSample { tick: k, rotor_torque_nm: [k as f64, 1.0, 2.0], ..Default::default() }
    }

    /// A run of `ticks` recorded into a ring of 512 slots, its halves moved as it goes:
    /// the run directory (`kept`) with its segments and the ring beside them.
    fn recorded(name: &str, ticks: u64) -> PathBuf {
        let base =
            std::env::temp_dir().join(format!("rotorloop-read-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&base);
        let (staged, kept) = (base.join("staged"), base.join("kept"));
        let cap = ring_capacity(ticks, 512);
        let r = FlightRecorder::<TorqueSample>::open(Some(&staged), Stream::PlantTorque, cap, "t");
        let mut mover = Mover::new(&staged, &kept);
        for k in 0..ticks {
            r.record(&torque(k));
            assert!(mover.pass(k).is_empty());
        }
        std::fs::create_dir_all(&kept).expect("kept");
        std::fs::copy(Stream::PlantTorque.path(&staged), Stream::PlantTorque.path(&kept))
            .expect("the ring beside its segments");
        kept
    }

    fn read(dir: &Path, limit: u64) -> FlightLog<TorqueSample> {
        FlightLog::read(dir, Stream::PlantTorque, limit).expect("read")
    }

    /// 40 segments and the ring: every tick in order, looked up again far back, and the
    /// reader's memory the same blocks whatever the length.
    #[test]
    fn many_segments_read_in_order_and_back_in_bounded_blocks() {
        let dir = recorded("many", 10_000);
        assert!(segments(&dir, Stream::PlantTorque).len() >= 36);
        let log = read(&dir, 10_063);
        assert_eq!(log.last(), Some(9_999));
        assert!(log.problems.is_empty(), "{:?}", log.problems);
        let ticks: Vec<u64> = log.iter().map(|t| t.tick).collect();
        assert_eq!(ticks, (0..10_000).collect::<Vec<_>>());
        assert_eq!(log.count(9_999), StreamCount { records: 10_000, ..Default::default() });
        for k in [9_000, 17, 5_000, 9_999, 0] {
            assert_eq!(log.get(k), Some(torque(k)));
        }
        let cache = log.cache.borrow();
        assert!(cache.blocks.len() <= BLOCKS);
        assert!(cache.held() <= BYTES_KEPT.max(2 * 4096 * slot_len::<TorqueSample>()));
        drop(cache);
        let _ = std::fs::remove_dir_all(dir.parent().expect("base"));
    }

    /// A torn segment (cut short by a full disk, say) and a missing one: their ticks read
    /// as missing, the problem is named, and every other tick is read.
    #[test]
    fn a_torn_and_a_missing_segment_leave_the_rest_readable() {
        let dir = recorded("torn", 3_000);
        let torn = segment_path(&dir, Stream::PlantTorque, 2); // ticks 512–767
        let len = std::fs::metadata(&torn).expect("segment").len();
        std::fs::OpenOptions::new()
            .write(true)
            .open(&torn)
            .expect("open")
            .set_len(len / 2)
            .expect("cut");
        std::fs::remove_file(segment_path(&dir, Stream::PlantTorque, 4)).expect("rm"); // 1024–1279
        let empty = segment_path(&dir, Stream::PlantTorque, 5);
        std::fs::write(&empty, b"").expect("zero-length");
        let log = read(&dir, 3_063);
        assert_eq!(log.problems.len(), 2, "{:?}", log.problems);
        assert!(log.problems[0].contains("torn or damaged"), "{}", log.problems[0]);
        let c = log.count(2_999);
        assert_eq!(c.missing, vec![[512, 767], [1024, 1535]]);
        assert_eq!(c.records, 3_000 - 256 - 512);
        assert_eq!(log.get(768), Some(torque(768)));
        // Sound segments follow the torn and the empty one: holes, not a crash's tail.
        assert!(log.damaged && !log.torn_last);
        let _ = std::fs::remove_dir_all(dir.parent().expect("base"));
    }

    /// The newest segments left empty, as a machine crash leaves those the mover had made
    /// but not yet synced (it syncs several at once): each is named, none is damage (seen
    /// in CI: three such segments of a stream read as "record damaged").
    #[test]
    fn the_newest_segments_left_empty_are_a_crashs_tail_not_damage() {
        let dir = recorded("tail", 3_000);
        let all = segments(&dir, Stream::PlantTorque);
        assert!(all.len() > 3, "{all:?}");
        for newest in &all[all.len() - 2..] {
            std::fs::write(newest, b"").expect("zero-length");
        }
        let log = read(&dir, 3_063);
        assert_eq!(log.problems.len(), 2, "{:?}", log.problems);
        assert!(log.torn_last && !log.damaged);
        let _ = std::fs::remove_dir_all(dir.parent().expect("base"));
    }

    /// The segments are packed (a fraction of a raw half's bytes), and a packed chunk
    /// damaged inside (a flipped byte in its frame) reads as missing ticks, not as wrong
    /// samples: every other tick is read.
    #[test]
    fn segments_are_packed_and_a_damaged_chunk_reads_as_missing() {
        let dir = recorded("packed", 3_000);
        let raw = HEADER as u64 + 256 * slot_len::<TorqueSample>() as u64;
        let seg = segment_path(&dir, Stream::PlantTorque, 3); // ticks 768–1023
        let mut bytes = std::fs::read(&seg).expect("segment");
        assert!((bytes.len() as u64) < raw / 4, "{} bytes of {raw}", bytes.len());
        let end = bytes.len();
        bytes[end - 12] ^= 0x5a;
        std::fs::write(&seg, &bytes).expect("damage");
        let log = read(&dir, 3_063);
        let c = log.count(2_999);
        assert_eq!(c.missing, vec![[768, 1023]]);
        assert_eq!(c.records, 3_000 - 256);
        assert_eq!(log.get(1_024), Some(torque(1_024)));
        let _ = std::fs::remove_dir_all(dir.parent().expect("base"));
    }

    /// The rings moved into the run directory at the end are packed (a fraction of their
    /// bytes, their header words kept) and read as the raw ones, every tick; moved raw
    /// where asked. A file that is not a whole raw record is moved as it is.
    #[test]
    fn a_ring_moved_at_the_end_is_packed_and_reads_as_the_raw_one() {
        for packed in [true, false] {
            let dir = recorded(&format!("ring-{packed}"), 3_000); // the ring copied in raw
            let raw = read(&dir, 3_063);
            let (opens, raw): (u64, Vec<TorqueSample>) = (raw.opens, raw.iter().collect());
            let staged = dir.parent().expect("base").join("staged");
            std::fs::write(staged.join("reference.flight"), b"not a record").expect("foreign");
            std::fs::remove_file(Stream::PlantTorque.path(&dir)).expect("the copy");
            assert_eq!(super::super::move_records(&staged, &dir, packed).expect("moved"), 2);
            let ring = Stream::PlantTorque.path(&dir);
            let (w, _) = check_header::<TorqueSample>(&ring).expect("a sound ring");
            assert_eq!(w[word::MAGIC], if packed { PACKED_MAGIC } else { MAGIC });
            let len = std::fs::metadata(&ring).expect("ring").len();
            let whole = HEADER as u64 + 512 * slot_len::<TorqueSample>() as u64;
            assert!(if packed { len < whole / 3 } else { len == whole }, "{len} of {whole}");
            assert_eq!(
                std::fs::read(Stream::Reference.path(&dir)).expect("as it was"),
                b"not a record"
            );
            let log = read(&dir, 3_063);
            assert!(log.problems.is_empty(), "{:?}", log.problems);
            assert_eq!((log.opens, log.last()), (opens, Some(2_999)));
            assert!(log.iter().eq(raw), "every tick as the raw ring had it");
            let _ = std::fs::remove_dir_all(dir.parent().expect("base"));
        }
    }

    /// The controller's torques and the plant's, recorded over 3000 ticks, where the plant
    /// did not receive tick 1100: each half the plant has byte for byte is a header naming
    /// the plant's segment, the half that differs is packed on its own, and both streams
    /// read every tick they hold. A header whose segment is gone, or that names one of
    /// another size, reads as missing, named.
    #[test]
    fn a_controller_half_the_plant_has_byte_for_byte_is_kept_once() {
        let base = std::env::temp_dir().join(format!("rotorloop-read-{}-same", std::process::id()));
        let _ = std::fs::remove_dir_all(&base);
        let (staged, kept) = (base.join("staged"), base.join("kept"));
        let cap = ring_capacity(3_000, 512);
        let open = |s| FlightRecorder::<TorqueSample>::open(Some(&staged), s, cap, "t");
        let (plant, controller) = (open(Stream::PlantTorque), open(Stream::ControllerTorque));
        let mut mover = Mover::new(&staged, &kept);
        for k in 0..3_000 {
            controller.record(&torque(k));
            if k != 1_100 {
                plant.record(&torque(k));
            }
            assert!(mover.pass(k).is_empty());
        }
        for s in [Stream::PlantTorque, Stream::ControllerTorque] {
            std::fs::copy(s.path(&staged), s.path(&kept)).expect("the ring beside its segments");
        }
        let len = |j| {
            std::fs::metadata(segment_path(&kept, Stream::ControllerTorque, j)).map(|m| m.len())
        };
        assert_eq!(len(0).expect("segment 0"), HEADER as u64);
        assert!(len(4).expect("segment 4") > HEADER as u64, "ticks 1024–1279 differ");
        assert_eq!(len(5).expect("segment 5"), HEADER as u64);
        let controller =
            FlightLog::<TorqueSample>::read(&kept, Stream::ControllerTorque, 3_063).expect("read");
        assert!(controller.problems.is_empty(), "{:?}", controller.problems);
        assert_eq!(controller.count(2_999).records, 3_000);
        assert_eq!(controller.get(1_100), Some(torque(1_100)));
        assert_eq!(read(&kept, 3_063).count(2_999).missing, vec![[1_100, 1_100]]);
        std::fs::remove_file(segment_path(&kept, Stream::PlantTorque, 1)).expect("rm");
        let plant3 = segment_path(&kept, Stream::PlantTorque, 3);
        std::fs::write(
            &plant3,
            &std::fs::read(segment_path(&kept, Stream::ControllerTorque, 3)).expect("header")[..],
        )
        .expect("a header naming itself");
        let controller =
            FlightLog::<TorqueSample>::read(&kept, Stream::ControllerTorque, 3_063).expect("read");
        assert_eq!(controller.count(2_999).missing, vec![[256, 511], [768, 1023]]);
        assert_eq!(controller.problems.len(), 2, "{:?}", controller.problems);
        assert!(
            controller.problems[0].contains("the same as plant-torque, which cannot be read"),
            "{:?}",
            controller.problems
        );
        assert!(
            controller.problems[1].contains("not a record of 256 slots of its own"),
            "{:?}",
            controller.problems
        );
        let _ = std::fs::remove_dir_all(&base);
    }

    /// The rings moved in at the end: the controller's, where the plant's holds the same
    /// slots byte for byte, is a header naming it, and reads every tick with its own
    /// header words; where they differ (tick 300 lost on its way) it is packed on its own.
    /// Without the plant's ring it is refused, named.
    #[test]
    fn a_controller_ring_the_plant_has_byte_for_byte_is_kept_once() {
        for lost in [None, Some(300)] {
            let base = std::env::temp_dir()
                .join(format!("rotorloop-read-{}-ring-same-{lost:?}", std::process::id()));
            let _ = std::fs::remove_dir_all(&base);
            let (staged, kept) = (base.join("staged"), base.join("kept"));
            let cap = ring_capacity(600, 1 << 12);
            let open = |s| FlightRecorder::<TorqueSample>::open(Some(&staged), s, cap, "t");
            let (plant, controller) = (open(Stream::PlantTorque), open(Stream::ControllerTorque));
            for k in 0..600 {
                controller.record(&torque(k));
                if Some(k) != lost {
                    plant.record(&torque(k));
                }
            }
            drop((plant, controller));
            assert_eq!(super::super::move_records(&staged, &kept, true).expect("moved"), 2);
            let ring = Stream::ControllerTorque.path(&kept);
            let (w, _) = check_header::<TorqueSample>(&ring).expect("a sound header");
            let magic = if lost.is_some() { PACKED_MAGIC } else { SAME_MAGIC };
            assert_eq!(w[word::MAGIC], magic, "{lost:?}");
            let len = std::fs::metadata(&ring).expect("ring").len();
            assert_eq!(len == HEADER as u64, lost.is_none(), "{len} bytes");
            let c = FlightLog::<TorqueSample>::read(&kept, Stream::ControllerTorque, 663);
            let c = c.expect("read");
            assert!(c.problems.is_empty(), "{:?}", c.problems);
            assert_eq!((c.opens, c.count(599).records), (1, 600));
            assert!(c.iter().eq((0..600).map(torque)), "every tick the controller published");
            let p = read(&kept, 663).count(599).missing;
            assert_eq!(p, lost.map(|k| vec![[k, k]]).unwrap_or_default());
            std::fs::remove_file(Stream::PlantTorque.path(&kept)).expect("rm");
            let c = FlightLog::<TorqueSample>::read(&kept, Stream::ControllerTorque, 663);
            match (lost, c) {
                (Some(_), c) => assert_eq!(c.expect("its own").count(599).records, 600),
                (None, Err(e)) => assert!(
                    e.to_string().contains("the same as plant-torque, which cannot be read"),
                    "{e}"
                ),
                (None, Ok(_)) => panic!("read without the ring it names"),
            }
            let _ = std::fs::remove_dir_all(&base);
        }
    }

    /// A tick far beyond the run written into the ring (tag and sample agreeing, as a
    /// fuzzer wrote it: capacity × 2⁴⁰) allocates nothing and is not the run's.
    #[test]
    fn a_far_future_tick_is_counted_and_ignored_not_allocated() {
        let dir = recorded("far", 300);
        let ring = Stream::PlantTorque.path(&dir);
        let (_, cap) = check_header::<TorqueSample>(&ring).expect("ring");
        let k = cap.capacity << 40;
        let f = std::fs::OpenOptions::new().write(true).open(&ring).expect("open");
        let mut slot = (k + 1).to_ne_bytes().to_vec();
        slot.extend_from_slice(&k.to_ne_bytes());
        f.write_all_at(&slot, HEADER as u64).expect("write");
        let log = read(&dir, 363);
        assert_eq!(log.last(), Some(299));
        assert_eq!(log.get(k), None);
        assert!(log.problems[0].contains("beyond the run's last tick 363"), "{:?}", log.problems);
        assert_eq!(log.count(299).missing, vec![[0, 0]]);
        let _ = std::fs::remove_dir_all(dir.parent().expect("base"));
    }

    /// `ROTORLOOP_READ_DIR=DIR cargo test --release -p rotorloop-common read::tests::speed --
    /// --ignored --nocapture` reads every tick of each stream of the run directory `DIR`'s
    /// `flight/` in order, as a pass of the readers does, and prints ticks a second.
    #[test]
    #[ignore = "a measurement on a run's files"]
    fn speed() {
        let Some(dir) = std::env::var_os("ROTORLOOP_READ_DIR") else {
            eprintln!("set ROTORLOOP_READ_DIR to a run directory with flight records");
            return;
        };
        let flight = PathBuf::from(dir).join("flight");
        fn pass<T: Record>(flight: &Path, stream: Stream) {
            let t0 = std::time::Instant::now();
            let log = FlightLog::<T>::read(flight, stream, u64::MAX).expect("read");
            let opened_s = t0.elapsed().as_secs_f64();
            let t1 = std::time::Instant::now();
            let n = log.iter().count();
            let s = t1.elapsed().as_secs_f64();
            let t2 = std::time::Instant::now();
            let counted = log.count(log.last().unwrap_or(0));
            let count_s = t2.elapsed().as_secs_f64();
            assert_eq!(counted.records, n as u64, "a count reads every sample the reader reads");
            println!("{}: counted in {count_s:.2} s", stream.name());
            println!(
                "{}: opened in {opened_s:.2} s; {n} ticks in {s:.2} s, {:.2} M ticks/s, {:.0} MB/s \
                 of slots",
                stream.name(),
                n as f64 / s / 1e6,
                (n * slot_len::<T>()) as f64 / s / 1e6
            );
        }
        pass::<crate::wire::StateSample>(&flight, Stream::PlantState);
        pass::<TorqueSample>(&flight, Stream::PlantTorque);
        pass::<TorqueSample>(&flight, Stream::ControllerTorque);
        pass::<crate::wire::ReferenceSample>(&flight, Stream::Reference);
    }

    /// A ring whose header claims more slots than its file holds is refused before
    /// anything is read.
    #[test]
    fn a_ring_whose_header_lies_about_its_size_is_refused() {
        let dir = recorded("lies", 300);
        let ring = Stream::PlantTorque.path(&dir);
        let f = std::fs::OpenOptions::new().write(true).open(&ring).expect("open");
        f.write_all_at(&(1u64 << 60).to_ne_bytes(), 8 * word::CAPACITY as u64).expect("write");
        let e = FlightLog::<TorqueSample>::read(&dir, Stream::PlantTorque, 363).expect_err("lies");
        assert!(e.to_string().contains("not a file of 1152921504606846976 slots"), "{e}");
        let _ = std::fs::remove_dir_all(dir.parent().expect("base"));
    }
}
