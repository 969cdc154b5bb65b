//! Every sample that crosses a process boundary, in one place.
//!
//! Each is `#[repr(C)]`, `Copy`, `ZeroCopySend`, made of fixed-size fields only, with an
//! explicit iceoryx2 type name that carries [`LAYOUT_VERSION`] and a compile-time size
//! assert. iceoryx2 compares type name, size and alignment between processes but not
//! field order: bump the version in every name whenever a layout changes, so a process
//! of another build is refused instead of reading garbage.
//!
//! Units are in the field names; timestamps are `u64` ns of `CLOCK_MONOTONIC`;
//! matrices are row-major.

use glam::{DMat3, DVec3};
use iceoryx2::prelude::ZeroCopySend;

use crate::params::{ReferenceState, RotorBodyState};
use crate::so3::{from_rows, to_row_major};

/// How many reference samples the generator may publish ahead of the newest state (the
/// wire contract: a reference further ahead is refused, [`TickBound`]).
pub const REFERENCE_LEAD: u64 = 16;

/// One field of a wire sample, as the `wire_struct!` macro of this module lists it: what `rotorloop wire`
/// publishes (docs/wire.md, the Python module, the C header) and what the layout test
/// compares with Python's ctypes and a C compiler.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WireField {
    /// The field's name.
    pub name: &'static str,
    /// Its offset from the start of the sample (bytes).
    pub offset: usize,
    /// Its size (bytes).
    pub size: usize,
    /// Its Rust type, as written (`u64`, `f64`, `[f64; 9]`, `[u64; MAX_EFFECTS]`, `SendCost`).
    pub ty: &'static str,
    /// Its doc comment.
    pub doc: &'static str,
}

