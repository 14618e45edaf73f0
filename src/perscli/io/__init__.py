"""One FITS layer for every command: frames in, FITS files out."""
