"""Fuzz ``sensors.eddie.parse_reply``: random and mutated reply lines must either parse or raise
BoardError -- never anything else -- and well-formed replies must parse back to their numbers.

Run: ``.venv/bin/python bench/fuzz_eddie_replies.py [--count 1000000] [--seed 0]``.
Prints the number of inputs, the outcome counts and the time; exits 1 on any other exception
or any round-trip mismatch.
"""

from __future__ import annotations

import argparse
import random
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sensors.eddie import COMMANDS, MAX_PINGS, BoardError, parse_reply  # noqa: E402
from sensors.eddie_emulator import format_fields  # noqa: E402

NAMES = sorted(COMMANDS)
ALPHABET = b"0123456789ABCDEFabcdef ERROR-\r\n\t\x00\xff"
MAX_REPORTED = 5  # failures printed in full


def valid_reply(rng: random.Random, cmd: str) -> tuple[bytes, tuple[int, ...]]:
    spec = COMMANDS[cmd]
    fields = spec.reply * rng.randint(0, MAX_PINGS) if spec.repeated_reply else spec.reply
    values = tuple(rng.randint(f.lo, f.hi) for f in fields)
    return format_fields(values, fields), values


def mutate(rng: random.Random, line: bytes) -> bytes:
    kind = rng.randrange(6)
    if kind == 0:  # truncate
        return line[: rng.randint(0, len(line))]
    if kind == 1 and line:  # flip one byte
        i = rng.randrange(len(line))
        return line[:i] + bytes([rng.randrange(256)]) + line[i + 1 :]
    if kind == 2:  # noise in front
        return rng.randbytes(rng.randint(1, 8)) + line
    if kind == 3:  # two replies run together
        return line + line
    if kind == 4 and line:  # drop one byte
        i = rng.randrange(len(line))
        return line[:i] + line[i + 1 :]
    return bytes(rng.choice(ALPHABET) for _ in range(rng.randint(0, 40)))


def generate(rng: random.Random) -> Callable[[], tuple[str, bytes, tuple[int, ...] | None]]:
    def one() -> tuple[str, bytes, tuple[int, ...] | None]:
        cmd = rng.choice(NAMES)
        roll = rng.random()
        if roll < 0.2:
            line, values = valid_reply(rng, cmd)
            return cmd, line, values
        if roll < 0.3:
            return cmd, rng.randbytes(rng.randint(0, 300)), None
        if roll < 0.35:
            return cmd, b"ERROR - " + rng.randbytes(rng.randint(0, 30)) + b"\r", None
        line, _ = valid_reply(rng, rng.choice(NAMES))  # maybe another command's reply
        return cmd, mutate(rng, line), None

    return one


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--count", type=int, default=1_000_000, help="inputs to try")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    next_case = generate(random.Random(args.seed))
    outcomes: Counter[str] = Counter()
    failures = 0
    t0 = time.perf_counter()
    for _ in range(args.count):
        cmd, line, expected = next_case()
        try:
            values = parse_reply(cmd, line)
        except BoardError:
            outcomes["BoardError"] += 1
            continue
        except Exception:  # the point of the fuzzer: anything else is a bug
            failures += 1
            if failures <= MAX_REPORTED:
                print(f"FAIL {cmd} {line!r}\n{traceback.format_exc()}", file=sys.stderr)
            continue
        outcomes["parsed"] += 1
        if expected is not None and values != expected:
            failures += 1
            if failures <= MAX_REPORTED:
                print(f"MISMATCH {cmd} {line!r}: {values} != {expected}", file=sys.stderr)
    wall = time.perf_counter() - t0
    print(
        f"{args.count} inputs in {wall:.1f} s ({args.count / wall:,.0f}/s): "
        f"{outcomes['parsed']} parsed, {outcomes['BoardError']} BoardError, {failures} failures"
    )
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
