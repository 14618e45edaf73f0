"""render's settings (perscli.render.settings.RenderOptions): defaults written once, read by the command
and the library; the module stays light so that ``perscli render --help`` is fast."""

import dataclasses
import subprocess
import sys

import pytest

from perscli.render.settings import DEFAULT_HDUS, HDU_NAMES, RenderOptions


def test_the_settings_module_imports_nothing_heavy():
    code = ("import sys, perscli.render.settings, perscli.cli.render; "
            "print(sorted(m for m in ('numpy', 'galsim', 'astropy', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_command_takes_its_defaults_from_render_options():
    from perscli.cli.render import render

    d = RenderOptions()
    params = {p.name: p for p in render.params}
    assert params["hdus"].default == ",".join(d.hdus) == ",".join(DEFAULT_HDUS)
    assert params["compress"].default == d.compress
    assert params["persistence_source"].default == d.persistence_source
    assert params["strict"].default is d.strict
    assert set(DEFAULT_HDUS) <= set(HDU_NAMES)


def test_options_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        RenderOptions().compress = "gzip"