/// Defines a wire sample and its field table (`FIELDS`) from one field list, so the
/// table cannot leave a field out or get an offset wrong.
macro_rules! wire_struct {
    (
        $(#[doc = $sdoc:literal])*
        #[derive($($derive:path),*)]
        $(#[$outer:meta])*
        pub struct $name:ident {
            $(
                $(#[doc = $doc:literal])*
                pub $field:ident : $ty:ty,
            )*
        }
    ) => {
        $(#[doc = $sdoc])*
        #[derive($($derive),*)]
        $(#[$outer])*
        pub struct $name {
            $(
                $(#[doc = $doc])*
                pub $field: $ty,
            )*
        }

        impl $name {
            /// What the type's doc comment says.
            pub const DOC: &'static str = concat!($($sdoc, "\n"),*);
            /// Every field in order, with its offset, size, type and doc comment.
            pub const FIELDS: &'static [WireField] = &[
                $(
                    WireField {
                        name: stringify!($field),
                        offset: ::core::mem::offset_of!($name, $field),
                        size: ::core::mem::size_of::<$ty>(),
                        ty: stringify!($ty),
                        doc: concat!($($doc, "\n"),*),
                    },
                )*
            ];
        }
    };
}

/// The layout version carried in every type name.
pub const LAYOUT_VERSION: u32 = 6;

/// How many of the torques that took effect in one tick a state sample records (tick and
/// offset each): what `sim --replay` can reconstruct. A plant catching up after a stall of
/// a few ms sees several arrive in one tick (four seen under CI load, with room for three).
pub const MAX_EFFECTS: usize = 8;

/// "No torque sample" in [`StateSample::applied_torque_tick`].
pub const NO_TICK: u64 = u64::MAX;

/// [`StateSample::flags`]: this is the run's last tick.
pub const FLAG_LAST: u64 = 1;
/// [`StateSample::flags`]: the plant runs on a real-time grid.
pub const FLAG_REALTIME: u64 = 1 << 1;
/// [`StateSample::flags`]: safe mode (no fresh torque for too long: rotors coast).
pub const FLAG_SAFE_MODE: u64 = 1 << 2;
/// [`StateSample::flags`]: the torque held over `[t_k−1, t_k]` was limited by the
/// actuators (torque saturation or the rotor speed limit).
pub const FLAG_SATURATED: u64 = 1 << 3;

/// [`TorqueSample::flags`]: the controller did not compute this tick: its state was
/// rejected, or there was no reference to track (none paired yet, or the hold of a
/// missing or rejected one ran out); the torque fields are zero and the plant must treat the sample as a
/// missing torque (hold, then safe mode).
pub const TORQUE_SKIPPED: u64 = 1;

wire_struct! {
/// The plant's state at tick `tick`, published once per tick.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend, serde::Serialize)]
#[type_name("rotorloop::StateSample_v6")]
#[repr(C)]
pub struct StateSample {
    /// Tick index `k`.
    pub tick: u64,
    /// `t_k = k dt` (s).
    pub t_s: f64,
    /// `R` (row-major).
    pub r_row_major: [f64; 9],
    /// `Ω` (rad/s, body frame).
    pub omega_body_rad_s: [f64; 3],
    /// `Ω_r` (rad/s, relative to the body).
    pub omega_rotor_rad_s: [f64; 3],
    /// `Θ` (rad).
    pub theta_rotor_rad: [f64; 3],
    /// Rotor torque held over `[t_k−1, t_k]` (N m).
    pub applied_rotor_torque_nm: [f64; 3],
    /// Body torque held over `[t_k−1, t_k]` (N m).
    pub applied_body_torque_nm: [f64; 3],
    /// Tick of the torque sample held over `[t_k−1, t_k]`, or [`NO_TICK`].
    pub applied_torque_tick: u64,
    /// When the plant received that torque sample (ns), 0 if none.
    pub applied_torque_recv_ns: u64,
    /// The tick's grid time in real-time mode (ns), 0 in lockstep.
    pub deadline_ns: u64,
    /// When the plant woke for this tick (ns).
    pub wake_ns: u64,
    /// When the sample was published (ns).
    pub publish_ns: u64,
    /// Ticks so far on which no fresh torque had arrived in time (cumulative).
    pub misses: u64,
    /// Torque samples received so far.
    pub torques_received: u64,
    /// Torque samples known lost (gaps in their tick sequence) so far.
    pub torques_lost: u64,
    /// Ticks so far spent in safe mode (cumulative).
    pub safe_mode_ticks: u64,
    /// Torque samples rejected by validation so far (NaN, infinite, absurd).
    pub torques_rejected: u64,
    /// Ticks so far whose held torque the actuator limits changed (cumulative).
    pub saturated_ticks: u64,
    /// [`FLAG_LAST`], [`FLAG_REALTIME`], [`FLAG_SAFE_MODE`], [`FLAG_SATURATED`].
    pub flags: u64,
    /// The integrator's `h` (N m s, inertial): with `p` and `R`, an exact resume point.
    pub internal_h: [f64; 3],
    /// The integrator's rotor momenta `p = K(Ω+Ω_r)` (N m s).
    pub internal_p: [f64; 3],
    /// Rotor work over `[t_k−1, t_k]` (J): the sum over the tick's pieces of `u · ΔΘ`
    /// (delayed zero-order hold: a torque takes effect inside the tick).
    pub rotor_work_j: f64,
    /// How many new torques took effect during `[t_k−1, t_k]` (may exceed [`MAX_EFFECTS`]).
    pub effects: u64,
    /// The ticks of the first [`MAX_EFFECTS`] of them.
    pub effect_ticks: [u64; MAX_EFFECTS],
    /// When each took effect, after `t_k−1` (s).
    pub effect_offsets_s: [f64; MAX_EFFECTS],
    /// What publishing the previous state cost (the stage breakdown of `rotorloop bench`).
    pub prev_publish: SendCost,
}
}
const _: () = assert!(size_of::<StateSample>() == 520);

wire_struct! {
/// The desired attitude for tick `tick`, published ahead of the plant.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend, serde::Serialize)]
#[type_name("rotorloop::ReferenceSample_v6")]
#[repr(C)]
pub struct ReferenceSample {
    /// Tick index `k`.
    pub tick: u64,
    /// `t_k` (s).
    pub t_s: f64,
    /// `R_d` (row-major).
    pub r_d_row_major: [f64; 9],
    /// `Ω_d` (rad/s).
    pub omega_d_rad_s: [f64; 3],
    /// `Ω̇_d` (rad/s²).
    pub omega_d_dot_rad_s2: [f64; 3],
    /// The dummy body's rotor rates (rad/s): with `R_d`, `Ω_d` enough to resume it.
    pub omega_rotor_rad_s: [f64; 3],
    /// The dummy body's rotor angles (rad).
    pub theta_rotor_rad: [f64; 3],
    /// When the sample was published (ns).
    pub publish_ns: u64,
    /// The dummy body's integrator `h` (exact resume point).
    pub internal_h: [f64; 3],
    /// The dummy body's integrator rotor momenta `p`.
    pub internal_p: [f64; 3],
}
}
const _: () = assert!(size_of::<ReferenceSample>() == 240);

wire_struct! {
/// The controller's answer to state sample `tick`.
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend, serde::Serialize)]
#[type_name("rotorloop::TorqueSample_v6")]
#[repr(C)]
pub struct TorqueSample {
    /// The state tick this answers.
    pub tick: u64,
    /// Rotor torque `u` (N m).
    pub rotor_torque_nm: [f64; 3],
    /// Body torque `τ` (N m).
    pub body_torque_nm: [f64; 3],
    /// When the controller received the state sample (ns).
    pub state_recv_ns: u64,
    /// When this sample was published (ns).
    pub publish_ns: u64,
    /// State samples received so far.
    pub states_received: u64,
    /// State samples known lost so far.
    pub states_lost: u64,
    /// State samples taken but not answered because a newer one was already there.
    pub states_skipped: u64,
    /// Ticks whose reference sample was not there when the state arrived.
    pub reference_misses: u64,
    /// Torque samples published so far, this one included (so a subscriber's losses
    /// are `published − received`, whatever ticks the controller skipped).
    pub published: u64,
    /// State samples rejected by validation so far.
    pub states_rejected: u64,
    /// Reference samples rejected by validation so far.
    pub references_rejected: u64,
    /// [`TORQUE_SKIPPED`].
    pub flags: u64,
    /// When the state had passed the answer rule and its validation (ns).
    pub validated_ns: u64,
    /// When the state was paired with its reference (ns).
    pub paired_ns: u64,
    /// When the law's torques were computed (ns).
    pub computed_ns: u64,
    /// The tick of the previous torque published ([`NO_TICK`] if none).
    pub prev_tick: u64,
    /// What publishing it cost.
    pub prev_publish: SendCost,
}
}
const _: () = assert!(size_of::<TorqueSample>() == 192);

wire_struct! {
/// What one publish cost (ns): loaning the sample, from the publish timestamp until
/// `send` returned, and notifying the listeners after it. Carried in the publisher's
/// next sample (a sample cannot carry the cost of its own send).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend, serde::Serialize)]
#[repr(C)]
pub struct SendCost {
    /// `loan_uninit` (before the publish timestamp: not part of the hop it starts).
    pub loan_ns: u64,
    /// From the publish timestamp until `send` returned: the sample is delivered.
    pub send_ns: u64,
    /// The notifier's `notify` (wakes the listeners; after the delivery).
    pub notify_ns: u64,
}
}
const _: () = assert!(size_of::<SendCost>() == 24);

impl StateSample {
    /// The kinematic state carried.
    pub fn body_state(&self) -> RotorBodyState {
        RotorBodyState {
            r: mat(&self.r_row_major),
            omega: DVec3::from_array(self.omega_body_rad_s),
            omega_r: DVec3::from_array(self.omega_rotor_rad_s),
            theta: DVec3::from_array(self.theta_rotor_rad),
        }
    }

    /// A sample of `x` at tick `tick` with every other field zero.
    pub fn of(tick: u64, t_s: f64, x: &RotorBodyState) -> Self {
        Self {
            tick,
            t_s,
            r_row_major: to_row_major(&x.r),
            omega_body_rad_s: x.omega.to_array(),
            omega_rotor_rad_s: x.omega_r.to_array(),
            theta_rotor_rad: x.theta.to_array(),
            applied_rotor_torque_nm: [0.0; 3],
            applied_body_torque_nm: [0.0; 3],
            applied_torque_tick: NO_TICK,
            applied_torque_recv_ns: 0,
            deadline_ns: 0,
            wake_ns: 0,
            publish_ns: 0,
            misses: 0,
            torques_received: 0,
            torques_lost: 0,
            safe_mode_ticks: 0,
            torques_rejected: 0,
            saturated_ticks: 0,
            flags: 0,
            internal_h: [0.0; 3],
            internal_p: [0.0; 3],
            rotor_work_j: 0.0,
            effects: 0,
            effect_ticks: [NO_TICK; MAX_EFFECTS],
            effect_offsets_s: [f64::NAN; MAX_EFFECTS],
            prev_publish: SendCost::default(),
        }
    }

    /// The actuation delay of the first torque that took effect during the previous tick
    /// `[t_k−1, t_k]` (s): when it took effect minus its own tick's time, with ticks of
    /// `dt`; NaN when none did (the trace's `delay_s` of row `k − 1`).
    pub fn first_effect_delay_s(&self, dt: f64) -> f64 {
        match self.effects {
            0 => f64::NAN,
            _ => effect_delay_s(
                self.tick.saturating_sub(1),
                self.effect_ticks[0],
                self.effect_offsets_s[0],
                dt,
            ),
        }
    }
}

/// The actuation delay of the torque of tick `source` that took effect `offset_s` into
/// tick `tick` (s): `(tick − source) dt + offset`. The plant process and the in-process
/// simulator both compute it here, so their traces agree bit for bit.
pub fn effect_delay_s(tick: u64, source: u64, offset_s: f64, dt: f64) -> f64 {
    tick.saturating_sub(source) as f64 * dt + offset_s
}

impl ReferenceSample {
    /// A sample of `tick` with every field zero (`R_d` too: not a rotation until set), to
    /// build others from with struct update syntax.
    pub const fn zeroed(tick: u64) -> Self {
        Self {
            tick,
            t_s: 0.0,
            r_d_row_major: [0.0; 9],
            omega_d_rad_s: [0.0; 3],
            omega_d_dot_rad_s2: [0.0; 3],
            omega_rotor_rad_s: [0.0; 3],
            theta_rotor_rad: [0.0; 3],
            publish_ns: 0,
            internal_h: [0.0; 3],
            internal_p: [0.0; 3],
        }
    }
}

impl ReferenceSample {
    /// What the controller needs.
    pub fn reference_state(&self) -> ReferenceState {
        ReferenceState {
            r_d: mat(&self.r_d_row_major),
            omega_d: DVec3::from_array(self.omega_d_rad_s),
            omega_d_dot: DVec3::from_array(self.omega_d_dot_rad_s2),
        }
    }

    /// The dummy body's full state (to resume the generator).
    pub fn body_state(&self) -> RotorBodyState {
        RotorBodyState {
            r: mat(&self.r_d_row_major),
            omega: DVec3::from_array(self.omega_d_rad_s),
            omega_r: DVec3::from_array(self.omega_rotor_rad_s),
            theta: DVec3::from_array(self.theta_rotor_rad),
        }
    }
}

/// A received torque more than this many times the configured limit is absurd (the
/// actuators would merely saturate at a few times the limit).
pub const ABSURD_TORQUE_FACTOR: f64 = 1e3;
/// Largest magnitude accepted for a received rate, torque or momentum without a
/// configured limit (the scenario loader's bound on every vector entry).
pub const MAX_WIRE_MAGNITUDE: f64 = crate::scenario::MAX_MAGNITUDE;
/// Largest accepted rotor angle or integral state (they accumulate over a run).
pub const MAX_WIRE_ACCUMULATED: f64 = 1e12;
/// Largest entry of `RᵀR − I`, and `|det R − 1|`, accepted in a received attitude.
pub const WIRE_ORTHONORMAL_TOL: f64 = 1e-6;

/// Why a received sample was rejected. Names the field; no allocation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum WireFault {
    /// NaN or infinity.
    NonFinite {
        /// The field.
        field: &'static str,
    },
    /// A finite value beyond what the receiver accepts.
    Absurd {
        /// The field.
        field: &'static str,
        /// The offending entry.
        value: f64,
        /// The largest magnitude accepted.
        limit: f64,
    },
    /// An attitude off SO(3).
    NotOrthonormal {
        /// The field.
        field: &'static str,
        /// `max(max |RᵀR − I|, |det R − 1|)`.
        deviation: f64,
    },
    /// A tick the loop has not reached ([`TickBound`]).
    FutureTick {
        /// The field.
        field: &'static str,
        /// The sample's tick.
        tick: u64,
        /// The newest tick accepted.
        allowed: u64,
    },
}

impl WireFault {
    /// Short name of the kind: `non-finite`, `absurd`, `non-orthonormal` or `future-tick`.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::NonFinite { .. } => "non-finite",
            Self::Absurd { .. } => "absurd",
            Self::NotOrthonormal { .. } => "non-orthonormal",
            Self::FutureTick { .. } => "future-tick",
        }
    }

    /// The field that was rejected.
    pub fn field(&self) -> &'static str {
        match self {
            Self::NonFinite { field }
            | Self::Absurd { field, .. }
            | Self::NotOrthonormal { field, .. }
            | Self::FutureTick { field, .. } => field,
        }
    }
}

