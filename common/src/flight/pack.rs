//! Packed segments: how the mover writes a half of a ring to disk in about a quarter of
//! its bytes, losslessly, and how a reader gets a chunk of its slots back.
//!
//! A record's slots are words (a tag and the sample's `u64` and `f64` fields), and a word
//! changes little from one tick to the next: a tick counts up, a stamp moves by about a
//! period, a float of a smooth trajectory follows its last few values. So each **column**
//! (the same word of every slot) of a chunk of [`CHUNK_SLOTS`] slots is replaced by its
//! residual against a prediction, with the predictor that leaves the smallest residuals
//! for that column of that chunk ([`Transform`]: none, the last value, the last two, the
//! word to its left, or an extrapolation in `f64` of the last two to four). Then the bytes
//! are shuffled (every column's byte 0, then its byte 1, …: the zero high bytes of small
//! residuals come together) and the chunk is compressed with zstd.
//!
//! **The file.** The segment's 64-byte header as a raw segment has it, but with
//! [`super::PACKED_MAGIC`], then a table of `(offset, length)` pairs, one per chunk, then
//! the chunks: each its columns' transforms (a byte each) and one zstd frame. A chunk
//! unpacks to exactly its slots or not at all: a table, a frame or a transform that does
//! not fit is an error, and the reader reads that chunk's ticks as missing.
//!
//! **Lossless by construction.** Decoding repeats the predictions on the values already
//! decoded with the same `f64` operations in the same order (no fused multiply-add), and
//! adds the residual to the prediction's bits with wrapping integer arithmetic: the bits
//! come back whatever they are, NaN and infinities included (a prediction that is not
//! finite is taken as 0). The unit tests round-trip words of every kind.

/// Slots per chunk (the unit a reader decodes: 2.2 MB of plant states).
pub const CHUNK_SLOTS: u64 = 4096;
/// The zstd level: level 1 leaves about 1.5 % more bytes at twice the speed; higher
/// levels gain under 1 %.
const LEVEL: i32 = 3;
/// The zstd level of a journal frame packed with its stream's last transforms.
const FRAME_LEVEL: i32 = -1;

/// A column's predictor (module docs). The residual is `zigzag(word − prediction)` for
/// the integer ones and `zigzag(bits(x) − bits(prediction))` for the float ones.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
enum Transform {
    Raw = 0,
    /// The previous slot's word.
    Delta = 1,
    /// The previous slot's word plus its change from the one before.
    Delta2 = 2,
    /// The word to the left in the same slot (a stamp after a stamp).
    Left = 3,
    /// `2x₁ − x₂` in `f64`.
    Float2 = 4,
    /// `3x₁ − 3x₂ + x₃` in `f64`.
    Float3 = 5,
    /// `4x₁ − 6x₂ + 4x₃ − x₄` in `f64`.
    Float4 = 6,
}

const TRANSFORMS: [Transform; 7] = [
    Transform::Raw,
    Transform::Delta,
    Transform::Delta2,
    Transform::Left,
    Transform::Float2,
    Transform::Float3,
    Transform::Float4,
];

impl Transform {
    fn from_u8(b: u8) -> Option<Self> {
        TRANSFORMS.get(usize::from(b)).copied()
    }

    /// The prediction of row `r`'s word from the column's earlier words `col[..r]` and
    /// the row's word to the left (`left`): what [`Transform::encode`] computes, a row at a
    /// time (the tests' reference).
    #[cfg(test)]
    fn predict(self, col: &[u64], r: usize, left: u64) -> u64 {
        let at = |back: usize| if r >= back { col[r - back] } else { 0 };
        let f = |back: usize| f64::from_bits(at(back));
        let float = |p: f64| if p.is_finite() { p.to_bits() } else { 0 };
        match self {
            Self::Raw => 0,
            Self::Delta => at(1),
            Self::Delta2 => at(1).wrapping_add(at(1).wrapping_sub(at(2))),
            Self::Left => left,
            Self::Float2 => float(2.0 * f(1) - f(2)),
            Self::Float3 => float(3.0 * f(1) - 3.0 * f(2) + f(3)),
            Self::Float4 => float(4.0 * f(1) - 6.0 * f(2) + 4.0 * f(3) - f(4)),
        }
    }
}

#[inline]
fn zigzag(d: u64) -> u64 {
    (d << 1) ^ ((d as i64 >> 63) as u64)
}

#[inline]
fn unzigzag(z: u64) -> u64 {
    (z >> 1) ^ (z & 1).wrapping_neg()
}

/// Bytes a residual needs beyond its leading zero bytes: the cost the choice of
/// transform minimises (a cheap stand-in for its compressed size).
#[inline]
fn significant_bytes(z: u64) -> u64 {
    u64::from(8 - z.leading_zeros() / 8)
}

