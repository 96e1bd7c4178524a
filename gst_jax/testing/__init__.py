"""Helpers for tests and benchmarks, importable by both, never used by the library itself.

    release.py  replaying one run of the authors' release (the parity fixture)
    drawn.py    what a figure draws: its lines, bars and pixels in colour
"""
