//! rotorloop's C API (`include/rotorloop.h`): what a controller written in C, C++ or
//! generated C needs to take the controller's place in a run, through the same ports the
//! built-in controller opens (docs/wire.md). The library is `librotorloop_c.so`, built by
//! `cargo build --release --workspace` into `target/release/`.
//!
//! One handle, [`RotorloopController`], made once by [`rotorloop_controller_open`]:
//! the node `rotorloop/<D>/controller`, the torque publisher and its notifier, the state
//! and reference subscribers (and their event listeners when the wait is `event` or
//! `hybrid`), and a ring of the last [`REFERENCE_RING`] references by tick. After that the
//! library allocates nothing per tick (a publish allocates only what iceoryx2's loan and
//! send of a sample do: `tests/no_alloc.rs`), starts no thread and keeps none: every
//! call runs on the caller's thread and returns. A call that fails returns an error code and
//! leaves its message for [`rotorloop_last_error`].
//!
//! The per-tick calls: [`rotorloop_controller_receive_state`] (the newest state, waiting
//! for one up to a timeout), [`rotorloop_controller_reference`] (the reference of a tick,
//! waiting for it up to a timeout), [`rotorloop_controller_loan`] (a zeroed torque sample
//! in shared memory, written in place) and [`rotorloop_controller_publish`] (stamps it,
//! sends it, wakes the plant and the monitor). [`rotorloop_controller_close`] waits for
//! the readers to take the last answers and frees everything.

use std::cell::RefCell;
use std::ffi::{CStr, CString, c_char};

use rotorloop_common::clock::now_ns;
use rotorloop_common::controller_json::ControllerJson;
use rotorloop_common::graph::Topic;
use rotorloop_common::ipc::IpcError;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::ipc::ports::{Inbox, Outbox, RoleNode};
use rotorloop_common::ipc::wait::Wait;
use rotorloop_common::wire::{NO_TICK, ReferenceSample, SendCost, StateSample, TorqueSample};

/// References kept, by tick (`tick % REFERENCE_RING`): the reference runs up to 16 ticks
/// ahead of the plant, and a controller pairs the state it takes with one of them.
pub const REFERENCE_RING: usize = 64;

/// How far beyond the newest state taken a reference is accepted: the reference's lead
/// (16 ticks, `REFERENCE_LEAD`) plus the states a controller may not have taken yet.
const REFERENCE_ACCEPT_AHEAD: u64 = 48;

/// What a call returns (`rotorloop_status` in the header).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RotorloopStatus {
    /// Done.
    Ok = 0,
    /// Nothing arrived before the timeout: not an error (look again, or give up).
    Timeout = 1,
    /// A null pointer, a string that is not UTF-8, a bad domain name or wait mode.
    ErrArgument = 2,
    /// A live controller already holds this domain's controller node.
    ErrRoleTaken = 3,
    /// The domain's services carry another layout version (another rotorloop build).
    ErrLayout = 4,
    /// iceoryx2 refused (open, loan, send, receive, wait).
    ErrIpc = 5,
    /// `controller.json` cannot be read, parsed, or has another layout version.
    ErrConfig = 6,
    /// A call out of order: publish without a loan, a second loan before the publish.
    ErrOrder = 7,
}

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

/// Records `msg` as this thread's last error and returns `status`.
fn fail(status: RotorloopStatus, msg: impl std::fmt::Display) -> RotorloopStatus {
    let text = CString::new(msg.to_string().replace('\0', " ")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = text);
    status
}

/// A call's status from its body, which returns a failure's status early (with `?`).
fn status(body: impl FnOnce() -> Result<RotorloopStatus, RotorloopStatus>) -> RotorloopStatus {
    body().unwrap_or_else(|s| s)
}

/// `p`, or an argument error naming the call and the argument where it is null.
fn non_null<T>(p: *mut T, call: &str, what: &str) -> Result<*mut T, RotorloopStatus> {
    match p.is_null() {
        true => Err(fail(RotorloopStatus::ErrArgument, format!("{call}: {what} is NULL"))),
        false => Ok(p),
    }
}

