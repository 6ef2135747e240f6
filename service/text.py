"""Text that is not text: a lone surrogate in a parsed JSON document.

    lone_surrogate({"name": "a\\ud800"})      # ("name", "a\\\\ud800"): the field, escaped

Python's JSON reader turns ``"\\ud800"`` (and the UTF-8 bytes ED A0 80) into
a str holding half of a UTF-16 pair. No database, JSON writer or file name
takes it; found late, it is a 500 far from its cause. Requests are checked
where they are parsed (service.api.deps, scenes' upload), so the 422 names
the field.
"""

from __future__ import annotations

import re
from typing import Any

__all__ = ["lone_surrogate", "escaped"]

_SURROGATE = re.compile("[\ud800-\udfff]")


def escaped(text: str) -> str:
    """`text` with each lone surrogate written as its escape (``\\ud800``)."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def lone_surrogate(document: Any) -> tuple[str, str] | None:
    """(the field's name, its escaped text) of the first string of a parsed JSON
    document, a key or a value, that holds a lone surrogate; None if none does.
    Names read as elsewhere: ``options.radius``, ``configs[2].method``."""
    pending: list[tuple[str, Any]] = [("", document)]
    while pending:
        name, value = pending.pop()
        if isinstance(value, str):
            if _SURROGATE.search(value):
                return name, escaped(value)
        elif isinstance(value, dict):
            for key, item in value.items():
                if _SURROGATE.search(key):
                    return (f"{name}.{escaped(key)}" if name else escaped(key)), escaped(key)
                pending.append((f"{name}.{key}" if name else key, item))
        elif isinstance(value, list):
            pending.extend((f"{name}[{i}]", item) for i, item in enumerate(value))
    return None
