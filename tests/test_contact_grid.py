"""The articulated rest's two grids (`sim.contact_grid`, `ArticulatedConfig.coarse_sub`): the
coarse grid's contact heights against the image grid's, and the rests with and without it."""

import dataclasses

import pytest
import torch
from test_articulated import _bodies

from pressurepose.body.kinematics import pose_in_mat, rest_joints
from pressurepose.errors import UserError
from pressurepose.mat import MatSpec
from pressurepose.sim.articulated import ArticulatedConfig, rest_articulated
from pressurepose.sim.articulation import to_part_frames
from pressurepose.sim.contact_grid import ContactGrid
from pressurepose.sim.mattress import MattressParams
from pressurepose.sim.rest_setup import SurfaceLayout


def _points(model, p):
    """The posed body's surface points in their parts' frames, sorted by part, and which are vertices."""
    layout = SurfaceLayout.build(model.faces, model.part_labels)
    rot, joints = pose_in_mat(rest_joints(model, p.shape), p)
    pts = layout.points(model(p).vertices)[0].transpose(1, 2).contiguous()
    return to_part_frames(pts, layout.labels, rot, joints), layout.labels, layout.vertex, rot, joints


def test_coarse_cells_hold_the_fine_cells_lowest_vertex(anny64):
    """A coarse cell (one per taxel) over the vertices is never lower than the lowest of its four
    image-grid cells over every point (the vertices are a subset), and within a few mm of it
    where the body is near the bed (the vertices are dense enough to stand for the surface)."""
    mat, mp = MatSpec(), MattressParams()
    p = _bodies(anny64, 1)
    local, labels, vert, rot, joints = _points(anny64, p)
    fine = ContactGrid.build(mat, mp, 2, None, torch.float64, "cpu")
    coarse = ContactGrid.build(mat, mp, 1, None, torch.float64, "cpu")
    h_f, _, _ = fine.heights(local, labels, rot, joints)
    h_c, part_c, _ = coarse.heights(local[:, vert], labels[vert], rot, joints)
    assert h_f.shape == (1, fine.nr * fine.nc) and h_c.shape == (1, coarse.nr * coarse.nc)
    # The four image cells of each coarse cell (the grids share their origin).
    lowest4 = h_f.view(coarse.nr, 2, coarse.nc, 2).amin((1, 3)).reshape(1, -1)
    assert bool((h_c >= lowest4 - 1e-12).all())
    near = lowest4 < 0.35  # the body's underside (it starts 25 cm up)
    assert int(near.sum()) > 300
    assert float((h_c - lowest4)[near].median()) < 0.003
    assert bool((part_c[near] >= 0).all())


def test_two_grid_rest_of_a_settling_body_is_the_image_grid_rest(anny64):
    """The home-pose body settles on either path: the coarse re-posings only bring it near its
    rest, which the image grid then finds (3.6 mm, image L1 0.03 when measured)."""
    p = _bodies(anny64, 1)
    two = rest_articulated(anny64, p)
    one = rest_articulated(anny64, p, config=ArticulatedConfig(coarse_sub=0))
    assert one.failure == two.failure == [""] and bool(one.settled[0]) and bool(two.settled[0])
    assert two.foundation_pa.shape == one.foundation_pa.shape  # the image's grid
    assert float((one.joints - two.joints).norm(dim=-1).amax()) < 0.01
    l1 = (one.foundation_pa - two.foundation_pa).abs().sum() / one.foundation_pa.sum()
    assert float(l1) < 0.08
    torch.testing.assert_close(two.force_n, one.force_n, rtol=2e-3, atol=0)