impl std::fmt::Display for WireFault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::NonFinite { field } => write!(f, "{field} is not finite"),
            Self::Absurd { field, value, limit } => {
                write!(f, "{field} has {value:e}, beyond the accepted ±{limit:e}")
            }
            Self::NotOrthonormal { field, deviation } => write!(
                f,
                "{field} is not a rotation (deviation {deviation:e}, allowed {WIRE_ORTHONORMAL_TOL:e})"
            ),
            Self::FutureTick { field, tick, allowed } => write!(
                f,
                "{field} is {tick}, a tick the loop has not reached (accepted up to {allowed})"
            ),
        }
    }
}

/// A receiver's refusals by kind ([`WireFault`]), counted as they happen: the plant keeps
/// its torque refusals in a slot of their own ([`Refusals::SLOT`]) the moment it refuses
/// one, so the launcher can say what was wrong with a controller's answers (and sees a
/// refusal that ends no tick, as one for a tick not reached in lockstep). Not a wire
/// sample: a resume slot's content.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("rotorloop::Refusals_v1")]
#[repr(C)]
pub struct Refusals {
    /// Every refusal (the plant's `torques_rejected`, as of the last refusal).
    pub total: u64,
    /// NaN or infinite entries.
    pub non_finite: u64,
    /// Finite entries beyond the accepted magnitude.
    pub absurd: u64,
    /// A tick the loop has not reached.
    pub future_tick: u64,
    /// Another kind (an attitude off SO(3)).
    pub other: u64,
    /// The tick of the last sample refused.
    pub last_tick: u64,
}

impl Refusals {
    /// The resume-slot name of the plant's torque refusals.
    pub const SLOT: &'static str = "plant-refusals";

