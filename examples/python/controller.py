"""The paper's geometric PID tracking law as a rotorloop controller in Python (numpy).

Run it in the built-in controller's place:

    rotorloop run --scenario paper-sinusoid --mode lockstep \
        --controller-cmd "python3 examples/python/controller.py" --out out/py

It speaks only the published wire contract (docs/wire.md) through iceoryx2's Python
binding, `python/rotorloop_wire.py` and `python/rotorloop_iox.py`, and learns the run from the environment the
launcher gives it (`ROTORLOOP_*`: src/run/external.rs). Arguments the launcher appends
(the built-in controller's) are ignored.

The law (spec "The control law"; controller/src/law/geometric_pid.rs):
    E = R_d R^T,  s = vee(P E - E^T P),  eta = R (Omega_d - Omega)
    a = -kp s - kd eta - ki xi_I
    Omega_dot* = Omega_d_dot + Omega x Omega_d - R^T a
    tau = I Omega_dot* - (I Omega) x Omega
    u = (K (Omega + Omega_r)) x Omega - tau
    xi_I <- xi_I + dt s   (after the tick's torques)

A restart continues from its resume state (ROTORLOOP_STATE_DIR/pid.state: the last
answer and xi_I, two copies and a generation counter in a mapped file), bumpless: a state
it has answered already gets the same answer again. Actuator limits (and so
anti-windup) are not implemented here: a scenario with limits is refused (exit 2).
"""

import ctypes
import json
import mmap
import os
import struct
import sys
import time

import numpy as np
import iceoryx2 as iox2

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "python"))
import rotorloop_wire as w  # noqa: E402
import rotorloop_iox as rl  # noqa: E402

CLOCK = time.CLOCK_MONOTONIC
HOLD_TICKS = 1000  # how long a missing reference is propagated (real time), as the built-in (docs/wire.md)


def now_ns() -> int:
    return time.clock_gettime_ns(CLOCK)


def vee(a):
    return 0.5 * np.array([a[2, 1] - a[1, 2], a[0, 2] - a[2, 0], a[1, 0] - a[0, 1]])


