"""Shared fixtures: small frames with real-looking headers, and the real data folder."""

import os
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits


def _signals_back_to_default():
    """Undo an ignored SIGINT or SIGHUP that the suite inherited (started under nohup, or with & from a script).

    Ignored signals are inherited across exec: the commands the tests start and then interrupt would ignore
    them too, and the tests of Ctrl-C and hangups would test nothing.
    """
    import signal

    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if signal.getsignal(signal.SIGHUP) == signal.SIG_IGN:
        signal.signal(signal.SIGHUP, signal.SIG_DFL)


_signals_back_to_default()

SHARED_DATA = Path(os.environ.get("PERSCLI_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
SAMPLE_DATA = Path(__file__).resolve().parents[1] / "sample_data"


def write_frame(path, data, *, start=None, exptime=139.8, end=None, bunit="electron", extname="SCI",
                **keywords):
    """Write a frame: ``data`` in a SCI extension with timing keywords (MJD)."""
    hdr = fits.Header()
    if bunit is not None:
        hdr["BUNIT"] = bunit
    if exptime is not None:
        hdr["EXPTIME"] = exptime
    if start is not None:
        hdr["EXPSTART"] = start
        hdr["EXPEND"] = end if end is not None else start + exptime / 86400.0
    for key, value in keywords.items():
        hdr[key.replace("_", "-") if key in ("MJD_BEG", "MJD_END", "DATE_OBS", "TIME_OBS") else key] = value
    if extname is None:
        hdul = fits.HDUList([fits.PrimaryHDU(np.asarray(data), hdr)])
    else:
        hdul = fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.asarray(data), hdr, name=extname)])
    hdul.writeto(path, overwrite=True)
    return str(path)


@pytest.fixture
def frame_writer(tmp_path):
    """``frame_writer(name, data, **kw)`` writes ``tmp_path/name`` with :func:`write_frame`."""

    def make(name, data, **kw):
        return write_frame(tmp_path / name, data, **kw)

    return make


@pytest.fixture
def shared_data():
    """../shared/data, or skip when it is absent (a clone without the shared folder)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} not present")
    return SHARED_DATA


def fluence_grid(shape=(16, 16), seed=1):
    """Fluences spanning every branch of the model: negative, zero, linear, Fermi, far above x0."""
    rng = np.random.default_rng(seed)
    x = 10 ** rng.uniform(0, 5.7, shape)
    flat = x.reshape(-1)
    flat[:6] = [-100.0, 0.0, 1.0, 4.99e4, 5.0e4, 5.01e4]
    return x


@pytest.fixture(autouse=True)
def _checksums_stay_on():
    """--no-checksum holds for its command only (perscli.io.checksum.read_options): never after it."""
    from perscli.io.checksum import checksums_enabled

    yield
    assert checksums_enabled(), "a test left CHECKSUM verification off"
