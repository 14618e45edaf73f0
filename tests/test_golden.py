"""perscli's products are the ones recorded in tests/golden/, within tolerances that fit each product.

tests/golden.py says how they are recorded and compared (integers, strings and
integer-valued images exactly; floating data to tolerances justified by the
arithmetic that makes them).  The comparison holds whatever the library versions
and whatever the CPU: the products are made here with this machine's code paths,
and again (slow) with numpy's and OpenBLAS's other code paths forced, which moves
their last bits as another machine would.
"""

import gzip
import os
import shutil
import sys

import numpy as np
import pytest
from astropy.io import fits

import golden


def _check(found):
    assert not found, "products changed beyond their tolerances:\n  " + "\n  ".join(found) + \
        "\n(a change meant: python tests/golden.py --record [--study], said why in the commit)"


def test_the_commands_make_the_recorded_products(tmp_path):
    _check(golden.compare_tree(golden.run_commands(tmp_path), golden.RECORDS / "commands"))


@pytest.mark.slow
def test_the_ci_study_makes_the_recorded_products(tmp_path):
    from test_study import CI

    _check(golden.compare_tree(golden.run_study(tmp_path / "study", CI), golden.RECORDS / "study"))


#: numpy's dispatch without AVX2/FMA (X86_V3) and OpenBLAS's kernels of an older CPU: other roundings, as on
#: another machine (on this one they change the last bits of the fits' results, and so the bytes of measure's
#: products and of every statistic of the study)
OTHER_CODE_PATHS = {"NPY_DISABLE_CPU_FEATURES": "X86_V3", "OPENBLAS_CORETYPE": "Nehalem"}


@pytest.mark.slow
def test_other_code_paths_make_the_recorded_products_within_the_tolerances(tmp_path):
    import numpy

    found = numpy._core._multiarray_umath.__cpu_features__ if hasattr(numpy, "_core") else {}
    env = dict(os.environ, **OTHER_CODE_PATHS)
    if not found.get("AVX2", False):
        env.pop("NPY_DISABLE_CPU_FEATURES")     # nothing to disable: the baseline path is already another
    from test_study import CI

    _check(golden.compare_tree(golden.run_commands(tmp_path / "commands", env=env), golden.RECORDS / "commands"))
    _check(golden.compare_tree(golden.run_study(tmp_path / "study", CI, env=env), golden.RECORDS / "study"))


# -- the comparison can fail ------------------------------------------------------------------------------

