//! Per-hop latency histograms of the multi-process loop (HdrHistogram, nanoseconds): the
//! whole-run histogram, a `.hgrm` percentile distribution per hop, and a V2-compressed
//! interval log per hop with one histogram per second of run time, flushed as it goes,
//! so a run that dies still leaves its data.

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use hdrhistogram::Histogram;
use hdrhistogram::serialization::V2DeflateSerializer;
use hdrhistogram::serialization::interval_log::IntervalLogWriterBuilder;
use serde::Serialize;

use crate::plot::{PlotError, Series, YScale, line_chart};
use crate::prefaulted;

/// The hops of one loop tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Hop {
    /// Plant publishes state k → controller receives it.
    StateTransport,
    /// Controller receives state k → publishes torque k.
    ControllerCompute,
    /// Controller publishes torque k → plant receives it.
    TorqueTransport,
    /// Plant publishes state k → plant holds torque k: the loop.
    SenseToActuate,
    /// Plant wake-up minus its absolute grid time (real-time mode; cyclictest-style).
    TickLateness,
    /// How long before state k the reference sample k was published.
    ReferenceLead,
}

impl Hop {
    /// Every hop, in report order.
    pub const ALL: [Hop; 6] = [
        Hop::SenseToActuate,
        Hop::StateTransport,
        Hop::ControllerCompute,
        Hop::TorqueTransport,
        Hop::TickLateness,
        Hop::ReferenceLead,
    ];

    /// File and JSON name.
    pub fn name(self) -> &'static str {
        match self {
            Hop::StateTransport => "state_transport",
            Hop::ControllerCompute => "controller_compute",
            Hop::TorqueTransport => "torque_transport",
            Hop::SenseToActuate => "sense_to_actuate",
            Hop::TickLateness => "tick_lateness",
            Hop::ReferenceLead => "reference_lead",
        }
    }
}

/// Summary statistics of one hop (ns).
#[derive(Debug, Clone, Copy, Serialize, Default)]
pub struct HopStats {
    /// Samples recorded.
    pub count: u64,
    /// Minimum.
    pub min: u64,
    /// Mean.
    pub mean: f64,
    /// Percentiles.
    pub p50: u64,
    /// 90th percentile.
    pub p90: u64,
    /// 99th percentile.
    pub p99: u64,
    /// 99.9th percentile.
    pub p99_9: u64,
    /// 99.99th percentile.
    pub p99_99: u64,
    /// Maximum.
    pub max: u64,
}

impl HopStats {
    /// The statistics of a histogram.
    pub fn of(h: &Histogram<u64>) -> Self {
        if h.is_empty() {
            return Self::default();
        }
        Self {
            count: h.len(),
            min: h.min(),
            mean: h.mean(),
            p50: h.value_at_quantile(0.5),
            p90: h.value_at_quantile(0.9),
            p99: h.value_at_quantile(0.99),
            p99_9: h.value_at_quantile(0.999),
            p99_99: h.value_at_quantile(0.9999),
            max: h.max(),
        }
    }
}

/// One point of the latency-over-time plot: `(second, p50, p99, max)` in µs.
pub type IntervalPoint = (f64, f64, f64, f64);

/// Most points kept of a latency-over-time series, whatever the run's length.
pub const MAX_SERIES_POINTS: usize = 4096;

/// The per-second latency series of one hop for the over-time plot, in bounded memory:
/// its capacity is reserved once, and when it is full, neighbouring points are merged
/// (worst of each statistic) and the seconds per point double. A run of any length
/// keeps at most [`MAX_SERIES_POINTS`] points and never grows the vector.
#[derive(Debug, Clone)]
pub struct IntervalSeries {
    points: Vec<IntervalPoint>,
    stride: u64,
    pending: Option<(IntervalPoint, u64)>,
}

fn worst(a: IntervalPoint, b: IntervalPoint) -> IntervalPoint {
    (a.0, a.1.max(b.1), a.2.max(b.2), a.3.max(b.3))
}

impl Default for IntervalSeries {
    fn default() -> Self {
        Self { points: prefaulted(MAX_SERIES_POINTS), stride: 1, pending: None }
    }
}

