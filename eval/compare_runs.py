"""Compare the outputs of two runs of the same experiments (e.g. before and after a
refactor): every ``theta.npy`` under the first folder against its namesake under the
second (max |dtheta|), and every number of every top-level JSON, timings excluded.

    python eval/compare_runs.py out/before out/after --json out/compare.json

Prints one line per differing file or number and a summary; exits 1 when anything
differs or is missing, so a refactor that must not change results can be checked by
its exit status.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

#: keys of timings, which differ from run to run
TIMING_KEYS = ("second", "time", "_s", "fps", "ms")


def numbers(x, path: str = ""):
    """(path, value) of every number in a JSON value."""
    if isinstance(x, dict):
        for k, v in x.items():
            yield from numbers(v, f"{path}/{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from numbers(v, f"{path}[{i}]")
    elif isinstance(x, (int, float)) and not isinstance(x, bool):
        yield path, float(x)


def compare(a: Path, b: Path) -> dict:
    """The comparison of run folders ``a`` and ``b`` (see the module docstring)."""
    thetas, worst, problems = 0, 0.0, []
    for f in sorted(a.rglob("theta.npy")):
        g = b / f.relative_to(a)
        if not g.exists():
            problems.append(f"missing {g}")
            continue
        x, y = np.load(f), np.load(g)
        d = float(np.abs(x - y).max()) if x.shape == y.shape else float("inf")
        thetas, worst = thetas + 1, max(worst, d)
        if d > 0:
            problems.append(f"{f.relative_to(a)}: max |dtheta| {d:g}")
    files = {}
    for f in sorted(a.glob("*.json")):
        g = b / f.name
        if not g.exists():
            problems.append(f"missing {g}")
            continue
        A, B = dict(numbers(json.loads(f.read_text()))), dict(numbers(json.loads(g.read_text())))
        keep = [k for k in A if not any(t in k for t in TIMING_KEYS)]
        diff = [k for k in keep if B.get(k) != A[k]]
        files[f.name] = {"numbers": len(keep), "differ": len(diff)}
        problems += [f"{f.name}{k}: {A[k]!r} -> {B.get(k)!r}" for k in diff[:20]]
    return {"theta_files": thetas, "max_abs_dtheta": worst, "json": files, "problems": problems}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("before", type=Path, help="the first run's folder")
    ap.add_argument("after", type=Path, help="the second run's folder")
    ap.add_argument("--json", type=Path, default=None, help="write the comparison here")
    args = ap.parse_args(argv)
    for folder in (args.before, args.after):
        if not folder.is_dir():
            ap.error(f"{folder}: not a folder")
    result = compare(args.before, args.after)
    for line in result["problems"]:
        print(line)
    print(f"{result['theta_files']} theta files, max |dtheta| = {result['max_abs_dtheta']:g}; "
          + ", ".join(f"{k}: {v['numbers']} numbers, {v['differ']} differ" for k, v in result["json"].items()))
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1))
    return 1 if result["problems"] else 0


if __name__ == "__main__":
    sys.exit(main())
