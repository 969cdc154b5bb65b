//! HdrHistogram's percentile-distribution text (`.hgrm`), in µs, as HdrHistogram's own
//! tools write it: the monitor writes one per hop, the plant its own sense-to-actuate.
//! Its checked reader ([`read_distribution`]) is beside the writer.

use std::io::{self, Write};

use hdrhistogram::Histogram;

/// Writes HdrHistogram's percentile-distribution text format (values in µs, 5 ticks per
/// half distance), as `outputPercentileDistribution` does.
pub fn write_percentile_distribution(h: &Histogram<u64>, out: &mut impl Write) -> io::Result<()> {
    writeln!(
        out,
        "{:>12} {:>14} {:>10} {:>14}\n",
        "Value", "Percentile", "TotalCount", "1/(1-Percentile)"
    )?;
    let mut total = 0u64;
    if !h.is_empty() {
        for v in h.iter_quantiles(5) {
            total += v.count_since_last_iteration();
            let q = v.quantile_iterated_to();
            let value = v.value_iterated_to() as f64 / 1e3;
            if q < 1.0 {
                writeln!(out, "{value:12.3} {q:2.12} {total:10} {:14.2}", 1.0 / (1.0 - q))?;
            } else {
                writeln!(out, "{value:12.3} {q:2.12} {total:10}")?;
            }
        }
    }
    let (mean, sd, max) = if h.is_empty() {
        (0.0, 0.0, 0.0)
    } else {
        (h.mean() / 1e3, h.stdev() / 1e3, h.max() as f64 / 1e3)
    };
    writeln!(out, "#[Mean    = {mean:12.3}, StdDeviation   = {sd:12.3}]")?;
    writeln!(out, "#[Max     = {max:12.3}, Total count    = {:12}]", h.len())?;
    writeln!(out, "#[Buckets = {:12}, SubBuckets     = {:12}]", h.buckets(), h.distinct_values())
}

/// Writes `h` as a `.hgrm` file at `path`.
pub fn write_hgrm_file(path: &std::path::Path, h: &Histogram<u64>) -> io::Result<()> {
    let mut text = Vec::new();
    write_percentile_distribution(h, &mut text)?;
    crate::outdir::write_file(path, text)
        .map_err(|e| io::Error::new(e.kind(), format!("cannot write {}: {e}", path.display())))
}

/// The largest `.hgrm` file read (bytes): a distribution is a few hundred lines.
pub const MAX_FILE_BYTES: u64 = 16 << 20;
/// The largest value a distribution read as delays may hold (µs): an hour, as
/// `--actuation-delay` allows.
pub const MAX_VALUE_US: f64 = 3.6e9;

/// The percentile distribution of the `.hgrm` file `path`: `(percentile, value in s)`,
/// both non-decreasing, at least two points. Lines that are not `Value Percentile …`
/// (the header, the `#[…]` footer) are skipped; a value out of `0..=MAX_VALUE_US` or a
/// percentile out of `[0, 1]` is refused naming the line. The file is read as any input
/// named on the command line ([`crate::input`]): regular, bounded, UTF-8.
pub fn read_distribution(path: &std::path::Path) -> Result<Vec<(f64, f64)>, String> {
    let text = crate::input::read_text(path, MAX_FILE_BYTES).map_err(|e| e.to_string())?;
    let mut q: Vec<(f64, f64)> = Vec::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !l.trim_start().starts_with('#')) {
        let f: Vec<&str> = line.split_whitespace().collect();
        let (Some(v), Some(p)) = (f.first(), f.get(1)) else { continue };
        let (Ok(v_us), Ok(p)) = (v.parse::<f64>(), p.parse::<f64>()) else { continue };
        if !((0.0..=MAX_VALUE_US).contains(&v_us) && (0.0..=1.0).contains(&p)) {
            let shown: String = line.chars().take(80).collect();
            return Err(format!(
                "line {}: `{shown}` is not allowed: a value in µs from 0 to {MAX_VALUE_US:e} \
                 (an hour) and a percentile from 0 to 1",
                i + 1
            ));
        }
        if q.last().is_none_or(|(lp, lv)| p >= *lp && v_us * 1e-6 >= *lv) {
            q.push((p, v_us * 1e-6));
        }
    }
    if q.len() < 2 {
        return Err("no percentile distribution in it (HdrHistogram's .hgrm text: Value \
                    Percentile TotalCount …)"
            .into());
    }
    Ok(q)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What the writer writes, the reader reads; delays beyond an hour (1e300 µs ran) and
    /// percentiles beyond 1 are refused naming the line.
    #[test]
    fn the_reader_reads_what_the_writer_wrote_and_refuses_absurd_values() {
        let dir = std::env::temp_dir().join(format!("rl-hgrm-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let mut h = Histogram::<u64>::new(3).expect("histogram");
        for ns in [1_000, 2_000, 50_000] {
            h.record(ns).expect("record");
        }
        let path = dir.join("ok.hgrm");
        write_hgrm_file(&path, &h).expect("write");
        let q = read_distribution(&path).expect("read");
        assert!(q.len() >= 2 && (q[q.len() - 1].1 - 50e-6).abs() < 1e-7, "{q:?}");
        for (line, what) in [("1e300 0.5 1", "line 2: `1e300 0.5 1`"), ("5.0 1.5 1", "line 2")] {
            std::fs::write(&path, format!("1.0 0.0 1\n{line}\n")).expect("write");
            let e = read_distribution(&path).expect_err(line);
            assert!(e.starts_with(what) && e.contains("is not allowed"), "{e}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