def hat(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def exp_so3(v):
    th = float(np.linalg.norm(v))
    k = hat(v)
    if th < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + (np.sin(th) / th) * k + ((1.0 - np.cos(th)) / th**2) * (k @ k)


class Law:
    """The geometric PID with its integral state."""

    def __init__(self, cfg):
        g = cfg["gains"]
        self.kp, self.kd, self.ki = g["kp"], g["kd"], g["ki"]
        self.p = np.array(g["p"], dtype=float)
        self.inertia = np.array(cfg["model"]["inertia"], dtype=float)
        self.k = np.array(cfg["model"]["rotor_inertia"], dtype=float)
        self.xi = np.zeros(3)

    def step(self, r, omega, omega_r, rd, omega_d, omega_d_dot, dt):
        e = rd @ r.T
        pe = self.p @ e
        eta = r @ (omega_d - omega)
        s = vee(pe - e.T @ self.p)
        a = -self.kp * s - self.kd * eta - self.ki * self.xi
        omega_dot_star = omega_d_dot + np.cross(omega, omega_d) - r.T @ a
        tau = self.inertia @ omega_dot_star - np.cross(self.inertia @ omega, omega)
        u = np.cross(self.k * (omega + omega_r), omega) - tau
        self.xi = self.xi + dt * s
        return u, tau


class ResumeState:
    """The last answer and xi_I, in a mapped file that survives a kill -9."""

    FMT = "<Q3d3d3d"  # tick, xi, u, tau
    SIZE = struct.calcsize(FMT)

    def __init__(self, path):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
        os.ftruncate(fd, 8 + 2 * self.SIZE)
        self.map = mmap.mmap(fd, 8 + 2 * self.SIZE)
        os.close(fd)

    def load(self):
        (gen,) = struct.unpack_from("<Q", self.map, 0)
        if gen == 0:
            return None
        v = struct.unpack_from(self.FMT, self.map, 8 + (gen % 2) * self.SIZE)
        return v[0], np.array(v[1:4]), np.array(v[4:7]), np.array(v[7:10])

    def store(self, tick, xi, u, tau):
        (gen,) = struct.unpack_from("<Q", self.map, 0)
        nxt = gen + 1
        struct.pack_into(self.FMT, self.map, 8 + (nxt % 2) * self.SIZE, tick, *xi, *u, *tau)
        struct.pack_into("<Q", self.map, 0, nxt)


def finite_rotation(m):
    m = np.asarray(m)
    if not np.all(np.isfinite(m)) or np.max(np.abs(m)) > 2.0:
        return False
    return np.max(np.abs(m.T @ m - np.eye(3))) <= 1e-6 and abs(np.linalg.det(m) - 1.0) <= 1e-6


def main() -> int:
    env = os.environ
    try:
        cfg = json.load(open(env["ROTORLOOP_CONTROLLER_JSON"]))
        domain, mode, wait = env["ROTORLOOP_DOMAIN"], env["ROTORLOOP_MODE"], env["ROTORLOOP_WAIT"]
    except KeyError as e:
        print(f"controller.py: {e} is not set: start me with rotorloop run --controller-cmd", file=sys.stderr)
        return 2
    if cfg["law"] != "geometric-pid" or cfg["limits"]["rotor_torque_nm"] or cfg["limits"]["rotor_rate_rad_s"]:
        print("controller.py: only the geometric PID without actuator limits", file=sys.stderr)
        return 2
    dt = cfg["dt_s"]
    lockstep = mode == "lockstep"
    iox2.set_log_level_from_env_or(iox2.LogLevel.Error)
    node = rl.open_domain(env["ROTORLOOP_IOX2_CONFIG"], domain, "controller")

    states = rl.pubsub(node, domain, "state").subscriber_builder().buffer_size(16).create()
    refs = rl.pubsub(node, domain, "reference").subscriber_builder().buffer_size(64).create()
    torque_service = rl.pubsub(node, domain, "torque")
    out = torque_service.publisher_builder().create()
    notifier = rl.event(node, domain, "torque").notifier_builder().create()
    listen = wait != "spin"
    state_listener = rl.event(node, domain, "state").listener_builder().create() if listen else None
    ref_listener = rl.event(node, domain, "reference").listener_builder().create() if listen else None

    law = Law(cfg)
    slot = ResumeState(os.path.join(env["ROTORLOOP_STATE_DIR"], "pid.state"))
    last = slot.load()
    if last is not None:
        law.xi = last[1].copy()
        print(f"controller.py: resuming after tick {last[0]} with its integral state", file=sys.stderr)
    references = {}
    newest_ref = None
    counts = dict(received=0, skipped=0, ref_misses=0, published=0, rejected=0, refs_rejected=0)
    prev_cost = (0, 0, 0)
    prev_tick = w.NO_TICK if last is None else last[0]

    def take_references():
        nonlocal newest_ref
        while True:
            s = refs.receive()
            if s is None:
                return
            r = s.payload().contents
            if not finite_rotation(np.array(r.r_d_row_major).reshape(3, 3)):
                counts["refs_rejected"] += 1
                continue
            references[r.tick] = (
                np.array(r.r_d_row_major).reshape(3, 3),
                np.array(r.omega_d_rad_s),
                np.array(r.omega_d_dot_rad_s2),
            )
            if newest_ref is None or r.tick > newest_ref[0]:
                newest_ref = (r.tick, references[r.tick])
            while len(references) > 256:
                del references[min(references)]

    def reference_for(k):
        if k in references:
            return references[k]
        counts["ref_misses"] += 1
        if lockstep:
            while k not in references:
                if ref_listener is not None:
                    ref_listener.timed_wait(iox2.Duration.from_millis(100))
                take_references()
            return references[k]
        older = [t for t in references if t < k]
        if not older or k - max(older) > HOLD_TICKS:
            return None
        t = max(older)
        rd, wd, wdd = references[t]
        return rd @ exp_so3((k - t) * dt * wd), wd, wdd

    def publish(k, u, tau, recv, stamps, flags):
        nonlocal prev_cost, prev_tick
        t0 = now_ns()
        sample = out.loan_uninit()
        t1 = now_ns()
        counts["published"] += 1
        payload = w.TorqueSample(
            tick=k,
            rotor_torque_nm=(ctypes.c_double * 3)(*u),
            body_torque_nm=(ctypes.c_double * 3)(*tau),
            state_recv_ns=recv,
            publish_ns=t1,
            states_received=counts["received"],
            states_skipped=counts["skipped"],
            reference_misses=counts["ref_misses"],
            published=counts["published"],
            states_rejected=counts["rejected"],
            references_rejected=counts["refs_rejected"],
            flags=flags,
            validated_ns=stamps[0],
            paired_ns=stamps[1],
            computed_ns=stamps[2],
            prev_tick=prev_tick,
            prev_publish=w.SendCost(*prev_cost),
        )
        sample.write_payload(payload).send()
        t2 = now_ns()
        notifier.notify()
        prev_cost = (t1 - t0, t2 - t1, now_ns() - t2)
        prev_tick = k

    answered = last
    while True:
        take_references()
        newest = None
        while True:
            s = states.receive()
            if s is None:
                break
            if newest is not None:
                counts["skipped"] += 1
            newest = s.payload().contents
            newest = w.StateSample.from_buffer_copy(newest)
            counts["received"] += 1
        if newest is None:
            if state_listener is not None:
                state_listener.timed_wait(iox2.Duration.from_millis(100))
            continue
        recv = now_ns()
        k = newest.tick
        if answered is not None and k <= answered[0]:
            # A restarted plant asks again: the same answer, no second integration.
            if k == answered[0]:
                publish(k, answered[2], answered[3], recv, (recv, recv, recv), 0)
            continue
        r = np.array(newest.r_row_major).reshape(3, 3)
        if not finite_rotation(r) or not np.all(np.isfinite(newest.omega_body_rad_s)):
            counts["rejected"] += 1
            publish(k, np.zeros(3), np.zeros(3), recv, (recv, recv, recv), w.TORQUE_SKIPPED)
            continue
        validated = now_ns()
        ref = reference_for(k)
        paired = now_ns()
        if ref is None:
            publish(k, np.zeros(3), np.zeros(3), recv, (validated, paired, paired), w.TORQUE_SKIPPED)
            continue
        u, tau = law.step(
            r, np.array(newest.omega_body_rad_s), np.array(newest.omega_rotor_rad_s), *ref, dt
        )
        computed = now_ns()
        slot.store(k, law.xi, u, tau)  # before the send: a kill in between re-sends it
        answered = (k, law.xi, u, tau)
        publish(k, u, tau, recv, (validated, paired, computed), 0)
        if newest.flags & w.FLAG_LAST:
            break
    # Keep the publisher until its readers have taken the last answers (at most 10 s).
    until = now_ns() + 10_000_000_000
    dyn = torque_service.dynamic_config
    while dyn.number_of_subscribers > 0 and now_ns() < until:
        time.sleep(0.01)
    return 0


if __name__ == "__main__":
    sys.exit(main())
