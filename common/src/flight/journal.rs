//! The journal: the newest ticks of every stream on the output disk, durably, within a
//! second, so that a crash of the whole machine (a kernel panic, a reset, a power cut: the
//! rings on tmpfs are gone) loses at most the last second of the record.
//!
//! The rings stay the hot path (a role's record is a `memcpy` into tmpfs); the mover's
//! thread ([`super::Mover::journal`]), every [`JOURNAL_PERIOD`], first makes the segments
//! written since the last time durable and removes the journals of their halves, then reads
//! each ring's ticks past its last durable segment that it has not journaled yet (the
//! range at once), packs them ([`super::pack`]) into a **frame** and appends the frame to
//! `OUT/flight/STREAM.NNNNNN.journal` (`NNNNNN`: the half of the ring the ticks belong to,
//! 0 for a ring that never comes round); then it makes the frames durable (`fdatasync` of
//! each file, an `fsync` of the directory after a file is made) before the next period's.
//! So no frame reaches the disk before the segments written ahead of it. A frame rewrites
//! the last few ticks of the one before (a torque recorded just after its state, the
//! reference ahead of the plant): a reader takes, for a tick, the ring's slot, else its
//! segment's, else the newest frame that holds it.
//!
//! **A frame** is a packed segment ([`super::pack`]) whose header has the magic
//! `rlfljrnl`, the ring's header words (its writer's opens among them), its slots as
//! [`super::word::CAPACITY`], its first tick as [`super::word::MOVED`] and its length in
//! bytes as [`super::word::BASE`]. A reader walks a journal frame by frame from its start,
//! and stops at the first frame that does not fit (a crash in the middle of an append:
//! what the disk had not yet made durable), naming it.

use std::fs::File;
use std::os::unix::fs::{FileExt, OpenOptionsExt};
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::pack::{CHUNK_SLOTS, chunk_table};
use super::{HEADER, Stream, word};

/// A journal frame's magic: "rlfljrnl".
pub(super) const JOURNAL_MAGIC: u64 = 0x6c6e_726a_6c66_6c72;

/// How often the newest ticks are journaled and made durable. A crash loses what was
/// recorded since the last durable frame: at most this period and the time one period's
/// writes take to reach the disk (measured in docs/flight-recorders.md).
pub const JOURNAL_PERIOD: Duration = Duration::from_millis(200);

/// How far from the disk the newest ticks may fall before a mover in the background
/// ([`super::Mover::in_background`]) is made an ordinary thread again: two periods.
pub const CATCH_UP: Duration = Duration::from_millis(400);

/// What a machine crash may cost a run at most: the last second of its record. A run
/// whose newest ticks were ever further from the disk says so (`summary.json`
/// `flight.durable_lag_max_s`, and a warning).
pub const DURABLE_BOUND: Duration = Duration::from_secs(1);

/// A stream's journal frames search for their transforms once in this many; the others
/// take the last search's (`pack::pack_reusing`): 5 s of frames.
pub(super) const RESEARCH: u64 = 25;

/// Ticks of the frame before that a frame writes again (a torque recorded just after its
/// state; a sample recorded a moment after the frame read its slot).
pub(super) const OVERLAP: u64 = 8;

/// The journal file of half `j` of `stream`'s ring in `dir`.
pub fn journal_path(dir: &Path, stream: Stream, j: u64) -> PathBuf {
    dir.join(format!("{}.{j:06}.journal", stream.name()))
}

/// The journal of half `j` of `stream` in `dir` kept beside its segment: the ring had come
/// round over some of the half's ticks before the mover read it, so the segment lacks ticks
/// the journal holds (a realtime mover held up, seen when a `fdatasync` took 2 s beside a
/// build). Readers read it as any journal; moving the rings in at the end leaves it.
pub fn kept_journal_path(dir: &Path, stream: Stream, j: u64) -> PathBuf {
    dir.join(format!("{}.{j:06}.kept.journal", stream.name()))
}

/// The journal files of `stream` in `dir` (kept ones among them), by half, in order.
pub fn journals(dir: &Path, stream: Stream) -> Vec<(u64, PathBuf)> {
    let prefix = format!("{}.", stream.name());
    let mut out: Vec<(u64, PathBuf)> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().into_string().ok()?;
            let half = name.strip_prefix(&prefix)?.strip_suffix(".journal")?;
            let j = half.strip_suffix(".kept").unwrap_or(half).parse().ok()?;
            Some((j, e.path()))
        })
        .collect();
    out.sort();
    out
}

