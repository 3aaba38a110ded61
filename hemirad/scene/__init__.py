"""What a user describes and how it becomes triangles: the scene model, the YAML loader,
mesh files, and meshing into elements."""
from hemirad.scene.model import (Box, Camera, FaceOverride, Material, MeshFile, Quad, RefineOptions, Room, Scene,
                                 SceneObject, SolverOptions)

__all__ = ["Box", "Camera", "FaceOverride", "Material", "MeshFile", "Quad", "RefineOptions", "Room", "Scene",
           "SceneObject", "SolverOptions"]
