//! `timing.csv`: one row per state sample `k`, what `sim --replay` and the fault report
//! need beyond the trace: when the state was published, the torque in force at the end of
//! tick `k − 1`, the flags, and the torques that took effect during tick `k − 1` (how
//! many, then tick and offset from `t_k−1` in s of the first [`MAX_EFFECTS`]; empty
//! when fewer). One row type ([`TimingRow`]) with its writer and its checked reader, as
//! `trace.csv` has ([`crate::trace`]); every float in its shortest round-trip form.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

use rotorloop_common::wire::{MAX_EFFECTS, NO_TICK, StateSample};

/// The header of `timing.csv`.
pub fn header() -> String {
    let mut h = "tick,state_publish_ns,applied_torque_tick,flags,effects".to_owned();
    for i in 1..=MAX_EFFECTS {
        h += &format!(",effect{i}_tick,effect{i}_offset_s");
    }
    h
}

/// One row of `timing.csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimingRow {
    /// The state's tick `k`.
    pub tick: u64,
    /// When the plant published it (monotonic ns).
    pub state_publish_ns: u64,
    /// The torque tick in force at the end of tick `k − 1` (`None`: none, the rotors
    /// coasted; `-1` in the file).
    pub applied_torque_tick: Option<u64>,
    /// The state's flags (`rotorloop_common::wire::FLAG_*`).
    pub flags: u64,
    /// How many torques took effect during tick `k − 1` (may exceed [`MAX_EFFECTS`]).
    pub effects: u64,
    /// The first of them (up to [`MAX_EFFECTS`]): their torque tick and offset (s).
    pub recorded: [(u64, f64); MAX_EFFECTS],
}

impl TimingRow {
    /// The row of a state sample.
    pub fn of(s: &StateSample) -> Self {
        let mut recorded = [(NO_TICK, f64::NAN); MAX_EFFECTS];
        for (i, r) in recorded.iter_mut().enumerate().take(s.effects as usize) {
            *r = (s.effect_ticks[i], s.effect_offsets_s[i]);
        }
        Self {
            tick: s.tick,
            state_publish_ns: s.publish_ns,
            applied_torque_tick: (s.applied_torque_tick != NO_TICK)
                .then_some(s.applied_torque_tick),
            flags: s.flags,
            effects: s.effects,
            recorded,
        }
    }

    /// The torques that took effect and are recorded: at most [`MAX_EFFECTS`].
    pub fn recorded(&self) -> &[(u64, f64)] {
        &self.recorded[..(self.effects as usize).min(MAX_EFFECTS)]
    }

    /// Writes the row (with its newline).
    pub fn write(&self, out: &mut impl Write) -> std::io::Result<()> {
        let applied = self.applied_torque_tick.map_or(-1, |t| t as i64);
        write!(
            out,
            "{},{},{applied},{},{}",
            self.tick, self.state_publish_ns, self.flags, self.effects
        )?;
        let n = self.recorded().len();
        for (i, (tick, offset)) in self.recorded.iter().enumerate() {
            match i < n {
                true => write!(out, ",{tick},{offset}")?,
                false => write!(out, ",,")?,
            }
        }
        writeln!(out)
    }

    /// Parses one line, or says which column is wrong.
    pub fn parse(line: &str) -> Result<Self, String> {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 5 + 2 * MAX_EFFECTS {
            return Err(format!("{} columns, not {}", f.len(), 5 + 2 * MAX_EFFECTS));
        }
        let num = |j: usize, name: &str| {
            f[j].parse::<u64>().map_err(|_| format!("{name} `{}` is not a count", f[j]))
        };
        let applied = match f[2] {
            "-1" => None,
            _ => Some(num(2, "applied_torque_tick").map_err(|e| e + " or -1")?),
        };
        let effects = num(4, "effects")?;
        let mut recorded = [(NO_TICK, f64::NAN); MAX_EFFECTS];
        for (i, r) in recorded.iter_mut().enumerate().take(effects as usize) {
            let offset = f[6 + 2 * i].parse::<f64>().ok().filter(|o| o.is_finite());
            let offset =
                offset.ok_or_else(|| format!("effect{}_offset_s is not a number", i + 1))?;
            *r = (num(5 + 2 * i, &format!("effect{}_tick", i + 1))?, offset);
        }
        Ok(Self {
            tick: num(0, "tick")?,
            state_publish_ns: num(1, "state_publish_ns")?,
            applied_torque_tick: applied,
            flags: num(3, "flags")?,
            effects,
            recorded,
        })
    }
}

/// `timing.csv` read a row at a time in tick order ([`crate::rows`]): its header must be
/// this version's, and a row that does not parse is an error naming the file and tick.
#[derive(Debug)]
pub struct TimingRows {
    rows: crate::rows::TickRows,
    path: std::path::PathBuf,
}

impl TimingRows {
    /// Opens `path` and checks its header.
    pub fn open(path: &Path) -> anyhow::Result<Self> {
        Self::of_rows(crate::rows::TickRows::open(path)?, path)
    }