/// Creates or opens `path` to append to: owner-only (0600) whatever the umask, never
/// through a link, closed on exec. Returns the file and whether it was made now.
pub(super) fn open_private_append(path: &Path) -> std::io::Result<(File, bool)> {
    let open = |create: bool| {
        std::fs::OpenOptions::new()
            .append(true)
            .read(true)
            .create_new(create)
            .mode(0o600)
            .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
            .open(path)
    };
    match open(true) {
        Ok(f) => Ok((f, true)),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok((open(false)?, false)),
        Err(e) => Err(e),
    }
}

/// Creates `path` anew (an earlier file of that name, never a link, is replaced): owner-only
/// (0600), never through a link, closed on exec.
pub(super) fn create_private(path: &Path) -> std::io::Result<File> {
    if std::fs::symlink_metadata(path).is_ok() {
        std::fs::remove_file(path)?; // a link itself, never its target
    }
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)
}

/// `fsync` of the directory `dir` (a file made or renamed in it is then durable by name).
pub(super) fn sync_dir(dir: &Path) -> std::io::Result<()> {
    File::open(dir)?.sync_all()
}

/// A frame's bytes: the ring's header `ring_header` (its words kept but the magic, the
/// capacity and the two below), the slots `body` of ticks `first…`, packed with the
/// stream's transforms `codes` (searched for where it is empty: `pack::pack_reusing`).
pub(super) fn frame(
    ring_header: &[u8],
    first: u64,
    (body, slot_len): (&[u8], usize),
    codes: &mut Vec<u8>,
) -> std::io::Result<Vec<u8>> {
    let mut header = ring_header[..HEADER].to_vec();
    let set =
        |h: &mut [u8], w: usize, v: u64| h[8 * w..8 * w + 8].copy_from_slice(&v.to_ne_bytes());
    set(&mut header, word::MAGIC, JOURNAL_MAGIC);
    set(&mut header, word::CAPACITY, (body.len() / slot_len) as u64);
    set(&mut header, word::MOVED, first);
    let mut bytes = super::pack::pack_reusing(&header, body, slot_len, codes)?;
    let len = bytes.len() as u64;
    set(&mut bytes, word::BASE, len);
    Ok(bytes)
}

/// One frame of a journal, as a reader finds it.
#[derive(Debug, Clone)]
pub(super) struct Frame {
    /// Its first tick.
    pub first: u64,
    /// Its slots.
    pub slots: u64,
    /// Its chunks, where they lie in the journal file.
    pub chunks: Vec<(u64, u64)>,
    /// Its header's words.
    pub words: [u64; 8],
}

/// The frames of the journal `path` for samples of `size` bytes, in the order they were
/// written, and what stopped the walk before the file's end (a frame cut short by a crash,
/// or damage), in words.
pub(super) fn read_frames(path: &Path, size: u64) -> (Vec<Frame>, Option<String>) {
    let mut frames = Vec::new();
    let Ok(f) = File::open(path) else {
        return (frames, Some(format!("{}: cannot be opened", path.display())));
    };
    let len = f.metadata().map(|m| m.len()).unwrap_or(0);
    let slot = 8 + (size as usize).next_multiple_of(8);
    let mut at = 0u64;
    while at < len {
        let stop = |why: String| {
            Some(format!(
                "{}: a frame at byte {at} of {len} {why} (cut short by a crash, or damaged): \
                 the journal is read up to it",
                path.display()
            ))
        };
        let mut h = [0u8; HEADER];
        if f.read_exact_at(&mut h, at).is_err() {
            return (frames, stop("shorter than a header".into()));
        }
        let w: [u64; 8] = std::array::from_fn(|i| {
            u64::from_ne_bytes(h[8 * i..8 * i + 8].try_into().unwrap_or_default())
        });
        let (slots, frame_len) = (w[word::CAPACITY], w[word::BASE]);
        if w[word::MAGIC] != JOURNAL_MAGIC
            || w[word::VERSION] != u64::from(crate::wire::LAYOUT_VERSION)
            || w[word::SIZE] != size
        {
            return (frames, stop("is not a frame of this stream".into()));
        }
        let table = 16 * u128::from(slots.div_ceil(CHUNK_SLOTS));
        if slots == 0
            || u128::from(frame_len) < HEADER as u128 + table
            || at.checked_add(frame_len).is_none_or(|end| end > len)
        {
            return (frames, stop(format!("of {frame_len} bytes, {slots} slots, does not fit")));
        }
        let mut t = vec![0u8; table as usize]; // within the file: checked
        if f.read_exact_at(&mut t, at + HEADER as u64).is_err() {
            return (frames, stop("has no chunk table".into()));
        }
        match chunk_table(&t, (slots, slot), frame_len) {
            Ok(chunks) => frames.push(Frame {
                first: w[word::MOVED],
                slots,
                chunks: chunks.into_iter().map(|(o, l)| (at + o, l)).collect(),
                words: w,
            }),
            Err(e) => return (frames, stop(e)),
        }
        at += frame_len;
    }
    (frames, None)
}