/// An iceoryx2 error as a status.
fn ipc_fail(e: &IpcError) -> RotorloopStatus {
    let status = match e {
        IpcError::Domain(_) => RotorloopStatus::ErrArgument,
        IpcError::DuplicateRole { .. } => RotorloopStatus::ErrRoleTaken,
        IpcError::LayoutSkew { .. } => RotorloopStatus::ErrLayout,
        _ => RotorloopStatus::ErrIpc,
    };
    fail(status, e)
}

/// The message of the last call that failed on this thread (UTF-8, NUL-terminated; ""
/// if none). Valid until the next failing call on the same thread.
#[unsafe(no_mangle)]
pub extern "C" fn rotorloop_last_error() -> *const c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}

/// `CLOCK_MONOTONIC` in ns: the clock of every stamp on the wire.
#[unsafe(no_mangle)]
pub extern "C" fn rotorloop_now_ns() -> u64 {
    now_ns()
}

/// A C string argument, or `env` when it is null.
///
/// # Safety
/// `s` is null or a NUL-terminated string.
unsafe fn arg_or_env(s: *const c_char, what: &str, env: &str) -> Result<String, RotorloopStatus> {
    if s.is_null() {
        return std::env::var(env).map_err(|_| {
            fail(
                RotorloopStatus::ErrArgument,
                format!("{what} is NULL and ${env} is not set (start the program with rotorloop run --controller-cmd)"),
            )
        });
    }
    // SAFETY: the caller passes a NUL-terminated string.
    let c = unsafe { CStr::from_ptr(s) };
    c.to_str()
        .map(str::to_owned)
        .map_err(|_| fail(RotorloopStatus::ErrArgument, format!("{what} is not UTF-8")))
}

/// The law's parameters from `controller.json`, as C reads them (`rotorloop_law_config`).
/// Matrices row-major; a limit that is not set is 0 with its `has_` flag 0.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotorloopLawConfig {
    /// `controller.json`'s `layout_version`.
    pub layout_version: u64,
    /// The law's name, NUL-terminated (`geometric-pid`, `mrp-pid`).
    pub law: [c_char; 32],
    /// 1: internal actuation (answer with the rotor torque `u`); 0: external (`τ`).
    pub internal_actuation: u64,
    /// Ticks in the run.
    pub ticks: u64,
    /// The tick (s).
    pub dt_s: f64,
    /// The rate (Hz).
    pub rate_hz: f64,
    /// `k_p`.
    pub kp: f64,
    /// `k_d`.
    pub kd: f64,
    /// `k_i`.
    pub ki: f64,
    /// `P`, row-major.
    pub p_row_major: [f64; 9],
    /// The model of `I`, row-major (kg m²).
    pub inertia_row_major: [f64; 9],
    /// The model of `K`'s diagonal (kg m²).
    pub rotor_inertia: [f64; 3],
    /// Whether `rotor_torque_limit_nm` is set.
    pub has_rotor_torque_limit: u64,
    /// `u_max` (N m).
    pub rotor_torque_limit_nm: f64,
    /// Whether `rotor_rate_limit_rad_s` is set.
    pub has_rotor_rate_limit: u64,
    /// `Ω_max` (rad/s).
    pub rotor_rate_limit_rad_s: f64,
    /// 1: conditional integration (`anti_windup = "conditional"`); 0: none.
    pub anti_windup_conditional: u64,
}
const _: () = assert!(size_of::<RotorloopLawConfig>() == 304);

/// Reads `controller.json` (`path`, or `$ROTORLOOP_CONTROLLER_JSON` when null) into
/// `out`. `ErrConfig` when it cannot be read or parsed, or has another layout version
/// than this library's.
///
/// # Safety
/// `path` is null or a NUL-terminated string; `out` points to a writable
/// `rotorloop_law_config`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn rotorloop_law_config_load(
    path: *const c_char,
    out: *mut RotorloopLawConfig,
) -> RotorloopStatus {
    status(|| {
        let out = non_null(out, "rotorloop_law_config_load", "out")?;
        // SAFETY: the caller's string.
        let path = unsafe { arg_or_env(path, "path", "ROTORLOOP_CONTROLLER_JSON") }?;
        let c = load_config(&path)
            .map_err(|e| fail(RotorloopStatus::ErrConfig, format!("{path}: {e:#}")))?;
        // SAFETY: checked non-null; the caller's writable struct.
        unsafe { out.write(c) };
        Ok(RotorloopStatus::Ok)
    })
}

