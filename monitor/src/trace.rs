//! `trace.csv`: one row per recorded tick, every float in its shortest round-trip
//! decimal form (Rust's `Display` for `f64`), so a trace reads back bit for bit.

use std::io::{self, Write};

use crate::metrics::TraceRow;

/// The trace header. The first columns are the documented contract; then the invariant
/// checks, the tick, and the actuation delay in force (`delay_s`, NaN for a tick in which
/// no new torque took effect).
pub const HEADER: &str = "t,R11,R12,R13,R21,R22,R23,R31,R32,R33,\
Rd11,Rd12,Rd13,Rd21,Rd22,Rd23,Rd31,Rd32,Rd33,W1,W2,W3,Wd1,Wd2,Wd3,Wr1,Wr2,Wr3,\
u1,u2,u3,tau1,tau2,tau3,err_deg,werr,h1,h2,h3,h_drift_rel,energy_residual,tick,delay_s";

/// A row's values in [`HEADER`]'s order, as [`TraceWriter::write`] writes them (the tick
/// as a float): the line parsed back, without formatting it.
pub fn values(row: &TraceRow) -> Vec<f64> {
    let mut v = Vec::with_capacity(43);
    v.push(row.t);
    for a in [&row.r, &row.r_d] {
        v.extend_from_slice(a);
    }
    for a in [&row.omega, &row.omega_d, &row.omega_r, &row.u, &row.tau] {
        v.extend_from_slice(a);
    }
    v.extend([row.err_deg, row.werr]);
    v.extend_from_slice(&row.h);
    v.extend([row.h_drift_rel, row.energy_residual, row.tick as f64, row.delay_s]);
    v
}

/// Writes trace rows as CSV.
#[derive(Debug)]
pub struct TraceWriter<W: Write> {
    out: W,
}

impl<W: Write> TraceWriter<W> {
    /// Writes the header and returns the writer.
    pub fn new(mut out: W) -> io::Result<Self> {
        writeln!(out, "{HEADER}")?;
        Ok(Self { out })
    }

    /// A writer that appends to an existing trace (no header).
    pub fn append(out: W) -> Self {
        Self { out }
    }

    /// Appends one row.
    pub fn write(&mut self, row: &TraceRow) -> io::Result<()> {
        let o = &mut self.out;
        write!(o, "{}", row.t)?;
        for v in row.r.iter().chain(&row.r_d).chain(&row.omega).chain(&row.omega_d) {
            write!(o, ",{v}")?;
        }
        for v in row.omega_r.iter().chain(&row.u).chain(&row.tau) {
            write!(o, ",{v}")?;
        }
        write!(o, ",{},{}", row.err_deg, row.werr)?;
        for v in &row.h {
            write!(o, ",{v}")?;
        }
        writeln!(o, ",{},{},{},{}", row.h_drift_rel, row.energy_residual, row.tick, row.delay_s)
    }

    /// Flushes what was written so far to the file.
    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }

    /// Flushes and returns the inner writer.
    pub fn finish(mut self) -> io::Result<W> {
        self.out.flush()?;
        Ok(self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trace_floats_round_trip_exactly() {
        let row = TraceRow {
            tick: 7,
            t: 0.007,
            r: [0.1 + 0.2, -1e-300, 1.0 / 3.0, 2.0f64.sqrt(), 0.0, -0.0, 1e17, 5e-324, 1.0],
            err_deg: std::f64::consts::PI,
            ..TraceRow::default()
        };
        let mut w = TraceWriter::new(Vec::new()).expect("vec");
        w.write(&row).expect("vec");
        let text = String::from_utf8(w.finish().expect("vec")).expect("utf8");
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().expect("header").split(',').collect();
        let values: Vec<&str> = lines.next().expect("row").split(',').collect();
        assert_eq!(header.len(), values.len());
        let col = |name: &str| values[header.iter().position(|h| *h == name).expect(name)];
        for (name, want) in [
            ("R11", row.r[0]),
            ("R12", row.r[1]),
            ("R13", row.r[2]),
            ("R21", row.r[3]),
            ("R32", row.r[7]),
            ("err_deg", row.err_deg),
        ] {
            let got: f64 = col(name).parse().expect("float");
            assert_eq!(got.to_bits(), want.to_bits(), "{name}");
        }
        // The values unformatted are the line parsed back, column by column.
        let parsed: Vec<f64> = values.iter().map(|v| v.parse().expect("float")).collect();
        let direct = super::values(&row);
        assert_eq!(direct.len(), header.len());
        for (i, (a, b)) in parsed.iter().zip(&direct).enumerate() {
            assert_eq!(a.to_bits(), b.to_bits(), "{}", header[i]);
        }
    }
}