impl IntervalSeries {
    /// Adds one interval's point.
    pub fn push(&mut self, p: IntervalPoint) {
        let (acc, n) = match self.pending.take() {
            Some((acc, n)) => (worst(acc, p), n + 1),
            None => (p, 1),
        };
        if n < self.stride {
            self.pending = Some((acc, n));
            return;
        }
        self.points.push(acc);
        if self.points.len() == MAX_SERIES_POINTS {
            let half = MAX_SERIES_POINTS / 2;
            for i in 0..half {
                self.points[i] = worst(self.points[2 * i], self.points[2 * i + 1]);
            }
            self.points.truncate(half);
            self.stride *= 2;
        }
    }

    /// The points, oldest first (the last, partial stride not included).
    pub fn points(&self) -> &[IntervalPoint] {
        &self.points
    }

    /// Seconds per point now.
    pub fn stride(&self) -> u64 {
        self.stride
    }
}

struct HopRecorder {
    total: Histogram<u64>,
    interval: Histogram<u64>,
    /// The interval log; `None` once it could not be written (the histograms go on).
    log: Option<BufWriter<File>>,
    serializer: V2DeflateSerializer,
    series: IntervalSeries,
}

/// An empty whole-run histogram, 1 ns to 1 h at 3 significant digits, its pages faulted in.
pub fn histogram() -> Histogram<u64> {
    let mut h =
        Histogram::new_with_bounds(1, 3_600_000_000_000, 3).expect("constant bounds are valid");
    // The counts come zeroed from the allocator, not yet resident; writing them once
    // faults every page in now rather than one by one as new latencies first appear.
    h.reset();
    h
}

/// The latency recorder of a run.
pub struct Latency {
    hops: Vec<HopRecorder>,
    dir: PathBuf,
    start_ns: u64,
    interval_index: u64,
    /// Why the interval logs stopped, if they did (a full disk).
    log_error: Option<String>,
}

impl std::fmt::Debug for Latency {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Latency").field("dir", &self.dir).field("start_ns", &self.start_ns).finish()
    }
}

impl Latency {
    /// A recorder writing interval logs `DIR/<hop>.hlog`. With `append`, existing logs are
    /// continued (a restarted monitor). Run time counts from `start_ns`.
    pub fn new(dir: &Path, start_ns: u64, append: bool) -> io::Result<Self> {
        let mut hops = Vec::new();
        let mut log_error = None;
        for hop in Hop::ALL {
            let log = Self::open_log(dir, hop, append)
                .map_err(|e| log_error.get_or_insert(format!("{}.hlog: {e}", hop.name())).clone())
                .ok();
            hops.push(HopRecorder {
                total: histogram(),
                interval: histogram(),
                log,
                serializer: V2DeflateSerializer::new(),
                series: IntervalSeries::default(),
            });
        }
        Ok(Self { hops, dir: dir.to_owned(), start_ns, interval_index: 0, log_error })
    }

    /// Opens (or continues) the interval log of `hop`, with its header when new.
    fn open_log(dir: &Path, hop: Hop, append: bool) -> io::Result<BufWriter<File>> {
        let path = dir.join(format!("{}.hlog", hop.name()));
        let fresh = !append || !path.exists();
        let name = format!("{}.hlog", hop.name());
        let out =
            rotorloop_common::outdir::OutDir::open(dir).map_err(rotorloop_common::outdir::to_io)?;
        let file = if append { out.append(&name)? } else { out.create(&name)? };
        let mut log = BufWriter::new(file);
        if fresh {
            let mut ser = V2DeflateSerializer::new();
            IntervalLogWriterBuilder::new()
                .add_comment(&format!("rotorloop {} latency (ns), 1 s intervals", hop.name()))
                .with_start_time(std::time::SystemTime::now())
                .begin_log_with(&mut log, &mut ser)?;
            writeln!(
                log,
                "\"StartTimestamp\",\"Interval_Length\",\"Interval_Max\",\"Interval_Compressed_Histogram\""
            )?;
            log.flush()?;
        }
        Ok(log)
    }

    /// Why the interval logs stopped being written, if they did.
    pub fn log_error(&self) -> Option<&str> {
        self.log_error.as_deref()
    }

