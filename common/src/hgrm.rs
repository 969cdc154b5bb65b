//! HdrHistogram's percentile-distribution text (`.hgrm`), in µs, as HdrHistogram's own
//! tools write it: the monitor writes one per hop, the plant its own sense-to-actuate.

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
    let mut f =
        io::BufWriter::new(std::fs::File::create(path).map_err(|e| {
            io::Error::new(e.kind(), format!("cannot write {}: {e}", path.display()))
        })?);
    write_percentile_distribution(h, &mut f)?;
    f.flush()
}
