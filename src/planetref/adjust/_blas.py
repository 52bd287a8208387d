"""Compatibility name of :mod:`planetref.blas` (BLAS thread limits live there)."""

from planetref.blas import single_threaded_blas

__all__ = ["single_threaded_blas"]