/// Packs the slots `slots` (whole slots of `words` words each) into one chunk.
///
/// The words are first laid out column by column; each transform's residuals of a column
/// are then one tight loop ([`encode`]), given up as soon as they cost more than the best
/// so far. The bytes are those of the straightforward search (every transform of
/// [`Transform::predict`] row by row, the first of the cheapest kept): a unit test holds
/// the two together. 2.6 times faster than that search here (`pack::tests::speed`).
fn pack_chunk(slots: &[u8], words: usize) -> std::io::Result<Vec<u8>> {
    pack_chunk_as(slots, words, None)
}

/// [`pack_chunk`], with `given` (a transform per column, as a chunk's first bytes hold
/// them) taken as they are instead of searched for: what a journal frame does with the
/// transforms its stream's last search chose ([`pack_reusing`]).
fn pack_chunk_as(slots: &[u8], words: usize, given: Option<&[u8]>) -> std::io::Result<Vec<u8>> {
    let given: Option<Vec<Transform>> = given
        .filter(|g| g.len() == words)
        .and_then(|g| g.iter().map(|b| Transform::from_u8(*b)).collect());
    let rows = slots.len() / (8 * words);
    let mut cols = vec![0u64; rows * words];
    for (r, slot) in slots.chunks_exact(8 * words).enumerate() {
        for (c, w) in slot.chunks_exact(8).enumerate() {
            cols[c * rows + r] = u64::from_ne_bytes(w.try_into().unwrap_or_default());
        }
    }
    let zeros = vec![0u64; rows];
    let mut codes = Vec::with_capacity(words);
    let mut residuals = vec![0u64; rows * words];
    let mut trial = vec![0u64; rows];
    for c in 0..words {
        let col = &cols[c * rows..(c + 1) * rows];
        let left = if c > 0 { &cols[(c - 1) * rows..c * rows] } else { &zeros[..] };
        let best = &mut residuals[c * rows..(c + 1) * rows];
        let mut best_cost = u64::MAX;
        let mut chosen = Transform::Raw;
        if let Some(g) = &given {
            g[c].encode(col, left, best, u64::MAX);
            codes.push(g[c] as u8);
            continue;
        }
        for t in TRANSFORMS {
            let cost = t.encode(col, left, &mut trial, best_cost);
            if cost < best_cost {
                (best_cost, chosen) = (cost, t);
                best.copy_from_slice(&trial);
            }
        }
        codes.push(chosen as u8);
    }
    // Byte planes: each column's byte 0 of every row, then its byte 1, …
    let mut shuffled = vec![0u8; rows * words * 8];
    for (c, col) in residuals.chunks_exact(rows.max(1)).enumerate().take(words) {
        for b in 0..8 {
            let plane = &mut shuffled[(c * 8 + b) * rows..(c * 8 + b + 1) * rows];
            for (out, z) in plane.iter_mut().zip(col) {
                *out = (z >> (8 * b)) as u8;
            }
        }
    }
    // With its checksum: damage inside a frame is an error, not other samples. The
    // compressor is the thread's, kept: a fresh one's workspace, five times a second for the
    // journal, was most of the journal's page faults.
    let level = if given.is_some() { FRAME_LEVEL } else { LEVEL };
    COMPRESSOR.with(|z| {
        let mut z = z.borrow_mut();
        let (at, z) = match &mut *z {
            Some(z) => (&mut z.0, &mut z.1),
            none => {
                let mut fresh = zstd::bulk::Compressor::new(level)?;
                fresh.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true))?;
                let z = none.insert((level, fresh));
                (&mut z.0, &mut z.1)
            }
        };
        if *at != level {
            z.set_parameter(zstd::zstd_safe::CParameter::CompressionLevel(level))?;
            *at = level;
        }
        codes.extend_from_slice(&z.compress(&shuffled)?);
        Ok(codes)
    })
}

