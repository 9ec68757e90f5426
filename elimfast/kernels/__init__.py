"""Numba kernels: floats and arrays only, status codes out (see STYLE.md)."""
