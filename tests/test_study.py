"""perscli study: the description, its task graph, and runs that resume and agree across schedulers."""

import json
import os
import shutil
import subprocess
import sys
import time

import pytest

from fits_factory import invoke, one_line_error, run
from perscli import PerscliError
from perscli.study.config import load_study
from perscli.study.plan import build, frame_seed, select_exposures, variant_name

SCHEDULE = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "roman",
                        "Roman_WAS_obseq_11_1_23.fits")
needs_schedule = pytest.mark.skipif(not os.path.exists(SCHEDULE), reason="../shared/data (Roman schedule) absent")

#: the CI-sized study with a planned sequence: no data needed
CI = ["exposures.source=plan", "persistence.models=[typical]"]


# -- the description -------------------------------------------------------------------------

def test_typos_are_named_with_the_closest_key(tmp_path):
    with pytest.raises(PerscliError, match=r"exposures.cout.*did you mean exposures.count"):
        load_study(None, preset="ci", overrides=["exposures.cout=3"])
    path = tmp_path / "s.yaml"
    path.write_text("feild: {ra: 10}\n")
    with pytest.raises(PerscliError, match="did you mean field"):
        load_study(str(path))
    result = run("study", path, "-o", tmp_path / "out", code=1)
    assert "did you mean field" in result.output


def test_types_and_values_are_checked():
    with pytest.raises(PerscliError, match="must be a finite number"):
        load_study(None, preset="ci", overrides=["field.ra=east"])
    # what a fuzzer found passing the dry run (or crashing): each refused up front, in one line
    bad = {"exposures.count=2.5": "whole number", "exposures.count=true": "finite number",
           "field.radius=.nan": "finite number", "persistence.models=5": "persistence model",
           "correlate.npatch=0": "npatch", "measure.stamp=7": "measure.stamp",
           "catalog.galaxy_density=-3": "galaxy_density", "catalog.margin_arcsec=-1": "margin",
           "measure.min_snr=-2": "min_snr", "correlate.thresholds=[0]": "thresholds",
           "budget.bands=nonsense": "budget bands", "budget.modes=Q": "modes",
           "catalog.gaia=[/no/such/chunk.fits]": "catalog.gaia"}
    for override, message in bad.items():
        with pytest.raises(PerscliError, match=message):
            load_study(None, preset="ci", overrides=[override])
    with pytest.raises(PerscliError, match="ra must be in"):
        load_study(None, preset="ci", overrides=["field.ra=370"])
    with pytest.raises(PerscliError, match="persistence.sources"):
        load_study(None, preset="ci", overrides=["persistence.sources=[planets]"])
    with pytest.raises(PerscliError, match="scas"):
        load_study(None, preset="ci", overrides=["scas=[19]"])