/// `controller.json` at `path` as the C struct.
fn load_config(path: &str) -> anyhow::Result<RotorloopLawConfig> {
    use anyhow::Context;
    let text = std::fs::read_to_string(path).context("cannot read")?;
    let j: ControllerJson = serde_json::from_str(&text).context("not a controller.json")?;
    let version = rotorloop_common::controller_json::CONTROLLER_JSON_VERSION;
    anyhow::ensure!(
        j.layout_version == version,
        "layout_version {} is not this library's {version}: rebuild against the run's rotorloop",
        j.layout_version
    );
    let mut law = [0 as c_char; 32];
    anyhow::ensure!(j.law.len() < law.len(), "law `{}` is longer than 31 bytes", j.law);
    for (d, s) in law.iter_mut().zip(j.law.bytes()) {
        *d = s as c_char;
    }
    let rows = |m: [[f64; 3]; 3]| std::array::from_fn(|i| m[i / 3][i % 3]);
    Ok(RotorloopLawConfig {
        layout_version: u64::from(j.layout_version),
        law,
        internal_actuation: u64::from(j.actuation == "internal"),
        ticks: j.ticks,
        dt_s: j.dt_s,
        rate_hz: j.rate_hz,
        kp: j.gains.kp,
        kd: j.gains.kd,
        ki: j.gains.ki,
        p_row_major: rows(j.gains.p),
        inertia_row_major: rows(j.model.inertia),
        rotor_inertia: j.model.rotor_inertia,
        has_rotor_torque_limit: u64::from(j.limits.rotor_torque_nm.is_some()),
        rotor_torque_limit_nm: j.limits.rotor_torque_nm.unwrap_or(0.0),
        has_rotor_rate_limit: u64::from(j.limits.rotor_rate_rad_s.is_some()),
        rotor_rate_limit_rad_s: j.limits.rotor_rate_rad_s.unwrap_or(0.0),
        anti_windup_conditional: u64::from(j.anti_windup == "conditional"),
    })
}

/// A controller's port of a run's domain (`rotorloop_controller` in the header).
#[derive(Debug)]
pub struct RotorloopController {
    out: Outbox<TorqueSample>,
    states: Inbox<StateSample>,
    refs: Inbox<ReferenceSample>,
    wait: Wait,
    /// The references by `tick % REFERENCE_RING` (a slot's tick says which it holds).
    ring: [ReferenceSample; REFERENCE_RING],
    /// The newest state tick taken, or [`NO_TICK`].
    newest_state: u64,
    /// Whether a loaned sample waits for its publish.
    loaned: bool,
    /// The tick and cost of the last publish (carried in the next sample).
    last_publish: (u64, SendCost),
    states_received: u64,
    states_skipped: u64,
    references_rejected: u64,
    published: u64,
    // Last: the node outlives the ports (fields drop in order).
    _node: RoleNode,
    _domain: Domain,
}

/// Opens the controller's ports of run domain `domain` (null: `$ROTORLOOP_DOMAIN`),
/// waiting as `wait` says (`event`, `spin` or `hybrid`; null: `$ROTORLOOP_WAIT`, or
/// `event` when unset), with the QoS every rotorloop process uses. On success `*out` is
/// the handle; free it with [`rotorloop_controller_close`].
///
/// # Safety
/// `domain` and `wait` are null or NUL-terminated strings; `out` points to a writable
/// pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn rotorloop_controller_open(
    domain: *const c_char,
    wait: *const c_char,
    out: *mut *mut RotorloopController,
) -> RotorloopStatus {
    status(|| {
        let out = non_null(out, "rotorloop_controller_open", "out")?;
        // SAFETY: the caller's strings.
        let (name, wait) =
            unsafe { (arg_or_env(domain, "domain", "ROTORLOOP_DOMAIN"), wait_arg(wait)) };
        let c = open(&name?, wait?).map_err(|e| ipc_fail(&e))?;
        // SAFETY: checked non-null; the caller's writable pointer.
        unsafe { out.write(Box::into_raw(c)) };
        Ok(RotorloopStatus::Ok)
    })
}

