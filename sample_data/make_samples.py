"""Regenerate the bundled sample exposures: `make samples` (or python sample_data/make_samples.py DIR)."""
import sys

from perscli.samples import make_sample_sequence

if __name__ == "__main__":
    for path in make_sample_sequence(sys.argv[1] if len(sys.argv) > 1 else "sample_data"):
        print(path)
