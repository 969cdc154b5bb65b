"""A controller that misbehaves on purpose, for tests/misbehaving.rs: it joins the loop as
any outside controller does (docs/wire.md, python/rotorloop_iox.py) and then answers
wrongly, as its first argument says (the launcher's own arguments follow and are ignored):

    silent        subscribes, never publishes
    nan           answers every state, with NaN torques
    future        answers state k as tick k + 1000 (a tick the loop has not reached)
    old           answers state k as tick k - 5 (an old tick; tick 0..4 as tick 0)
    late=S        answers every state S seconds after it arrived
    every-other   answers only the states of even ticks
    crash-at=K    answers every state with zero torque, and exits 1 at state K (once: its
                  restart, which finds its mark in ROTORLOOP_STATE_DIR, goes on answering)

Every torque it sends is zero (or NaN): the supervision is under test, not the law.
"""

import ctypes
import os
import sys
import time

import iceoryx2 as iox2

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "python"))
import rotorloop_wire as w  # noqa: E402
import rotorloop_iox as rl  # noqa: E402


def main() -> int:
    how = sys.argv[1]
    name, _, value = how.partition("=")
    env = os.environ
    domain = env["ROTORLOOP_DOMAIN"]
    iox2.set_log_level_from_env_or(iox2.LogLevel.Error)
    node = rl.open_domain(env["ROTORLOOP_IOX2_CONFIG"], domain, "controller")
    states = rl.pubsub(node, domain, "state").subscriber_builder().buffer_size(16).create()
    out = rl.pubsub(node, domain, "torque").publisher_builder().create()
    notifier = rl.event(node, domain, "torque").notifier_builder().create()
    listener = rl.event(node, domain, "state").listener_builder().create()
    published = 0

    def publish(tick, value):
        nonlocal published
        published += 1
        now = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
        sample = out.loan_uninit()
        payload = w.TorqueSample(
            tick=tick,
            rotor_torque_nm=(ctypes.c_double * 3)(value, value, value),
            body_torque_nm=(ctypes.c_double * 3)(value, value, value),
            state_recv_ns=now,
            publish_ns=now,
            published=published,
            validated_ns=now,
            paired_ns=now,
            computed_ns=now,
            prev_tick=w.NO_TICK,
        )
        sample.write_payload(payload).send()
        notifier.notify()

    while True:
        s = states.receive()
        if s is None:
            listener.timed_wait(iox2.Duration.from_millis(100))
            continue
        state = w.StateSample.from_buffer_copy(s.payload().contents)
        k = state.tick
        if state.flags & w.FLAG_LAST and name != "silent":
            publish(k, 0.0)
            return 0
        if name == "silent":
            continue
        if name == "nan":
            publish(k, float("nan"))
        elif name == "future":
            publish(k + 1000, 0.0)
        elif name == "old":
            publish(max(k, 5) - 5, 0.0)
        elif name == "late":
            time.sleep(float(value))
            publish(k, 0.0)
        elif name == "every-other":
            if k % 2 == 0:
                publish(k, 0.0)
        elif name == "crash-at":
            mark = os.path.join(env["ROTORLOOP_STATE_DIR"], "crashed")
            if k >= int(value) and not os.path.exists(mark):
                open(mark, "w").close()
                return 1
            publish(k, 0.0)


if __name__ == "__main__":
    sys.exit(main())
