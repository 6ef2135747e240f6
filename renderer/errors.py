"""The renderer's exceptions, as one small tree.

    RenderError                 anything the renderer refuses or cannot do
     ├── SceneError             a scene document is invalid (names where: `location`)
     └── SpecError              render parameters are invalid (names the field)

Domain code raises these; the service maps them to HTTP status codes in one
place, the CLI prints them. Neither knows about the other.
"""

from __future__ import annotations

__all__ = ["RenderError", "SceneError", "SpecError"]


class RenderError(Exception):
    """Base class of everything the renderer refuses."""


class SceneError(RenderError):
    """An invalid scene document; `location` is a JSON path such as
    ``shapes[3].to_world`` (empty for the document as a whole)."""

    def __init__(self, message: str, location: str = ""):
        self.message = message
        self.location = location
        super().__init__(f"{location}: {message}" if location else message)


class SpecError(RenderError):
    """Invalid render parameters; `field` names the offending parameter."""

    def __init__(self, field: str, message: str):
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")
