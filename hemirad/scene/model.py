"""What a scene is: materials, objects, camera, solver options, sensors and calculation
grids (data only).

Reading these from a YAML file is ``loader.py``'s job; turning objects into triangles is
``meshing.py``'s. Lengths are in scene units (``Scene.metres_per_unit`` metres each);
radiosity and emission are exitances per square metre (W/m^2, or lm/m^2 in a photometric
scene); colours are linear RGB.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import torch

from hemirad.geometry.patterns import NO_REFINEMENT

#: The per-shot refinement criteria by name. Each is defined in
#: ``hemirad.adaptive.criteria.CRITERIA``, whose keys are checked against these (the loader, a
#: layer below, reads the names from here).
SHOT_CRITERION_NAMES = ("gradient", "receiver", "partial_visibility", "neighbor_difference", "uniform")
#: What a scene's ``refine.criterion`` (and ``--criterion``) may be: a per-shot criterion,
#: ``answer``: refine between converged solves where the solution is worst (``adaptive.answer``),
#: or ``auto``: ``answer`` where patches shoot, the paper's ``gradient`` where every element
#: does (``Scene.refine_criterion``).
ANSWER = "answer"
AUTO_CRITERION = "auto"
CRITERION_NAMES = SHOT_CRITERION_NAMES + (ANSWER, AUTO_CRITERION)
#: The criterion ``auto`` means where every element shoots (and for a refiner without a scene).
PAPER_CRITERION = "gradient"
#: What a scene's ``refine.importance`` (and ``--importance``) may be: weigh an element's
#: error by the pixels per unit area the camera gives it, by nothing beside its area, or
#: ``auto``: the camera unless the scene has sensors or grids (``Scene.refine_importance``).
CAMERA_IMPORTANCE, SURFACES_IMPORTANCE, AUTO_IMPORTANCE = "camera", "surfaces", "auto"
IMPORTANCE_CHOICES = (AUTO_IMPORTANCE, CAMERA_IMPORTANCE, SURFACES_IMPORTANCE)


#: The emission a material may have, besides 0: radiosity (up to emission / (1 - reflectance),
#: times areas for power) must stay a normal 32-bit float in the PLY and glTF outputs.
MIN_EMISSION, MAX_EMISSION = 1e-20, 1e20


#: What a scene's ``units`` may be: what its emissions (and so its results) are measured in.
UNITS = ("radiometric", "photometric")
#: How receivers that cover few hemicube pixels get their form factors: what a scene's
#: ``solver.small_receivers`` (and ``--small-receivers``) may be: their pixels' sum; the
#: closed form times the visibility the hemicube finds (``transport.smallreceivers``) in the
#: lamps' shots (``lamps``), and in every shot for receivers under a pixel too
#: (``closed_form``); or ``auto`` (``resolved_small_receivers``).
SMALL_RECEIVER_CHOICES = ("auto", "pixels", "lamps", "closed_form")


#: ``reflector_resolution: auto`` halves ``resolution`` for reflecting nodes down to this.
REFLECTOR_RESOLUTION_FLOOR = 128


def resolved_reflector_resolution(options: "SolverOptions") -> int:
    """``solver.reflector_resolution`` made definite: ``auto`` is half of ``resolution``, but
    not under ``REFLECTOR_RESOLUTION_FLOOR`` (nor over ``resolution``). A reflector's light
    reaches each receiver from hundreds of nodes, whose pixel luck averages out, and is
    weaker than a lamp's; its hemicube's cost is mostly its pixels. Measured on the furnished
    room (hemicube 256, 10,164 elements, 185 path-traced points): reflectors at 128, 14.8 and
    15.3 s against 18.7 and 18.0 s interleaved, median error 2.20% against 2.09%, relative RMS
    4.66% against 4.56%. At 128 and under, as the bundled scenes ask, nothing changes; nor
    where reflectors' small receivers get closed forms (``ProgressiveSolver._renderer_of``)."""
    if options.reflector_resolution != "auto":
        return int(options.reflector_resolution)
    return min(options.resolution, max(REFLECTOR_RESOLUTION_FLOOR, options.resolution // 2 // 2 * 2))


def resolved_small_receivers(small_receivers: str, refined: bool) -> str:
    """``solver.small_receivers`` made definite for a solve on a mesh that is ``refined`` (by
    shots' refinement, or the answer's rounds after the first) or not: ``auto`` is
    ``closed_form`` on a refined mesh and ``lamps`` on an unrefined one. Measured, converged
    (relMSE): on the bundled scenes' shipped meshes ``lamps`` 0.00117 (Cornell box), 0.00162
    (floating), 0.00072 (office) in the seconds of the pixel sums' 0.00136, 0.00164,
    0.00077, where ``closed_form`` gives the same error in 30-50% more seconds; floating
    refined by the answer to 11,000 elements, ``lamps`` 0.00014 and ``closed_form`` 0.00004 in
    the same seconds (refined elements are under a pixel even from their near shooters). The
    answer's first solve, on the unrefined mesh, with ``lamps`` rather than ``closed_form``:
    the same relMSE to 2% (from x1: 0.00059, 0.00026, 0.00052 on the Cornell box, floating,
    office), the same elements split, in about two thirds of the seconds (floating from x1
    4.6 s -> 2.9 s)."""
    if small_receivers != "auto":
        return small_receivers
    return "closed_form" if refined else "lamps"


#: ``solver.reconstruction`` (and ``--reconstruction``): how element values reach the vertices
#: that shading, exports and error estimates interpolate: a quadratic fitted around each
#: vertex, or the paper's area-weighted mean (``hemirad.output.reconstruction``).
RECONSTRUCTION_CHOICES = ("quadratic", "mean")
#: ``solver.final_gather`` (and ``--final-gather``): which elements take, once the solve ends,
#: the light a hemicube at their centroid gathers (``hemirad.lighting.gathered``): none; those
#: beside contact lines and the rims of what stands on or hangs under a surface; or all.
FINAL_GATHER_CHOICES = ("none", "contacts", "all")


@dataclass
class Material:
    """A diffuse material. An emitter gives either ``emission`` (an exitance) or ``flux``
    (the total luminous flux, in lumens, of every surface of the material together, turned
    into an exitance once the scene is meshed; ``colour`` is then its chromaticity)."""

    name: str
    reflectance: tuple[float, float, float]  # diffuse, each in [0, 1)
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)  # exitance, >= 0
    flux: float | None = None  # lumens, instead of emission
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)  # the flux's colour (linear RGB)

    @property
    def emits(self) -> bool:
        return max(self.emission) > 0 or (self.flux is not None and self.flux > 0)