    /// Counts one refusal.
    #[inline]
    pub fn count(&mut self, tick: u64, f: &WireFault) {
        self.total += 1;
        match f {
            WireFault::NonFinite { .. } => self.non_finite += 1,
            WireFault::Absurd { .. } => self.absurd += 1,
            WireFault::FutureTick { .. } => self.future_tick += 1,
            WireFault::NotOrthonormal { .. } => self.other += 1,
        }
        self.last_tick = tick;
    }

    /// The refusals since `before` (counts that went back, a slot started again, count
    /// from zero).
    pub fn since(&self, before: &Self) -> Self {
        let d = |a: u64, b: u64| if a >= b { a - b } else { a };
        Self {
            total: d(self.total, before.total),
            non_finite: d(self.non_finite, before.non_finite),
            absurd: d(self.absurd, before.absurd),
            future_tick: d(self.future_tick, before.future_tick),
            other: d(self.other, before.other),
            last_tick: self.last_tick,
        }
    }

    /// The kinds refused, with their counts, in words: `250 with NaN or infinite torques,
    /// 3 for ticks not reached` (`none` when there were none).
    pub fn describe(&self) -> String {
        let kinds = [
            (self.non_finite, "with NaN or infinite torques"),
            (self.absurd, "with torques beyond the accepted magnitude"),
            (self.future_tick, "for ticks the loop had not reached"),
            (self.other, "otherwise invalid"),
        ];
        let said: Vec<String> =
            kinds.iter().filter(|(n, _)| *n > 0).map(|(n, what)| format!("{n} {what}")).collect();
        if said.is_empty() { "none".to_owned() } else { said.join(", ") }
    }
}

#[inline]
fn check_entries(field: &'static str, v: &[f64], limit: f64) -> Result<(), WireFault> {
    for &x in v {
        if !x.is_finite() {
            return Err(WireFault::NonFinite { field });
        }
        if x.abs() > limit {
            return Err(WireFault::Absurd { field, value: x, limit });
        }
    }
    Ok(())
}

/// The numbers the sweep of a good sample compares with ([`StateSample::validate`],
/// [`ReferenceSample::validate`]), each bound as `[-b, b]`, in one place read as data.
/// Folded into the code as constants they were five loads from the binary's constant
/// pool, on three pages shared with unrelated code: after a wait each was a miss of its
/// own (the validation of a state took about 250 ns where its work alone is about 35).
/// Two lines, asked for with the rest of the tick's ([`prefetch_sweep`]).
#[repr(C, align(64))]
struct Sweep {
    magnitude: [f64; 2],
    accumulated: [f64; 2],
    rotation_entry: [f64; 2],
    orthonormal: [f64; 2],
    /// `I`'s diagonal, for `RᵀR − I`.
    one: f64,
}

static SWEEP: Sweep = Sweep {
    magnitude: [-MAX_WIRE_MAGNITUDE, MAX_WIRE_MAGNITUDE],
    accumulated: [-MAX_WIRE_ACCUMULATED, MAX_WIRE_ACCUMULATED],
    rotation_entry: [-2.0, 2.0],
    orthonormal: [-WIRE_ORTHONORMAL_TOL, WIRE_ORTHONORMAL_TOL],
    one: 1.0,
};

/// [`SWEEP`], read from its line (not folded into the code).
#[inline(always)]
fn sweep() -> Sweep {
    // SAFETY: a read of a live, aligned static of plain f64s.
    unsafe { std::ptr::read_volatile(&SWEEP) }
}

/// Asks for the lines of the numbers a sample's validation compares with
/// ([`crate::prefetch`]).
#[inline(always)]
pub fn prefetch_sweep() {
    crate::prefetch::lines(&SWEEP);
    crate::prefetch::lines(&STATE_BOUNDS);
}

/// The bound of each number of a state's sweep ([`StateSample::validate`]), entry by
/// entry so that the sweep compares two at a time (`within_each`): `R` through `τ`
/// (24 numbers in a row from `r_row_major`), `h` and `p` (6 in a row), and `RᵀR − I`
/// on and below its diagonal with `det R − 1` and a 0 (8: [`rotation_residuals_lower`]).
/// Read as data, like [`SWEEP`]; five lines, prefetched with it.
#[repr(C, align(64))]
struct StateBounds {
    /// `-0.0`: the sign bit `|x|` clears.
    sign: [f64; 2],
    core: [f64; 24],
    internal: [f64; 6],
    orthonormal: [f64; 8],
}

static STATE_BOUNDS: StateBounds = {
    const M: f64 = MAX_WIRE_MAGNITUDE;
    const A: f64 = MAX_WIRE_ACCUMULATED;
    StateBounds {
        sign: [-0.0, -0.0],
        #[rustfmt::skip]
        core: [
            2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, // R's entries
            M, M, M, // ω
            M, M, M, // Ω
            A, A, A, // θ
            M, M, M, // u applied
            M, M, M, // τ applied
        ],
        internal: [A; 6],
        orthonormal: [WIRE_ORTHONORMAL_TOL; 8],
    }
};

// The state's numbers the two runs of bounds cover lie in a row, as `within_each` reads them.
const _: () = {
    use std::mem::offset_of;
    assert!(
        offset_of!(StateSample, applied_body_torque_nm) + 24
            == offset_of!(StateSample, r_row_major) + 8 * 24
    );
    assert!(offset_of!(StateSample, internal_p) == offset_of!(StateSample, internal_h) + 24);
};

/// Whether every `|v[i]| ≤ b[i]` (NaN and ±∞ fail): the same test as [`within`]'s
/// `[-b, b]`, two entries at a time with SSE2 (x86-64's baseline), one mask at the end.
/// `sign` is [`StateBounds::sign`]. Elsewhere, entry by entry.
#[inline(always)]
fn within_each<const N: usize>(v: &[f64; N], b: &[f64; N], sign: &[f64; 2]) -> bool {
    const { assert!(N % 2 == 0) };
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{
            _mm_and_pd, _mm_andnot_pd, _mm_cmple_pd, _mm_loadu_pd, _mm_movemask_pd,
        };
        // SAFETY: SSE2 is part of x86-64; every load reads two f64 within `v`, `b` or
        // `sign` (N is even).
        unsafe {
            let s = _mm_loadu_pd(sign.as_ptr());
            let pair = |i: usize| {
                let x = _mm_andnot_pd(s, _mm_loadu_pd(v.as_ptr().add(i)));
                _mm_cmple_pd(x, _mm_loadu_pd(b.as_ptr().add(i)))
            };
            let mut ok = pair(0);
            let mut i = 2;
            while i < N {
                ok = _mm_and_pd(ok, pair(i));
                i += 2;
            }
            _mm_movemask_pd(ok) == 3
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = sign;
        v.iter().zip(b).fold(true, |ok, (x, b)| ok & (x.abs() <= *b))
    }
}

