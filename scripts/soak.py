#!/usr/bin/env python3
"""A soak of `rotorloop run`, measured from outside (docs/measurements.md, issue 43).

    scripts/soak.py OUT [RUN ARGS...]

runs `target/release/rotorloop run --out OUT --domain soak-PID RUN ARGS...` with every
rotorloop process reporting its peak memory (ROTORLOOP_PEAK_RSS=OUT.peaks), samples each
process's RSS every 10 s into OUT.rss.csv, notes when the plant process ends (its last
tick, within a second) and when the launcher does, and prints:

- the time after the last tick (the launcher's end minus the plant's), and its share of
  the run's duration;
- each process's peak RSS (VmHWM, from OUT.peaks);
- the output's bytes by kind and per second of run.

Standard library only; Linux /proc.
"""

import json
import os
import subprocess
import sys
import time
from pathlib import Path


def rss_kib(pid):
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def processes(domain):
    """pid -> role name (plant, controller, ...) of the run's role processes."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            argv = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        args = [a.decode(errors="replace") for a in argv if a]
        if domain not in args or len(args) < 3 or args[1] != "role":
            continue
        out[int(d.name)] = args[2]
    return out


def kind(name):
    if name.startswith("flight/") or name.startswith("flight"):
        return "flight records"
    for k in ("trace.csv", "timing.csv", "run.mcap", "sched.csv", "sched.csv.zst", "incidents.csv"):
        if name == k:
            return k
    if name.endswith(".hlog") or name.endswith(".hgrm"):
        return "histograms"
    if name.endswith(".png"):
        return "figures"
    return "other"


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    out = Path(sys.argv[1])
    args = sys.argv[2:]
    domain = f"soak-{os.getpid()}"
    peaks = Path(f"{out}.peaks")
    peaks.unlink(missing_ok=True)
    binary = Path(__file__).resolve().parent.parent / "target/release/rotorloop"
    env = dict(os.environ, ROTORLOOP_PEAK_RSS=str(peaks))
    cmd = [str(binary), "run", "--out", str(out), "--domain", domain, "--quiet", *args]
    print(" ".join(cmd), flush=True)
    start = time.time()
    launcher = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL)
    plant_seen = plant_end = None
    next_sample = start
    with open(f"{out}.rss.csv", "w") as rss:
        rss.write("t_s,process,rss_kib\n")
        while launcher.poll() is None:
            now = time.time()
            roles = processes(domain)
            if "plant" in roles.values():
                plant_seen = True
            elif plant_seen and plant_end is None:
                plant_end = now
            if now >= next_sample:
                next_sample += 10
                for pid, role in list(roles.items()) + [(launcher.pid, "launcher")]:
                    r = rss_kib(pid)
                    if r is not None:
                        rss.write(f"{now - start:.0f},{role},{r}\n")
                rss.flush()
            time.sleep(1)
    end = time.time()
    print(f"exit {launcher.returncode}; {end - start:.0f} s in all")
    try:
        s = json.loads((out / "summary.json").read_text())
        run_s = s["ticks"] / s["rate_hz"]
    except (OSError, ValueError, KeyError):
        run_s = (plant_end or end) - start
    if plant_end is not None:
        after = end - plant_end
        print(f"after the last tick: {after:.0f} s ({100 * after / run_s:.2f} % of {run_s:.0f} s)")
    if peaks.exists():
        best = {}
        for line in peaks.read_text().splitlines():
            what, kib = line.rsplit("\t", 1)
            words = what.split()
            name = " ".join(words[:2]) if words[0] == "role" else words[0]
            best[name] = max(best.get(name, 0), int(kib))
        for name, kib in sorted(best.items()):
            print(f"peak {name}: {kib / 1024:.1f} MiB")
    sizes = {}
    for p in out.rglob("*"):
        if p.is_file():
            k = kind(str(p.relative_to(out)))
            sizes[k] = sizes.get(k, 0) + p.stat().st_size
    total = sum(sizes.values())
    for k, b in sorted(sizes.items(), key=lambda kv: -kv[1]):
        print(f"{k}: {b / 1e6:.1f} MB ({b / run_s / 1e6:.3f} MB/s)")
    print(f"output: {total / 1e6:.1f} MB, {total / run_s / 1e6:.3f} MB per second of run")


if __name__ == "__main__":
    main()
