"""Numba kernels: floats and arrays only, status codes out (see STYLE.md).

Importing this package first points Numba's cache for elimfast's code at a folder keyed
by the kernels' sources (_cache.py), before any kernel is compiled or loaded.
"""
from . import _cache

_cache.install()
