#!/usr/bin/env python3
"""How far one flight-record segment compresses, four ways (docs/measurements.md).

Usage: scripts/flight-compressibility.py SEGMENT SLOT_BYTES

SEGMENT is a `STREAM.NNNNNN.flight` file of a run's `flight/` folder (a 64-byte header,
then slots of SLOT_BYTES: the segment's length less 64, divided by its slot count, 32768
with the default ring). Needs the `zstd` command. Prints the ratio of raw to compressed
bytes for: zstd level 3; the slots' bytes transposed (byte i of every slot together),
then zstd; each 8-byte word XORed with the same word of the slot before, transposed,
then zstd, at level 3 and 19.
"""
import array
import subprocess
import sys


def zstd_len(data: bytes, level: int) -> int:
    out = subprocess.run(["zstd", "-q", "-c", f"-{level}", "-T1"], input=data,
                         capture_output=True, check=True)
    return len(out.stdout)


def shuffled(data: bytes, slot: int) -> bytes:
    return b"".join(data[i::slot] for i in range(slot))


def main() -> int:
    if len(sys.argv) != 3 or not sys.argv[2].isdigit() or int(sys.argv[2]) % 8:
        print(__doc__.strip().splitlines()[2], file=sys.stderr)
        print("SLOT_BYTES: a multiple of 8", file=sys.stderr)
        return 2
    path, slot = sys.argv[1], int(sys.argv[2])
    data = open(path, "rb").read()[64:]
    if len(data) % slot:
        print(f"{path}: {len(data)} bytes after the header is not a whole number of "
              f"{slot}-byte slots", file=sys.stderr)
        return 2
    words = array.array("Q", data)
    per_slot = slot // 8
    xored = array.array("Q", words)
    for k in range(len(words) - 1, per_slot - 1, -1):
        xored[k] ^= words[k - per_slot]
    xs = shuffled(xored.tobytes(), slot)
    n = len(data)
    print(f"{path}: {n} bytes; zstd-3 {n / zstd_len(data, 3):.2f}x, "
          f"shuffled zstd-3 {n / zstd_len(shuffled(data, slot), 3):.2f}x, "
          f"xor+shuffled zstd-3 {n / zstd_len(xs, 3):.2f}x, "
          f"xor+shuffled zstd-19 {n / zstd_len(xs, 19):.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