/// The wait mode argument, or `$ROTORLOOP_WAIT`, or `event`.
///
/// # Safety
/// `wait` is null or a NUL-terminated string.
unsafe fn wait_arg(wait: *const c_char) -> Result<Wait, RotorloopStatus> {
    let text = if wait.is_null() {
        std::env::var("ROTORLOOP_WAIT").unwrap_or_else(|_| "event".into())
    } else {
        // SAFETY: the caller's string.
        unsafe { arg_or_env(wait, "wait", "ROTORLOOP_WAIT")? }
    };
    text.parse().map_err(|e| fail(RotorloopStatus::ErrArgument, format!("wait: {e}")))
}

/// The ports, opened in the built-in controller's order (the state subscriber last: the
/// plant starts when it sees its state subscribers).
fn open(name: &str, wait: Wait) -> Result<Box<RotorloopController>, IpcError> {
    rotorloop_common::ipc::quiet_iceoryx_logs();
    let domain = Domain::new(name)?;
    let node = domain.node(rotorloop_common::graph::Role::Controller.name())?;
    let out = domain.outbox::<TorqueSample>(&node, Topic::Torque)?;
    let refs = domain.inbox::<ReferenceSample>(&node, Topic::Reference, 128, wait.listens())?;
    let states = domain.inbox::<StateSample>(&node, Topic::State, 8, wait.listens())?;
    let empty = empty_reference();
    Ok(Box::new(RotorloopController {
        out,
        states,
        refs,
        wait,
        ring: [empty; REFERENCE_RING],
        newest_state: NO_TICK,
        loaned: false,
        last_publish: (NO_TICK, SendCost::default()),
        states_received: 0,
        states_skipped: 0,
        references_rejected: 0,
        published: 0,
        _node: node,
        _domain: domain,
    }))
}

/// The handle behind a C pointer, or an argument error naming the call.
///
/// # Safety
/// `c` is null or a handle from [`rotorloop_controller_open`] not closed yet.
unsafe fn handle<'a>(
    c: *mut RotorloopController,
    call: &str,
) -> Result<&'a mut RotorloopController, RotorloopStatus> {
    // SAFETY: the caller's handle.
    unsafe { c.as_mut() }
        .ok_or_else(|| fail(RotorloopStatus::ErrArgument, format!("{call}: the handle is NULL")))
}

/// Takes every state waiting; the newest goes to `*state` (the older ones are skipped and
/// counted), with the time it was taken in `*recv_ns`. Waits for one up to `timeout_ns`
/// (0: only looks): `Timeout` when none came. This is "wait for the next state" and
/// "receive the newest" in one call.
///
/// # Safety
/// `c` is an open handle; `state` points to a writable `StateSample`; `recv_ns` is null
/// or writable.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn rotorloop_controller_receive_state(
    c: *mut RotorloopController,
    timeout_ns: u64,
    state: *mut StateSample,
    recv_ns: *mut u64,
) -> RotorloopStatus {
    const CALL: &str = "rotorloop_controller_receive_state";
    status(|| {
        // SAFETY: the caller's handle.
        let c = unsafe { handle(c, CALL) }?;
        let state = non_null(state, CALL, "state")?;
        let deadline = now_ns().saturating_add(timeout_ns);
        let (mut received, mut skipped) = (0u64, 0u64);
        let newest = c.states.wait_for(c.wait, deadline, |inbox| {
            let mut newest: Option<StateSample> = None;
            inbox.drain(|s| {
                received += 1;
                skipped += u64::from(newest.is_some());
                newest = Some(s);
            })?;
            Ok(newest.map(|s| (s, now_ns())))
        });
        c.states_received += received;
        c.states_skipped += skipped;
        let Some((s, t)) = newest.map_err(|e| ipc_fail(&e))? else {
            return Ok(RotorloopStatus::Timeout);
        };
        c.newest_state = s.tick;
        // SAFETY: checked non-null; the caller's writable sample and stamp.
        unsafe {
            state.write(s);
            if !recv_ns.is_null() {
                recv_ns.write(t);
            }
        }
        Ok(RotorloopStatus::Ok)
    })
}

