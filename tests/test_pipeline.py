"""A real shell pipeline: FITS through pipes between perscli processes."""

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from astropy.io import fits

from conftest import SAMPLE_DATA

PERSCLI = shutil.which("perscli", path=os.path.dirname(sys.executable)) or shutil.which("perscli")


@pytest.mark.skipif(PERSCLI is None, reason="perscli console script not installed")
def test_pipe_in_and_out_equals_one_run(tmp_path):
    exp = [SAMPLE_DATA / f"exp{k}.fits" for k in (1, 2, 3, 4)]
    piped = tmp_path / "piped.fits"
    once = tmp_path / "once.fits"
    # exp3's persistence added in one process, exp2's in the next, through two pipes
    cmd = (f"cat {exp[3]} | {PERSCLI} apply-persistence - {exp[2]} --max-previous 0 -o - "
           f"| {PERSCLI} apply-persistence - {exp[1]} -o - > {piped}")
    proc = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    subprocess.run([PERSCLI, "apply-persistence", str(exp[3]), str(exp[1]), str(exp[2]), "-o", str(once)],
                   check=True)
    with fits.open(piped, checksum=True) as a, fits.open(once) as b:
        np.testing.assert_allclose(a["SCI"].data, b["SCI"].data, rtol=1e-6)
        assert a["SCI"].data.max() > 0
        assert sum("apply-persistence" in str(h) for h in a[0].header["HISTORY"]) == 2
        assert a[0].header["PSCUR"] == "stdin"


@pytest.mark.skipif(PERSCLI is None, reason="perscli console script not installed")
def test_error_in_a_pipe_is_one_line_and_nothing_on_stdout(tmp_path):
    proc = subprocess.run(["bash", "-c", f"echo 'not fits' | {PERSCLI} apply-persistence - "
                                         f"{SAMPLE_DATA / 'exp1.fits'} -o -"], capture_output=True)
    assert proc.returncode == 1
    assert proc.stdout == b""
    lines = proc.stderr.decode().strip().splitlines()
    assert len(lines) == 1 and "stdin" in lines[0] and "FITS" in lines[0]