/// [`STATE_BOUNDS`], its lines read (not folded into the code as constants).
#[inline(always)]
fn state_bounds() -> &'static StateBounds {
    std::hint::black_box(&STATE_BOUNDS)
}

/// Whether [`check_entries`] accepts `v` (every entry finite and within `b`: `[-limit,
/// limit]`), two comparisons per entry and no branch: NaN fails both, ±∞ one. The path of
/// a good sample; a refused one goes through [`check_entries`] for its fault.
#[inline(always)]
fn within(v: &[f64], [lo, hi]: [f64; 2]) -> bool {
    v.iter().fold(true, |ok, &x| ok & (lo <= x) & (x <= hi))
}

/// What SO(3) asks to be zero of `R` (row-major `m`): the nine entries of `RᵀR − I`
/// and `det R − 1`, with `one` for 1 (the sweep's own, [`Sweep::one`], read as data).
#[inline(always)]
fn rotation_residuals(m: &[f64; 9], one: f64) -> [f64; 10] {
    let r = mat(m);
    let g = (r.transpose() * r).to_cols_array();
    let mut res = [g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8], r.determinant()];
    for i in [0, 4, 8, 9] {
        res[i] -= one;
    }
    res
}

/// [`rotation_residuals`] on and below the diagonal of `RᵀR − I`, then `det R − 1` and a
/// 0 (eight, for the sweep's pairs). The three left out are the same numbers bit for bit:
/// entries `(i, j)` and `(j, i)` are the same three products summed in the same order, so
/// the verdict is the same, and their products are not computed.
#[inline(always)]
fn rotation_residuals_lower(m: &[f64; 9], one: f64) -> [f64; 8] {
    let r = rotation_residuals(m, one);
    [r[0], r[1], r[2], r[4], r[5], r[8], r[9], 0.0]
}

/// `R`'s deviation from SO(3): the largest entry of `|RᵀR − I|` and `|det R − 1|`.
#[inline]
fn rotation_deviation(m: &[f64; 9]) -> f64 {
    let res = rotation_residuals(m, 1.0);
    res[..9].iter().fold(res[9].abs(), |a, x| a.max(x.abs()))
}

/// Whether [`check_rotation`] accepts `m` (entries within 2 and on SO(3)), without a
/// branch per entry: every entry of `RᵀR − I` and `det R − 1` within the tolerance,
/// which is [`rotation_deviation`] ≤ it for the finite entries the first test lets
/// through.
#[inline(always)]
fn is_rotation(m: &[f64; 9], b: &Sweep) -> bool {
    within(m, b.rotation_entry) && within(&rotation_residuals(m, b.one), b.orthonormal)
}

#[inline]
fn check_rotation(field: &'static str, m: &[f64; 9]) -> Result<(), WireFault> {
    check_entries(field, m, 2.0)?;
    let dev = rotation_deviation(m);
    if dev > WIRE_ORTHONORMAL_TOL {
        return Err(WireFault::NotOrthonormal { field, deviation: dev });
    }
    Ok(())
}

impl StateSample {
    /// Checks every number a receiver uses: finite, plausible magnitudes, `R` on SO(3).
    /// A good sample passes every check in one sweep without a branch per number; a
    /// refused one is checked field by field for the first fault, which names the field.
    #[inline]
    pub fn validate(&self) -> Result<(), WireFault> {
        let (b, e) = (sweep(), state_bounds());
        let base = std::ptr::from_ref(self).cast::<u8>();
        // SAFETY: the numbers from `r_row_major` through `applied_body_torque_nm`, and
        // `internal_h` with `internal_p`, are f64 fields in a row (asserted at
        // `STATE_BOUNDS`), read through a pointer to the whole sample.
        let (core, internal) = unsafe {
            (
                &*base.add(std::mem::offset_of!(Self, r_row_major)).cast::<[f64; 24]>(),
                &*base.add(std::mem::offset_of!(Self, internal_h)).cast::<[f64; 6]>(),
            )
        };
        let good = within(&[self.t_s], b.accumulated)
            & within_each(core, &e.core, &e.sign)
            & within_each(internal, &e.internal, &e.sign);
        // `R`'s entries are within [-2, 2] (in `core`), as `is_rotation` asks first.
        if good
            && within_each(
                &rotation_residuals_lower(&self.r_row_major, b.one),
                &e.orthonormal,
                &e.sign,
            )
        {
            return Ok(());
        }
        self.first_fault()
    }

    /// The first check [`StateSample::validate`] refuses, field by field in the order of
    /// the wire contract.
    #[cold]
    fn first_fault(&self) -> Result<(), WireFault> {
        check_entries("state.t_s", &[self.t_s], MAX_WIRE_ACCUMULATED)?;
        check_rotation("state.r", &self.r_row_major)?;
        check_entries("state.omega_body", &self.omega_body_rad_s, MAX_WIRE_MAGNITUDE)?;
        check_entries("state.omega_rotor", &self.omega_rotor_rad_s, MAX_WIRE_MAGNITUDE)?;
        check_entries("state.theta_rotor", &self.theta_rotor_rad, MAX_WIRE_ACCUMULATED)?;
        check_entries(
            "state.applied_rotor_torque",
            &self.applied_rotor_torque_nm,
            MAX_WIRE_MAGNITUDE,
        )?;
        check_entries(
            "state.applied_body_torque",
            &self.applied_body_torque_nm,
            MAX_WIRE_MAGNITUDE,
        )?;
        check_entries("state.internal_h", &self.internal_h, MAX_WIRE_ACCUMULATED)?;
        check_entries("state.internal_p", &self.internal_p, MAX_WIRE_ACCUMULATED)
    }
}