def _unpack(name, dest):
    """The recorded product ``name`` of the commands as a plain FITS file in ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    with gzip.open(golden.RECORDS / "commands" / golden.record_name(name)) as src, open(dest / name, "wb") as out:
        shutil.copyfileobj(src, out)
    return dest / name


def _edit(path, edit):
    with fits.open(path, mode="update", checksum=False) as hdul:
        edit(hdul)
        hdul.flush(output_verify="silentfix")


def _differences(path, name):
    return golden.differences(path, golden.RECORDS / "commands" / golden.record_name(name), name)


def test_the_records_compare_equal_to_themselves(tmp_path):
    for name in golden.COMMANDS:
        assert _differences(_unpack(name, tmp_path), name) == []


def test_a_fitted_value_moved_beyond_its_tolerance_is_a_changed_product(tmp_path):
    """measure's g1 within FIT's tolerance passes; ten times beyond it fails, naming the product, HDU and column."""
    path = _unpack("shapes.fits", tmp_path)
    g1 = fits.getdata(path, "SHAPES")["g1"].copy()
    allowed = float(golden.FIT.bound(g1[:1])[0])

    def shift(by):
        def edit(hdul):
            hdul["SHAPES"].data["g1"][0] = g1[0] + by
        return edit

    _edit(path, shift(0.5 * allowed))
    assert _differences(path, "shapes.fits") == []
    _edit(path, shift(10 * allowed))
    found = _differences(path, "shapes.fits")
    assert len(found) == 1 and found[0].startswith("shapes.fits[SHAPES] column g1: 1 value(s) beyond"), found


def test_an_integer_a_whole_dn_and_a_header_value_are_compared(tmp_path):
    cases = {
        "shapes.fits": lambda h: h["SHAPES"].data["nfev"].__setitem__(0, h["SHAPES"].data["nfev"][0] + 1),
        "e1.fits": lambda h: h["SCI"].data.__setitem__((40, 40), h["SCI"].data[40, 40] + 1),
        "e0.fits": lambda h: h["SCI"].header.__setitem__("SKYRATE", h["SCI"].header["SKYRATE"] * (1 + 1e-9)),
        "truth.fits": lambda h: h["TRUTH"].header.__setitem__("NGAL", h["TRUTH"].header["NGAL"] + 1),
    }
    for name, edit in cases.items():
        path = _unpack(name, tmp_path / name.split(".")[0])
        _edit(path, edit)
        found = _differences(path, name)
        assert len(found) == 1, (name, found)
    assert "column nfev" in _differences(tmp_path / "shapes" / "shapes.fits", "shapes.fits")[0]
    assert "SKYRATE" in _differences(tmp_path / "e0" / "e0.fits", "e0.fits")[0]


def test_the_clock_checksums_input_digests_and_version_are_not_compared(tmp_path):
    path = _unpack("e1.fits", tmp_path)

    def edit(hdul):
        hdul[0].header["DATE"] = "2099-01-01T00:00:00"
        hdul[0].header["PRV01DS"] = "123"              # DATASUM of an input: follows the input's bytes
        hdul[0].header["CREATOR"] = "perscli 9.9.9"
        hdul["SCI"].data[0, 0] = hdul["SCI"].data[0, 0]

    _edit(path, edit)
    with fits.open(path, mode="update") as hdul:
        hdul.flush()                                   # new CHECKSUM/DATASUM cards
    assert _differences(path, "e1.fits") == []


def test_a_float32_image_within_two_ulp_passes_and_beyond_fails(tmp_path):
    path = _unpack("predict.fits", tmp_path)
    sci = fits.getdata(path, "SCI").astype(np.float32)
    k = np.unravel_index(int(np.argmax(sci)), sci.shape)

    def set_to(value):
        def edit(hdul):
            hdul["SCI"].data[k] = value
        return edit

    _edit(path, set_to(np.nextafter(np.nextafter(sci[k], np.float32(np.inf)), np.float32(np.inf))))
    assert _differences(path, "predict.fits") == []
    _edit(path, set_to(sci[k] * np.float32(1 + 1e-5)))
    assert "predict.fits[SCI]: 1 value(s) beyond" in _differences(path, "predict.fits")[0]


def test_printed_numbers_are_compared_to_their_printed_digits():
    tol = golden.DE_STATS
    assert golden.text_differs("xi+ 5.13e-08 (4 bins)", "xi+ 5.14e-08 (4 bins)", tol) is None
    assert golden.text_differs("xi+ 5.13e-08 (4 bins)", "xi+ 6.13e-08 (4 bins)", tol)
    assert golden.text_differs("xi+ 5.13e-08 (4 bins)", "xi+ 5.13e-08 (5 bins)", tol)      # integers exact
    assert golden.text_differs("perscli 0.1.0: DATASUM 12", "perscli 0.2.0: DATASUM 13", tol) is None


def test_a_figure_that_lost_a_curve_is_a_changed_product(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def draw(path, curve):
        fig, ax = plt.subplots(figsize=(4, 3), dpi=50)
        ax.plot([0, 1], [0, 1], color="k")
        if curve:
            ax.plot([0, 1], [1, 0], color="k", lw=4)
        fig.savefig(path)
        plt.close(fig)

    draw(tmp_path / "a.png", True)
    draw(tmp_path / "b.png", True)
    draw(tmp_path / "c.png", False)
    record = golden.thumbnail(tmp_path / "a.png")
    assert golden.png_differences(tmp_path / "b.png", record, "f.png") == []
    assert "grey levels" in golden.png_differences(tmp_path / "c.png", record, "f.png")[0]


def test_every_command_product_is_recorded():
    recorded = {golden._product_of(p.name) for p in (golden.RECORDS / "commands").iterdir()}
    assert recorded == set(golden.COMMANDS), sys.exc_info()
