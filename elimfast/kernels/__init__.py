"""Numba kernels: floats and arrays only, status codes out (see STYLE.md).

Importing this package first points Numba's cache for elimfast's code at a folder keyed
by the kernels' sources (_cache.py), and registers the one-line compile notice
(compile_notice.py), before any kernel is compiled or loaded.
"""
from .. import compile_notice
from . import _cache

_cache.install()
compile_notice.announce()
