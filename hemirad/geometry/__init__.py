"""Triangle meshes and what is computed from their geometry alone: the ``Mesh`` type,
edge keys, splitting (patterns 1 and 2, 2:1 grading) and closed-form form factors."""
