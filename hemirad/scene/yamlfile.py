"""YAML as scene files are written: YAML 1.2 numbers, merge keys, and no key given twice;
with limits, so a small hostile file cannot exhaust time or memory."""
from __future__ import annotations

import re
from typing import Any

import yaml

from hemirad.core.errors import SceneError

#: How deep a document may nest (a scene needs about 6 levels).
MAX_DEPTH = 64
#: How many values a document may hold once its aliases are expanded (a scene with a
#: thousand objects holds well under 100,000).
MAX_VALUES = 1_000_000
#: The most digits an integer may have: a longer one is read as a number too large for a float.
MAX_DIGITS = 400


class _YamlLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that reads ``1e-3`` as a float and refuses duplicate keys.

    PyYAML follows YAML 1.1, where a float needs a dot (``1e-3`` would be a string);
    scene files are written by people who expect YAML 1.2 numbers. Silently keeping the
    last of two equal keys hides typos, so that is an error too (a key a merge key
    ``<<: *base`` brings in may be overridden, as YAML says). A document nested deeper
    than ``MAX_DEPTH`` or that expands (through aliases) to more than ``MAX_VALUES``
    values is refused before any of it is built.
    """

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent, index):
        # The composer recurses once per level: refuse depth before Python's recursion limit.
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise yaml.composer.ComposerError(
                    None, None, f"the document nests deeper than {MAX_DEPTH} levels", self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_document(self, node):
        _check_expanded_size(node)
        return super().construct_document(node)


def _check_expanded_size(root: yaml.Node) -> None:
    """Refuse a node graph whose aliases expand it beyond ``MAX_VALUES`` values or
    ``MAX_DEPTH`` levels, or that contains itself; linear in the nodes written."""
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    open_: set[int] = set()
    stack = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        key = id(node)
        children = [n for pair in node.value for n in pair] if isinstance(node, yaml.MappingNode) \
            else node.value if isinstance(node, yaml.SequenceNode) else []
        if children_done:
            open_.discard(key)
            size[key] = min(1 + sum(size[id(c)] for c in children), MAX_VALUES + 1)
            depth[key] = 1 + max((depth[id(c)] for c in children), default=0)
            if size[key] > MAX_VALUES or depth[key] > MAX_DEPTH:
                what = (f"expands to more than {MAX_VALUES:,} values" if size[key] > MAX_VALUES
                        else f"nests deeper than {MAX_DEPTH} levels")
                raise yaml.composer.ComposerError(None, None, f"the document {what} (through its aliases)",
                                                  node.start_mark)
            continue
        if key in size:
            continue
        if key in open_:
            raise yaml.composer.ComposerError(None, None, "an alias refers to the value it is inside of",
                                              node.start_mark)
        open_.add(key)
        stack.append((node, True))
        stack.extend((c, False) for c in children if id(c) not in size)


_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?(?:[eE][-+]?[0-9]+)?
                    |[-+]?(?:[0-9][0-9_]*)?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


def _construct_int(loader: _YamlLoader, node: yaml.ScalarNode):
    """An integer; one of more than ``MAX_DIGITS`` digits is infinite as a float, and is read
    as ``_HugeNumber`` (Python refuses to convert more than 4,300 digits at all)."""
    digits = sum(ch.isdigit() for ch in node.value)
    if digits > MAX_DIGITS:
        return _HugeNumber(digits)
    return loader.construct_yaml_int(node)


class _HugeNumber(float):
    """An integer written with too many digits for any float: infinite, shown by its length."""

    def __new__(cls, digits: int):
        self = super().__new__(cls, "inf")
        self.digits = digits
        return self

    def __repr__(self):
        return f"<an integer of {self.digits:,} digits>"


def _construct_mapping(loader: _YamlLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue  # the keys it brings in are checked where they were written
        key = loader.construct_object(key_node, deep=deep)
        if isinstance(key, (str, int, float, bool)) and key in seen:
            raise yaml.constructor.ConstructorError(
                "while reading a mapping", node.start_mark,
                f"found the key {key!r} twice (first on line {seen[key] + 1})", key_node.start_mark)
        if isinstance(key, (str, int, float, bool)):
            seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_YamlLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_YamlLoader.add_constructor("tag:yaml.org,2002:int", _construct_int)


def parse_yaml(shown: str, text: str) -> Any:
    """The document ``text`` as plain data (dicts, lists, numbers, strings); SceneError
    naming ``shown`` and the line where parsing stopped."""
    try:
        return yaml.load(text, Loader=_YamlLoader)  # a SafeLoader: builds only plain data
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "an unknown line"
        problem = " ".join(str(part) for part in (exc.context, exc.problem) if part)
        raise SceneError(shown, "", "valid YAML",
                         hint=f"The YAML parser stopped at {where}: {problem}.") from exc
    except yaml.YAMLError as exc:
        raise SceneError(shown, "", "valid YAML", hint=f"The YAML parser failed: {exc}.") from exc
