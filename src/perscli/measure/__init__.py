"""Galaxy shape measurement: exact exponential-mixture fits through the PSF."""
