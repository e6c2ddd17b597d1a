"""The occupancy-grid cover: every border cell inside the union of the fitted ellipses (proved: all four
corners of every cell, in floats), a count that follows the outline, growths that contain the Minkowski
sum with the margin disc, and the thin-ellipse trap avoided."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from services.geometry import Ellipse, EllipseStack
from schemas.occupancy import OccupancyGrid, load_map
from services.ellipsoids.grid_cover import GridCover, GridCoverSettings
from services.ellipsoids.mvee import mvee_fast

CORNERS = np.array([[0, 0], [1, 0], [0, 1], [1, 1]])


def _all_pieces(cover: GridCover):
    nx, ny = cover.tiles_shape
    return cover.pieces([(x, y) for x in range(nx) for y in range(ny)])


def _proved(grid: OccupancyGrid, pieces) -> np.ndarray:
    """For each border cell: whether one fitted (raw) ellipse has all four of its corners at level ≤ 1."""
    cells = grid.border_cells()
    corners = grid.to_world(((cells[:, None, :] + CORNERS[None]).reshape(-1, 2)) * grid.resolution_m)
    stack = EllipseStack.of([p.raw for p in pieces])
    inside = np.zeros(len(cells), dtype=bool)
    for lo in range(0, len(stack), 64):  # (cells × 4, 64) levels at a time
        part = EllipseStack(A=stack.A[lo : lo + 64], b=stack.b[lo : lo + 64])
        inside |= np.any(np.all((part.levels(corners) <= 1.0).reshape(len(cells), 4, -1), axis=1), axis=1)
    return inside


@pytest.mark.parametrize("yaw", [0.0, 0.35])
def test_every_border_cell_of_the_depot_is_inside_a_fitted_ellipse(shared_dir: Path, tmp_path: Path, yaw: float):
    depot = load_map(shared_dir / "maps" / "depot.yaml")
    grid = OccupancyGrid(state=depot.state, resolution_m=depot.resolution_m, origin_x_m=2.0, origin_y_m=-1.0,
                         origin_yaw_rad=yaw)
    cover = GridCover(grid, margin_m=0.45)
    pieces = _all_pieces(cover)
    assert _proved(grid, pieces).all()
    # The count follows the outline: thousands of border cells, a few hundred ellipses.
    assert len(grid.border_cells()) > 5000 and len(pieces) < 450
    assert max(p.excess_m for p in pieces) <= cover.settings.tolerance_m


def test_specks_of_one_and_two_cells_are_covered():
    blocked = np.zeros((60, 60), dtype=bool)
    blocked[10, 10] = True
    blocked[30, 30:32] = True
    blocked[45, 45] = blocked[46, 46] = True  # two cells touching at a corner
    grid = OccupancyGrid.from_mask(blocked, resolution_m=0.05)
    pieces = _all_pieces(GridCover(grid, margin_m=0.45))
    assert _proved(grid, pieces).all()
    inner = [p for p in pieces if np.all((p.cells >= 0) & (p.cells < 60))]
    assert len(inner) == 3  # one ellipse per speck (the map's ring beyond its edges aside)


def _wall(length_m: float, *, thickness_cells: int, res: float = 0.05, jag: bool = False) -> OccupancyGrid:
    """A straight wall in the middle of a free map with 2 m of floor round it."""
    n = int(round(length_m / res))
    margin = int(round(2.0 / res))
    blocked = np.zeros((2 * margin + 4, n + 2 * margin), dtype=bool)
    blocked[margin : margin + thickness_cells, margin : margin + n] = True
    if jag:  # every seventh cell one cell proud of the wall
        blocked[margin + thickness_cells, margin : margin + n : 7] = True
    return OccupancyGrid.from_mask(blocked, resolution_m=res)


@pytest.mark.parametrize("thickness, jag", [(1, False), (2, False), (2, True)])
def test_a_straight_20_m_wall_is_a_handful_of_ellipses(thickness, jag):
    grid = _wall(20.0, thickness_cells=thickness, jag=jag)
    cover = GridCover(grid, margin_m=0.45)  # its 2.4 m tiles fitted together: pieces run across their edges
    inside = lambda c: np.all((c >= 0) & (c < [grid.shape[1], grid.shape[0]]))  # noqa: E731 (not the ring)
    pieces = [p for p in _all_pieces(cover) if inside(p.cells)]
    assert _proved(grid, _all_pieces(cover)).all()
    # 400 × thickness border cells (a rectangle per cell of a wall this thin: hundreds); 12 ellipses.
    assert len(pieces) <= 14, len(pieces)
    # The middle of the wall is covered by long thin ellipses, grown to the wall's grown half-width
    # (margin + half its thickness, a jag more) within the tolerance: not to √2 · margin.
    longest = max(pieces, key=lambda p: p.grown.semi_axes[0])
    assert longest.grown.semi_axes[0] >= 5.0
    half_width = 0.45 + 0.025 * (thickness + jag)
    assert longest.grown.semi_axes[1] <= half_width + cover.settings.tolerance_m
    assert longest.raw.grown(0.45).semi_axes[1] >= 0.62  # the least-area growth of the same fit


def test_the_growth_contains_the_fit_plus_the_margin_disc():
    grid = _wall(6.0, thickness_cells=2, jag=True)
    for piece in _all_pieces(GridCover(grid, margin_m=0.45)):
        # Points of the fit's boundary pushed out along the normal by the margin lie in the growth.
        theta = np.linspace(0.0, 2.0 * np.pi, 256, endpoint=False)
        u = np.column_stack([np.cos(theta), np.sin(theta)])
        A, b = piece.raw.A, piece.raw.b
        boundary = np.linalg.solve(A, (u - b).T).T
        normal = u @ A  # the gradient of ‖A z + b‖ is Aᵀ u
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        assert piece.grown.level(boundary + 0.45 * normal).max() <= 1.0 + 1e-9


def test_the_least_area_growth_of_a_thin_wall_is_the_trap_the_chosen_growth_avoids():
    grid = _wall(6.0, thickness_cells=1)
    cover = GridCover(grid, margin_m=0.45, settings=GridCoverSettings(tile_m=20.0, halo_m=6.0))
    piece = max(_all_pieces(cover), key=lambda p: p.raw.semi_axes[0])
    assert piece.grown.semi_axes[1] <= 0.5  # about r
    assert piece.raw.grown(0.45).semi_axes[1] >= 0.6  # Ellipse.grown's least area: about √2 r


def test_a_piece_is_the_loewner_john_ellipse_of_its_bounding_rectangle():
    grid = _wall(1.0, thickness_cells=3)
    cover = GridCover(grid, margin_m=0.45, settings=GridCoverSettings(tile_m=20.0, halo_m=6.0))
    piece = next(p for p in _all_pieces(cover) if len(p.cells) >= 30)
    lo, hi = piece.cells.min(axis=0), piece.cells.max(axis=0) + 1
    box = grid.to_world(np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]]) * 0.05)
    reference = mvee_fast(box)  # eq. 1 solved numerically on the rectangle's corners
    assert piece.raw.area == pytest.approx(reference.area, rel=1e-6)
    np.testing.assert_allclose(piece.raw.center, reference.center, atol=1e-9)


def test_the_proof_margin_holds_for_far_from_the_origin_maps():
    """Map coordinates of kilometres: the corners' computed levels still stay below 1."""
    blocked = np.zeros((40, 40), dtype=bool)
    blocked[10:12, 5:35] = True
    grid = OccupancyGrid.from_mask(blocked, resolution_m=0.05, origin=(2500.0, -4100.0, 1.1))
    assert _proved(grid, _all_pieces(GridCover(grid, margin_m=0.3))).all()


