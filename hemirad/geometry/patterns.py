"""The split patterns by name: the one list a scene's ``refine.pattern``, the command line's
``--refine``, the refiner and the splitter all take their names from.

Pattern 1 splits a triangle at its centroid into three; pattern 2 at its edge midpoints
into four (Hasebe & Makino). ``"none"`` is not a pattern: it turns refinement off.
"""
from __future__ import annotations

#: The refine setting that splits nothing.
NO_REFINEMENT = "none"

#: Children per split, by pattern.
CHILDREN = {"pattern1": 3, "pattern2": 4}

#: Where each pattern splits a triangle, for help texts.
SPLITS_AT = {"pattern1": "centroid", "pattern2": "edge midpoints"}

PATTERNS = tuple(CHILDREN)

#: What ``refine.pattern`` (and ``--refine``) may be.
PATTERN_CHOICES = (NO_REFINEMENT, *PATTERNS)


def describe_patterns() -> str:
    """``"pattern1 (centroid, 1 -> 3), pattern2 (edge midpoints, 1 -> 4)"``"""
    return ", ".join(f"{p} ({SPLITS_AT[p]}, 1 -> {CHILDREN[p]})" for p in PATTERNS)
