"""hemirad: progressive-refinement radiosity with OpenGL hemicubes and autograd-driven meshing."""
from hemirad.core.errors import HemiradInputError, SceneError
from hemirad.pipeline import Result, solve
from hemirad.scene.loader import bundled_scenes, load_scene

__all__ = ["load_scene", "bundled_scenes", "solve", "Result", "HemiradInputError", "SceneError"]
__version__ = "0.5.0"
