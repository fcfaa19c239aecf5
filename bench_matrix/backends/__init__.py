"""The backend axis: the abstract interface and the entry-point registry plugins register with."""

from bench_matrix.backends.base import Backend, ConvertRequest, Session, Support
from bench_matrix.backends.registry import ENTRY_POINT_GROUP, BackendLoadError, available, load_backend

__all__ = ["ENTRY_POINT_GROUP", "Backend", "BackendLoadError", "ConvertRequest", "Session", "Support",
           "available", "load_backend"]
