"""Test helper (not a test file): copies of JSON documents with one field changed or removed."""
from __future__ import annotations

import copy
from typing import Any


def with_field(doc: dict, dotted: str, value: Any) -> dict:
    """A deep copy of ``doc`` with the field at ``dotted`` (e.g. "objects.0.location"; digits
    index lists) set to ``value``, or deleted when ``value`` is ``KeyError``."""
    doc = copy.deepcopy(doc)
    keys = [int(k) if k.isdigit() else k for k in dotted.split(".")]
    node = doc
    for k in keys[:-1]:
        node = node[k]
    if value is KeyError:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return doc
