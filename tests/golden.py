"""Recorded digests of perscli's products, so that a refactoring shows it changed no byte.

``python tests/golden.py --record`` runs the commands below (and, with ``--study``, the
``ci`` study) with the perscli found on ``PYTHONPATH`` and writes their digests to
``tests/golden.json``, with the versions of the libraries that made them;
tests/test_golden.py runs the same commands and compares.  A digest covers every
HDU's header cards (but DATE and CHECKSUM, which change with the clock) and data
bytes, or a non-FITS file's bytes.  Other library versions may legitimately change
the numbers (a GalSim release redraws a PSF), so the test skips, saying so, when
the versions differ from the recorded ones.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
SAMPLES = HERE.parent / "sample_data"
RECORD = HERE / "golden.json"
LIBRARIES = ("numpy", "scipy", "astropy", "fitsio", "galsim", "treecorr", "matplotlib")

POINT = ["--ra", "10", "--dec", "-44", "--pa", "30", "--filter", "J129", "--sca", "7",
         "--bounds", "1001", "1096", "2001", "2096"]
EXPS = [str(SAMPLES / f"exp{i}.fits") for i in (1, 2, 3, 4)]

#: name -> arguments of one perscli run, in order (later runs read earlier products)
COMMANDS = {
    "truth.fits": ["catalog", "--ra", "9.5386", "--dec", "-44.0435", "--size", "1", "--star-density", "10",
                   "--seed", "1"],
    "e0.fits": ["render", "truth.fits", *POINT, "--mjd", "61541.97", "--seed", "11"],
    "e1.fits": ["render", "truth.fits", *POINT, "--mjd", "61541.97196528", "--seed", "12",
                "--previous", "e0.fits"],
    "e1_dark.fits": ["render", "truth.fits", *POINT, "--mjd", "61541.97196528", "--seed", "12",
                     "--set", "dark.current=0.3", "--persistence-source", "all", "--previous", "e0.fits"],
    "add.fits": ["apply-persistence", EXPS[3], *EXPS[:3]],
    "predict.fits": ["apply-persistence", EXPS[3], *EXPS[:3], "--mode", "predict"],
    "subtract_set.fits": ["apply-persistence", EXPS[3], *EXPS[:3], "--mode", "subtract", "--model", "pessimistic",
                          "--set", "persistence.gamma=1.1"],
    "wfc3.fits": ["apply-persistence", EXPS[3], *EXPS[:3], "--model", "wfc3", "--mode", "predict"],
    "shapes.fits": ["measure", "e1.fits", "--catalog", "truth.fits"],
    "joint.fits": ["measure", "e0.fits", "e1.fits", "--catalog", "truth.fits", "--joint"],
}


def versions():
    """The versions of the libraries whose arithmetic the products depend on."""
    from importlib.metadata import version

    return {name: version(name) for name in LIBRARIES}


def digest(path):
    """sha256 of a product: FITS cards but DATE/CHECKSUM and data bytes, else the bytes."""
    h = hashlib.sha256()
    path = Path(path)
    if path.suffix == ".fits":
        import fitsio

        with fitsio.FITS(str(path)) as f:
            for hdu in f:
                for r in hdu.read_header().records():
                    if r["name"] not in ("DATE", "CHECKSUM", "DATASUM"):
                        h.update(repr((r["name"], str(r.get("value")), r.get("comment"))).encode())
                if hdu.has_data():
                    h.update(hdu.read().tobytes())
    else:
        h.update(path.read_bytes())
    return h.hexdigest()


def run_commands(workdir, env=None):
    """Run :data:`COMMANDS` in ``workdir``; return {product: digest}."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    out = {}
    for name, args in COMMANDS.items():
        subprocess.run([sys.executable, "-m", "perscli", *args, "-o", name, "--overwrite"], cwd=workdir,
                       env=env, check=True, capture_output=True)
        out[name] = digest(workdir / name)
    return out


def study_digests(root):
    """{product: digest} of a study folder, but the run's records and timings."""
    root = Path(root)
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        if p.is_file() and not rel.startswith(".state") and rel not in ("cost.json", "study.yaml"):
            out[rel] = digest(p)
    return out


def run_study(dest, settings, env=None):
    """Run the ci study serially into ``dest`` with ``settings`` (--set strings)."""
    args = [sys.executable, "-m", "perscli", "study", "--preset", "ci", "-o", str(dest), "--scheduler", "serial"]
    for s in settings:
        args += ["--set", s]
    subprocess.run(args, env=env, check=True, capture_output=True)
    return study_digests(dest)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--record", action="store_true", help="write tests/golden.json")
    parser.add_argument("--study", action="store_true", help="also the ci study (minutes)")
    parser.add_argument("--workdir", default="golden_work")
    a = parser.parse_args(argv)
    record = {"versions": versions(), "commands": run_commands(Path(a.workdir) / "commands")}
    if a.study:
        sys.path.insert(0, str(HERE))
        from test_study import CI

        record["study"] = run_study(Path(a.workdir) / "study", CI)
    elif RECORD.exists():
        record["study"] = json.loads(RECORD.read_text()).get("study")
    text = json.dumps(record, indent=1, sort_keys=True) + "\n"
    if a.record:
        RECORD.write_text(text)
    print(text)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
