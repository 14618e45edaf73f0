"""The ``perscli`` command line: a thin layer over the library modules."""