impl ReferenceSample {
    /// Checks every number a receiver uses: finite, plausible magnitudes, `R_d` on SO(3).
    /// One sweep for a good sample, field by field for a refused one (as
    /// [`StateSample::validate`]).
    #[inline]
    pub fn validate(&self) -> Result<(), WireFault> {
        let b = sweep();
        let good = within(&[self.t_s], b.accumulated)
            & within(&self.omega_d_rad_s, b.magnitude)
            & within(&self.omega_d_dot_rad_s2, b.magnitude)
            & within(&self.omega_rotor_rad_s, b.magnitude)
            & within(&self.theta_rotor_rad, b.accumulated)
            & within(&self.internal_h, b.accumulated)
            & within(&self.internal_p, b.accumulated);
        if good && is_rotation(&self.r_d_row_major, &b) {
            return Ok(());
        }
        self.first_fault()
    }

    /// The first check [`ReferenceSample::validate`] refuses, field by field.
    #[cold]
    fn first_fault(&self) -> Result<(), WireFault> {
        check_entries("reference.t_s", &[self.t_s], MAX_WIRE_ACCUMULATED)?;
        check_rotation("reference.r_d", &self.r_d_row_major)?;
        check_entries("reference.omega_d", &self.omega_d_rad_s, MAX_WIRE_MAGNITUDE)?;
        check_entries("reference.omega_d_dot", &self.omega_d_dot_rad_s2, MAX_WIRE_MAGNITUDE)?;
        check_entries("reference.omega_rotor", &self.omega_rotor_rad_s, MAX_WIRE_MAGNITUDE)?;
        check_entries("reference.theta_rotor", &self.theta_rotor_rad, MAX_WIRE_ACCUMULATED)?;
        check_entries("reference.internal_h", &self.internal_h, MAX_WIRE_ACCUMULATED)?;
        check_entries("reference.internal_p", &self.internal_p, MAX_WIRE_ACCUMULATED)
    }

    /// Checks the tick against the newest state the plant has published: the reference
    /// runs at most [`REFERENCE_LEAD`] ticks ahead of it ([`TickBound`]).
    #[inline]
    pub fn check_tick(&self, newest_state: u64) -> Result<(), WireFault> {
        check_tick("reference.tick", self.tick, newest_state.saturating_add(REFERENCE_LEAD))
    }
}

impl TorqueSample {
    /// The largest torque entry a receiver accepts, given the rotor torque limit of the
    /// scenario (`None`: unlimited).
    pub fn absurd_limit(rotor_torque_limit: Option<f64>) -> f64 {
        rotor_torque_limit
            .map_or(MAX_WIRE_MAGNITUDE, |u| (u * ABSURD_TORQUE_FACTOR).min(MAX_WIRE_MAGNITUDE))
    }

    /// Checks the torques against `limit` (see [`TorqueSample::absurd_limit`]).
    #[inline]
    pub fn validate(&self, limit: f64) -> Result<(), WireFault> {
        check_entries("torque.rotor_torque", &self.rotor_torque_nm, limit)?;
        check_entries("torque.body_torque", &self.body_torque_nm, limit)
    }

    /// Whether the controller computed this tick (not [`TORQUE_SKIPPED`]).
    #[inline]
    pub fn computed(&self) -> bool {
        self.flags & TORQUE_SKIPPED == 0
    }

    /// Checks the tick against the newest state the plant has published: a torque answers
    /// a state, so its tick is at most that state's ([`TickBound`]).
    #[inline]
    pub fn check_tick(&self, newest_state: u64) -> Result<(), WireFault> {
        check_tick("torque.tick", self.tick, newest_state)
    }
}

#[inline]
fn check_tick(field: &'static str, tick: u64, allowed: u64) -> Result<(), WireFault> {
    match tick <= allowed {
        true => Ok(()),
        false => Err(WireFault::FutureTick { field, tick, allowed }),
    }
}

/// The tick rule: a receiver refuses a torque or a reference for a tick the loop has not
/// reached. A torque answers a state the plant has published, so its tick is at most the
/// newest state's; the reference publishes at most [`REFERENCE_LEAD`] ticks ahead of the
/// newest state. Accepted, a sample beyond would be "the newest" for ever after and every
/// true one after it "older" (one valid zero torque for tick 10¹² silenced control for the
/// rest of a run). It is rejected ([`WireFault::FutureTick`]), counted, and not counted as
/// received (its tick would make every tick before it a loss). An older tick is no fault:
/// each receiver has its rule for those (the plant ignores a torque older than the one in
/// force).
///
/// The plant knows its newest state exactly ([`TorqueSample::check_tick`] with the tick it
/// waits for). Another receiver knows the newest state it has taken, which may be behind
/// the plant's (a torque taken before its state; the reference saw a newer state than the
/// controller has): a sample beyond that is checked again against the newest state the
/// plant has **published** (`published`: its resume slot, stored just before each state
/// is published, so no true sample is beyond it), read only then, off the common path.
/// Where this host has none (`None`: the other host of a split run, or before the plant's
/// first state) the run's last tick stands in, and only ticks the run never reaches are
/// refused.
#[derive(Debug, Clone, Copy)]
pub struct TickBound {
    newest: u64,
    last: u64,
}

impl TickBound {
    /// No state seen yet (tick 0 stands in), in a run whose last tick is `last`.
    pub fn new(last: u64) -> Self {
        Self { newest: 0, last }
    }

    /// A state of tick `tick` was taken (or resumed from).
    #[inline]
    pub fn saw_state(&mut self, tick: u64) {
        self.newest = self.newest.max(tick);
    }

    /// The newest state tick known.
    pub fn newest(&self) -> u64 {
        self.newest
    }

    /// Checks torque `t`'s tick; `published` is asked only when it is beyond the newest
    /// state known.
    #[inline]
    pub fn torque(
        &mut self,
        t: &TorqueSample,
        published: impl FnOnce() -> Option<u64>,
    ) -> Result<(), WireFault> {
        self.check(|n| t.check_tick(n), published)
    }

    /// Checks reference `r`'s tick; `published` is asked only when it is beyond the newest
    /// state known and its lead.
    #[inline]
    pub fn reference(
        &mut self,
        r: &ReferenceSample,
        published: impl FnOnce() -> Option<u64>,
    ) -> Result<(), WireFault> {
        self.check(|n| r.check_tick(n), published)
    }

    #[inline]
    fn check(
        &mut self,
        rule: impl Fn(u64) -> Result<(), WireFault>,
        published: impl FnOnce() -> Option<u64>,
    ) -> Result<(), WireFault> {
        if rule(self.newest).is_ok() {
            return Ok(());
        }
        match published() {
            Some(p) => {
                self.saw_state(p);
                rule(self.newest)
            }
            None => rule(self.newest.max(self.last)),
        }
    }
}