@dataclass
class FaceOverride:
    """Per-face settings of a room; ``None`` means "as the room"."""

    material: str | None = None
    element_size: float | None = None


@dataclass
class Room:
    """An axis-aligned cuboid seen from inside: six faces with inward normals.

    Faces are named ``floor`` (y = min), ``ceiling`` (y = max), ``x_min``, ``x_max``,
    ``z_min`` and ``z_max``.
    """

    min: tuple[float, float, float]
    max: tuple[float, float, float]
    material: str
    element_size: float
    faces: dict[str, FaceOverride] = field(default_factory=dict)
    name: str = "room"
    patch_size: float | str | None = None  # "auto", "none" or a length; None: the solver's

    FACE_NAMES = ("floor", "ceiling", "x_min", "x_max", "z_min", "z_max")


@dataclass
class Box:
    """An axis-aligned box seen from outside: six faces with outward normals."""

    min: tuple[float, float, float]
    max: tuple[float, float, float]
    material: str
    element_size: float
    name: str = "box"
    patch_size: float | str | None = None  # "auto", "none" or a length; None: the solver's


@dataclass
class Quad:
    """A one-sided planar quadrilateral; the front is where its corners run counter-clockwise."""

    corners: tuple[tuple[float, float, float], ...]  # four points
    material: str
    element_size: float
    name: str = "quad"
    patch_size: float | str | None = None  # "auto", "none" or a length; None: the solver's