/// Puts reference `r` into `ring`, unless it is beyond the newest state taken
/// (`newest`) and [`REFERENCE_ACCEPT_AHEAD`]: refused and counted in `rejected` (it would
/// displace a true one).
fn store(
    ring: &mut [ReferenceSample; REFERENCE_RING],
    newest: u64,
    rejected: &mut u64,
    r: ReferenceSample,
) {
    let ahead = newest != NO_TICK && r.tick > newest.saturating_add(REFERENCE_ACCEPT_AHEAD);
    if ahead || r.tick == NO_TICK {
        *rejected += 1;
    } else {
        ring[(r.tick % REFERENCE_RING as u64) as usize] = r;
    }
}

/// A reference sample of no tick ([`NO_TICK`]), every number 0.
fn empty_reference() -> ReferenceSample {
    // SAFETY: every field is an integer or a float (or an array of them): all-zero bytes
    // are a valid value.
    let mut r: ReferenceSample = unsafe { std::mem::zeroed() };
    r.tick = NO_TICK;
    r
}

/// The reference of `tick` if `ring` holds it.
fn lookup(ring: &[ReferenceSample; REFERENCE_RING], tick: u64) -> Option<ReferenceSample> {
    let r = ring[(tick % REFERENCE_RING as u64) as usize];
    (r.tick == tick).then_some(r)
}

/// The reference of tick `tick` into `*reference`, waiting for it up to `timeout_ns`
/// (0: only looks). `Timeout` when it did not come: `*reference` is then the newest
/// reference the library holds for an earlier tick (its `tick` says which; `NO_TICK`
/// when none), for a controller that propagates it.
///
/// # Safety
/// `c` is an open handle; `reference` points to a writable `ReferenceSample`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn rotorloop_controller_reference(
    c: *mut RotorloopController,
    tick: u64,
    timeout_ns: u64,
    reference: *mut ReferenceSample,
) -> RotorloopStatus {
    const CALL: &str = "rotorloop_controller_reference";
    status(|| {
        // SAFETY: the caller's handle.
        let c = unsafe { handle(c, CALL) }?;
        let reference = non_null(reference, CALL, "reference")?;
        let deadline = now_ns().saturating_add(timeout_ns);
        let RotorloopController { refs, ring, newest_state, references_rejected, wait, .. } = c;
        // In hand: no look at the topic (the reference works ahead and publishes in batches).
        let found = match lookup(ring, tick) {
            Some(r) => Some(r),
            None => refs
                .wait_for(*wait, deadline, |inbox| {
                    inbox.drain(|r| store(ring, *newest_state, references_rejected, r))?;
                    Ok(lookup(ring, tick))
                })
                .map_err(|e| ipc_fail(&e))?,
        };
        let out = found.unwrap_or_else(|| {
            let earlier = c.ring.iter().filter(|r| r.tick != NO_TICK && r.tick < tick);
            earlier.max_by_key(|r| r.tick).copied().unwrap_or(empty_reference())
        });
        // SAFETY: checked non-null; the caller's writable sample.
        unsafe { reference.write(out) };
        Ok(if found.is_some() { RotorloopStatus::Ok } else { RotorloopStatus::Timeout })
    })
}