    fn index(hop: Hop) -> usize {
        Hop::ALL.iter().position(|h| *h == hop).unwrap_or(0)
    }

    /// Records `value_ns` for `hop`, observed at monotonic time `at_ns`. Never fails: an
    /// interval log that cannot be written is given up ([`Self::log_error`]), the
    /// histograms go on.
    #[inline]
    pub fn record(&mut self, hop: Hop, value_ns: u64, at_ns: u64) {
        let idx = at_ns.saturating_sub(self.start_ns) / 1_000_000_000;
        if idx > self.interval_index {
            self.rotate();
            self.interval_index = idx;
        }
        let h = &mut self.hops[Self::index(hop)];
        let v = value_ns.max(1);
        h.total.saturating_record(v);
        h.interval.saturating_record(v);
    }

    /// Writes the current interval of every hop to its log and flushes it.
    pub fn rotate(&mut self) {
        let start = Duration::from_secs(self.interval_index);
        for (hop, h) in Hop::ALL.iter().zip(&mut self.hops) {
            if h.interval.is_empty() {
                continue;
            }
            if let Some(log) = &mut h.log {
                let written = IntervalLogWriterBuilder::new()
                    .begin_log_with(&mut *log, &mut h.serializer)
                    .map_err(|e| io::Error::other(format!("{e:?}")))
                    .and_then(|mut w| {
                        w.write_histogram(&h.interval, start, Duration::from_secs(1), None)
                            .map_err(|e| io::Error::other(format!("{e:?}")))
                    })
                    .and_then(|()| log.flush());
                if let Err(e) = written {
                    self.log_error.get_or_insert(format!("{}.hlog: {e}", hop.name()));
                    h.log = None;
                }
            }
            let us = |q: f64| h.interval.value_at_quantile(q) as f64 / 1e3;
            h.series.push((
                self.interval_index as f64,
                us(0.5),
                us(0.99),
                h.interval.max() as f64 / 1e3,
            ));
            h.interval.reset();
        }
    }

    /// The whole-run histogram of a hop.
    pub fn histogram(&self, hop: Hop) -> &Histogram<u64> {
        &self.hops[Self::index(hop)].total
    }

    /// Statistics of a hop.
    pub fn stats(&self, hop: Hop) -> HopStats {
        HopStats::of(self.histogram(hop))
    }

    /// Flushes the last interval and writes `<hop>.hgrm` for every hop into `dir`.
    pub fn finish(&mut self, dir: &Path) -> io::Result<Vec<String>> {
        self.rotate();
        let mut files = Vec::new();
        let od =
            rotorloop_common::outdir::OutDir::open(dir).map_err(rotorloop_common::outdir::to_io)?;
        for hop in Hop::ALL {
            let name = format!("{}.hgrm", hop.name());
            let mut out = BufWriter::new(od.atomic(&name)?);
            rotorloop_common::hgrm::write_percentile_distribution(self.histogram(hop), &mut out)?;
            out.into_inner().map_err(|e| e.into_error())?.commit()?;
            files.push(name);
        }
        Ok(files)
    }

