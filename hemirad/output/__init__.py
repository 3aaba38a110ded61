"""What a solve is turned into: per-vertex display values and tone mapping, the camera view,
surface mesh views, PNG / PLY / JSON and glTF files."""
