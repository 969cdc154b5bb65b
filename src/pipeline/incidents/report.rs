//! The incidents' files: `incidents.csv` (one row each, in time order), `incidents.md`
//! (the worst first, in words), `incidents.png` (the deviation of the worst from the loop
//! that had no incident), and their figures in `summary.json`.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;

use anyhow::Context;
use rotorloop_monitor::plot::{Series, YScale, line_chart};

use super::{Explained, Incident};

/// `incidents.csv`'s header.
pub const HEADER: &str = "start_tick,end_tick,start_s,duration_s,kind,cause_role,cause_stage,\
                          evidence,flags,misses,peak_deviation_deg,recovery_s";

fn quoted(s: &str) -> String {
    format!("\"{}\"", s.replace('"', "\"\""))
}

fn opt(v: Option<f64>) -> String {
    v.map(|v| format!("{v}")).unwrap_or_default()
}

/// `incidents.csv`, a row at a time as the incidents are found: written to
/// an exclusive temporary ([`rotorloop_common::outdir::Atomic`]) renamed when complete, so a
/// reader never takes a partial file for the run's incidents (and an analysis that fails
/// leaves no temporary behind).
pub struct Rows {
    out: std::io::BufWriter<rotorloop_common::outdir::Atomic>,
    path: std::path::PathBuf,
}

impl Rows {
    /// Starts `DIR/incidents.csv` with its header.
    pub fn create(dir: &Path) -> anyhow::Result<Self> {
        let path = dir.join("incidents.csv");
        let file = rotorloop_common::outdir::OutDir::open(dir)?
            .atomic("incidents.csv")
            .with_context(|| format!("cannot write {}", path.display()))?;
        let mut rows = Self { out: std::io::BufWriter::new(file), path };
        writeln!(rows.out, "{HEADER}").with_context(|| rows.failed())?;
        Ok(rows)
    }

    fn failed(&self) -> String {
        format!("cannot write {}", self.path.display())
    }

    /// One incident's row.
    pub fn add(&mut self, i: &Incident) -> anyhow::Result<()> {
        let Incident { start_tick, end_tick, start_s, duration_s, kind, cause_role, .. } = i;
        let (stage, evidence) = (quoted(&i.cause_stage), quoted(&i.evidence));
        let (flags, misses) = (quoted(&i.flags), i.misses);
        let (peak, recovery) = (opt(i.peak_deviation_deg), opt(i.recovery_s));
        writeln!(
            self.out,
            "{start_tick},{end_tick},{start_s:.6},{duration_s:.6},{kind},{cause_role},{stage},\
             {evidence},{flags},{misses},{peak},{recovery}"
        )
        .with_context(|| self.failed())
    }

    /// Completes the file.
    pub fn finish(self) -> anyhow::Result<()> {
        let failed = self.failed();
        let file = self.out.into_inner().map_err(|e| e.into_error()).context(failed.clone())?;
        file.commit().context(failed)
    }
}

fn markdown(dir: &Path, found: &Explained) -> String {
    let mut md = format!("# Incidents of {}\n\n", dir.display());
    let _ = writeln!(
        md,
        "{} incident(s): windows of abnormal ticks (a plant wake or an answer later than {:.3} \
         ms beyond the usual, misses, safe mode, rejected samples, faults, injected delays). \
         The cost of each is its peak attitude deviation from the loop that had no incident \
         (the same plant, law state and references from its first tick, its abnormal ticks \
         undisturbed at the run's median actuation delay of {:.3} ms), and the time until \
         that deviation is below 10 % of its peak.\n",
        found.count,
        found.threshold_s * 1e3,
        found.median_delay_s * 1e3,
    );
    let [same, computed] = found.law_reproduced;
    if computed == 0 {
        md += "No answer of the controller was found in the flight records (neither its own \
               `controller-torque.flight` nor the plant's `plant-torque.flight` holds one), so \
               the law in process has nothing to start from: no incident's cost can be computed.\n\n";
    } else {
        let _ = writeln!(
            md,
            "{} of them costed: the launcher's faults' first, then the longest, as many as \
             {} ticks of counterfactual for each second of the run hold ({} stepped); the \
             others are listed with their cause.\n",
            found.costed,
            super::COST_TICKS_PER_S,
            found.counterfactual_ticks,
        );
        let _ = writeln!(
            md,
            "The law in process reproduced {same} of the controller's {computed} answers bit for bit{}.\n",
            if same == computed {
                ""
            } else {
                " (the others: the counterfactual starts from an approximate law state)"
            }
        );
    }
    if !found.kernel_view {
        md += "No `sched.csv`: the kernel's view of the processes is missing.\n\n";
    }
    for (n, (i, inc)) in found.costliest.iter().enumerate() {
        let _ = writeln!(
            md,
            "## {}. {} at {:.3} s ({:.1} ms, ticks {}–{}, row {} of incidents.csv)\n",
            n + 1,
            inc.kind,
            inc.start_s,
            inc.duration_s * 1e3,
            inc.start_tick,
            inc.end_tick,
            i + 1
        );
        let _ = writeln!(md, "- **Cause:** {}: {}.", inc.cause_role, inc.cause_stage);
        let _ = writeln!(md, "- **Evidence:** {}.", inc.evidence);
        let _ = writeln!(md, "- **Ticks:** {} ({} miss(es)).", inc.flags, inc.misses);
        let cost = match (inc.peak_deviation_deg, inc.recovery_s) {
            (None, _) if computed == 0 => {
                "not computed (no record of the controller's answers)".to_owned()
            }
            (None, _) => "not computed (beyond the costing's share of the run)".to_owned(),
            (Some(p), Some(r)) => {
                format!("peak deviation {p:.4}°, below 10 % of it after {r:.3} s")
            }
            (Some(p), None) => {
                format!("peak deviation {p:.4}°, not back below 10 % of it within the run")
            }
        };
        let _ = writeln!(md, "- **Cost:** {cost}.\n");
    }
    if found.count > found.costliest.len() {
        let _ =
            writeln!(md, "… and {} more in incidents.csv.", found.count - found.costliest.len());
    }
    md
}

