//! The tick rule (issue 42, point 4): a torque or a reference for a tick the loop has not
//! reached, published into a running loop by a same-user process, is rejected and
//! counted by every receiver, reported by the monitor, and changes nothing: the run's
//! trace is the simulator's, bit for bit.
//!
//! Deterministic: the loop runs in lockstep and is held at one tick (its controller stops
//! itself between storing its answer and sending it, so the plant waits for that answer)
//! while the test publishes, from its own node `intruder` on the topic's second publisher
//! slot (the one a link gateway would take), one valid sample for tick 10¹²; then the
//! controller is continued.

use std::fmt::Debug;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use iceoryx2::prelude::ZeroCopySend;
use rotorloop_common::graph::Topic;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::so3::to_row_major;
use rotorloop_common::wire::{ReferenceSample, TorqueSample};

use super::LIMIT;
use crate::common::harness::{Harness, ROTORLOOP, assert_same_trace, json, sim_trace};

/// A tick no run reaches: 31 years at 1 kHz.
const FAR: u64 = 1_000_000_000_000;
/// The tick at which the loop is held while the sample is published.
const HELD_AT: &str = "500";
const SCENARIO: &str = "paper-sinusoid";
const DURATION: &str = "2";

/// The state letter of `pid` (`/proc/PID/stat`), if it runs.
fn state_of(pid: u32) -> Option<char> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    stat.rsplit(')').next()?.split_whitespace().next()?.chars().next()
}

/// The pid of the run's controller once it has stopped itself (state `T`).
fn stopped_controller(h: &mut Harness, run: usize) -> u32 {
    let until = Instant::now() + LIMIT;
    loop {
        let pid = crate::common::harness::pid_of_role(&h.domain, "controller");
        if let Some(pid) = pid.filter(|p| state_of(*p) == Some('T')) {
            return pid;
        }
        if h.child(run).try_wait().expect("try_wait").is_some() {
            panic!("the run ended before its controller stopped: {}", h.stderr_of(run));
        }
        assert!(Instant::now() < until, "the controller did not stop at tick {HELD_AT}");
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// A lockstep run held at tick [`HELD_AT`] while `sample` is published on `topic` by a
/// node of the test's own (as any process of the run's user could); then continued to
/// its end. No watchdog: nobody is restarted while the loop is held. Returns the run's
/// directory.
fn held_run<T: ZeroCopySend + Debug + Copy + 'static>(
    h: &mut Harness,
    topic: Topic,
    sample: T,
) -> PathBuf {
    let out = h.path("run");
    let args: Vec<String> = [
        "run",
        "--scenario",
        SCENARIO,
        "--duration",
        DURATION,
        "--mode",
        "lockstep",
        "--quiet",
        "--watchdog-ms",
        "0",
        "--test-stop-before-send-at",
        HELD_AT,
        "--domain",
        &h.domain,
        "--out",
        out.to_str().expect("utf8"),
    ]
    .iter()
    .map(|s| (*s).to_owned())
    .collect();
    let run = h.spawn(ROTORLOOP, &args);
    let controller = stopped_controller(h, run);
    let domain = Domain::new(&h.domain).expect("the run's domain");
    let node = domain.node("intruder").expect("a node of the run's user");
    let intruder = domain.outbox::<T>(&node, topic).expect("the topic's second publisher slot");
    intruder.send(sample, |_| {}).expect("published");
    // SAFETY: continues a process of this test's own run.
    assert_eq!(unsafe { libc::kill(controller as libc::pid_t, libc::SIGCONT) }, 0);
    let status = h.wait_all(LIMIT);
    assert!(status[run].success(), "the run failed: {}", h.stderr_of(run));
    drop((intruder, node));
    domain.cleanup().expect("cleanup");
    out
}

/// The run's summary, with checks every held run passes: it completed, and its trace is
/// the simulator's, bit for bit (nothing the intruder sent changed anything).
fn summary_of_unchanged_run(h: &Harness, out: &std::path::Path) -> serde_json::Value {
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    let trace = std::fs::read(out.join("trace.csv")).expect("trace");
    assert_same_trace("intruder", &trace, &sim_trace(h, SCENARIO, DURATION, &[]));
    s
}

/// Whether the monitor reported a `future-tick` fault event for `topic` at tick [`FAR`],
/// its detail naming the field.
fn reported(s: &serde_json::Value, topic: &str) -> bool {
    let events = s["wire_faults"].as_array().expect("wire_faults");
    events.iter().any(|e| {
        e["topic"] == topic
            && e["tick"] == FAR
            && e["kind"] == "future-tick"
            && e["detail"].as_str().is_some_and(|d| d.contains(&format!("{topic}.tick is {FAR}")))
    })
}

/// One valid zero torque for tick 10¹² from a same-user process (issue 42: accepted, it
/// made every true torque after it "older", and control was silenced for the rest of the
/// run, uncounted) is rejected and counted by the plant and the monitor, never displaces
/// the torque in force, and costs no miss and no tick of safe mode.
#[test]
fn a_torque_for_a_far_future_tick_is_rejected_counted_and_never_silences_control() {
    let mut h = Harness::new("tick-torque");
    let out = held_run(&mut h, Topic::Torque, TorqueSample { tick: FAR, ..Default::default() });
    let s = summary_of_unchanged_run(&h, &out);
    let rejected = &s["wire_rejected"];
    assert_eq!(rejected["plant.torque"], 1, "{rejected}");
    assert_eq!(rejected["monitor.torque"], 1, "{rejected}");
    assert!(reported(&s, "torque"), "no future-tick torque event: {}", s["wire_faults"]);
    assert_eq!(s["safe_mode_ticks"], 0);
    assert_eq!(s["misses"], 0);
    h.assert_no_leftovers();
}

/// One valid reference for tick 10¹² (far beyond the newest state and the reference's
/// lead) is rejected and counted by the controller and the monitor, and never displaces
/// a true reference (its ring entry, `tick mod 256`, is the true tick 512's).
#[test]
fn a_reference_far_beyond_the_lead_is_rejected_counted_and_displaces_none() {
    let mut h = Harness::new("tick-ref");
    let identity = to_row_major(&glam::DMat3::IDENTITY);
    let far = ReferenceSample { r_d_row_major: identity, ..ReferenceSample::zeroed(FAR) };
    let out = held_run(&mut h, Topic::Reference, far);
    let s = summary_of_unchanged_run(&h, &out);
    let rejected = &s["wire_rejected"];
    assert_eq!(rejected["controller.reference"], 1, "{rejected}");
    assert_eq!(rejected["monitor.reference"], 1, "{rejected}");
    assert!(reported(&s, "reference"), "no future-tick reference event: {}", s["wire_faults"]);
    h.assert_no_leftovers();
}