def test_heights_use_their_own_grids_top_sections_pillow_and_tissue():
    """`ContactGrid.heights` on each grid against a cell-by-cell reference: the air preset's top,
    the raised section's cells, the pillow's cells and the tissue in series, the points' sag."""
    from test_articulated_batch import _lowest_reference

    from pressurepose.bed import BedShape
    from pressurepose.sim.pillow import Pillow, in_series
    from pressurepose.sim.raised import RaisedBed

    mat, mp = MatSpec(), MattressParams.preset("air")
    g = torch.Generator().manual_seed(3)
    B, P = 2, 2500
    pts = torch.stack(
        [
            torch.rand(B, P, generator=g, dtype=torch.float64) * 2.0,
            torch.rand(B, P, generator=g, dtype=torch.float64) * 0.9,
            torch.rand(B, P, generator=g, dtype=torch.float64) * 0.1,
        ],
        -1,
    )
    labels = torch.sort(torch.randint(0, 24, (P,), generator=g)).values
    tissue = 1e5 + 1e5 * torch.rand(B, P, generator=g, dtype=torch.float64)
    sag = 0.01 * torch.rand(B, P, generator=g, dtype=torch.float64)
    rot = torch.eye(3, dtype=torch.float64).expand(B, 24, 3, 3)  # part frames = the mat's
    joints = torch.zeros(B, 24, 3, dtype=torch.float64)
    raised = RaisedBed(BedShape(30.0), mat, torch.float64, "cpu")
    pillow, thick = Pillow(), torch.tensor([0.05, 0.0], dtype=torch.float64)
    for sub in (1, 2):
        grid = ContactGrid.build(mat, mp, sub, raised, torch.float64, "cpu")
        under = (grid.xy[None, :, 0] < 0.4).expand(B, -1) & (thick[:, None] > 0)
        h, part, cell_tissue = grid.heights(
            pts, labels, rot, joints, sag=sag, tissue=tissue, raised=raised, pillow=(thick, under, pillow)
        )
        down = pts.clone()
        down[..., 2] -= sag
        want_h, want_part, want_t = _lowest_reference(raised.to_surface(down), labels, mat, sub, tissue)
        head = grid.xy[:, 0] < raised.hinge_x
        assert bool(head.any()) and not bool(head.all())
        torch.testing.assert_close(
            h, want_h - mp.top_height(grid.xy[:, 0]) - thick[:, None] * under, rtol=0, atol=1e-12
        )
        assert torch.equal(part, want_part + 24 * head.long())
        torch.testing.assert_close(cell_tissue, in_series(want_t, pillow, thick, under), rtol=1e-12, atol=0)


def test_the_coarse_reposings_come_first_and_the_rest_is_on_the_image_grid(anny64, monkeypatch):
    """With `outer` 6 and `fine_reposings` 3, the first 3 re-posings find their contacts on the
    coarse grid, every later one and the rest on the image's."""
    from pressurepose.sim import articulated

    subs, finished = [], []
    heights, finish = ContactGrid.heights, articulated.RestsDone.finish

    def spy_heights(self, *args, **kwargs):
        subs.append(self.sub)
        return heights(self, *args, **kwargs)

    def spy_finish(self, *args, **kwargs):
        finished.append(subs[-1])
        return finish(self, *args, **kwargs)

    monkeypatch.setattr(ContactGrid, "heights", spy_heights)
    monkeypatch.setattr(articulated.RestsDone, "finish", spy_finish)
    r = rest_articulated(anny64, _bodies(anny64, 1), config=ArticulatedConfig(outer=6, fine_reposings=3))
    assert subs[:3] == [1, 1, 1] and set(subs[3:]) == {2} and len(subs) == int(r.reposings[0]) + 1
    assert finished == [2] and r.failure == [""]
    assert r.foundation_pa.shape[1:] == (MatSpec().covered_rows * 2, MatSpec().covered_cols * 2)


def test_no_coarse_grid_when_the_fine_reposings_take_them_all(anny64):
    """`fine_reposings` >= `outer`: every re-posing on the image grid, the rest bit for bit that of
    `coarse_sub=0` (the same code path)."""
    p = _bodies(anny64, 1)
    a = rest_articulated(anny64, p, config=ArticulatedConfig(outer=4, fine_reposings=4))
    b = rest_articulated(anny64, p, config=ArticulatedConfig(outer=4, coarse_sub=0))
    assert torch.equal(a.joints, b.joints) and torch.equal(a.foundation_pa, b.foundation_pa)


def test_coarse_reposings_count():
    """Every body's re-posings on the coarse grid: `outer` minus the image grid's, none without
    a coarse grid or when the image grid's take them all."""
    assert ArticulatedConfig(outer=24, fine_reposings=8).coarse_reposings == 16
    assert ArticulatedConfig(outer=4, fine_reposings=4).coarse_reposings == 0
    assert ArticulatedConfig(outer=4, fine_reposings=9).coarse_reposings == 0
    assert ArticulatedConfig(outer=24, coarse_sub=0).coarse_reposings == 0


def test_the_coarse_grid_config_is_checked():
    for bad in ({"coarse_sub": -1}, {"coarse_sub": 2}, {"fine_reposings": 0}, {"coarse_inner": 0}):
        with pytest.raises(UserError, match="coarse_sub"):
            dataclasses.replace(ArticulatedConfig(), **bad)