def test_presets_file_and_overrides_stack(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("preset: ci\nexposures: {count: 3}\npersistence: {sources: [stars, 1.0e5]}\n")
    s = load_study(str(path), overrides=["exposures.history=2"])
    assert s["bounds"] == [1, 512, 1, 512]                    # from the preset
    assert s["exposures"]["count"] == 3                        # from the file
    assert s["exposures"]["history"] == 2                      # from the command line
    assert s["persistence"]["sources"] == ["stars", 1.0e5]


@pytest.mark.parametrize("joint", [True, False])
def test_differential_plan_renders_each_final_once_for_every_variant(joint):
    s = load_study(None, preset="ci", overrides=CI + ["exposures.count=3", "exposures.history=2",
                                                      "persistence.models=[typical, pessimistic]",
                                                      f"measure.joint={str(joint).lower()}"])
    tasks = build(s)
    keys = [t.key for t in tasks]
    assert len(keys) == len(set(keys))
    finals = [t for t in tasks if t.kind == "final"]
    # consecutive finals of an SCA go together (measure.chunk, 32 by default): their earlier exposures are
    # drawn once
    assert len(finals) == 1
    each = finals[0].params["finals"]
    assert len(each) == 3 and all(len(f["history"]) == 2 for f in each)
    assert len({f["seed"] for f in each}) == 3
    # earlier exposures are drawn inside each final (the light drawn on them): no frame of theirs is rendered
    assert not any(t.kind == "render" for t in tasks)
    for t in finals:
        assert set(t.params["variants"]) == {"drawn-typical", "drawn-pessimistic"}   # one render for all
        assert ("regions" if joint else "catalog") in t.deps
        assert all(dep in keys[:keys.index(t.key)] for dep in t.deps)
        assert t.output.startswith("frames/" if joint else "shapes/")
    assert [t.kind for t in tasks].count("changes") == (2 if joint else 0)          # measure.parts
    corr = [t for t in tasks if t.kind == "correlate"]
    assert all(len(t.params["tables"]) == (2 if joint else 1) for t in corr)   # parts or chunks pooled
    chunked = build(load_study(None, preset="ci", overrides=CI + ["exposures.count=3", "exposures.history=2",
                                                                  f"measure.joint={str(joint).lower()}",
                                                                  "measure.chunk=2"]))
    assert [len(t.params["finals"]) for t in chunked if t.kind == "final"] == [2, 1]


def test_realisations_repeat_the_study_with_their_own_seeds():
    s = load_study(None, preset="ci", overrides=CI + ["realisations=3", "seed=5"])
    tasks = build(s)
    cats = [t for t in tasks if t.kind == "catalog"]
    assert [t.output for t in cats] == ["r0005/truth.fits", "r0006/truth.fits", "r0007/truth.fits"]
    assert [t.params["seed"] for t in cats] == [5, 6, 7]
    seeds = [f["seed"] for t in tasks if t.kind == "final" for f in t.params["finals"]]
    assert len(set(seeds)) == len(seeds)
    summary = tasks[-1]
    assert summary.kind == "summary" and [r["seed"] for r in summary.params["realisations"]] == [5, 6, 7]
    with pytest.raises(PerscliError, match="realisations"):
        load_study(None, preset="ci", overrides=["realisations=0"])
    with pytest.raises(PerscliError, match="realisations"):
        load_study(None, preset="ci", overrides=["seed=1000", "realisations=2"])
    with pytest.raises(PerscliError, match="differential"):
        build(load_study(None, preset="ci", overrides=["differential=true", "persistence.sources=[all]"]))


def test_plan_renders_each_sca_exposure_once_and_shares_seeds():
    s = load_study(None, preset="ci", overrides=CI + ["exposures.count=3", "exposures.history=2",
                                                      "differential=false"])
    tasks = build(s)
    keys = [t.key for t in tasks]
    assert len(keys) == len(set(keys))
    refs = [t for t in tasks if t.key.startswith("render/ref/")]
    assert len(refs) == 5                                      # 3 finals + 2 earlier: histories overlap
    pers = [t for t in tasks if t.kind == "render" and not t.key.startswith("render/ref/")]
    assert len(pers) == 3
    for t in pers:
        ref = next(r for r in refs if r.params["pointing"]["expid"] == t.params["pointing"]["expid"])
        assert t.params["seed"] == ref.params["seed"]          # frames with and without share their noise
        assert len(t.params["previous"]) <= 2
        assert all(dep in keys[:keys.index(t.key)] for dep in t.deps)
    assert frame_seed(1, 1, 5) != frame_seed(1, 2, 5) != frame_seed(2, 1, 5)
    assert variant_name(1e5, "typical") == "above1e+05-typical"


@needs_schedule
def test_schedule_finals_and_their_histories_of_the_same_sca():
    s = load_study(None, preset="small", overrides=[f"exposures.schedule={SCHEDULE}"])
    ex = select_exposures(s)
    finals = ex.finals[7]
    assert len(finals) == 3 and all(p.filter.upper() == "J129" for p in finals)
    for p in finals:
        hist = ex.history[(7, p.expid)]
        assert len(hist) == 10
        # the schedule rows just before it, in time, whatever their filter
        assert all(q.mjd < p.mjd for q in hist)
        assert all(q.sca == 7 for q in hist)


def test_dry_run_reports_the_graph(tmp_path):
    result = run("study", "--preset", "ci", "-o", tmp_path / "o", "--dry-run", *sum([["--set", c] for c in CI], []))
    assert "tasks" in result.output and "final" in result.output
    assert not (tmp_path / "o").exists()


def test_bad_scheduler_cost_file_and_output_are_one_line_before_anything_runs(tmp_path):
    args = ["study", "--preset", "ci", "--dry-run"]
    one_line_error(invoke(*args, "-o", tmp_path / "o", "--scheduler", "bogus"), "--scheduler", "tcp://HOST:8786",
                   code=2)
    for text, message in (("{\n", "not JSON at line 2"), ("[]", "not a study's cost.json"),
                          ('{"final": {"tasks": 1}}', "entry 'final' lacks")):
        bad = tmp_path / "cost.json"
        bad.write_text(text)
        one_line_error(invoke(*args, "-o", tmp_path / "o", "--cost-from", bad), message, bad)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    one_line_error(invoke(*args, "-o", a_file), "is a file")
    one_line_error(invoke(*args, "-o", "-"), "not a stream")
    assert a_file.read_text() == "x" and not (tmp_path / "o").exists()


def test_a_cost_file_lacking_kinds_says_what_the_projection_leaves_out(tmp_path):
    from perscli.study.summary import project_cost

    # one final drawing its exposure and two earlier ones: three draws at the measured 10 s / 4 draws
    final = {"pointing": {"expid": 7}, "history": [{"expid": 3}, {"expid": 5}]}
    tasks = [{"kind": "final", "key": "final/sca1/e1", "params": {"finals": [final]}},
             {"kind": "budget", "key": "b", "params": {}}]
    p = project_cost(tasks, {"final": {"tasks": 2, "cpu_s": 10.0, "bytes": 100, "draws": 4}})
    assert p["missing"] == ["budget"] and abs(p["cpu_hours"] - 3 * 2.5 / 3600) < 1e-12


# -- runs ------------------------------------------------------------------------------------

def _products(root):
    """Every product of a study folder but the run's own records and timings."""
    out = {}
    for d, _, files in os.walk(root):
        for f in files:
            rel = os.path.relpath(os.path.join(d, f), root)
            if rel.startswith(".state") or rel in ("cost.json", "study.yaml"):
                continue
            out[rel] = os.path.join(d, f)
    return out


def _fits_content(path):
    import fitsio

    parts = []
    with fitsio.FITS(path) as f:
        for hdu in f:
            hdr = hdu.read_header()
            cards = [(r["name"], str(r.get("value")), r.get("comment")) for r in hdr.records()
                     if r["name"] not in ("DATE", "CHECKSUM")]
            data = hdu.read() if hdu.has_data() else None
            parts.append((cards, None if data is None else data.tobytes()))
    return parts


def assert_same_products(a, b):
    pa, pb = _products(a), _products(b)
    assert sorted(pa) == sorted(pb)
    for rel in pa:
        if rel.endswith(".fits"):
            assert _fits_content(pa[rel]) == _fits_content(pb[rel]), rel
        else:
            with open(pa[rel], "rb") as fa, open(pb[rel], "rb") as fb:
                assert fa.read() == fb.read(), rel


@pytest.fixture(scope="module")
def serial_study(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "study"
    args = ["study", "--preset", "ci", "-o", out, "--scheduler", "serial", *sum([["--set", c] for c in CI], [])]
    run(*args)
    return out


@pytest.fixture(scope="module")
def full_study(tmp_path_factory):
    """The same study computed in full: every frame rendered whole, every galaxy measured in each variant."""
    out = tmp_path_factory.mktemp("full") / "study"
    run("study", "--preset", "ci", "-o", out, "--scheduler", "serial",
        *sum([["--set", c] for c in [*CI, "differential=false"]], []))
    return out


@pytest.mark.slow
def test_ci_study_makes_every_product(serial_study):
    out = serial_study
    summary = json.loads((out / "summary.json").read_text())
    assert [r["variant"] for r in summary["results"]] == ["drawn-typical"]
    res = summary["results"][0]
    assert res["n"] > 0 and "frac_ge" in res and "frac_dabs_ge" in res and res["catalogue"] >= res["sample"]
    assert summary["differential"] is True
    for rel in ["truth.fits", "pointings.fits", "regions.fits", "shapes/part1of2.fits", "shapes/part2of2.fits",
                "xi/drawn-typical.fits", "budget/drawn-typical.fits", "summary.md",
                "frames/sca01/c000003/e000003_final.fits", "frames/sca01/c000003/e000004_final.fits",
                "figures/ghosts_by_magnitude.png", "figures/galaxy_beside_ghost.png", "cost.json"]:
        assert (out / rel).exists(), rel
    assert not list((out / "frames").glob("*/*_stars.fits")) and not list((out / "frames").glob("*/*_ref.fits"))
    cost = json.loads((out / "cost.json").read_text())
    # the two finals of SCA 1 in one task (measure.chunk): their earlier exposures drawn once
    assert cost["final"]["tasks"] == 1 and cost["changes"]["tasks"] == 2 and cost["regions"]["tasks"] == 1
    assert cost["final"]["bytes"] > 0
    # a rerun makes nothing
    result = run("study", "--preset", "ci", "-o", out, "--scheduler", "serial", *sum([["--set", c] for c in CI], []))
    assert "0 products made" in result.output


@pytest.mark.slow
def test_full_ci_study_makes_every_product(full_study):
    out = full_study
    for rel in ["shapes/ref.fits", "shapes/drawn-typical.fits", "xi/drawn-typical.fits", "summary.md"]:
        assert (out / rel).exists(), rel
    cost = json.loads((out / "cost.json").read_text())
    assert cost["render_ref_final"]["tasks"] == 2 and cost["render_ref_history"]["tasks"] == 3
    assert cost["render_ref_history"]["bytes"] > 0 and cost["render_persist"]["tasks"] == 2


@pytest.mark.slow
def test_local_cluster_with_two_workers_gives_the_serial_products(serial_study, tmp_path):
    out = tmp_path / "dask"
    run("study", "--preset", "ci", "-o", out, "--scheduler", "local", "--workers", 2,
        *sum([["--set", c] for c in CI], []))
    assert_same_products(serial_study, out)


@pytest.mark.slow
def test_a_killed_run_resumes_and_finishes_with_the_same_products(serial_study, tmp_path):
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "perscli", "study", "--preset", "ci", "-o", str(out),
           "--scheduler", "serial", "-q", *sum([["--set", c] for c in CI], [])]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE)
    state = out / ".state"
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if state.exists() and len(list(state.glob("*.json"))) >= 5:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the study finished before it could be killed"
    proc.kill()
    proc.wait()
    made = {p.name for p in state.glob("*.json")}
    assert 0 < len(made) < 13
    result = subprocess.run(cmd, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert_same_products(serial_study, out)


def _fits_data(path):
    import fitsio

    with fitsio.FITS(path) as f:
        return [(h.read().dtype.str, h.read().tobytes()) if h.has_data() else None for h in f]


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_the_makefile_of_single_commands_agrees_with_the_study(full_study, tmp_path):
    # examples/persistence-study composes the same study from catalog, pointings, render, measure,
    # correlate and budget; with the same settings its products hold the same data
    here = os.path.join(os.path.dirname(__file__), "..", "examples", "persistence-study")
    perscli = shutil.which("perscli", path=os.path.dirname(sys.executable)) or "perscli"
    out = tmp_path / "mk"
    result = subprocess.run(["make", "-j2", "-C", here, f"OUT={out}", "MODELS=typical", f"PERSCLI={perscli}"],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]
    made = [os.path.relpath(os.path.join(d, f), out) for d, _, fs in os.walk(out) for f in fs if f.endswith(".fits")]
    assert len(made) >= 12 and "xi/drawn-typical.fits" in made and "shapes/ref.fits" in made
    for rel in made:
        assert _fits_data(out / rel) == _fits_data(full_study / rel), rel


def test_persistence_models_by_name_or_file_are_checked_before_anything_runs(tmp_path):
    model = tmp_path / "strong.yaml"
    model.write_text("base: typical\nA: 0.03\n")
    study = tmp_path / "s.yaml"
    study.write_text("preset: ci\npersistence: {models: [typical, strong.yaml]}\n")  # relative to the file
    s = load_study(str(study))
    assert s["persistence"]["models"][1] == str(model)
    tasks = build(s)
    finals = [t for t in tasks if t.kind == "final"]
    assert finals and "persistence.A=0.03" in finals[0].params["variants"]["drawn-strong"]
    with pytest.raises(PerscliError, match="persistence.models: nomodel: no such law or file"):
        load_study(None, preset="ci", overrides=["persistence.models=[nomodel]"])
    with pytest.raises(PerscliError, match="read_noise"):
        load_study(None, preset="ci", overrides=["render.set=[read_noise.sigma=-3]"])


def test_half_written_files_of_a_killed_run_are_removed_before_the_next(tmp_path):
    from perscli.study.runner import remove_stale_parts

    d = tmp_path / "s"
    (d / "records").mkdir(parents=True)
    (d / "shapes").mkdir()
    dead = d / "records" / "a.json.999999999.part"          # no such process
    alive = d / "records" / f"b.json.{os.getppid()}.part"   # a running process's
    writer = d / "shapes" / ".perscli-abc123.part.fits"
    folder = d / ".perscli-diagnose-xyz"
    for p in (dead, alive, writer):
        p.write_text("half")
    folder.mkdir()
    # a per-exposure final's scratch frame, named as the task names it (NAME.eEXPID.PID.part)
    scratch = d / "shapes" / "e004184.fits.e005524.999999999.part"
    scratch.write_text("half")
    (d / "shapes" / "done.fits").write_text("whole")
    assert remove_stale_parts(str(d)) == 4
    assert not dead.exists() and not writer.exists() and not folder.exists() and not scratch.exists()
    assert alive.exists() and (d / "shapes" / "done.fits").exists()


def test_the_summary_reads_products_only_not_what_a_killed_task_left_beside_them(tmp_path):
    from perscli.study.summary import _products

    d = tmp_path / "shapes" / "sca08"
    d.mkdir(parents=True)
    for name in ("e004184.fits", "e004185.fits", "e004184.fits.13740.e005524.fits", "e004184.fits.e1.2.part"):
        (d / name).write_text("x")
    found = _products(str(tmp_path / "shapes" / "sca*" / "e*.fits"), r"e\d+\.fits")
    assert [os.path.basename(p) for p in found] == ["e004184.fits", "e004185.fits"]
