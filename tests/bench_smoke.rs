//! A short `rotorloop bench` (two cells, one baseline, a fraction of a second each)
//! produces every output file, well formed. Numbers are not asserted: timing lives in
//! the bench itself, not in tests.

mod common;

use std::time::Duration;

use common::harness::{Harness, ok};

#[test]
fn short_bench_writes_every_output_file() {
    let h = Harness::new("bench");
    let out = h.path("bench");
    ok(&h.rotorloop(
        &[
            "bench",
            "--rates",
            "500",
            "--wait",
            "event",
            "--placement",
            "same-core,cross-core",
            "--baselines",
            "iceoryx2",
            "--seconds",
            "0.3",
            "--out",
            out.to_str().expect("utf8"),
        ],
        Duration::from_secs(180),
    ));
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    assert!(header.contains(&"p99_9_us") && header.contains(&"achieved_rate_hz"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 4, "2 cells × (loop + iceoryx2)");
    for r in &rows {
        assert_eq!(r.len(), header.len());
        assert!(r[14].is_empty(), "nothing skipped here: {r:?}");
        let count: u64 = r[6].parse().expect("count");
        assert!(count > 0, "{r:?}");
        for col in 7..11 {
            let v: f64 = r[col].parse().expect("latency");
            assert!(v > 0.0, "{}: {v}", header[col]);
        }
    }
    let md = std::fs::read_to_string(out.join("bench.md")).expect("bench.md");
    assert!(md.contains("loop/iceoryx2 p50") && md.contains("Highest rate with zero misses"));
    for cell in ["r500-event-same-core-none", "r500-event-cross-core-none"] {
        for f in ["loop.hgrm", "iceoryx2.hgrm"] {
            let text = std::fs::read_to_string(out.join("cells").join(cell).join(f)).expect(f);
            assert!(text.contains("Total count"), "{cell}/{f}");
        }
    }
    for png in [
        "spectrum_same-core_500hz_event.png",
        "spectrum_cross-core_500hz_event.png",
        "misses_by_rate.png",
    ] {
        let b = std::fs::read(out.join(png)).expect(png);
        assert_eq!(&b[..4], b"\x89PNG", "{png}");
    }
}

/// A combination that cannot work (busy-wait with both ends on one core) is skipped with
/// the reason, not run into the ground.
#[test]
fn impossible_cells_are_skipped_with_a_reason() {
    let h = Harness::new("benchskip");
    let out = h.path("bench");
    ok(&h.rotorloop(
        &[
            "bench",
            "--rates",
            "500",
            "--wait",
            "spin",
            "--placement",
            "same-core",
            "--baselines",
            "atomic",
            "--seconds",
            "0.2",
            "--out",
            out.to_str().expect("utf8"),
        ],
        Duration::from_secs(60),
    ));
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    let rows: Vec<&str> = csv.lines().skip(1).collect();
    assert_eq!(rows.len(), 2);
    for r in rows {
        assert!(r.contains("busy-wait with both ends on one core"), "{r}");
    }
}