def test_a_tiles_grown_ellipses_stay_within_its_halo():
    grid = _wall(12.0, thickness_cells=2)
    cover = GridCover(grid, margin_m=0.45)
    for tile, pieces in ((t, cover.pieces([t])) for x in range(cover.tiles_shape[0]) for y in range(cover.tiles_shape[1])
                         for t in [(x, y)]):
        rows, cols = cover.tile_range(tile)
        lo = np.array([cols.start, rows.start]) * grid.resolution_m - cover.reach_m
        hi = np.array([cols.stop, rows.stop]) * grid.resolution_m + cover.reach_m
        for piece in pieces:
            e: Ellipse = piece.grown
            extent = np.sqrt(np.diag(np.linalg.inv(e.A @ e.A)))  # the ellipse's half-extent along x and y
            assert np.all(e.center - extent >= lo - 1e-9) and np.all(e.center + extent <= hi + 1e-9)
            assert math.isfinite(piece.excess_m)


def test_a_distance_window_is_the_rounding_of_the_exact_distance_on_every_call():
    """OpenCV's transform alone gives values an ulp off the exact one, and not the same from call to call."""
    from scipy import ndimage

    rng = np.random.default_rng(3)
    grid = OccupancyGrid.from_mask(rng.random((120, 160)) < 0.01, resolution_m=0.05)
    cover = GridCover(grid, margin_m=0.45)
    group = [(x, y) for x in range(cover.tiles_shape[0]) for y in range(cover.tiles_shape[1])]
    first = cover._window(group)
    r, c = first.distance.shape
    free = ~grid.padded_blocked(slice(first.row0, first.row0 + r), slice(first.col0, first.col0 + c))
    exact = np.maximum(ndimage.distance_transform_edt(free).astype(np.float32).astype(float) * 0.05 - 0.025, 0.0)
    # Compared where the window is exact (every cell within reach of a blocked one inside it).
    near = exact <= (cover.reach_cells - 2) * 0.05
    assert near.sum() > 1000
    assert np.array_equal(first.distance[near], exact.astype(np.float32)[near])
    for _ in range(5):
        assert np.array_equal(cover._window(group).distance, first.distance)