thread_local! {
    /// The thread's compressor ([`pack_chunk_as`]).
    static COMPRESSOR: std::cell::RefCell<Option<(i32, zstd::bulk::Compressor<'static>)>> =
        const { std::cell::RefCell::new(None) };
}

impl Transform {
    /// Writes the zigzagged residuals of `col` under this transform (`left`: the column to
    /// its left) into `out` and returns their cost ([`significant_bytes`]), or `u64::MAX`
    /// as soon as the cost reaches `limit` (`out` then half written). The predictions are
    /// [`Transform::predict`]'s, in a loop of its own per transform.
    fn encode(self, col: &[u64], left: &[u64], out: &mut [u64], limit: u64) -> u64 {
        let float = |p: f64| if p.is_finite() { p.to_bits() } else { 0 };
        let f = f64::from_bits;
        match self {
            Self::Raw => encode_with(col, out, limit, |_| 0),
            Self::Delta => encode_with(col, out, limit, |x| x[0]),
            Self::Delta2 => {
                encode_with(col, out, limit, |x| x[0].wrapping_add(x[0].wrapping_sub(x[1])))
            }
            Self::Left => {
                let mut cost = 0;
                let blocks = out.chunks_mut(512).zip(col.chunks(512)).zip(left.chunks(512));
                for ((o, w), l) in blocks {
                    for ((o, w), l) in o.iter_mut().zip(w).zip(l) {
                        let z = zigzag(w.wrapping_sub(*l));
                        *o = z;
                        cost += significant_bytes(z);
                    }
                    if cost >= limit {
                        return u64::MAX;
                    }
                }
                cost
            }
            Self::Float2 => encode_with(col, out, limit, |x| float(2.0 * f(x[0]) - f(x[1]))),
            Self::Float3 => {
                encode_with(col, out, limit, |x| float(3.0 * f(x[0]) - 3.0 * f(x[1]) + f(x[2])))
            }
            Self::Float4 => encode_with(col, out, limit, |x| {
                float(4.0 * f(x[0]) - 6.0 * f(x[1]) + 4.0 * f(x[2]) - f(x[3]))
            }),
        }
    }
}

/// [`Transform::encode`] of a transform that predicts from the column's words before the
/// row, newest first (0 before the first row).
#[inline(always)]
fn encode_with(col: &[u64], out: &mut [u64], limit: u64, predict: impl Fn([u64; 4]) -> u64) -> u64 {
    let (mut x, mut cost) = ([0u64; 4], 0);
    let head = col.len().min(4);
    for (o, w) in out[..head].iter_mut().zip(&col[..head]) {
        let z = zigzag(w.wrapping_sub(predict(x)));
        *o = z;
        cost += significant_bytes(z);
        x = [*w, x[0], x[1], x[2]];
    }
    // Then each row's four words before it, in a window: no value carried from one row to
    // the next but the cost.
    let mut r = head;
    while r < col.len() {
        let end = (r + 512).min(col.len());
        for (o, w) in out[r..end].iter_mut().zip(col[r - 4..end].windows(5)) {
            let z = zigzag(w[4].wrapping_sub(predict([w[3], w[2], w[1], w[0]])));
            *o = z;
            cost += significant_bytes(z);
        }
        if cost >= limit {
            return u64::MAX;
        }
        r = end;
    }
    cost
}

/// Turns a column's residuals (`col`, unzigzagged) into its words, in place, as
/// [`Transform::predict`] predicts them from the words before and the column to the left
/// (`left`, none for the first: zeros): the same operations in the same order, a loop per
/// transform.
fn decode_column(t: Transform, col: &mut [u64], left: Option<&[u64]>) {
    let float = |p: f64| if p.is_finite() { p.to_bits() } else { 0 };
    let f = f64::from_bits;
    // The words before, newest first (0 before the first row, as `predict` has it).
    let run = |col: &mut [u64], predict: &dyn Fn([u64; 4]) -> u64| {
        let mut x = [0u64; 4];
        for w in col.iter_mut() {
            *w = w.wrapping_add(predict(x));
            x = [*w, x[0], x[1], x[2]];
        }
    };
    match t {
        Transform::Raw => {}
        Transform::Delta => {
            let mut x1 = 0u64;
            for w in col.iter_mut() {
                *w = w.wrapping_add(x1);
                x1 = *w;
            }
        }
        Transform::Delta2 => run(col, &|x| x[0].wrapping_add(x[0].wrapping_sub(x[1]))),
        Transform::Left => {
            let left = left.unwrap_or_default().iter();
            col.iter_mut().zip(left).for_each(|(w, l)| *w = w.wrapping_add(*l));
        }
        Transform::Float2 => run(col, &|x| float(2.0 * f(x[0]) - f(x[1]))),
        Transform::Float3 => run(col, &|x| float(3.0 * f(x[0]) - 3.0 * f(x[1]) + f(x[2]))),
        Transform::Float4 => {
            run(col, &|x| float(4.0 * f(x[0]) - 6.0 * f(x[1]) + 4.0 * f(x[2]) - f(x[3])))
        }
    }
}

/// What unpacking a chunk needs besides its bytes, kept from one chunk to the next (a
/// reader unpacks thousands: fresh buffers of megabytes each time cost page faults).
struct Scratch {
    zstd: zstd::bulk::Decompressor<'static>,
    shuffled: Vec<u8>,
    /// The chunk's words, column-major.
    cols: Vec<u64>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Option<Scratch>> = const { std::cell::RefCell::new(None) };
}

/// Unpacks a chunk of `rows` slots of `words` words each into `out` (its slots' bytes), or
/// says why not; only the first `columns` words of each slot where that is fewer (the
/// decoding of a column needs only those before it).
fn unpack_chunk(
    chunk: &[u8],
    rows: usize,
    (words, columns): (usize, usize),
    out: &mut Vec<u8>,
) -> Result<(), String> {
    let (codes, frame) = chunk.split_at_checked(words).ok_or("a chunk shorter than its codes")?;
    let codes: Vec<Transform> = codes
        .iter()
        .map(|b| Transform::from_u8(*b).ok_or(format!("unknown transform {b}")))
        .collect::<Result<_, _>>()?;
    let want = rows * words * 8;
    SCRATCH.with_borrow_mut(|scratch| {
        let s = match scratch {
            Some(s) => s,
            None => scratch.insert(Scratch {
                zstd: zstd::bulk::Decompressor::new().map_err(|e| format!("zstd: {e}"))?,
                shuffled: Vec::new(),
                cols: Vec::new(),
            }),
        };
        s.shuffled.clear();
        s.shuffled.reserve(want);
        let n = s
            .zstd
            .decompress_to_buffer(frame, &mut s.shuffled)
            .map_err(|e| format!("a damaged frame: {e}"))?;
        if n != want {
            return Err(format!("{n} bytes where the chunk holds {want}"));
        }
        // Column by column into `cols` (column-major), then into slots a tile of rows at
        // a time (a column at a time would touch a cache line per word of the output).
        let columns = columns.min(words);
        s.cols.clear();
        s.cols.resize(rows * columns, 0);
        for (c, t) in codes.iter().enumerate().take(columns) {
            let planes = &s.shuffled[c * 8 * rows..(c + 1) * 8 * rows];
            let (before, this) = s.cols.split_at_mut(c * rows);
            let col = &mut this[..rows];
            for (i, plane) in planes.chunks_exact(rows).enumerate() {
                for (w, b) in col.iter_mut().zip(plane) {
                    *w |= u64::from(*b) << (8 * i);
                }
            }
            col.iter_mut().for_each(|w| *w = unzigzag(*w));
            decode_column(*t, col, before.get(before.len().saturating_sub(rows)..));
        }
        out.clear();
        out.resize(rows * columns * 8, 0);
        const TILE: usize = 64;
        for r0 in (0..rows).step_by(TILE) {
            let r1 = (r0 + TILE).min(rows);
            for (c, col) in s.cols.chunks_exact(rows).enumerate() {
                for (r, w) in col[r0..r1].iter().enumerate() {
                    let at = ((r0 + r) * columns + c) * 8;
                    out[at..at + 8].copy_from_slice(&w.to_ne_bytes());
                }
            }
        }
        Ok(())
    })
}

/// Packs a raw segment's slots (`body`, whole slots of `slot_len` bytes) behind `header`
/// (the raw segment's header with the packed magic in it): the packed file's bytes.
pub(super) fn pack(header: &[u8], body: &[u8], slot_len: usize) -> std::io::Result<Vec<u8>> {
    pack_between(header, body, slot_len, &mut || {})
}

/// [`pack`], calling `between` after each chunk (where the mover journals the newest
/// ticks: a half of the plant's states is 8 chunks, 0.15 s).
pub(super) fn pack_between(
    header: &[u8],
    body: &[u8],
    slot_len: usize,
    between: &mut dyn FnMut(),
) -> std::io::Result<Vec<u8>> {
    pack_chunks(header, (body, slot_len), None, between)
}

/// `body`'s chunks packed ([`pack_chunk_as`], with the transforms `given` where there are),
/// `between` called after each, behind `header`.
fn pack_chunks(
    header: &[u8],
    (body, slot_len): (&[u8], usize),
    given: Option<&[u8]>,
    between: &mut dyn FnMut(),
) -> std::io::Result<Vec<u8>> {
    let chunk_len = CHUNK_SLOTS as usize * slot_len;
    let mut chunks = Vec::with_capacity(body.len().div_ceil(chunk_len.max(1)));
    for c in body.chunks(chunk_len) {
        chunks.push(pack_chunk_as(c, slot_len / 8, given)?);
        between();
    }
    Ok(assemble(header, &chunks))
}

/// [`pack`] for a journal frame, which is packed every period: with `codes` (the
/// transforms of the stream's frame before, one per column) they are taken as they are
/// for each chunk, without the search that is most of a frame's cost; `codes` empty, they
/// are searched for and the first chunk's kept in it. (Lockstep's frames are of more than
/// a chunk: searched each time, they took most of the journal's time.)
pub(super) fn pack_reusing(
    header: &[u8],
    body: &[u8],
    slot_len: usize,
    codes: &mut Vec<u8>,
) -> std::io::Result<Vec<u8>> {
    let (words, chunk_len) = (slot_len / 8, CHUNK_SLOTS as usize * slot_len);
    if codes.len() != words {
        let packed = pack(header, body, slot_len)?;
        // The first chunk's transforms: after the header and the table.
        let first = header.len() + 16 * body.len().div_ceil(chunk_len).max(1);
        codes.clear();
        codes.extend_from_slice(packed.get(first..first + words).unwrap_or_default());
        return Ok(packed);
    }
    pack_chunks(header, (body, slot_len), Some(codes), &mut || {})
}

/// Packs the raw record file `from` (a ring: its header and its slots, as
/// [`super::FlightRecorder`] leaves it) into `to`, written whole or not at all (a `.part`
/// renamed), reading a chunk of slots at a time. Its header words stay as they are, but
/// for the magic. A file that is not a whole raw record is an error (and left as it is).
pub(super) fn pack_file(from: &std::path::Path, to: &std::path::Path) -> std::io::Result<()> {
    use std::os::unix::fs::FileExt;
    let f = std::fs::File::open(from)?;
    let (mut header, w) = super::read_header(&f)?;
    let slot_len = 8 + usize::try_from(w[super::word::SIZE]).unwrap_or(0).next_multiple_of(8);
    let capacity = w[super::word::CAPACITY];
    let whole = super::HEADER as u128 + u128::from(capacity) * slot_len as u128;
    if w[super::word::MAGIC] != super::MAGIC || u128::from(f.metadata()?.len()) != whole {
        return Err(std::io::Error::other("not a whole raw flight record"));
    }
    let mut chunks = Vec::new();
    let mut slots = Vec::new();
    for i in 0..capacity.div_ceil(CHUNK_SLOTS) {
        let rows = CHUNK_SLOTS.min(capacity - i * CHUNK_SLOTS) as usize;
        slots.resize(rows * slot_len, 0);
        f.read_exact_at(
            &mut slots,
            (super::HEADER + i as usize * CHUNK_SLOTS as usize * slot_len) as u64,
        )?;
        chunks.push(pack_chunk(&slots, slot_len / 8)?);
    }
    header[..8].copy_from_slice(&super::PACKED_MAGIC.to_ne_bytes());
    let part = to.with_extension("part");
    // 0600 whatever the umask, never through a link: the records are the run's user's alone.
    let written = {
        use std::io::Write;
        use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
        std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .mode(0o600)
            .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
            .open(&part)
            .and_then(|mut f| {
                f.set_permissions(std::fs::Permissions::from_mode(0o600))?;
                f.write_all(&assemble(&header, &chunks))
            })
    };
    if written.is_err() {
        let _ = std::fs::remove_file(&part); // a full disk: the ring is moved raw instead
    }
    written?;
    std::fs::rename(&part, to)
}

/// A packed file: `header`, the table of the chunks, the chunks.
fn assemble(header: &[u8], chunks: &[Vec<u8>]) -> Vec<u8> {
    let mut out = Vec::with_capacity(header.len() + 16 * chunks.len());
    out.extend_from_slice(header);
    let mut at = (header.len() + 16 * chunks.len()) as u64;
    for c in chunks {
        out.extend_from_slice(&at.to_le_bytes());
        out.extend_from_slice(&(c.len() as u64).to_le_bytes());
        at += c.len() as u64;
    }
    for c in chunks {
        out.extend_from_slice(c);
    }
    out
}

/// Where each chunk of a packed segment of `capacity` slots of `slot_len` bytes lies in its
/// file of `len` bytes, from its table (`table`: the bytes after the header), or why the
/// table does not fit the file (a chunk outside it, or longer than any chunk packs to: a
/// reader never allocates what a damaged table claims).
pub(super) fn chunk_table(
    table: &[u8],
    (capacity, slot_len): (u64, usize),
    len: u64,
) -> Result<Vec<(u64, u64)>, String> {
    let n = capacity.div_ceil(CHUNK_SLOTS) as usize;
    let most = slot_len / 8 + zstd::zstd_safe::compress_bound(CHUNK_SLOTS as usize * slot_len);
    let bytes = table.get(..16 * n).ok_or("a chunk table cut short")?;
    let start = super::HEADER as u64 + 16 * n as u64;
    let mut out = Vec::with_capacity(n);
    for e in bytes.chunks_exact(16) {
        let at = u64::from_le_bytes(e[..8].try_into().unwrap_or_default());
        let l = u64::from_le_bytes(e[8..].try_into().unwrap_or_default());
        if at < start || l > most as u64 || at.checked_add(l).is_none_or(|end| end > len) {
            return Err(format!(
                "a chunk at {at} of {l} bytes: outside the file's {len}, or longer than {most}"
            ));
        }
        out.push((at, l));
    }
    Ok(out)
}

/// The slots of chunk `i` (of a segment of `capacity` slots of `slot_len` bytes) from its
/// packed bytes, into `out` (its allocation reused); with `ticks`, only the first two words
/// of each slot (its tag and its sample's tick): a few columns decoded of a slot's dozens.
pub(super) fn unpack(
    chunk: &[u8],
    (i, capacity, slot_len): (u64, u64, usize),
    ticks: bool,
    out: &mut Vec<u8>,
) -> Result<(), String> {
    let rows = CHUNK_SLOTS.min(capacity.saturating_sub(i * CHUNK_SLOTS)) as usize;
    let words = slot_len / 8;
    unpack_chunk(chunk, rows, (words, if ticks { 2 } else { words }), out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Slots of `words` words: a tag counting up, a stamp with jitter, a stamp after it, a
    /// smooth float, a float of noise, special floats, zeros, a counter that jumps.
    fn slots(rows: usize, words: usize, seed: u64) -> Vec<u8> {
        let mut x = seed | 1;
        let mut rnd = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let mut out = Vec::new();
        for r in 0..rows {
            let t = r as f64 * 1e-3;
            let stamp = 1_000_000 * r as u64 + rnd() % 50_000;
            let row: [u64; 8] = [
                r as u64 + 1,
                stamp,
                stamp + rnd() % 9_000,
                (t.sin() * 0.3).to_bits(),
                f64::from_bits((rnd() >> 12) | 0x3ff0_0000_0000_0000).to_bits(),
                [f64::NAN, f64::INFINITY, -0.0, f64::MIN_POSITIVE][r % 4].to_bits(),
                0,
                if r % 1000 == 0 { rnd() } else { r as u64 / 100 },
            ];
            (0..words).for_each(|c| out.extend_from_slice(&row[c % 8].to_ne_bytes()));
        }
        out
    }

    fn unpacked(chunk: &[u8], rows: usize, words: usize) -> Vec<u8> {
        let mut out = vec![7u8; 3]; // whatever a reused buffer held
        unpack_chunk(chunk, rows, (words, words), &mut out).expect("unpacks");
        out
    }

    #[test]
    fn every_kind_of_word_comes_back_bit_for_bit() {
        for (rows, words, seed) in [(4096, 8, 1), (4096, 66, 2), (100, 25, 3), (1, 8, 4)] {
            let raw = slots(rows, words, seed);
            let packed = pack_chunk(&raw, words).expect("packs");
            assert_eq!(unpacked(&packed, rows, words), raw, "{rows}x{words}");
        }
        // Random words of any pattern, NaN payloads included.
        let raw: Vec<u8> =
            (0..4096 * 8 * 8).map(|i| ((i as u64 * 0x9e37_79b9) >> 13) as u8).collect();
        assert_eq!(unpacked(&pack_chunk(&raw, 8).expect("packs"), 4096, 8), raw);
    }

    /// The decoder's loop per transform undoes exactly what the packer's predictions did,
    /// for every transform (the packer picks one per column; this forces each), on words
    /// of every kind: a smooth float, noise, NaN, infinities, a counter.
    #[test]
    fn each_transform_decodes_what_its_prediction_encoded() {
        let raw = slots(300, 8, 9);
        let word = |r: usize, c: usize| {
            u64::from_ne_bytes(raw[(r * 8 + c) * 8..(r * 8 + c) * 8 + 8].try_into().expect("8"))
        };
        for c in 1..8 {
            let col: Vec<u64> = (0..300).map(|r| word(r, c)).collect();
            let left: Vec<u64> = (0..300).map(|r| word(r, c - 1)).collect();
            for t in TRANSFORMS {
                let mut res: Vec<u64> =
                    (0..300).map(|r| col[r].wrapping_sub(t.predict(&col, r, left[r]))).collect();
                decode_column(t, &mut res, Some(&left));
                assert_eq!(res, col, "column {c}, {t:?}");
            }
        }
    }

    /// The search as first written: every transform's prediction row by row, the first of
    /// the cheapest kept, then the byte planes and zstd.
    fn pack_chunk_by_rows(slots: &[u8], words: usize) -> Vec<u8> {
        let rows = slots.len() / (8 * words);
        let word = |r: usize, c: usize| {
            let at = (r * words + c) * 8;
            u64::from_ne_bytes(slots[at..at + 8].try_into().expect("8"))
        };
        let (mut codes, mut residuals) = (Vec::new(), Vec::new());
        for c in 0..words {
            let col: Vec<u64> = (0..rows).map(|r| word(r, c)).collect();
            let left: Vec<u64> =
                (0..rows).map(|r| if c > 0 { word(r, c - 1) } else { 0 }).collect();
            let mut best: Option<(u64, Transform, Vec<u64>)> = None;
            for t in TRANSFORMS {
                let res: Vec<u64> = (0..rows)
                    .map(|r| zigzag(col[r].wrapping_sub(t.predict(&col, r, left[r]))))
                    .collect();
                let cost = res.iter().map(|z| significant_bytes(*z)).sum();
                if best.as_ref().is_none_or(|b| cost < b.0) {
                    best = Some((cost, t, res));
                }
            }
            let (_, t, res) = best.expect("a transform");
            codes.push(t as u8);
            residuals.extend(res);
        }
        let mut shuffled = Vec::new();
        for c in 0..words {
            for b in 0..8 {
                shuffled.extend((0..rows).map(|r| residuals[c * rows + r].to_le_bytes()[b]));
            }
        }
        let mut z = zstd::bulk::Compressor::new(LEVEL).expect("zstd");
        z.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true)).expect("checksum");
        codes.extend_from_slice(&z.compress(&shuffled).expect("compresses"));
        codes
    }

    /// The packer's column loops choose the same transforms and write the same bytes as the
    /// row-by-row search they replace (slots of every kind of word; random words, where
    /// every trial is given up early but the first).
    #[test]
    fn the_column_loops_pack_what_the_row_by_row_search_packed() {
        for (rows, words, seed) in [(4096, 66, 2), (1500, 25, 3), (100, 8, 4), (1, 8, 5), (2, 3, 6)]
        {
            let raw = slots(rows, words, seed);
            assert_eq!(pack_chunk(&raw, words).expect("packs"), pack_chunk_by_rows(&raw, words));
        }
        let raw: Vec<u8> =
            (0..4096 * 8 * 8).map(|i| ((i as u64 * 0x9e37_79b9) >> 13) as u8).collect();
        assert_eq!(pack_chunk(&raw, 8).expect("packs"), pack_chunk_by_rows(&raw, 8));
    }

    /// What the packer's search costs, against the row-by-row search it replaced, on a
    /// chunk of 4096 slots of 70 words (a plant state's): `cargo test -p rotorloop-common
    /// pack::tests::speed -- --ignored --nocapture`.
    #[test]
    #[ignore = "a measurement"]
    fn speed() {
        let raw = slots(4096, 70, 9);
        let time = |f: &dyn Fn() -> Vec<u8>| {
            let mut runs: Vec<f64> = (0..7)
                .map(|_| {
                    let t = std::time::Instant::now();
                    std::hint::black_box(f());
                    t.elapsed().as_secs_f64()
                })
                .collect();
            runs.sort_by(f64::total_cmp);
            runs[3]
        };
        let new = time(&|| pack_chunk(&raw, 70).expect("packs"));
        let old = time(&|| pack_chunk_by_rows(&raw, 70));
        println!(
            "a chunk of 4096x70 words: column loops {:.2} ms, row by row {:.2} ms (median of 7): \
             {:.1}x",
            new * 1e3,
            old * 1e3,
            old / new
        );
    }

    /// A journal frame packed with the transforms its stream's last search chose unpacks
    /// bit for bit; the search (no transforms yet) packs as a segment does and keeps the
    /// transforms it chose.
    #[test]
    fn a_frame_packed_with_the_last_searchs_transforms_comes_back_bit_for_bit() {
        let (words, header) = (25, [7u8; super::super::HEADER]);
        let mut codes = Vec::new();
        let first = slots(300, words, 1);
        let searched = pack_reusing(&header, &first, words * 8, &mut codes).expect("packs");
        assert_eq!(searched, pack(&header, &first, words * 8).expect("packs"));
        assert_eq!(codes.len(), words);
        let next = slots(200, words, 2);
        let reused = pack_reusing(&header, &next, words * 8, &mut codes).expect("packs");
        let len = reused.len() as u64;
        let table = chunk_table(&reused[header.len()..], (200, words * 8), len).expect("table");
        let (at, l) = (table[0].0 as usize, table[0].1 as usize);
        assert_eq!(reused[at..at + words], codes[..], "the transforms given");
        let mut out = Vec::new();
        unpack(&reused[at..at + l], (0, 200, words * 8), false, &mut out).expect("unpacks");
        assert_eq!(out, next);
        // A frame of more than a chunk (lockstep's): each chunk with the transforms given.
        let n = CHUNK_SLOTS + 904;
        let long = slots(n as usize, words, 3);
        let reused = pack_reusing(&header, &long, words * 8, &mut codes).expect("packs");
        let len = reused.len() as u64;
        let table = chunk_table(&reused[header.len()..], (n, words * 8), len).expect("table");
        assert_eq!(table.len(), 2);
        let mut all = Vec::new();
        for (i, (at, l)) in table.iter().map(|(a, l)| (*a as usize, *l as usize)).enumerate() {
            assert_eq!(reused[at..at + words], codes[..], "chunk {i}: the transforms given");
            let rows = if i == 0 { CHUNK_SLOTS } else { 904 };
            unpack(&reused[at..at + l], (0, rows, words * 8), false, &mut out).expect("unpacks");
            all.extend_from_slice(&out);
        }
        assert_eq!(all, long);
    }

    #[test]
    fn smooth_columns_pack_small() {
        let raw = slots(4096, 8, 5);
        let packed = pack_chunk(&raw, 8).expect("packs");
        // The noise column (about 6.5 bytes a slot) dominates; the rest nearly vanish.
        assert!(packed.len() < raw.len() / 3, "{} of {}", packed.len(), raw.len());
    }

    #[test]
    fn a_segment_round_trips_through_its_table_and_damage_is_an_error() {
        let words = 25;
        let rows = 2 * CHUNK_SLOTS as usize + 100;
        let raw = slots(rows, words, 6);
        let header = [7u8; super::super::HEADER];
        let file = pack(&header, &raw, words * 8).expect("packs");
        let len = file.len() as u64;
        let table =
            chunk_table(&file[header.len()..], (rows as u64, words * 8), len).expect("table");
        assert_eq!(table.len(), 3);
        let mut back = Vec::new();
        for (i, (at, l)) in table.iter().enumerate() {
            let chunk = &file[*at as usize..(*at + *l) as usize];
            let mut out = Vec::new();
            unpack(chunk, (i as u64, rows as u64, words * 8), false, &mut out).expect("chunk");
            back.extend(out);
        }
        assert_eq!(back, raw);
        // A table cut short, a chunk beyond the file, a damaged frame, an unknown code.
        assert!(
            chunk_table(&file[header.len()..header.len() + 20], (rows as u64, words * 8), len)
                .is_err()
        );
        assert!(chunk_table(&file[header.len()..], (rows as u64, words * 8), len - 1).is_err());
        // A chunk claiming more than any chunk packs to, in a file that long (sparse, say).
        let mut lying = file[header.len()..].to_vec();
        lying[8..16].copy_from_slice(&(1u64 << 40).to_le_bytes());
        let err = chunk_table(&lying, (rows as u64, words * 8), 1 << 50).expect_err("refused");
        assert!(err.contains("outside"), "{err}");
        let (at, l) = table[1];
        let mut chunk = file[at as usize..(at + l) as usize].to_vec();
        let mid = chunk.len() / 2;
        chunk[mid] ^= 0xff;
        chunk.truncate(chunk.len() - 3);
        assert!(unpack(&chunk, (1, rows as u64, words * 8), false, &mut Vec::new()).is_err());
        let mut chunk = file[at as usize..(at + l) as usize].to_vec();
        chunk[0] = 200;
        assert!(unpack(&chunk, (1, rows as u64, words * 8), false, &mut Vec::new()).is_err());
    }

    /// What packing costs and saves on a run's raw segments: `ROTORLOOP_PACK_DIR=DIR cargo
    /// test --release -p rotorloop-common pack::tests::cost -- --ignored --nocapture`
    /// packs and unpacks the first raw segment of each stream in `DIR` (a run directory's
    /// `flight/` written before segments were packed) and prints bytes a tick and speed.
    #[test]
    #[ignore = "a measurement on a run's files"]
    fn cost() {
        let Some(dir) = std::env::var_os("ROTORLOOP_PACK_DIR") else {
            eprintln!("set ROTORLOOP_PACK_DIR to a flight/ directory of raw segments");
            return;
        };
        let dir = std::path::PathBuf::from(dir);
        let seg = std::env::var("ROTORLOOP_PACK_SEGMENT").unwrap_or_else(|_| "000050".into());
        for stream in ["plant-state", "plant-torque", "controller-torque", "reference"] {
            let raw = std::fs::read(dir.join(format!("{stream}.{seg}.flight"))).expect("segment");
            let (header, body) = raw.split_at(super::super::HEADER);
            let size = u64::from_ne_bytes(header[16..24].try_into().expect("size")) as usize;
            let slot = 8 + size.next_multiple_of(8);
            let slots = (body.len() / slot) as u64;
            let t0 = std::time::Instant::now();
            let file = pack(header, body, slot).expect("packs");
            let packed_s = t0.elapsed().as_secs_f64();
            let table = chunk_table(&file[header.len()..], (slots, slot), file.len() as u64)
                .expect("table");
            let t1 = std::time::Instant::now();
            let (mut back, mut out) = (Vec::with_capacity(body.len()), Vec::new());
            for (i, (at, l)) in table.iter().enumerate() {
                let chunk = &file[*at as usize..(*at + *l) as usize];
                unpack(chunk, (i as u64, slots, slot), false, &mut out).expect("unpacks");
                back.extend_from_slice(&out);
            }
            let unpacked_s = t1.elapsed().as_secs_f64();
            assert!(back == body, "{stream}: not bit for bit");
            println!(
                "{stream}: {slot} B a slot raw, {:.1} B a tick packed ({:.2}x); pack {:.0} MB/s, \
                 unpack {:.0} MB/s (of raw)",
                file.len() as f64 / slots as f64,
                raw.len() as f64 / file.len() as f64,
                body.len() as f64 / packed_s / 1e6,
                body.len() as f64 / unpacked_s / 1e6,
            );
        }
    }
}