/// Bytes of a ring's slots for ticks `from..=to` (every one of them in the ring: `to − from`
/// under its capacity), read with `pread`, each slot whose tag is not its tick's zeroed (not
/// written yet, torn, or already the next round's); `None` if the file cannot be read.
pub(super) fn read_ticks(
    ring: &File,
    (capacity, slot): (u64, usize),
    from: u64,
    to: u64,
) -> Option<Vec<u8>> {
    let n = (to + 1 - from) as usize;
    let mut bytes = vec![0u8; n * slot];
    let mut k = from;
    let mut done = 0usize;
    while done < n {
        let s = k % capacity;
        let run = ((capacity - s) as usize).min(n - done);
        ring.read_exact_at(
            &mut bytes[done * slot..(done + run) * slot],
            (HEADER + s as usize * slot) as u64,
        )
        .ok()?;
        done += run;
        k += run as u64;
    }
    let sound = |s: &[u8], want: u64| {
        let tag = u64::from_ne_bytes(s[..8].try_into().unwrap_or_default());
        let tick = u64::from_ne_bytes(s[8..16].try_into().unwrap_or_default());
        tag == want + 1 && tick == want
    };
    let mut newest = None;
    for (i, s) in bytes.chunks_exact_mut(slot).enumerate() {
        match sound(s, from + i as u64) {
            true => newest = Some(i),
            false => s.fill(0),
        }
    }
    // A slot found empty before one found written may have been written after the read
    // passed it and before it reached the later one (a writer records in tick order): read
    // again, it holds its tick now, unless the tick was never recorded (a miss).
    for i in 0..newest.unwrap_or(0) {
        let s = &mut bytes[i * slot..(i + 1) * slot];
        if s[..8] == [0; 8] {
            let k = from + i as u64;
            ring.read_exact_at(s, (HEADER + (k % capacity) as usize * slot) as u64).ok()?;
            if !sound(s, k) {
                s.fill(0);
            }
        }
    }
    Some(bytes)
}

/// The slot length of samples of `size` bytes (as [`super::slot_len`] has it).
pub(super) fn slot_of(size: u64) -> usize {
    8 + (size as usize).next_multiple_of(8)
}

#[cfg(test)]
mod tests {
    use super::super::{FlightLog, FlightRecorder, Mover, segment_path, segments};
    use super::*;
    use crate::wire::TorqueSample;
    use std::os::unix::fs::PermissionsExt;

    fn torque(k: u64) -> TorqueSample {
        TorqueSample { tick: k, rotor_torque_nm: [k as f64, 1.0, 2.0], ..Default::default() }
    }

