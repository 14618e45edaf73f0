"""perscli's products are the bytes recorded in tests/golden.json (tests/golden.py says how).

A refactoring that moves code must not move a byte of what the commands write:
renders, apply-persistence in every mode and preset, measure (per frame and
joint), and the ci study.  An intended change of a product is re-recorded with
``python tests/golden.py --record --study`` in the same commit, which says why.
"""

import json

import pytest

import golden

RECORD = json.loads(golden.RECORD.read_text())


def _same_libraries():
    if golden.versions() != RECORD["versions"]:
        pytest.skip(f"recorded with {RECORD['versions']}, these are {golden.versions()}: other library versions "
                    "may change the numbers; re-record with python tests/golden.py --record --study")


def _compare(made, recorded):
    assert sorted(made) == sorted(recorded)
    changed = [name for name in recorded if made[name] != recorded[name]]
    assert not changed, f"products changed: {changed}"


def test_the_commands_write_the_recorded_bytes(tmp_path):
    _same_libraries()
    _compare(golden.run_commands(tmp_path), RECORD["commands"])


@pytest.mark.slow
def test_the_ci_study_makes_the_recorded_products(tmp_path):
    _same_libraries()
    from test_study import CI

    _compare(golden.run_study(tmp_path / "study", CI), RECORD["study"])


def test_a_changed_byte_changes_the_digest(tmp_path):
    """The digest sees data and cards but not DATE/CHECKSUM (else the tests above could not fail)."""
    import numpy as np
    from astropy.io import fits

    path = tmp_path / "a.fits"
    hdu = fits.PrimaryHDU(np.arange(6.0).reshape(2, 3))
    hdu.header["DATE"] = "2026-01-01"
    hdu.writeto(path, checksum=True)
    before = golden.digest(path)
    hdu.header["DATE"] = "2026-01-02"
    hdu.writeto(path, overwrite=True, checksum=True)
    assert golden.digest(path) == before
    hdu.data[1, 2] = np.nextafter(5.0, 6.0)
    hdu.writeto(path, overwrite=True, checksum=True)
    assert golden.digest(path) != before
    hdu.data[1, 2] = 5.0
    hdu.header["EXPTIME"] = 139.8
    hdu.writeto(path, overwrite=True, checksum=True)
    assert golden.digest(path) != before
