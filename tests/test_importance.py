"""The camera's importance (``hemirad.output.importance``): the weight refinement judged on the
answer gives an element's error beside its area, the pixels per unit area the camera gives it."""
import json
from pathlib import Path

import torch

import hemirad
from hemirad.adaptive.answer import split_by_error
from hemirad.adaptive.refine import Refiner
from hemirad.cli import main
from hemirad.output.importance import UNSEEN, view_importance
from hemirad.scene.model import Camera, RefineOptions, Sensor
from patches import quad, quads_mesh

DATA = Path(__file__).parent / "data"


def _facing_squares():
    """Squares facing a camera that looks down -z, side by side at 4 m and 8 m (each 4-9
    degrees off its axis), of 128 elements each, and one behind it."""
    near = quad([-0.6, -0.25, -4.0], [0.5, 0, 0], [0, 0.5, 0])  # front along +z, toward the camera
    far = quad([0.2, -0.5, -8.0], [1, 0, 0], [0, 1, 0])
    behind = quad([-0.5, -0.5, 4.0], [0, 1, 0], [1, 0, 0])
    mesh = quads_mesh([near, far, behind], [0.0625, 0.125, 0.125])
    camera = Camera(position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, -1.0), fov=20.0, width=512, height=512)
    count = mesh.num_elements // 3
    return mesh, camera, [slice(0, count), slice(count, 2 * count), slice(2 * count, None)]


def test_pixels_per_unit_area_fall_as_the_square_of_the_distance_and_unseen_elements_keep_a_floor():
    mesh, camera, (near, far, behind) = _facing_squares()
    weight = view_importance(mesh, camera)
    assert torch.all(weight[behind] == UNSEEN)
    # a square twice as far fills a quarter of the pixels per unit area (the perspective's
    # 1 / d^2, times cos^3 of the angle off the axis: within 1.5% of each other here)
    seen_near, seen_far = ((weight[part] - UNSEEN) / (1 - UNSEEN) for part in (near, far))
    ratio = float(seen_near.mean() / seen_far.mean())
    assert abs(ratio - 4.0) < 0.12, ratio
    # 1 at the picture's mean: the seen squares' weights average 1 over their area
    mean = (0.25 * float(seen_near.mean()) + float(seen_far.mean())) / 1.25
    assert abs(mean - 1.0) < 0.02, mean
    # each element, however few pixel centres fall on it, is weighed by the surface around it
    assert float(seen_near.std() / seen_near.mean()) < 0.05


def test_the_ranking_splits_where_the_camera_looks_first():
    # the square behind the camera has twice the others' squared error times area: by area
    # alone its elements are split; weighed by the camera, the near square's
    mesh, camera, (near, far, behind) = _facing_squares()
    errors = mesh.areas.rsqrt()
    errors[behind] *= 2 ** 0.5
    refiner = Refiner(RefineOptions(pattern="pattern2", criterion="answer", max_depth=1), torch.zeros(mesh.num_elements, 3))
    count = mesh.num_elements // 3
    for importance, chosen in ((None, behind), (view_importance(mesh, camera), near)):
        _, parent = split_by_error(refiner, mesh, errors, count, importance)
        split = torch.bincount(parent, minlength=mesh.num_elements) > 1
        assert bool(split[chosen].all()) and int(split.sum()) == count


def test_a_run_weighs_by_the_camera_unless_it_has_sensors_or_grids(tmp_path):
    scene = hemirad.load_scene(DATA / "small_room.yaml")
    scene.refine.pattern, scene.refine.criterion = "pattern2", "answer"
    assert scene.refine_importance == "camera"
    scene.refine.importance = "surfaces"
    assert scene.refine_importance == "surfaces"
    scene.refine.importance = "auto"
    scene.sensors = [Sensor((0.5, 0.1, 0.5), (0.0, 1.0, 0.0), "desk")]
    assert scene.refine_importance == "surfaces"
    for option in ("camera", "surfaces"):
        out = tmp_path / option
        assert main([str(DATA / "small_room.yaml"), "-q", "-o", str(out), "--refine", "pattern2", "--criterion", "answer",
                     "--importance", option, "--unshot-fraction", "0.05", "--resolution", "32",
                     "--error-samples", "0"]) == 0
        stats = json.loads((out / "stats.json").read_text())
        assert stats["refine"]["importance"] == option and stats["refine"]["rounds"][0]["split"] > 0
