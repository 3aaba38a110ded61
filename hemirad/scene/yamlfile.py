"""YAML as scene files are written: YAML 1.2 numbers, and no key given twice."""
from __future__ import annotations

import re
from typing import Any

import yaml

from hemirad.core.errors import SceneError


class _YamlLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that reads ``1e-3`` as a float and refuses duplicate keys.

    PyYAML follows YAML 1.1, where a float needs a dot (``1e-3`` would be a string);
    scene files are written by people who expect YAML 1.2 numbers. Silently keeping the
    last of two equal keys hides typos, so that is an error too.
    """


_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?(?:[eE][-+]?[0-9]+)?
                    |[-+]?(?:[0-9][0-9_]*)?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


def _construct_mapping(loader: _YamlLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if isinstance(key, (str, int, float, bool)) and key in seen:
            raise yaml.constructor.ConstructorError(
                "while reading a mapping", node.start_mark,
                f"found the key {key!r} twice (first on line {seen[key] + 1})", key_node.start_mark)
        if isinstance(key, (str, int, float, bool)):
            seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_YamlLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


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