/// A torque sample in shared memory for the next publish, every byte zero, in
/// `*sample`: write the answer into it in place, then [`rotorloop_controller_publish`].
/// After the first publish the sample is already loaned (each publish loans the next
/// one once its own is on its way, off the path from state to torque): this only zeroes
/// it.
/// `ErrOrder` when a loaned sample is not published yet.
///
/// # Safety
/// `c` is an open handle; `sample` points to a writable pointer. The sample is valid
/// until the publish (or the close).
#[unsafe(no_mangle)]
pub unsafe extern "C" fn rotorloop_controller_loan(
    c: *mut RotorloopController,
    sample: *mut *mut TorqueSample,
) -> RotorloopStatus {
    const CALL: &str = "rotorloop_controller_loan";
    status(|| {
        // SAFETY: the caller's handle.
        let c = unsafe { handle(c, CALL) }?;
        let sample = non_null(sample, CALL, "sample")?;
        if c.loaned {
            let why = format!("{CALL}: the sample loaned before is not published yet");
            return Err(fail(RotorloopStatus::ErrOrder, why));
        }
        c.out.prewrite(TorqueSample::default()).map_err(|e| ipc_fail(&e))?;
        let Some(ptr) = c.out.prewritten_ptr() else {
            return Err(fail(RotorloopStatus::ErrIpc, format!("{CALL}: no sample was loaned")));
        };
        c.loaned = true;
        // SAFETY: checked non-null; the caller's writable pointer.
        unsafe { sample.write(ptr) };
        Ok(RotorloopStatus::Ok)
    })
}

/// Publishes the loaned sample and wakes its readers (the plant, the monitor). Sets, just
/// before the send: `publish_ns`, `prev_tick` and `prev_publish` (the previous publish),
/// `published` (this one included), `states_received` and `states_skipped` (as
/// [`rotorloop_controller_receive_state`] counted them). Every other field is the
/// controller's. `ErrOrder` without a loan.
///
/// # Safety
/// `c` is an open handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn rotorloop_controller_publish(
    c: *mut RotorloopController,
) -> RotorloopStatus {
    const CALL: &str = "rotorloop_controller_publish";
    status(|| {
        // SAFETY: the caller's handle.
        let c = unsafe { handle(c, CALL) }?;
        if !c.loaned {
            return Err(fail(RotorloopStatus::ErrOrder, format!("{CALL}: no sample is loaned")));
        }
        c.loaned = false;
        let (prev_tick, prev_cost) = c.last_publish;
        let counts = (c.published + 1, c.states_received, c.states_skipped);
        // SAFETY: the loaned sample, in shared memory, written by the caller; read only.
        let tick = c.out.prewritten_ptr().map_or(NO_TICK, |p| unsafe { (*p).tick });
        let patch = |s: &mut TorqueSample, t: u64| {
            s.publish_ns = t;
            (s.prev_tick, s.prev_publish) = (prev_tick, prev_cost);
            (s.published, s.states_received, s.states_skipped) = counts;
        };
        let sent = c.out.send_prewritten(TorqueSample::default(), patch, |_| ());
        let cost = sent.map_err(|e| ipc_fail(&e))?;
        c.published += 1;
        c.last_publish = (tick, cost);
        // The next answer's sample, loaned now (after this one is on its way), as the
        // built-in controller does: its loan then only zeroes it.
        c.out.prewrite(TorqueSample::default()).map_err(|e| ipc_fail(&e))?;
        Ok(RotorloopStatus::Ok)
    })
}

/// Readers of the torque topic now connected (the plant and the monitor, and a link
/// gateway's): 0 once they have unsubscribed, which they do after the run's last tick.
///
/// # Safety
/// `c` is an open handle (null: 0).
#[unsafe(no_mangle)]
pub unsafe extern "C" fn rotorloop_controller_readers(c: *const RotorloopController) -> u64 {
    // SAFETY: the caller's handle.
    unsafe { c.as_ref() }.map_or(0, |c| c.out.subscribers() as u64)
}