@pytest.mark.parametrize("yaw", [0.0, 0.35])
def test_the_distance_at_points_reads_their_clearance_within_a_cell(shared_dir: Path, yaw: float):
    """`GridCover.distance_at` reads the tiles' transforms (fitting the tiles asked about): within a cell of
    the exact clearance wherever that is below the margin plus the tolerance (the point is half a diagonal
    from its cell's centre, whose D may exceed the centre's clearance by (√2 − 1) / 2 of a cell), above it
    beyond, 0 in blocked cells and beyond the map's ring."""
    depot = load_map(shared_dir / "maps" / "depot.yaml")
    grid = OccupancyGrid(state=depot.state, resolution_m=depot.resolution_m, origin_x_m=2.0, origin_y_m=-1.0,
                         origin_yaw_rad=yaw)
    cover = GridCover(grid, margin_m=0.45)
    res = grid.resolution_m
    rng = np.random.default_rng(5)
    w, h = grid.size_m
    points = grid.to_world(rng.uniform((-1.0, -1.0), (w + 1.0, h + 1.0), size=(4000, 2)))
    read, exact = cover.distance_at(points), grid.clearance(points)
    bound = 0.45 + cover.settings.tolerance_m
    near = exact < bound
    assert near.sum() > 1000 and (~near).sum() > 1000
    assert np.all(np.abs(read[near] - exact[near]) <= res)
    assert np.all(read[~near] >= bound - res)
    frame = grid.to_grid(points)
    beyond = np.any((frame < -res) | (frame > np.array((w, h)) + res), axis=1)
    assert beyond.sum() > 100 and np.all(read[beyond] == 0.0)
    assert np.all(read[exact == 0.0] == 0.0)