    fn base(name: &str) -> PathBuf {
        let b =
            std::env::temp_dir().join(format!("rotorloop-journal-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&b);
        b
    }

    /// What a machine crash leaves of a run recorded into rings of 512 slots (2000 ticks,
    /// a journal frame every 100): the segments and the journal, no ring. Every tick up to
    /// the last frame's is read back, the journal of each half whose segment is durable is
    /// gone, the files are the user's alone, and the reader says the ring is missing.
    #[test]
    fn after_a_crash_the_segments_and_the_journal_hold_every_tick_to_the_last_frame() {
        let b = base("crash");
        let (staged, kept) = (b.join("staged"), b.join("kept"));
        let r = FlightRecorder::<TorqueSample>::open(Some(&staged), Stream::PlantTorque, 512, "t");
        let mut mover = Mover::new(&staged, &kept).with_half(256);
        for k in 0..2000 {
            r.record(&torque(k));
            assert!(mover.pass(k).is_empty());
            if k % 100 == 99 {
                assert!(mover.journal(k).is_empty());
            }
        }
        // Halves 0–6 are in segments (half j once tick (j + 1.5)·256 is out); half 7
        // (1792–2047) is journaled only.
        assert_eq!(segments(&kept, Stream::PlantTorque).len(), 7);
        let left: Vec<u64> = journals(&kept, Stream::PlantTorque).iter().map(|(j, _)| *j).collect();
        assert_eq!(left, vec![7], "the journals of the halves in segments are gone");
        for (_, p) in journals(&kept, Stream::PlantTorque) {
            let mode = std::fs::metadata(&p).expect("journal").permissions().mode();
            assert_eq!(mode & 0o777, 0o600, "{}", p.display());
        }
        let seg = std::fs::metadata(segment_path(&kept, Stream::PlantTorque, 0)).expect("seg");
        assert_eq!(seg.permissions().mode() & 0o777, 0o600);
        // The crash: the ring (tmpfs) is gone.
        drop(r);
        std::fs::remove_dir_all(&staged).expect("tmpfs gone");
        let log = FlightLog::<TorqueSample>::read(&kept, Stream::PlantTorque, 2063).expect("read");
        assert!(log.no_ring && !log.damaged);
        assert!(log.problems[0].contains("no flight record"), "{:?}", log.problems);
        assert_eq!(log.last(), Some(1999));
        assert_eq!(log.count(1999).missing, Vec::<[u64; 2]>::new());
        assert!(log.iter().eq((0..2000).map(torque)), "every tick as recorded");
        let _ = std::fs::remove_dir_all(&b);
    }

    /// A mover held up until the ring came round over the first ticks of a half (a real-time
    /// run's mover behind a `fdatasync` of 2 s): its segment lacks them, so the half's
    /// journal, which holds them, is kept beside it, read after a crash, and left by the
    /// move at the end. Without it a crash lost 212 ticks the disk had held.
    #[test]
    fn a_half_the_ring_came_round_over_keeps_its_journal() {
        let b = base("overran");
        let (staged, kept) = (b.join("staged"), b.join("kept"));
        let r = FlightRecorder::<TorqueSample>::open(Some(&staged), Stream::PlantTorque, 512, "t");
        let mut mover = Mover::new(&staged, &kept).with_half(256);
        for k in 0..300 {
            r.record(&torque(k));
        }
        assert!(mover.journal(299).is_empty());
        // Held up: ticks 512–611 take the slots of ticks 0–99 before half 0 is read.
        for k in 300..612 {
            r.record(&torque(k));
        }
        assert!(mover.pass(611).is_empty());
        assert!(mover.journal(611).is_empty());
        let kept_journal = kept_journal_path(&kept, Stream::PlantTorque, 0);
        assert!(kept_journal.exists(), "{:?}", journals(&kept, Stream::PlantTorque));
        assert!(!journal_path(&kept, Stream::PlantTorque, 0).exists());
        assert_eq!(segments(&kept, Stream::PlantTorque).len(), 1);
        // A crash now: every tick to the last frame's.
        let crashed = b.join("crashed");
        std::fs::create_dir_all(&crashed).expect("dir");
        for e in std::fs::read_dir(&kept).expect("kept").flatten() {
            std::fs::copy(e.path(), crashed.join(e.file_name())).expect("copy");
        }
        let log =
            FlightLog::<TorqueSample>::read(&crashed, Stream::PlantTorque, 700).expect("read");
        assert_eq!(log.last(), Some(611));
        assert!(log.iter().eq((0..612).map(torque)), "every tick, the first 100 from the journal");
        // The end of the run: the ring moved in, the kept journal left.
        for k in 612..700 {
            r.record(&torque(k));
        }
        drop(r);
        super::super::move_records(&staged, &kept, true).expect("moved");
        assert_eq!(journals(&kept, Stream::PlantTorque), vec![(0, kept_journal)]);
        let log = FlightLog::<TorqueSample>::read(&kept, Stream::PlantTorque, 700).expect("read");
        assert!(log.iter().eq((0..700).map(torque)));
        let _ = std::fs::remove_dir_all(&b);
    }

    /// A ring that never comes round (the whole run) is only journaled: without it, the
    /// journal holds every tick up to its last frame; with it, the ring is read first.
    /// Moving the rings in at the end makes them durable and removes the journal.
    #[test]
    fn a_whole_run_ring_is_journaled_and_the_journal_goes_once_the_ring_is_moved() {
        let b = base("whole");
        let (staged, kept) = (b.join("staged"), b.join("kept"));
        let r = FlightRecorder::<TorqueSample>::open(Some(&staged), Stream::Reference, 1065, "t");
        let mut mover = Mover::new(&staged, &kept).whole_run();
        for k in 0..1000 {
            r.record(&torque(k));
            assert!(mover.pass(k).is_empty());
            if k % 150 == 0 {
                assert!(mover.journal(k).is_empty());
            }
        }
        assert!(segments(&kept, Stream::Reference).is_empty(), "nothing moved");
        assert_eq!(journals(&kept, Stream::Reference).len(), 1);
        let both = FlightLog::<TorqueSample>::read(&staged, Stream::Reference, 1063).expect("ring");
        assert_eq!(both.last(), Some(999));
        let copy = b.join("crashed");
        std::fs::create_dir_all(&copy).expect("copy");
        let (_, j) = &journals(&kept, Stream::Reference)[0];
        std::fs::copy(j, copy.join(j.file_name().expect("name"))).expect("copy");
        let log = FlightLog::<TorqueSample>::read(&copy, Stream::Reference, 1063).expect("read");
        // The last frame was at tick 900: it holds what was recorded, to tick 900.
        assert_eq!(log.last(), Some(900));
        assert!(log.iter().eq((0..=900).map(torque)));
        drop(r);
        super::super::move_records(&staged, &kept, true).expect("moved");
        assert!(journals(&kept, Stream::Reference).is_empty(), "the journal went");
        let log = FlightLog::<TorqueSample>::read(&kept, Stream::Reference, 1063).expect("read");
        assert_eq!(log.last(), Some(999));
        let _ = std::fs::remove_dir_all(&b);
    }

    /// A frame cut short (a crash in the middle of an append) and a journal whose middle is
    /// damaged: the frames before it are read, the rest of the journal is not misread, and
    /// the problem is named; a ring that is torn is skipped the same way.
    #[test]
    fn a_half_written_frame_and_a_torn_ring_are_skipped_and_named() {
        let b = base("torn");
        let (staged, kept) = (b.join("staged"), b.join("kept"));
        let r = FlightRecorder::<TorqueSample>::open(Some(&staged), Stream::PlantTorque, 1065, "t");
        let mut mover = Mover::new(&staged, &kept).whole_run();
        for k in 0..1000 {
            r.record(&torque(k));
            if k % 250 == 249 {
                assert!(mover.journal(k).is_empty());
            }
        }
        let (_, path) = journals(&kept, Stream::PlantTorque).remove(0);
        let len = std::fs::metadata(&path).expect("journal").len();
        let (frames, stop) = read_frames(&path, size_of::<TorqueSample>() as u64);
        assert_eq!((frames.len(), stop), (4, None));
        let last_frame = frames[3].chunks[0].0 - HEADER as u64 - 16;
        // The last frame cut in its middle.
        std::fs::OpenOptions::new()
            .write(true)
            .open(&path)
            .expect("open")
            .set_len((last_frame + len) / 2)
            .expect("cut");
        // A torn ring beside it (what was left of a file cut short).
        std::fs::create_dir_all(b.join("crashed")).expect("dir");
        let crashed = b.join("crashed");
        std::fs::copy(&path, crashed.join(path.file_name().expect("name"))).expect("copy");
        std::fs::write(Stream::PlantTorque.path(&crashed), [0u8; 100]).expect("torn ring");
        let log =
            FlightLog::<TorqueSample>::read(&crashed, Stream::PlantTorque, 1063).expect("read");
        assert!(log.damaged && !log.no_ring);
        assert_eq!(log.problems.len(), 2, "{:?}", log.problems);
        assert!(
            log.problems.iter().any(|p| p.contains("not a flight record")),
            "{:?}",
            log.problems
        );
        assert!(
            log.problems.iter().any(|p| p.contains("cut short by a crash")),
            "{:?}",
            log.problems
        );
        // Frames 0–2 were at ticks 249, 499, 749 (and the next 64 ticks the reference may
        // hold): ticks 0–749 are there.
        assert_eq!(log.last(), Some(749));
        assert!(log.iter().eq((0..=749).map(torque)));
        // Nothing sound at all: an error naming the ring.
        std::fs::remove_file(crashed.join(path.file_name().expect("name"))).expect("rm");
        let e =
            FlightLog::<TorqueSample>::read(&crashed, Stream::PlantTorque, 1063).expect_err("none");
        assert!(e.to_string().contains("plant-torque.flight"), "{e}");
        drop(r);
        let _ = std::fs::remove_dir_all(&b);
    }
}