    /// `latency_percentiles.png` (percentile spectrum per hop) and
    /// `latency_over_time.png` (per-second p50/p99/max of sense-to-actuate and the
    /// transport hops).
    pub fn plots(&self, title: &str) -> Result<Vec<String>, PlotError> {
        let mut files = Vec::new();
        let mut spectra = Vec::new();
        for hop in Hop::ALL {
            let h = self.histogram(hop);
            if h.is_empty() {
                continue;
            }
            // x = log10(1/(1 − q)), so 1 = p90, 2 = p99, 3 = p99.9 …
            let pts: Vec<(f64, f64)> = h
                .iter_quantiles(5)
                .filter(|v| v.quantile_iterated_to() < 1.0)
                .map(|v| {
                    (
                        (1.0 / (1.0 - v.quantile_iterated_to())).log10(),
                        v.value_iterated_to() as f64 / 1e3,
                    )
                })
                .collect();
            spectra.push((hop.name(), pts));
        }
        let series: Vec<Series<'_>> =
            spectra.iter().map(|(n, p)| Series { label: n, points: p, dashed: false }).collect();
        let file = "latency_percentiles.png";
        line_chart(
            &self.dir.join(file),
            &format!("{title}: latency percentile spectrum (x: 1 = p90, 2 = p99, 3 = p99.9)"),
            "log10(1 / (1 - percentile))",
            "µs (log)",
            &series,
            YScale::Log { floor: 0.01 },
        )?;
        files.push(file.to_owned());

        let series = &self.hops[Self::index(Hop::SenseToActuate)].series;
        let s2a = series.points();
        let p50: Vec<(f64, f64)> = s2a.iter().map(|p| (p.0, p.1)).collect();
        let p99: Vec<(f64, f64)> = s2a.iter().map(|p| (p.0, p.2)).collect();
        let max: Vec<(f64, f64)> = s2a.iter().map(|p| (p.0, p.3)).collect();
        let file = "latency_over_time.png";
        line_chart(
            &self.dir.join(file),
            &format!(
                "{title}: sense-to-actuate per {} s interval (worst of each)",
                series.stride()
            ),
            "run time (s)",
            "µs (log)",
            &[
                Series { label: "p50", points: &p50, dashed: false },
                Series { label: "p99", points: &p99, dashed: false },
                Series { label: "max", points: &max, dashed: true },
            ],
            YScale::Log { floor: 0.01 },
        )?;
        files.push(file.to_owned());
        Ok(files)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hdrhistogram::serialization::Deserializer;
    use hdrhistogram::serialization::interval_log::{IntervalLogIterator, LogEntry};

    #[test]
    fn interval_logs_read_back_and_hgrm_is_well_formed() {
        let dir = std::env::temp_dir().join(format!("rl-latency-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let mut lat = Latency::new(&dir, 0, false).expect("new");
        for i in 0..3000u64 {
            lat.record(Hop::SenseToActuate, 10_000 + i, i * 1_000_000);
        }
        let files = lat.finish(&dir).expect("finish");
        assert!(lat.log_error().is_none());
        assert_eq!(files.len(), Hop::ALL.len());
        let text = std::fs::read(dir.join("sense_to_actuate.hlog")).expect("log");
        let mut total = 0;
        let mut intervals = 0;
        for entry in IntervalLogIterator::new(&text) {
            if let Ok(LogEntry::Interval(ilh)) = entry {
                let bytes = base64_decode(ilh.encoded_histogram());
                let h: Histogram<u64> =
                    Deserializer::new().deserialize(&mut &bytes[..]).expect("decode");
                total += h.len();
                intervals += 1;
            }
        }
        assert_eq!(intervals, 3, "one interval per second of run time");
        assert_eq!(total, 3000);
        let hgrm = std::fs::read_to_string(dir.join("sense_to_actuate.hgrm")).expect("hgrm");
        assert!(
            hgrm.contains("Percentile") && hgrm.contains("Total count    =         3000"),
            "{hgrm}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn base64_decode(s: &str) -> Vec<u8> {
        const A: &[u8] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
        let mut out = Vec::new();
        let mut buf = 0u32;
        let mut bits = 0;
        for c in s.bytes().filter(|c| *c != b'=') {
            let v = A.iter().position(|a| *a == c).expect("base64") as u32;
            buf = (buf << 6) | v;
            bits += 6;
            if bits >= 8 {
                bits -= 8;
                out.push((buf >> bits) as u8);
            }
        }
        out
    }
}

#[cfg(test)]
mod series_tests {
    use super::*;

    #[test]
    fn a_day_of_intervals_stays_within_the_reserved_points_and_keeps_the_worst() {
        let mut s = IntervalSeries::default();
        let cap = s.points.capacity();
        for k in 0..86_400u64 {
            let spike = if k == 50_000 { 9_000.0 } else { 0.0 };
            s.push((k as f64, 40.0, 100.0, 200.0 + spike));
        }
        assert!(s.points().len() <= MAX_SERIES_POINTS);
        assert_eq!(s.points.capacity(), cap, "the vector must never grow");
        assert_eq!(s.stride(), 32);
        assert!(s.points().iter().any(|p| p.3 == 9_200.0), "the spike must survive merging");
        assert!(s.points().windows(2).all(|w| w[0].0 < w[1].0), "time order kept");
    }
}
