//! The faults a role injects into itself when asked: a corrupted sample at a chosen tick
//! (`rotorloop run --corrupt`, [`corrupted`]) and the tests' hooks ([`TestHooks`]).

use crate::flight::Record;
use crate::wire::{ReferenceSample, StateSample, TorqueSample};

/// Misbehaviour the tests ask of a role at a chosen moment, as hidden flags every role
/// takes (part of [`RoleArgs`](super::args::RoleArgs), so `rotorloop run` passes them to
/// each role and only the role named acts on its own).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::Args)]
pub struct TestHooks {
    /// The controller leaves the state of this tick unanswered.
    #[arg(long, hide = true, value_name = "TICK")]
    pub test_skip_state_at: Option<u64>,
    /// A first controller (not a restart) stalls at this tick holding a loaned sample, to
    /// be killed so.
    #[arg(long, hide = true, value_name = "TICK")]
    pub test_stall_with_loan_at: Option<u64>,
    /// A first reference (not a restart) starts this many ms late: states reach the
    /// controller before any reference.
    #[arg(long, hide = true, value_name = "MS")]
    pub test_reference_late_ms: Option<u64>,
    /// A first controller (not a restart) stops itself (SIGSTOP) at this tick between
    /// writing its resume slot and sending its answer: the slot then says it answered.
    #[arg(long, hide = true, value_name = "TICK")]
    pub test_stop_before_send_at: Option<u64>,
    /// A first monitor's (not a restart's) file thread waits this many ms before it writes
    /// its first rows: a stand-in for a `write(2)` held up by disk writeback.
    #[arg(long, hide = true, value_name = "MS")]
    pub test_files_stall_ms: Option<u64>,
    /// A first monitor (not a restart) waits this many ms after it connects, before it
    /// looks whether the plant has ended: a stand-in for a slow start on a loaded machine.
    #[arg(long, hide = true, value_name = "MS")]
    pub test_start_stall_ms: Option<u64>,
    /// The launcher's flight record mover waits this many ms before its first pass: a
    /// stand-in for a copy held up by disk writeback.
    #[arg(long, hide = true, value_name = "MS")]
    pub test_mover_stall_ms: Option<u64>,
}

impl TestHooks {
    /// The hooks that act in this incarnation of the controller: the stall and the stop
    /// only in a `first` one, not in a restart.
    pub fn first_run(mut self, first: bool) -> Self {
        if !first {
            (self.test_stall_with_loan_at, self.test_stop_before_send_at) = (None, None);
        }
        self
    }

    /// With `--test-start-stall-ms MS`, in a `first` run (not a restart): waits so long.
    pub fn start_stall(&self, first: bool) {
        if let Some(ms) = self.test_start_stall_ms.filter(|_| first) {
            std::thread::sleep(std::time::Duration::from_millis(ms));
        }
    }

    /// With `--test-stop-before-send-at K`: stops this process (SIGSTOP) at tick `k == K`.
    #[inline]
    pub fn stop_before_send(&self, k: u64) {
        if self.test_stop_before_send_at == Some(k) {
            crate::signals::stop_self();
        }
    }

    /// The hooks as a command line.
    pub fn to_args(&self) -> Vec<String> {
        [
            ("--test-skip-state-at", self.test_skip_state_at),
            ("--test-stall-with-loan-at", self.test_stall_with_loan_at),
            ("--test-reference-late-ms", self.test_reference_late_ms),
            ("--test-files-stall-ms", self.test_files_stall_ms),
            ("--test-start-stall-ms", self.test_start_stall_ms),
            ("--test-stop-before-send-at", self.test_stop_before_send_at),
            ("--test-mover-stall-ms", self.test_mover_stall_ms),
        ]
        .into_iter()
        .filter_map(|(flag, v)| v.map(|v| [flag.to_owned(), v.to_string()]))
        .flatten()
        .collect()
    }
}

/// How to corrupt a published sample (fault injection: `rotorloop run --corrupt`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CorruptKind {
    /// A NaN in the first vector the receiver uses.
    Nan,
    /// `+∞` there.
    Inf,
    /// `1e12` there: finite but absurd.
    Huge,
    /// An attitude that is not a rotation (a row scaled by 1.5): state and reference only.
    Skew,
}

/// One `--corrupt KIND@TICK`: publish tick `tick` corrupted instead of the true sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Corrupt {
    /// What to do to the sample.
    pub kind: CorruptKind,
    /// Which tick's sample.
    pub tick: u64,
}

impl std::str::FromStr for Corrupt {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("`{s}` is not allowed: KIND@TICK with KIND nan, inf, huge or skew");
        let (kind, tick) = s.split_once('@').ok_or_else(bad)?;
        let kind = match kind {
            "nan" => CorruptKind::Nan,
            "inf" => CorruptKind::Inf,
            "huge" => CorruptKind::Huge,
            "skew" => CorruptKind::Skew,
            _ => return Err(bad()),
        };
        Ok(Self { kind, tick: tick.parse().map_err(|_| bad())? })
    }
}

impl std::fmt::Display for Corrupt {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kind = match self.kind {
            CorruptKind::Nan => "nan",
            CorruptKind::Inf => "inf",
            CorruptKind::Huge => "huge",
            CorruptKind::Skew => "skew",
        };
        write!(f, "{kind}@{}", self.tick)
    }
}

/// A sample that fault injection can corrupt (at its tick: [`Record::tick`]).
pub trait Corruptible: Record {
    /// The vector a receiver reads first, and the attitude (if the sample has one).
    fn targets(&mut self) -> (&mut [f64; 3], Option<&mut [f64; 9]>);
}

impl Corruptible for StateSample {
    fn targets(&mut self) -> (&mut [f64; 3], Option<&mut [f64; 9]>) {
        (&mut self.omega_body_rad_s, Some(&mut self.r_row_major))
    }
}

impl Corruptible for ReferenceSample {
    fn targets(&mut self) -> (&mut [f64; 3], Option<&mut [f64; 9]>) {
        (&mut self.omega_d_rad_s, Some(&mut self.r_d_row_major))
    }
}

impl Corruptible for TorqueSample {
    fn targets(&mut self) -> (&mut [f64; 3], Option<&mut [f64; 9]>) {
        (&mut self.rotor_torque_nm, None)
    }
}

/// The sample to publish: `sample` itself, or a corrupted copy when `--corrupt` names
/// its tick. The caller keeps (and stores for a restart) the true sample.
#[inline]
pub fn corrupted<T: Corruptible>(corrupt: &[Corrupt], mut sample: T) -> T {
    corrupt_in_place(corrupt, &mut sample);
    sample
}

/// [`corrupted`] in place.
#[inline]
pub fn corrupt_in_place<T: Corruptible>(corrupt: &[Corrupt], sample: &mut T) {
    let tick = sample.tick();
    for c in corrupt.iter().filter(|c| c.tick == tick) {
        let (v, r) = sample.targets();
        match (c.kind, r) {
            (CorruptKind::Nan, _) => v[0] = f64::NAN,
            (CorruptKind::Inf, _) => v[0] = f64::INFINITY,
            (CorruptKind::Huge, _) => v[0] = 1e12,
            (CorruptKind::Skew, Some(r)) => r[..3].iter_mut().for_each(|x| *x *= 1.5),
            (CorruptKind::Skew, None) => v[0] = f64::NAN,
        }
    }
}