def test_a_tile_far_from_every_blocked_cell_has_no_pieces_and_a_finite_window():
    """Open floor wider than a window (a hall, a yard): OpenCV's transform of a window with no blocked cell
    is 2⁶⁴ everywhere, which once overflowed to infinity with a RuntimeWarning on the user's terminal."""
    blocked = np.zeros((400, 400), dtype=bool)
    blocked[5, 5] = True
    cover = GridCover(OccupancyGrid.from_mask(blocked, resolution_m=0.05), margin_m=0.45)
    middle = (cover.tiles_shape[0] // 2, cover.tiles_shape[1] // 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert cover.pieces([middle]) == []
    distance = cover._window([middle]).distance
    assert np.isfinite(distance).all()
    assert distance.min() > (cover.reach_cells - 2) * 0.05  # above the margin plus the tolerance everywhere


def test_a_goal_just_beyond_the_margin_is_let_out_of_the_cover_and_every_border_cell_stays_covered():
    """A point 2 cm further from a straight wall than the margin lies in the wall's grown ellipses, which
    may stick out of the grown wall by the tolerance (0.1 m): no plan could start or end there. The pieces
    holding it are refitted tighter; then none holds it, the wall is covered as before (every border cell
    proved inside a fitted ellipse), and the pieces away from it are the same. A point within the margin
    stays held, and asking again refits nothing."""
    grid = _wall(12.0, thickness_cells=2)  # the wall's face at y = 2.1 m
    cover = GridCover(grid, margin_m=0.45)
    before = _all_pieces(cover)
    goal = np.array([[7.5, 2.1 + 0.45 + 0.02]])
    holding = [p for p in before if np.linalg.norm(p.grown.A @ goal[0] + p.grown.b) <= 1.0]
    assert holding
    assert cover.tighten(goal)
    after = _all_pieces(cover)
    assert all(np.linalg.norm(p.grown.A @ goal[0] + p.grown.b) > 1.0 for p in after)
    assert _proved(grid, after).all()
    assert {id(p) for p in before} - {id(p) for p in holding} <= {id(p) for p in after}
    assert len(after) - len(before) < 30  # tighter only where the goal is
    within = np.array([[7.5, 2.1 + 0.3]])
    assert cover.tighten(within)
    assert any(np.linalg.norm(p.grown.A @ within[0] + p.grown.b) <= 1.0 for p in _all_pieces(cover))
    assert not cover.tighten(within)  # held by pieces fitted to the finest tolerance already: not refitted again
    assert _proved(grid, _all_pieces(cover)).all()


def test_tightening_round_random_points_keeps_every_border_cell_covered_and_lets_out_those_a_cm_clear():
    """Specks and two walls; every free point 0–15 cm beyond the margin that the cover holds is asked for
    at once. After the refit every border cell is still proved inside a fitted ellipse, and no point a
    centimetre or more beyond the margin is held (the finest refit's pieces are single cells, whose excess
    is about a fifth of a cell)."""
    rng = np.random.default_rng(5)
    blocked = rng.random((120, 160)) < 0.004
    blocked[40:44, 20:140] = True
    blocked[60:100, 80:83] = True
    grid = OccupancyGrid.from_mask(blocked, resolution_m=0.05)
    cover = GridCover(grid, margin_m=0.45)

    def held(points):
        stack = EllipseStack.of([p.grown for p in _all_pieces(cover)])
        return np.any(stack.levels(points) <= 1.0, axis=1)

    points = np.column_stack([rng.uniform(0.0, 8.0, 4000), rng.uniform(0.0, 6.0, 4000)])
    clearance = grid.clearance(points)
    near = (clearance >= 0.45) & (clearance < 0.6)
    points, clearance = points[near], clearance[near]
    before = held(points)
    assert before.sum() > 50
    assert cover.tighten(points[before])
    assert _proved(grid, _all_pieces(cover)).all()
    assert not np.any(held(points)[clearance >= 0.46])