@dataclass
class MeshFile:
    """A triangle mesh read by trimesh (OBJ, PLY, GLB, ...), placed by a 4x4 transform.

    Its faces have ``material``, or, when that is None, the materials the file gives them
    (glTF, OBJ + MTL: ``hemirad.scene.filematerials``), each the scene material that
    ``file_materials`` maps the file's material name to.
    """

    path: Path
    material: str | None
    element_size: float
    transform: tuple[tuple[float, ...], ...] = (
        (1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    crease_angle: float = 30.0  # degrees: vertices are not shared across sharper edges
    name: str = "mesh"
    patch_size: float | str | None = None  # "auto", "none" or a length; None: the solver's
    # the file's material name -> the scene's material name, for the materials its faces use
    file_materials: dict[str, str] = field(default_factory=dict)
    # the file as the loader read it (hemirad.scene.meshfile.MeshContents), so that meshing
    # does not parse it again; None: read when meshed
    contents: object = field(default=None, repr=False, compare=False)


SceneObject = Room | Box | Quad | MeshFile


@dataclass
class Camera:
    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov: float = 40.0  # vertical field of view, degrees
    width: int = 512
    height: int = 512
    exposure: float | None = None  # display value per unit radiosity; None: automatic
    supersample: int = 3  # antialiasing: rendered at this factor and box-filtered


@dataclass
class SolverOptions:
    max_shots: int = 100_000  # a guard: a run stops by unshot_fraction first
    unshot_fraction: float = 1e-3  # stop when unshot power / emitted power falls below
    resolution: int = 128  # hemicube top face is resolution x resolution pixels
    # with patches: the hemicube resolution of nodes that emit nothing; auto:
    # ``resolved_reflector_resolution``
    reflector_resolution: int | str = "auto"
    ambient: bool = True  # add Cohen et al.'s ambient term to the displayed radiosity
    device: str = "cpu"  # where the torch work runs: one of hemirad.core.device.DEVICE_NAMES
    # Patches that shoot for their elements: "auto" (about 2 x 2 elements), a side length,
    # or None: every element shoots (the paper's configuration).
    patch_size: float | str | None = "auto"
    overshoot: bool = True  # with patches: shoot rho times the ambient more (Feda & Purgathofer)
    # with patches: every patch with unshot power shoots at once from the kept light (Jacobi
    # sweeps) instead of the strongest alone, whenever no refiner runs the shots
    sweeps: bool = True
    shooter_split: float | None = None  # with patches: split a shooter where eq. 7 exceeds this share
    # with patches: an emitting node shoots from the centroids of 4**emitter_eyes equal parts
    # of each of its elements (``transport.shooters.eye_points``) instead of its centroid;
    # auto: ``assembly.emitter_eye_level``
    emitter_eyes: int | str = "auto"
    cache_mb: float = 256.0  # memory for form-factor rows kept between a shooter's shots
    # How receivers covering few hemicube pixels get their form factors: one of
    # SMALL_RECEIVER_CHOICES (hemirad.transport.smallreceivers).
    small_receivers: str = "auto"
    # points at which the solution checks itself (``evaluation.gathered_error``): stats.json's
    # estimated error, and what refinement judged on the answer stops by; 0: no estimate
    error_samples: int = 1000
    # the same check at points the camera's pixels see, weighted as a per-pixel comparison
    # with a rendered reference weighs them (``Result.estimate_image_error``): stats.json's
    # estimated_picture_error; 0 (the default): none, as it costs another 1-4 s
    picture_error_samples: int = 0
    reconstruction: str = "quadratic"  # one of RECONSTRUCTION_CHOICES
    final_gather: str = "none"  # one of FINAL_GATHER_CHOICES

    @property
    def shoots_patches(self) -> bool:
        """Whether patches shoot for their elements (``patch_size`` not none)."""
        return self.patch_size not in (None, "none")

    def paper(self) -> None:
        """Shoot as the paper does: every element, from its centroid, no overshooting, each
        receiver's form factor its pixels' sum, vertices shaded by the mean of their elements."""
        self.patch_size, self.overshoot, self.shooter_split, self.sweeps = None, False, None, False
        self.small_receivers, self.reconstruction = "pixels", "mean"


@dataclass
class RefineOptions:
    """Adaptive meshing during the solve (docs/DESIGN.md §2, §3)."""

    pattern: str = NO_REFINEMENT  # or a split pattern: hemirad.geometry.patterns.PATTERN_CHOICES
    # one of CRITERION_NAMES; the default, auto, is answer with patches: per element it beat
    # uniform meshes on every bundled scene, which no per-shot criterion did
    # (figures/accuracy_converged.md, figures/accuracy.md)
    criterion: str = AUTO_CRITERION
    threshold: float = 3e-4  # luminance of radiosity per shot (a length for the uniform criterion)
    relative: bool = True  # threshold as a fraction of the brightest emitter's radiosity
    max_depth: int = 4  # splits of one initial element, at most
    min_area: float = 0.0  # never make elements smaller than this
    max_elements: int = 200_000  # element budget; the largest scores are split first
    shots: int | None = None  # refine during the first this many shots, then shoot on; None: every shot
    interior: bool = True  # gradient terms, for accuracy studies
    shadow_edges: bool = True
    view_surface: str | None = None  # surface shown in mesh.png; default: the floor
    # criterion "answer": stop refining when the estimated relative RMS error (by final
    # gathers, ``evaluation.gathered_error``; about 1-2x what the references measure) is below
    # ``tolerance``, or after ``rounds`` refinements (each grows the elements at most 5.5 times,
    # and no more than the tolerance is predicted to need: ``adaptive.answer.tolerance_splits``)
    tolerance: float = 0.01
    rounds: int = 1  # each round grows the elements up to round_growth times, and the seconds more (figures/accuracy_converged.md)
    # criterion "answer": the most a round may grow the elements; fewer, larger rounds cost
    # fewer solves, more, smaller ones find what the coarser solves could not see (a contact
    # line's floor): ``adaptive.answer.ROUND_GROWTH``
    round_growth: float = 5.5
    # criterion "answer": what an element's error is weighed by beside its area, one of
    # IMPORTANCE_CHOICES: the pixels per unit area the scene's camera gives it (``camera``,
    # ``output.importance``), or nothing (``surfaces``); auto: camera unless the scene has
    # sensors or grids, whose light on the surfaces is what it is for
    importance: str = AUTO_IMPORTANCE

    @property
    def enabled(self) -> bool:
        return self.pattern != NO_REFINEMENT

    def resolved_criterion(self, patches: bool) -> str:
        """``criterion`` made definite for a solver where ``patches`` shoot or not: ``auto`` is
        ``answer`` where they do and the paper's ``gradient`` where every element shoots (the
        answer's rounds solve each refined mesh by patches)."""
        if self.criterion != AUTO_CRITERION:
            return self.criterion
        return ANSWER if patches else PAPER_CRITERION


@dataclass
class Sensor:
    """A point where the irradiance on a small area facing ``normal`` is wanted."""

    position: tuple[float, float, float]
    normal: tuple[float, float, float]  # non-zero; need not be a unit vector
    name: str


@dataclass
class Grid:
    """A calculation grid: the rectangle ``origin``, ``origin + u``, ``origin + u + v``,
    ``origin + v`` (``u`` and ``v`` perpendicular), its points at the centres of equal
    cells, each measuring the irradiance on a small area facing ``normal``.

    Attributes:
        spacing: the largest distance between points (scene units); None: EN 12464-1's
            from the longer side (``hemirad.lighting.grids.standard_spacing``).
        key: where the grid is in the scene file (``grids[0]``), for messages.
    """

    name: str
    origin: tuple[float, float, float]
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    normal: tuple[float, float, float]
    spacing: float | None = None
    key: str = ""


@dataclass
class MeshingOptions:
    """How the initial mesh is made (scene key ``meshing``)."""

    # Mesh each planar surface that others touch (a block on a floor) conforming to where
    # they touch, the covered part dropped (``hemirad.scene.contacts``). ``auto``: where
    # patches shoot, off in the paper's configuration (``Scene.meshes_contacts``; README,
    # Contact meshing). False: every surface is meshed on its own, as the paper's figures were.
    contacts: bool | str = "auto"
    # Cut surfaces where others pass through them (a lamp's barrel through its globe) and
    # drop what lies inside a closed solid (``hemirad.scene.intersections``): an element
    # straddling the other surface, or inside a solid, loses its light to back faces. On
    # by default: it changes no surface of a scene where nothing cuts through anything
    # (the bundled scenes, the paper's figures), and costs little where nothing does.
    intersections: bool = True
    # Grade quads' grids toward the sides where another surface stands facing them (a wall
    # on a floor): a strip of elements a quarter wide along every concave crease
    # (``hemirad.geometry.creases``). ``auto``: with refinement judged on the answer, whose
    # rounds refine elements whole and would spend a crease's whole length of them there.
    creases: bool | str = "auto"


@dataclass
class Scene:
    materials: list[Material]
    objects: list[SceneObject]
    camera: Camera
    solver: SolverOptions = field(default_factory=SolverOptions)
    refine: RefineOptions = field(default_factory=RefineOptions)
    source: Path | None = None  # the file it was read from
    sensors: list[Sensor] = field(default_factory=list)
    grids: list[Grid] = field(default_factory=list)
    units: str = "radiometric"  # one of UNITS
    metres_per_unit: float = 1.0  # the scene's length unit in metres (grid spacing, flux to exitance)
    # Keys whose value a command-line option set, e.g. {"solver.resolution": "--resolution"}:
    # an error about such a value names the option, not the scene file.
    command_line: dict[str, str] = field(default_factory=dict)
    # Surfaces (names as for refine.view_surface) drawn as false-colour maps of the light
    # falling on them, one falsecolour_<name>.png each.
    falsecolour: list[str] = field(default_factory=list)
    meshing: MeshingOptions = field(default_factory=MeshingOptions)

    @property
    def refine_criterion(self) -> str:
        """The refinement criterion this scene runs (``RefineOptions.resolved_criterion``)."""
        return self.refine.resolved_criterion(self.solver.shoots_patches)

    @property
    def refines_by_answer(self) -> bool:
        """Refinement between converged solves, judged on the solution (``adaptive.answer``)."""
        return self.refine.enabled and self.refine_criterion == ANSWER

    @property
    def meshes_contacts(self) -> bool:
        """``meshing.contacts`` made definite: ``auto`` is on where patches shoot (the default
        configuration, refinement judged on the answer included) and off in the paper's
        (every element shoots), whose figures keep the meshes they were measured with.
        Measured against the references (relMSE, converged, the default configuration), the
        uniform meshes: Cornell box 0.00117 -> 0.00058 (2,660 -> 2,582 elements) and 0.00035
        -> 0.00015 (10,162 -> 9,820), office 0.00072 -> 0.00050 and 0.00016 -> 0.00013, floating
        0.00162 -> 0.00029 and 0.00053 -> 0.00004 (the ceiling its lamp hangs under lost
        the dark halo that elements straddling the lamp's outline drew), in about the same
        hemicubes; the furnished room of ``scripts/peer_room.py`` median 2.2% -> 1.7%,
        relative RMS 4.7% -> 3.4% at its 185 points (its ceiling round the lamps' barrels).
        With the answer: the Cornell box's first round 0.00059 against 0.00084 without, its
        third 0.00021 against 0.00029, with 22 of the 26 floor points 1 cm outside the blocks
        within 5% (12 without; 25 since arithmetic 12). Locally, at the shipped 4 cm
        elements, the floor 1 cm beside a block reads further off with its footprint meshed
        (README, Contact meshing): the light changes too fast there for any element that
        size; refinement resolves it."""
        contacts = self.meshing.contacts
        return (self.solver.shoots_patches or self.refines_by_answer) if contacts == "auto" else bool(contacts)

    @property
    def refine_importance(self) -> str:
        """``refine.importance`` made definite: ``auto`` is ``camera`` unless the scene has
        sensors or grids (README, Refinement judged on the answer)."""
        importance = self.refine.importance
        if importance != AUTO_IMPORTANCE:
            return importance
        return SURFACES_IMPORTANCE if (self.sensors or self.grids) else CAMERA_IMPORTANCE

    @property
    def meshes_creases(self) -> bool:
        """``meshing.creases`` made definite: ``auto`` is on with refinement judged on the
        answer (README, Concave creases)."""
        creases = self.meshing.creases
        return self.refines_by_answer if creases == "auto" else bool(creases)

    def with_element_sizes_scaled(self, factor: float) -> "Scene":
        """A copy of the scene with every element size (room faces' too) times ``factor``."""
        scene = copy.deepcopy(self)
        for obj in scene.objects:
            obj.element_size *= factor
            for face in getattr(obj, "faces", {}).values():
                if face.element_size is not None:
                    face.element_size *= factor
        return scene

    def material_index(self, name: str) -> int:
        return [m.name for m in self.materials].index(name)

    def reflectance_table(self) -> torch.Tensor:
        """(M, 3) float64"""
        return torch.tensor([m.reflectance for m in self.materials], dtype=torch.float64)

    def emission_table(self) -> torch.Tensor:
        """(M, 3) float64"""
        return torch.tensor([m.emission for m in self.materials], dtype=torch.float64)