/// Closes the handle: first waits until the torque topic has no readers or `linger_ns`
/// passed (so that the last answers are read; the built-in controller lingers up to
/// 10 s), then drops every port and the node. A null handle is ignored.
///
/// # Safety
/// `c` is null or an open handle, not used after this call.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn rotorloop_controller_close(c: *mut RotorloopController, linger_ns: u64) {
    if c.is_null() {
        return;
    }
    // SAFETY: a handle from `rotorloop_controller_open`, given back once.
    let c = unsafe { Box::from_raw(c) };
    let until = now_ns().saturating_add(linger_ns);
    while c.out.subscribers() > 0 && now_ns() < until {
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    drop(c);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn last_error() -> String {
        // SAFETY: the library's own NUL-terminated message.
        unsafe { CStr::from_ptr(rotorloop_last_error()) }.to_string_lossy().into_owned()
    }

    /// Every refusal is a code with a message that names what was wrong.
    #[test]
    fn bad_arguments_are_refused_with_a_code_and_a_message() {
        let mut c: *mut RotorloopController = std::ptr::null_mut();
        let bad = c"no_underscores";
        // SAFETY: valid strings and a writable pointer.
        let s = unsafe { rotorloop_controller_open(bad.as_ptr(), c"event".as_ptr(), &mut c) };
        assert_eq!(s, RotorloopStatus::ErrArgument);
        assert!(last_error().contains("no_underscores"), "{}", last_error());
        // SAFETY: as above.
        let s = unsafe { rotorloop_controller_open(c"ok".as_ptr(), c"busy".as_ptr(), &mut c) };
        assert_eq!(s, RotorloopStatus::ErrArgument);
        assert!(last_error().contains("busy") && last_error().contains("spin"), "{}", last_error());
        assert!(c.is_null());
        // SAFETY: a null handle is allowed.
        let s = unsafe { rotorloop_controller_publish(std::ptr::null_mut()) };
        assert_eq!(s, RotorloopStatus::ErrArgument);
        let mut cfg = std::mem::MaybeUninit::<RotorloopLawConfig>::uninit();
        // SAFETY: a valid string and a writable struct.
        let s = unsafe {
            rotorloop_law_config_load(c"/nonexistent/controller.json".as_ptr(), cfg.as_mut_ptr())
        };
        assert_eq!(s, RotorloopStatus::ErrConfig);
        assert!(last_error().contains("/nonexistent/controller.json"), "{}", last_error());
    }

    /// `controller.json` as the launcher writes it reads into the C struct, rows kept.
    #[test]
    fn a_controller_json_reads_into_the_c_struct() {
        use rotorloop_common::controller_json::*;
        let j = ControllerJson {
            layout_version: CONTROLLER_JSON_VERSION,
            law: "geometric-pid".into(),
            actuation: "internal".into(),
            dt_s: 1e-3,
            rate_hz: 1e3,
            ticks: 7,
            gains: JsonGains {
                kp: 1.0,
                kd: 2.0,
                ki: 3.0,
                p: [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]],
            },
            model: JsonModel { inertia: [[0.0; 3]; 3], rotor_inertia: [0.1, 0.2, 0.3] },
            limits: JsonLimits { rotor_torque_nm: Some(0.5), rotor_rate_rad_s: None },
            anti_windup: "conditional".into(),
            law_params: serde_json::Map::new(),
        };
        let dir = std::env::temp_dir().join(format!("rl-capi-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("controller.json");
        std::fs::write(&path, serde_json::to_string(&j).expect("json")).expect("write");
        let c = load_config(path.to_str().expect("utf8")).expect("reads");
        assert_eq!(c.p_row_major, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]);
        assert_eq!((c.ticks, c.kd, c.internal_actuation), (7, 2.0, 1));
        assert_eq!((c.has_rotor_torque_limit, c.rotor_torque_limit_nm), (1, 0.5));
        assert_eq!((c.has_rotor_rate_limit, c.anti_windup_conditional), (0, 1));
        assert_eq!(c.law[..13].iter().map(|&b| b as u8).collect::<Vec<_>>(), b"geometric-pid");
        let mut old = j.clone();
        old.layout_version = 0;
        std::fs::write(&path, serde_json::to_string(&old).expect("json")).expect("write");
        let e = load_config(path.to_str().expect("utf8")).expect_err("another version");
        assert!(format!("{e:#}").contains("layout_version 0"), "{e:#}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