    /// The rows `rows` of a timing file (at `path`, as errors name it), its header checked.
    pub fn of_rows(rows: crate::rows::TickRows, path: &Path) -> anyhow::Result<Self> {
        anyhow::ensure!(
            rows.header() == header(),
            "{}: not a timing.csv of this version (header `{}`, expected `{}`)",
            path.display(),
            rows.header(),
            header()
        );
        Ok(Self { rows, path: path.to_owned() })
    }

    fn parse(&self, k: u64, line: &str) -> anyhow::Result<TimingRow> {
        TimingRow::parse(line).map_err(|e| anyhow::anyhow!("{} tick {k}: {e}", self.path.display()))
    }

    /// The row of tick `k` (ticks asked for in increasing order).
    pub fn row(&mut self, k: u64) -> anyhow::Result<Option<TimingRow>> {
        self.rows.row(k).map(|l| self.parse(k, &l)).transpose()
    }

    /// Whether no row is left.
    pub fn is_empty(&self) -> bool {
        self.rows.peek_tick().is_none()
    }

    /// Whether a row of a tick after `k` follows (rows up to `k` are passed over unread).
    pub fn more_after(&mut self, k: u64) -> bool {
        self.rows.skip_through(k);
        self.rows.peek_tick().is_some()
    }

    /// The next row.
    pub fn next_row(&mut self) -> anyhow::Result<Option<TimingRow>> {
        self.rows.next_row().map(|(k, l)| self.parse(k, &l)).transpose()
    }
}

/// Reads `path` (a `timing.csv`) by tick: its header must be this version's and every row
/// must parse; the error names the file and the line.
pub fn read(path: &Path) -> anyhow::Result<BTreeMap<u64, TimingRow>> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", path.display()))?;
    let mut lines = text.lines();
    let first = lines.next().unwrap_or_default();
    anyhow::ensure!(
        first == header(),
        "{}: not a timing.csv of this version (header `{first}`, expected `{}`)",
        path.display(),
        header()
    );
    let mut rows = BTreeMap::new();
    for (i, line) in lines.enumerate() {
        let row = TimingRow::parse(line)
            .map_err(|e| anyhow::anyhow!("{} line {}: {e}", path.display(), i + 2))?;
        rows.insert(row.tick, row);
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(effects: u64) -> StateSample {
        let mut s = StateSample {
            tick: 41,
            publish_ns: 123_456_789,
            applied_torque_tick: 39,
            flags: 5,
            effects,
            ..StateSample::of(
                41,
                0.041,
                &rotorloop_common::scenario::Scenario::load("paper-zero")
                    .expect("built-in")
                    .plant_init,
            )
        };
        for i in 0..MAX_EFFECTS {
            (s.effect_ticks[i], s.effect_offsets_s[i]) = (38 + i as u64, 0.1 + 0.2 * i as f64);
        }
        s
    }

    fn round_trip(row: &TimingRow) -> TimingRow {
        let mut out = Vec::new();
        row.write(&mut out).expect("vec");
        let line = String::from_utf8(out).expect("utf8");
        assert_eq!(line.trim_end().split(',').count(), header().split(',').count());
        TimingRow::parse(line.trim_end()).expect("its own row")
    }

    #[test]
    fn a_row_reads_back_as_written_bit_for_bit() {
        for effects in [0, 1, MAX_EFFECTS as u64, MAX_EFFECTS as u64 + 3] {
            let row = TimingRow::of(&sample(effects));
            let back = round_trip(&row);
            assert_eq!((back.tick, back.state_publish_ns, back.flags), (41, 123_456_789, 5));
            assert_eq!((back.applied_torque_tick, back.effects), (Some(39), effects));
            assert_eq!(back.recorded().len(), (effects as usize).min(MAX_EFFECTS));
            for (a, b) in back.recorded().iter().zip(row.recorded()) {
                assert_eq!((a.0, a.1.to_bits()), (b.0, b.1.to_bits()));
            }
        }
        let none = TimingRow::of(&StateSample { applied_torque_tick: NO_TICK, ..sample(0) });
        assert_eq!(round_trip(&none).applied_torque_tick, None, "-1 in the file");
    }

    #[test]
    fn a_bad_row_or_header_is_refused_naming_the_line_and_column() {
        let dir = std::env::temp_dir().join(format!("rl-timing-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("timing.csv");
        let mut good = Vec::new();
        TimingRow::of(&sample(1)).write(&mut good).expect("vec");
        let good = String::from_utf8(good).expect("utf8");
        std::fs::write(&path, format!("{}\n{good}", header())).expect("write");
        assert_eq!(read(&path).expect("valid").len(), 1);
        let bad_effect = good.replacen(",38,", ",x,", 1);
        for (text, want) in [
            (format!("tick,flags\n{good}"), "not a timing.csv of this version"),
            (format!("{}\n{good}1,2,3\n", header()), "line 3: 3 columns"),
            (format!("{}\n{bad_effect}", header()), "line 2: effect1_tick `x`"),
            (format!("{}\n{}", header(), good.replacen("41,", "-4,", 1)), "tick `-4`"),
        ] {
            std::fs::write(&path, text).expect("write");
            let e = read(&path).expect_err(want).to_string();
            assert!(e.contains(want) && e.contains("timing.csv"), "{want}: {e}");
        }
        std::fs::remove_dir_all(&dir).expect("clean");
    }
}