fn mat(m: &[f64; 9]) -> DMat3 {
    from_rows([[m[0], m[1], m[2]], [m[3], m[4], m[5]], [m[6], m[7], m[8]]])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_sample_round_trips_the_body_state_exactly() {
        let x = RotorBodyState {
            r: crate::so3::exp(DVec3::new(0.3, -0.2, 1.1)),
            omega: DVec3::new(0.1, 0.2, 0.3),
            omega_r: DVec3::new(-1.0, 2.0, 1.0 / 3.0),
            theta: DVec3::new(5.0, 6.0, 7.0),
        };
        assert_eq!(StateSample::of(3, 0.003, &x).body_state(), x);
    }

    fn good_state() -> StateSample {
        let x = RotorBodyState {
            r: crate::so3::exp(DVec3::new(0.3, -0.2, 1.1)),
            omega: DVec3::new(0.1, 0.2, 0.3),
            omega_r: DVec3::new(-1.0, 2.0, 0.5),
            theta: DVec3::new(5.0, 6.0, 7.0),
        };
        StateSample::of(3, 0.003, &x)
    }

    #[test]
    fn validation_names_the_field_and_the_kind_of_every_bad_value() {
        assert_eq!(good_state().validate(), Ok(()));
        let mut s = good_state();
        s.omega_rotor_rad_s[2] = f64::NAN;
        assert_eq!(s.validate(), Err(WireFault::NonFinite { field: "state.omega_rotor" }));
        let mut s = good_state();
        s.omega_body_rad_s[0] = -2e6;
        assert!(matches!(s.validate(), Err(WireFault::Absurd { field: "state.omega_body", .. })));
        let mut s = good_state();
        s.r_row_major[4] *= 1.0 + 1e-5;
        let e = s.validate().expect_err("skewed R");
        assert_eq!((e.kind(), e.field()), ("non-orthonormal", "state.r"));
        assert!(e.to_string().contains("state.r is not a rotation"), "{e}");
        // Rounding-level deviations of a real integrator pass.
        let mut s = good_state();
        s.r_row_major[4] *= 1.0 + 1e-12;
        assert_eq!(s.validate(), Ok(()));
    }

    /// The one-sweep path of a good state gives the same verdict as the field-by-field
    /// checks for every checked number made NaN, infinite, beyond its bound or just
    /// within it: no check of the wire contract is given up, and a refusal still names
    /// the first field that fails.
    #[test]
    fn the_sweep_of_a_good_state_refuses_what_the_field_checks_refuse() {
        type Field = fn(&mut StateSample) -> &mut [f64];
        let fields: [(Field, f64); 9] = [
            (|s| std::slice::from_mut(&mut s.t_s), MAX_WIRE_ACCUMULATED),
            (|s| &mut s.r_row_major, 2.0),
            (|s| &mut s.omega_body_rad_s, MAX_WIRE_MAGNITUDE),
            (|s| &mut s.omega_rotor_rad_s, MAX_WIRE_MAGNITUDE),
            (|s| &mut s.theta_rotor_rad, MAX_WIRE_ACCUMULATED),
            (|s| &mut s.applied_rotor_torque_nm, MAX_WIRE_MAGNITUDE),
            (|s| &mut s.applied_body_torque_nm, MAX_WIRE_MAGNITUDE),
            (|s| &mut s.internal_h, MAX_WIRE_ACCUMULATED),
            (|s| &mut s.internal_p, MAX_WIRE_ACCUMULATED),
        ];
        let (mut refused, mut passed) = (0, 0);
        for (field, bound) in fields {
            let n = field(&mut good_state()).len();
            for i in 0..n {
                for v in [f64::NAN, f64::INFINITY, -f64::INFINITY, 1.5 * bound, -bound, 0.0] {
                    let mut s = good_state();
                    field(&mut s)[i] = v;
                    assert_eq!(s.validate(), s.first_fault(), "entry {i} of a field = {v}");
                    match s.validate() {
                        Ok(()) => passed += 1,
                        Err(_) => refused += 1,
                    }
                }
            }
        }
        // Both verdicts were exercised: NaN, ∞ and beyond the bound refused everywhere.
        assert_eq!(refused, 4 * 31 + 9 * 2, "{refused} refused, {passed} passed");
    }

    /// Near the tolerance the sweep's rotation test (`RᵀR − I` and `det R − 1` each
    /// within it) and the field path's deviation (their largest magnitude) give the same
    /// verdict (the sweep alone: where it refuses, `validate` asks the field path), for a stretched, a sheared and a rotated-then-stretched `R`, on both sides
    /// of the tolerance, for the state and the reference.
    #[test]
    fn the_sweep_and_the_deviation_agree_on_a_rotation_at_the_tolerance() {
        let (c, s) = (0.6_f64, 0.8_f64);
        let turned = [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0];
        let (mut accepted, mut refused) = (0, 0);
        for base in [[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], turned] {
            for k in 0..=40 {
                let e = WIRE_ORTHONORMAL_TOL * (k as f64) / 40.0;
                // Entry `i` scaled by `f` and moved by `d`: three stretched, then three
                // sheared by up to twice the tolerance (each entry of `RᵀR` off the
                // diagonal, and its mirror, beyond it in turn).
                let (grow, shear) = (|f: f64| (f, 0.0), (1.0, 2.0 * e));
                let moves =
                    [(4, grow(1.0 + e / 2.0)), (0, grow(1.0 - e / 2.0)), (8, grow(1.0 + e))];
                for (i, (f, d)) in moves.into_iter().chain([(1, shear), (2, shear), (5, shear)]) {
                    let mut m = base;
                    m[i] = base[i] * f + d;
                    let want = rotation_deviation(&m) <= WIRE_ORTHONORMAL_TOL;
                    // The sweep by itself: a refusal of it falls back to the field path.
                    assert_eq!(is_rotation(&m, &sweep()), want, "R = {m:?}");
                    let mut st = good_state();
                    st.r_row_major = m;
                    assert_eq!(st.validate().is_ok(), want, "state, R = {m:?}");
                    assert_eq!(st.validate(), st.first_fault(), "state, R = {m:?}");
                    let mut r = ReferenceSample::zeroed(1);
                    r.r_d_row_major = m;
                    assert_eq!(r.validate(), r.first_fault(), "reference, R_d = {m:?}");
                    if want { accepted += 1 } else { refused += 1 }
                }
            }
        }
        assert!(
            accepted > 20 && refused > 20,
            "both sides: {accepted} accepted, {refused} refused"
        );
    }

    /// `RᵀR − I` is symmetric bit for bit (what lets the sweep leave out the three
    /// entries above the diagonal), for matrices near and far from SO(3).
    #[test]
    fn the_residuals_above_the_diagonal_are_those_below_bit_for_bit() {
        let mut x = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64 * 4.0 - 2.0
        };
        for _ in 0..10_000 {
            let m: [f64; 9] = std::array::from_fn(|_| next());
            let r = rotation_residuals(&m, 1.0);
            for (below, above) in [(1, 3), (2, 6), (5, 7)] {
                assert_eq!(r[below].to_bits(), r[above].to_bits(), "R = {m:?}");
            }
        }
    }

    #[test]
    fn torque_validation_scales_with_the_configured_limit() {
        let t = TorqueSample { tick: 1, rotor_torque_nm: [3.0, -2.0, 900.0], ..Default::default() };
        // Unlimited actuators: anything up to 1e6 N m passes.
        assert_eq!(t.validate(TorqueSample::absurd_limit(None)), Ok(()));
        // u_max = 1 N m: 900 is saturation, not yet absurd; 1001 is.
        assert_eq!(t.validate(TorqueSample::absurd_limit(Some(1.0))), Ok(()));
        let t2 = TorqueSample { rotor_torque_nm: [0.0, 0.0, 1001.0], ..t };
        assert!(matches!(
            t2.validate(TorqueSample::absurd_limit(Some(1.0))),
            Err(WireFault::Absurd { field: "torque.rotor_torque", .. })
        ));
        let t3 = TorqueSample { body_torque_nm: [f64::INFINITY, 0.0, 0.0], ..t };
        assert_eq!(t3.validate(1e6), Err(WireFault::NonFinite { field: "torque.body_torque" }));
        assert!(t.computed());
        assert!(!TorqueSample { flags: TORQUE_SKIPPED, ..t }.computed());
    }

    #[test]
    fn a_tick_the_loop_has_not_reached_is_refused_naming_the_field_and_what_is_accepted() {
        let t = |tick| TorqueSample { tick, ..Default::default() };
        assert_eq!(t(10).check_tick(10), Ok(()), "the answer to the newest state");
        assert_eq!(t(3).check_tick(10), Ok(()), "an older one is the receiver's business");
        let e = t(1_000_000_000_000).check_tick(10).expect_err("future");
        assert_eq!((e.kind(), e.field()), ("future-tick", "torque.tick"));
        assert_eq!(
            e.to_string(),
            "torque.tick is 1000000000000, a tick the loop has not reached (accepted up to 10)"
        );
        let r = ReferenceSample::zeroed;
        assert_eq!(r(10 + REFERENCE_LEAD).check_tick(10), Ok(()), "the reference's lead");
        let e = r(11 + REFERENCE_LEAD).check_tick(10).expect_err("beyond the lead");
        assert_eq!(e, WireFault::FutureTick { field: "reference.tick", tick: 27, allowed: 26 });
        assert_eq!(r(u64::MAX).check_tick(u64::MAX), Ok(()), "no overflow");
    }

    #[test]
    fn the_tick_bound_asks_what_the_plant_published_only_beyond_the_newest_state_known() {
        let t = |tick| TorqueSample { tick, ..Default::default() };
        let never = || -> Option<u64> { panic!("asked on the common path") };
        let mut b = TickBound::new(1000);
        assert_eq!(b.torque(&t(0), never), Ok(()), "start-up: tick 0");
        assert_eq!(b.reference(&ReferenceSample::zeroed(REFERENCE_LEAD), never), Ok(()));
        b.saw_state(5);
        assert_eq!(b.torque(&t(5), never), Ok(()));
        // Taken before its state: the plant's slot says state 7 is out.
        assert_eq!(b.torque(&t(7), || Some(7)), Ok(()));
        assert_eq!(b.newest(), 7);
        assert_eq!(b.torque(&t(7), never), Ok(()), "remembered");
        let far = b.torque(&t(1_000_000_000_000), || Some(8)).expect_err("future");
        assert_eq!(far.kind(), "future-tick");
        assert_eq!(b.newest(), 8);
        // No plant on this host: only ticks beyond the run's last are refused, and the
        // stand-in is not remembered.
        assert_eq!(b.torque(&t(1000), || None), Ok(()));
        assert_eq!(b.newest(), 8);
        assert_eq!(
            b.torque(&t(1001), || None),
            Err(WireFault::FutureTick { field: "torque.tick", tick: 1001, allowed: 1000 })
        );
        b.saw_state(3);
        assert_eq!(b.newest(), 8, "an older state does not move it back");
    }

    #[test]
    fn refusals_are_counted_by_kind_and_said_since_a_point() {
        let mut r = Refusals::default();
        assert_eq!(r.describe(), "none");
        r.count(3, &WireFault::NonFinite { field: "torque.rotor_torque" });
        let before = r;
        let absurd = WireFault::Absurd { field: "torque.body_torque", value: 1e9, limit: 1e3 };
        r.count(4, &absurd);
        r.count(9, &WireFault::FutureTick { field: "torque.tick", tick: 9, allowed: 5 });
        r.count(10, &WireFault::FutureTick { field: "torque.tick", tick: 10, allowed: 5 });
        assert_eq!((r.total, r.non_finite, r.absurd, r.future_tick, r.last_tick), (4, 1, 1, 2, 10));
        let d = r.since(&before);
        assert_eq!((d.total, d.non_finite, d.absurd, d.future_tick), (3, 0, 1, 2));
        assert_eq!(
            d.describe(),
            "1 with torques beyond the accepted magnitude, 2 for ticks the loop had not reached"
        );
        // A slot started again (counts below the point): counted from zero.
        assert_eq!(before.since(&r).total, 1);
    }

    #[test]
    fn type_names_carry_the_layout_version() {
        use iceoryx2::prelude::ZeroCopySend;
        let v = format!("_v{LAYOUT_VERSION}");
        // SAFETY: type_name only returns the static name.
        for name in unsafe {
            [StateSample::type_name(), ReferenceSample::type_name(), TorqueSample::type_name()]
        } {
            assert!(name.ends_with(&v), "{name}");
        }
    }
}
