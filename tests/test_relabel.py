"""Item atlases carried across splits: what a new render would see, but for edge ties."""
import torch

import hemirad
from hemirad.adaptive.refine import Refiner
from hemirad.adaptive.relabel import descendants, relabel_atlas, relabel_form_factors, split_pixels_of
from hemirad.scene.meshing import build_mesh
from hemirad.transport.formfactor import element_form_factors
from hemirad.transport.renderer import HemicubeRenderer

from patches import refined_solve


def test_descendants_group_new_elements_by_parent():
    parent = torch.tensor([0, 1, 2, 3, 1, 1, 3, 3, 3])  # as split_triangles makes it: 1 and 3 split
    d = descendants(parent, torch.tensor([1, 3]))
    assert d.count.tolist() == [1, 3, 1, 4]
    assert d.ordered[d.start[1]:d.start[1] + 3].tolist() == [1, 4, 5]
    assert d.ordered[d.start[3]:d.start[3] + 4].tolist() == [3, 6, 7, 8]


def test_relabelled_atlas_is_the_new_render_but_for_a_few_edge_pixels():
    scene = hemirad.load_scene("floating")
    scene.refine.pattern, scene.refine.criterion = "pattern2", "gradient"
    mesh = build_mesh(scene)
    emission = scene.emission_table()[mesh.material]
    lamp = int(torch.nonzero(emission.sum(1) > 0)[0])
    ff = HemicubeRenderer(mesh, 128)
    try:
        view = ff.render(lamp)
        seen = torch.bincount(view.element[view.front], minlength=mesh.num_elements) > 0
        selected = seen & (torch.arange(mesh.num_elements) % 3 == 0)  # a third of what the lamp sees
        selected[lamp] = False
        new_mesh, parent = Refiner(scene.refine, emission).split(mesh, selected)  # with 2:1 grading
        assert int((parent == lamp).sum()) == 1
        descent = descendants(parent, torch.unique(parent[mesh.num_elements:]))
        pixels = split_pixels_of(view.element, descent)
        assert len(pixels) > 10000
        relabelled = relabel_atlas(view.element, view.hits(pixels), pixels, descent, new_mesh)
        # the form factors carried over are those of the relabelled atlas, bit for bit
        weight = view.weight
        assert torch.equal(view.form_factors, element_form_factors(view.element, view.front, weight, mesh.num_elements))
        F_new = relabel_form_factors(view.form_factors, descent, relabelled, view.front, weight, pixels)
        assert torch.equal(F_new, element_form_factors(relabelled, view.front, weight, new_mesh.num_elements))
        ff.set_geometry(new_mesh)
        rendered = ff.render(int(torch.nonzero(parent == lamp)[0])).element
    finally:
        ff.close()
    differ = relabelled != rendered
    assert int(differ.sum()) <= 1e-3 * len(pixels), int(differ.sum())
    # where they differ, both are descendants of the same old element (a tie on a new edge)
    assert torch.equal(parent[relabelled[differ]], parent[rendered[differ]])


def test_a_solve_with_relabelled_passes_matches_one_that_renders_every_pass():
    results = {}
    for relabel in (True, False):
        solver = refined_solve("floating_coarse", 12, relabel=relabel)
        power = (solver.state.radiosity * solver.mesh.areas[:, None]).sum(0)
        results[relabel] = (solver.mesh.num_elements, power, solver.state.absorbed + solver.state.escaped)
    (n1, p1, out1), (n0, p0, out0) = results[True], results[False]
    assert n1 > build_mesh(hemirad.load_scene("floating_coarse")).num_elements
    assert abs(n1 - n0) <= 0.01 * n0
    torch.testing.assert_close(p1, p0, rtol=1e-3, atol=0)
    torch.testing.assert_close(out1, out0, rtol=1e-3, atol=0)