fn figure(dir: &Path, found: &Explained) -> anyhow::Result<()> {
    let worst: Vec<&(usize, Incident)> =
        found.costliest.iter().filter(|(_, i)| !i.curve.is_empty()).take(5).collect();
    let dt = found
        .costliest
        .first()
        .map_or(1e-3, |(_, i)| i.duration_s / (i.end_tick + 1 - i.start_tick) as f64);
    let points: Vec<Vec<(f64, f64)>> = worst
        .iter()
        .map(|(_, i)| i.curve.iter().enumerate().map(|(j, d)| (j as f64 * dt, *d)).collect())
        .collect();
    let labels: Vec<String> = worst
        .iter()
        .map(|(_, i)| format!("{} at {:.3} s ({})", i.kind, i.start_s, i.cause_role))
        .collect();
    let series: Vec<Series> = labels
        .iter()
        .zip(&points)
        .map(|(label, points)| Series { label, points, dashed: false })
        .collect();
    line_chart(
        &dir.join("incidents.png"),
        "deviation from the loop that had no incident (the worst incidents)",
        "s after the incident's start",
        "deviation (deg, log)",
        &series,
        YScale::Log { floor: 1e-4 },
    )?;
    Ok(())
}

/// Writes `incidents.md` and `incidents.png` (`incidents.csv` is [`Rows`]') and patches
/// `summary.json`.
pub fn write(dir: &Path, found: &Explained) -> anyhow::Result<()> {
    let path = dir.join("incidents.md");
    rotorloop_common::outdir::write_file(&path, markdown(dir, found))
        .with_context(|| format!("cannot write {}", path.display()))?;
    figure(dir, found)?;
    let worst = found.worst().cloned();
    rotorloop_monitor::summary::patch(dir, |j| {
        j["incidents"] = serde_json::json!({
            "count": found.count,
            "costed": found.costed,
            "counterfactual_ticks": found.counterfactual_ticks,
            "worst": worst,
            "threshold_s": found.threshold_s,
            "median_delay_s": found.median_delay_s,
            "law_reproduced": found.law_reproduced,
            "kernel_view": found.kernel_view,
            "files": ["incidents.csv", "incidents.md", "incidents.png"],
        });
        let Some(faults) = j.get_mut("faults").and_then(|f| f.as_array_mut()) else { return };
        for (f, held) in faults.iter_mut().zip(&found.faults) {
            f["incident"] = serde_json::json!(held.map(|h| h.row + 1));
            f["peak_deviation_deg"] = serde_json::json!(held.and_then(|h| h.peak_deviation_deg));
            f["recovery_s"] = serde_json::json!(held.and_then(|h| h.recovery_s));
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `incidents.csv` appears only whole: its rows go to a `.part` file renamed at the
    /// end, and an analysis that stops before the end leaves neither file.
    #[test]
    fn incidents_csv_appears_whole_or_not_at_all() {
        let dir = tempfile::tempdir().expect("tempdir");
        let csv = dir.path().join("incidents.csv");
        let names = || -> Vec<String> {
            let d = std::fs::read_dir(dir.path()).expect("read");
            d.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect()
        };
        let one = Incident {
            start_tick: 7,
            end_tick: 9,
            start_s: 0.007,
            duration_s: 0.003,
            kind: "miss",
            cause_role: "controller".into(),
            cause_stage: "controller compute".into(),
            evidence: "a \"quoted\" word".into(),
            flags: "miss".into(),
            misses: 3,
            peak_deviation_deg: Some(0.5),
            recovery_s: None,
            curve: Vec::new(),
            fault: None,
        };
        let mut rows = Rows::create(dir.path()).expect("create");
        rows.add(&one).expect("add");
        assert!(names().len() == 1 && !csv.exists(), "{:?}", names());
        drop(rows);
        assert!(names().is_empty(), "an unfinished analysis left a file: {:?}", names());
        let mut rows = Rows::create(dir.path()).expect("create");
        rows.add(&one).expect("add");
        rows.finish().expect("finish");
        assert_eq!(names(), ["incidents.csv"]);
        let text = std::fs::read_to_string(&csv).expect("incidents.csv");
        let want = "7,9,0.007000,0.003000,miss,controller,\"controller compute\",\
                    \"a \"\"quoted\"\" word\",\"miss\",3,0.5,\n";
        assert_eq!(text, format!("{HEADER}\n{want}"));
    }

    /// With no answer of the controller on record the report says why nothing is costed,
    /// in words, instead of "reproduced 0 of 0".
    #[test]
    fn a_run_without_the_controllers_answers_says_why_nothing_is_costed() {
        let mut found = Explained {
            count: 0,
            costed: 0,
            counterfactual_ticks: 0,
            costliest: Vec::new(),
            worst: None,
            faults: Vec::new(),
            threshold_s: 2.5e-4,
            median_delay_s: 1e-4,
            law_reproduced: [0, 0],
            realtime: true,
            kernel_view: true,
            traced: false,
        };
        let md = markdown(Path::new("run"), &found);
        assert!(md.contains("no incident's cost can be computed"), "{md}");
        assert!(!md.contains("reproduced 0 of"), "{md}");
        found.law_reproduced = [5, 5];
        let md = markdown(Path::new("run"), &found);
        assert!(md.contains("reproduced 5 of the controller's 5 answers"), "{md}");
    }
}
