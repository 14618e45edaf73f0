"""Build the compiled hot loops; everything else is declared in pyproject.toml."""
from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "perscli._kernels",
            ["src/perscli/_kernels.c"],
            extra_compile_args=["-O3", "-std=c99", "-fno-trapping-math"],
        )
    ]
)
