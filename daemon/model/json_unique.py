"""JSON whose objects name each key once: what the daemon reads from files and the wire.

``json.loads`` keeps the last of two equal keys silently: ``{"x_um": 10, "x_um": 400}`` is a target of
400 µm, and a model file edited by hand can carry two ``coef`` for one term, the second unseen by the
eye that checked the first. Here a key named twice in one object is :class:`DuplicateKeyError`.
"""

from __future__ import annotations

import json
from typing import Any


class DuplicateKeyError(ValueError):
    """An object names ``key`` twice: which value is meant cannot be told."""

    def __init__(self, key: str) -> None:
        self.key = key
        super().__init__(f"key {key!r} appears twice in one object (which value is meant cannot be told)")


def _unique_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    doc: dict[str, Any] = {}
    for key, value in pairs:
        if key in doc:
            raise DuplicateKeyError(key)
        doc[key] = value
    return doc


def loads_unique(text: str | bytes) -> Any:
    """``json.loads``, refusing a key named twice in one object (:class:`DuplicateKeyError`, a ValueError)."""
    return json.loads(text, object_pairs_hook=_unique_object)
