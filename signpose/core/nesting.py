"""A check a text reader runs before it parses YAML or JSON: bracket nesting.

PyYAML parses brackets nested a thousand deep for seconds before it gives up
with a RecursionError; a calibration file, a map or a bag's ``metadata.yaml``
is never nested more than a few levels, so deeper nesting is refused at once,
with the limit in the message. ``safe_load_unique`` is the YAML parse itself,
refusing a key given twice. In ``core`` so that every layer's readers (the
map loader in ``maps``, the file formats in ``io``) use the same check.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from signpose.core.errors import InputError

MAX_NESTING = 64  # flow brackets ([ {) open at once; real files use at most 3


def flow_nesting(text: str) -> int:
    """The deepest nesting of ``[``/``{`` in ``text``, outside quotes and ``#`` comments."""
    depth = deepest = 0
    quote = ""
    comment = False
    for ch in text:
        if comment:
            comment = ch != "\n"
        elif quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            comment = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth = max(0, depth - 1)
    return deepest


def check_nesting(text: str, path: Path, limit: int = MAX_NESTING) -> None:
    """InputError naming ``path`` when ``text`` nests brackets deeper than ``limit``."""
    if flow_nesting(text) > limit:
        raise InputError(f"{path}: brackets nested deeper than {limit} levels; not a valid file")


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a mapping that gives a key twice.

    ``yaml.safe_load`` keeps the last of two equal keys without a word: a map
    with two ``center_m:`` lines for one sign (an edit gone wrong) would put the
    sign where the second says. Refused instead, with the line.
    """

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                if isinstance(key, (str, int, float, bool)) or key is None:
                    if key in seen:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"found duplicate key {key!r}", key_node.start_mark
                        )
                    seen.add(key)
        return super().construct_mapping(node, deep)


def safe_load_unique(text: str):
    """``yaml.safe_load(text)``, but a key given twice in one mapping is a ConstructorError."""
    return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)
