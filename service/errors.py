"""The service's exceptions, as one small tree.

    ServiceError                  anything the service refuses
     ├── Unauthorized             no valid token (missing, unknown, expired, revoked)
     ├── Forbidden                a valid token whose role may not do this
     ├── RateLimited              too many requests for now; `retry_after` seconds
     ├── NotFound                 no such job, or its image is not there (yet), or not
     │    │                       the caller's to see (no existence leak)
     │    └── ResultNotReady      the job exists but has no finished image
     ├── Conflict                 the request contradicts the job's state
     │    └── IllegalTransition   a status change the state table forbids
     ├── InvalidRequest           a field of the request is invalid (names it)
     ├── TooLarge                 the request exceeds a size limit (names it)
     └── InsufficientStorage      no room for new work now (a full disk); `retry_after` seconds

The renderer's `SceneError` and `SpecError` are invalid requests too. Domain
code raises these; `service.api.errors` maps them to HTTP in one place.
"""

from __future__ import annotations

__all__ = ["ServiceError", "Unauthorized", "Forbidden", "RateLimited", "NotFound", "ResultNotReady", "Conflict", "IllegalTransition",
           "InvalidRequest", "TooLarge", "InsufficientStorage"]


class ServiceError(Exception):
    """Base class of everything the service refuses."""


class Unauthorized(ServiceError):
    pass


class Forbidden(ServiceError):
    pass


class RateLimited(ServiceError):
    """Refused for now; the same request may succeed after `retry_after` seconds."""

    def __init__(self, message: str, retry_after: float):
        self.retry_after = retry_after
        super().__init__(message)


class NotFound(ServiceError):
    pass


class ResultNotReady(NotFound):
    pass


class Conflict(ServiceError):
    pass


class IllegalTransition(Conflict):
    """`kind` ('job' or 'unit') `name` cannot go from `old` to `new`."""

    def __init__(self, kind: str, name: str, old: str, new: str, allowed: frozenset[str]):
        self.kind, self.name, self.old, self.new = kind, name, old, new
        options = ", ".join(sorted(allowed)) or "none, it is final"
        super().__init__(f"{kind} {name} cannot go from '{old}' to '{new}' "
                         f"(allowed from '{old}': {options})")


class InvalidRequest(ServiceError):
    """An invalid request field; `field` is its name (dotted for nested ones,
    ``files[2]`` for list items), `source` where it was sent (body, query, path)."""

    def __init__(self, field: str, message: str, source: str = "body"):
        self.field, self.message, self.source = field, message, source
        super().__init__(f"{field}: {message}")


class TooLarge(ServiceError):
    """The request is bigger than a limit allows (bytes, number of files)."""


class InsufficientStorage(ServiceError):
    """No room to store new work (the data dir's disk, the ledger); what is
    stored is kept. The same request may succeed after `retry_after` seconds."""

    def __init__(self, message: str, retry_after: float):
        self.retry_after = retry_after
        super().__init__(message)
