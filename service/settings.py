"""The service reads the one settings class of rayfarm (it lives in `worker`,
the lower layer, because the workers read it too)."""

from worker.settings import Settings

__all__ = ["Settings"]
