"""Helpers for tests and benchmarks, importable by both, never used by the library itself.

    release.py  replaying one run of the authors' release (the parity fixture)
"""
