"""Hostile and undefined specs: how long a refusal takes. One JSON line per input.

In-process timings (no interpreter start-up) of `certify.spec.parse.parse_expression` on hostile
expressions and of `System.from_text` (parse + domain check) on undefined specs and on the
built-in systems; medians over `--repeat` runs, seconds.

Run: python bench/parse.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import time

import sympy
from record import emit as record_line  # bench/record.py

from certify.errors import SpecError
from certify.spec.parse import parse_expression
from certify.spec.system import System, builtin_names, builtin_text

HOSTILE = {
    "9**9**9": "9**9**9",
    "10k-term sum": "+".join(["x1"] * 10_000),
    "2000-term sum": "+".join(["x1"] * 2_000),
    "nesting 70": "sin(" * 70 + "x1" + ")" * 70,
    "0.5**2000": "0.5**2000*x1",
    "exp(1000)": "exp(1000)*x1",
}

UNDEFINED = {
    "-sqrt(x1)**2": ["-sqrt(x1)**2", "-x2"],
    "(x1-0.3)/(x1-0.3)": ["-x1", "-x2*(x1-0.3)/(x1-0.3)"],
    "exp(log(x1))": ["exp(log(x1))", "-x2"],
    "x1**2/x1": ["x1**2/x1", "-x2"],
}


def _spec(f: list[str]) -> str:
    fs = ", ".join(f'"{e}"' for e in f)
    return (f'name = "t"\nstates = ["x1", "x2"]\noutputs = ["y"]\nf = [{fs}]\nh = ["x1"]\n'
            "[box]\nX = [[-1.0, 1.0], [-1.0, 1.0]]\nY = [[-1.0, 1.0]]\n")


def _time(fn, repeat: int) -> tuple[float, str]:
    times, outcome = [], ""
    for _ in range(repeat):
        t0 = time.perf_counter()
        try:
            fn()
            outcome = "accepted"
        except SpecError as exc:
            outcome = "refused: " + str(exc)[:80]
        times.append(time.perf_counter() - t0)
    return statistics.median(times), outcome


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    names = {"x1": sympy.Symbol("x1", real=True)}
    for label, text in HOSTILE.items():
        sec, outcome = _time(lambda t=text: parse_expression(t, names, "f[0]"), args.repeat)
        record_line({"bench": "parse", "input": label, "seconds": round(sec, 6),
                          "outcome": outcome})
    for label, f in UNDEFINED.items():
        sec, outcome = _time(lambda f=f: System.from_text(_spec(f)), args.repeat)
        record_line({"bench": "domain", "input": label, "seconds": round(sec, 6),
                          "outcome": outcome})
    for name in builtin_names():
        sec, outcome = _time(lambda n=name: System.from_text(builtin_text(n)), args.repeat)
        record_line({"bench": "builtin", "input": name, "seconds": round(sec, 6),
                          "outcome": outcome})


if __name__ == "__main__":
    main()
