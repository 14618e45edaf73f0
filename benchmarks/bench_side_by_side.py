"""Benchmark: the commands of two perscli source trees side by side, on the same full-SCA inputs.

A refactoring must not make perscli slower.  This runs each command with the
sources of an earlier checkout (``--before DIR``, e.g. ``git worktree add
/tmp/before HEAD~3`` plus its compiled ``_kernels`` module copied in) and with
this tree's, alternately, in fresh processes (``python -m perscli``, spawn to
exit, ``/usr/bin/time`` for the peak RSS), and writes the best wall time of
each into RESULTS.md (section ``side-by-side``), with the machine.

The inputs are those of ``make bench-diagnose`` (benchmarks/work/diagnose:
eleven 4088 x 4088 frames of SCA 7, measured and simulated, and their truth
catalogue), which must exist:

- apply-persistence: the last measured frame with its ten earlier ones,
  ``--mode predict --workers 1``;
- render: the full SCA from the truth catalogue, ``--workers 1``;
- measure: the last measured frame, every galaxy of the catalogue, ``--workers 1``;
- diagnose: the eleven pairs, ``--workers 2`` (once each: ~90 s a run).

Each pair of outputs is also compared (tests/golden.py's per-product tolerances, DATE/CHECKSUM
ignored): a refactoring that moves code moves no number beyond its tolerance.

    python benchmarks/bench_side_by_side.py --before /tmp/before/src
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from bench_apply_persistence import machine, write_section  # noqa: E402

WORK = HERE / "work" / "diagnose"


def cases(work: Path) -> dict:
    """name -> (perscli arguments without -o, output name, repeats)."""
    meas = [str(work / f"meas{k:02d}.fits") for k in range(11)]
    sims = [str(work / f"sim{k:02d}.fits") for k in range(11)]
    truth = str(work / "truth.fits")
    return {
        "apply-persistence": (["apply-persistence", meas[10], *meas[:10], "--mode", "predict", "--workers", "1"],
                              "ap.fits", 3),
        "render": (["render", truth, "--ra", "10", "--dec", "-44", "--pa", "30", "--filter", "J129", "--sca", "7",
                    "--mjd", "61541.97", "--seed", "100", "--workers", "1"], "r.fits", 3),
        "measure": (["measure", meas[10], "--catalog", truth, "--workers", "1"], "m.fits", 3),
        "diagnose": (["diagnose", *meas, *sum([["--simulated", s] for s in sims], []), "--workers", "2"], "diag", 1),
    }


def timed(args, dest, src=None) -> tuple:
    """(wall seconds, peak RSS in GB) of ``python -m perscli ARGS -o DEST`` with ``src`` first on the path."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if src is not None:
        env["PYTHONPATH"] = str(src)
    cmd = ["/usr/bin/time", "-f", "%e %M", sys.executable, "-m", "perscli", *args, "-o", str(dest), "--overwrite"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"{' '.join(args[:1])} failed:\n{proc.stderr[-2000:]}")
    wall, rss = proc.stderr.strip().splitlines()[-1].split()
    return float(wall), int(rss) / 1e6


def same_products(a: Path, b: Path) -> str:
    """'the same' when the two products agree within tests/golden.py's tolerances, else which differ."""
    import golden

    if a.is_dir():
        names = golden.products(a)
        diff = [n for n in names if golden.differences(a / n, b / n, n)]
        return "the same" if not diff else f"differ: {', '.join(diff)}"
    return "the same" if not golden.differences(a, b, a.name) else "differ"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", type=Path, required=True, help="the src/ folder of the earlier checkout")
    ap.add_argument("--label", default="before", help="what --before is, for the table (e.g. a commit)")
    ap.add_argument("--only", nargs="*", default=None, help="some of: apply-persistence render measure diagnose")
    ap.add_argument("--workdir", type=Path, default=HERE / "work" / "side_by_side")
    ap.add_argument("--results", type=Path, default=HERE / "RESULTS.md")
    a = ap.parse_args(argv)
    if not (WORK / "meas10.fits").exists():
        raise SystemExit(f"{WORK}: no inputs; run `make bench-diagnose` first (it renders them)")
    a.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, (args, out, repeats) in cases(WORK).items():
        if a.only and name not in a.only:
            continue
        runs = {"before": [], "now": []}
        for _ in range(repeats):
            for which, src in (("before", a.before), ("now", None)):
                runs[which].append(timed(args, a.workdir / f"{which}_{out}", src))
                print(f"{name} {which}: {runs[which][-1][0]:.2f} s, {runs[which][-1][1]:.2f} GB", file=sys.stderr)
        same = same_products(a.workdir / f"before_{out}", a.workdir / f"now_{out}")
        rows.append((name, runs, same))
    m = machine()
    lines = ["## Side by side: this tree against an earlier one (a refactoring must not be slower)", "",
             f"- command: `python benchmarks/bench_side_by_side.py --before SRC --label {a.label}`; inputs of "
             "`make bench-diagnose` (4088 x 4088, SCA 7); fresh process per run, alternating, best wall time",
             f"- machine: {m.get('cpu', '?')}, {m.get('nproc', '?')} cores, {m.get('memory', '?')}", "",
             f"| command | {a.label}: best (runs) | now: best (runs) | now / {a.label} | peak RSS | products |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, runs, same in rows:
        b, n = (min(t for t, _ in runs[w]) for w in ("before", "now"))
        fmt = {w: ", ".join(f"{t:.2f}" for t, _ in runs[w]) for w in runs}
        rss = max(r for _, r in runs["now"])
        lines.append(f"| {name} | {b:.2f} s ({fmt['before']}) | {n:.2f} s ({fmt['now']}) | {n / b:.2f} | "
                     f"{rss:.2f} GB | {same} |")
    write_section(a.results, "side-by-side", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
