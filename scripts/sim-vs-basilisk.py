#!/usr/bin/env python3
"""The in-process simulator's speed against Basilisk's own open-loop plant, in one run.

Basilisk (the `bsk` package, pinned in python/requirements-basilisk.txt) steps a
spacecraft hub with three reaction wheels at 1 kHz, open loop (a constant motor torque on
each wheel), with its default RK4 integrator; `rotorloop sim` runs the paper's closed loop
(plant, reference, law, metrics) on `paper-sinusoid`. The two alternate, `--repeat` times
each, so they share whatever load the machine has; the script prints every figure, the
medians and the ratio of the medians. With several `--rotorloop` binaries (an old and a
new build) each takes its turn in every round.

Basilisk is installed by this script, not by hand: without it the script makes
target/bsk-venv, installs the pinned requirements into it and runs itself there.

Basilisk's hub takes the paper plant's diagonal, diag(4.0, 5.2, 6.3) kg m²: the paper's
full inertia [[4, 1, 1], [1, 5.2, 2], [1, 2, 6.3]] has principal moments 3.42, 3.80 and
8.28, which break the triangle inequality of a rigid body, and Basilisk refuses it
("IHubPntBc_B is not a valid inertia tensor"). The step's cost does not depend on the
values. The wheels are the paper's rotors (spin inertia 5, 6, 7 kg m² about the body
axes, 0.5, 1.9, 1.5 rad/s).

    scripts/sim-vs-basilisk.py [--rotorloop target/release/rotorloop] [--repeat 3]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
REQUIREMENTS = ROOT / "python" / "requirements-basilisk.txt"
VENV = ROOT / "target" / "bsk-venv"


def ensure_basilisk():
    """Runs this script again under target/bsk-venv when Basilisk is not importable here,
    installing the pinned requirements first when the venv lacks them."""
    try:
        import Basilisk  # noqa: F401

        return
    except ImportError:
        pass
    python = VENV / "bin" / "python"
    if Path(sys.executable).resolve() == python.resolve() and os.environ.get("BSK_VENV_TRIED"):
        sys.exit(f"Basilisk does not import in {VENV} after installing {REQUIREMENTS}")
    if not python.exists():
        print(f"making {VENV} for Basilisk ({REQUIREMENTS.name})", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
    probe = subprocess.run([str(python), "-c", "import Basilisk"], capture_output=True)
    if probe.returncode != 0:
        subprocess.run(
            [str(python), "-m", "pip", "install", "--quiet", "-r", str(REQUIREMENTS)], check=True
        )
    env = dict(os.environ, BSK_VENV_TRIED="1")
    os.execve(str(python), [str(python), *sys.argv], env)


def basilisk_steps_per_s(seconds):
    """Basilisk's spacecraft with three reaction wheels, open loop at 1 kHz: steps per
    wall-clock second of `ExecuteSimulation` (set-up not counted)."""
    from Basilisk.architecture import messaging
    from Basilisk.simulation import reactionWheelStateEffector, spacecraft
    from Basilisk.utilities import SimulationBaseClass, macros, simIncludeRW

    sim = SimulationBaseClass.SimBaseClass()
    proc = sim.CreateNewProcess("plant")
    proc.addTask(sim.CreateNewTask("tick", macros.sec2nano(0.001)))
    sc = spacecraft.Spacecraft()
    sc.hub.mHub = 1.0
    sc.hub.IHubPntBc_B = [[4.0, 0.0, 0.0], [0.0, 5.2, 0.0], [0.0, 0.0, 6.3]]
    sc.hub.omega_BN_BInit = [[0.25], [0.42], [0.81]]
    wheels = simIncludeRW.rwFactory()
    rpm = 60.0 / (2.0 * 3.141592653589793)
    for axis, js, rate in (([1, 0, 0], 5.0, 0.5), ([0, 1, 0], 6.0, 1.9), ([0, 0, 1], 7.0, 1.5)):
        wheels.create(
            "custom", axis, Js=js, Omega=rate * rpm, u_max=1.0e6, RWModel=messaging.BalancedWheels
        )
    rw = reactionWheelStateEffector.ReactionWheelStateEffector()
    wheels.addToSpacecraft("wheels", rw, sc)
    sim.AddModelToTask("tick", rw, 2)
    sim.AddModelToTask("tick", sc, 1)
    cmd = messaging.ArrayMotorTorqueMsgPayload()
    cmd.motorTorque = [0.1, -0.2, 0.05]
    msg = messaging.ArrayMotorTorqueMsg().write(cmd)
    rw.rwMotorCmdInMsg.subscribeTo(msg)
    sim.InitializeSimulation()
    sim.ConfigureStopTime(macros.sec2nano(seconds))
    start = time.perf_counter()
    sim.ExecuteSimulation()
    wall = time.perf_counter() - start
    omega = sc.scStateOutMsg.read().omega_BN_B
    if not all(abs(w) < 1e3 for w in omega):
        sys.exit(f"Basilisk's hub diverged: omega {omega}")
    return seconds * 1000.0 / wall


def rotorloop_ticks_per_s(binary, seconds, out):
    """`rotorloop sim --scenario paper-sinusoid` for `seconds`: its summary's ticks/s."""
    subprocess.run(
        [
            str(binary), "sim", "--scenario", "paper-sinusoid", "--duration", str(seconds),
            "--trace-every", "100000", "--out", str(out),
        ],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    return json.loads((out / "summary.json").read_text())["ticks_per_second"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rotorloop", action="append", type=Path,
                    help="a rotorloop binary (repeat for several; default target/release/rotorloop)")
    ap.add_argument("--repeat", type=int, default=3, help="rounds, 1 to 100 (default 3)")
    ap.add_argument("--sim-seconds", type=float, default=600.0,
                    help="simulated seconds of each rotorloop run (default 600)")
    ap.add_argument("--basilisk-seconds", type=float, default=60.0,
                    help="simulated seconds of each Basilisk run (default 60)")
    args = ap.parse_args()
    if not 1 <= args.repeat <= 100:
        ap.error(f"--repeat {args.repeat}: 1 to 100 rounds")
    binaries = args.rotorloop or [ROOT / "target" / "release" / "rotorloop"]
    for b in binaries:
        if not b.is_file():
            ap.error(f"--rotorloop {b}: no such file (cargo build --release builds it)")
    ensure_basilisk()
    bsk, sims = [], {b: [] for b in binaries}
    with tempfile.TemporaryDirectory(prefix="sim-vs-bsk-") as tmp:
        for i in range(args.repeat):
            bsk.append(basilisk_steps_per_s(args.basilisk_seconds))
            print(f"round {i + 1}: basilisk {bsk[-1] / 1e3:.1f} k steps/s", flush=True)
            for b in binaries:
                sims[b].append(rotorloop_ticks_per_s(b, args.sim_seconds, Path(tmp) / "sim"))
                print(f"round {i + 1}: {b} {sims[b][-1] / 1e6:.3f} M ticks/s", flush=True)
    bsk_med = statistics.median(bsk)
    print(f"basilisk open-loop plant: median {bsk_med / 1e3:.1f} k steps/s")
    for b in binaries:
        med = statistics.median(sims[b])
        ratios = ", ".join(f"{s / k:.1f}" for s, k in zip(sims[b], bsk))
        print(f"{b}: median {med / 1e6:.3f} M ticks/s, {med / bsk_med:.1f} x basilisk "
              f"(per round {ratios})")


if __name__ == "__main__":
    main()
