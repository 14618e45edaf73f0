"""apply-persistence takes model overrides in the syntax of render's and study's --set (persistence.KEY=VALUE);
--param KEY=VALUE, the older spelling, gives the same bytes."""

import numpy as np

from conftest import fluence_grid
from fits_factory import invoke

DAY = 86400.0
T0 = 61541.972429


def frames(frame_writer):
    prev = frame_writer("prev.fits", fluence_grid(seed=3), start=T0)
    cur = frame_writer("cur.fits", np.full((16, 16), 400.0), start=T0 + 170.0 / DAY)
    return cur, prev


def body(path):
    # the data and every card but the dates and checksums, which differ between any two runs
    from astropy.io import fits

    with fits.open(path) as hdul:
        return [(h.data.tobytes() if h.data is not None else b"",
                 [c for c in h.header.cards if c.keyword not in ("DATE", "CHECKSUM", "DATASUM")]) for h in hdul]


def test_set_and_param_give_the_same_frame(frame_writer, tmp_path):
    cur, prev = frames(frame_writer)
    a, b, c = tmp_path / "a.fits", tmp_path / "b.fits", tmp_path / "c.fits"
    for out, extra in ((a, ["--set", "persistence.gamma=1.3", "--set", "persistence.A=0.05"]),
                       (b, ["--param", "gamma=1.3", "--param", "A=0.05"]), (c, [])):
        result = invoke("apply-persistence", cur, prev, "--mode", "predict", *extra, "-o", out)
        assert result.exit_code == 0, result.stderr
    assert str(body(a)) == str(body(b))
    assert str(body(a)) != str(body(c))          # the overrides act


def test_set_of_another_effect_or_without_a_path_is_one_line(frame_writer, tmp_path):
    cur, prev = frames(frame_writer)
    for text, needle in (("ipc.alpha=0.02", "persistence only"), ("gamma=1.1", "persistence.KEY=VALUE"),
                         ("persistence.gamma", "persistence.KEY=VALUE")):
        out = tmp_path / "x.fits"
        result = invoke("apply-persistence", cur, prev, "--set", text, "-o", out)
        assert result.exit_code == 2, (text, result.stderr)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0] and "--set" in lines[0], (text, result.stderr)
        assert not out.exists()
    result = invoke("apply-persistence", cur, prev, "--set", "persistence.beta=2", "-o", tmp_path / "y.fits")
    assert result.exit_code == 1 and "'beta'" in result.stderr and len(result.stderr.strip().splitlines()) == 1
