"""The bound that sorts a shard's rays before the samples pass walks them (mapping.samples_pass.owned_reach),
against the cells the slow reference traversal gives each ray: a ray it skips crosses none of the shard's tiles, and
a ray it walks as the whole window's walk does crosses only the shard's tiles. And the bound of a beam's rays under
every pose of a scan at once (scan_reach), against owned_reach's answer for each ray."""

import math

import numpy as np
import pytest

from mapping.beam_model import BeamTable
from mapping.samples_pass import (
    REACH_ALL,
    REACH_NONE,
    REACH_SOME,
    SCAN_YAW_SPREAD,
    owned_reach,
    owned_table,
    scan_reach,
)
from mapping.window_walk import Tiles
from reference import cells_on_ray
from worlds import OWNERSHIP_PATTERNS, ownership_pattern

RES = 0.1
SHIFT = 3  # tiles of 8 cells; tile (tx, ty) is entry (ty + 8, tx + 8): tiles -8..7 a side, cells -64..63
TX0 = TY0 = -8
#: one beam straight ahead in the laser frame: the ray's direction is the laser's heading
AHEAD = (np.array([1.0]), np.array([0.0]))


def reach(x0: float, y0: float, angle: float, stop: float, owned: np.ndarray) -> int:
    """owned_reach of the ray from (x0, y0) (m) at ``angle`` (rad), ``stop`` m long, for the shard owning the
    tiles where ``owned`` (16 x 16 bool) is True."""
    laser = np.array([x0, y0, angle])
    tiles = Tiles(owned, bool(owned.all()), SHIFT, TX0, TY0)
    heading = (math.cos(angle), math.sin(angle))
    return int(owned_reach(laser, heading, AHEAD, 0, stop, 1.0 / RES, tiles, owned_table(owned)))


def owned_on_ray(x0: float, y0: float, angle: float, stop: float, owned: np.ndarray) -> list[bool]:
    """For each cell the reference traversal gives the ray, whether the shard owns its tile."""
    return [
        bool(owned[(iy >> SHIFT) - TY0, (ix >> SHIFT) - TX0]) for ix, iy, _, _ in cells_on_ray(x0, y0, angle, stop, RES)
    ]


def rays(seed: int, count: int):
    """(x0, y0, angle, stop): origins within 2 m, lengths up to 3 m (every cell inside the 16 x 16 tiles), a third of
    the origins on grid points and a third of the angles along the axes or the diagonals."""
    rng = np.random.default_rng(seed)
    for i in range(count):
        x0, y0 = rng.uniform(-2.0, 2.0, 2)
        if i % 3 == 0:
            x0, y0 = round(x0 / RES) * RES, round(y0 / RES) * RES
        angle = float(rng.uniform(-math.pi, math.pi)) if i % 3 else float(rng.integers(-4, 4)) * math.pi / 4
        yield float(x0), float(y0), angle, float(rng.uniform(0.01, 3.0))


@pytest.mark.parametrize("pattern", OWNERSHIP_PATTERNS)
def test_a_skipped_ray_crosses_no_owned_tile_and_a_whole_walk_only_owned_ones(pattern):
    owned = ownership_pattern(pattern)
    seen = {REACH_NONE: 0, REACH_SOME: 0, REACH_ALL: 0}
    for ray in rays(4, 600):
        answer = reach(*ray, owned)
        flags = owned_on_ray(*ray, owned)
        seen[answer] += 1
        if answer == REACH_NONE:
            assert not any(flags), ray
        elif answer == REACH_ALL:
            assert all(flags), ray
    if pattern in ("random", "blocks"):
        assert min(seen.values()) > 0, seen  # every answer is given somewhere: the checks above are not idle


def test_every_tile_owned_walks_every_ray_whole_and_none_owned_skips_every_ray():
    for ray in rays(5, 200):
        assert reach(*ray, np.ones((16, 16), bool)) == REACH_ALL, ray
        assert reach(*ray, np.zeros((16, 16), bool)) == REACH_NONE, ray


def test_a_ray_ending_a_rounding_short_of_an_unowned_tile_is_not_walked_whole():
    """From (0.25, 0.25) m along +x to a nanometre short of x = 0.8 m, the line between tiles 0 and 1 (cells 0..7
    and 8..15): the box takes a cell beyond the end cell, so a shard owning tile 0 but not tile 1 walks the ray as one
    that may reach another shard's tile (a ray whose end lands within rounding of a line may cross into the cell
    beyond it). Ending at 0.6 m, its box (cells 1..7) lies in tile 0."""
    owned = np.zeros((16, 16), bool)
    owned[0 - TY0, 0 - TX0] = True  # tile (0, 0)
    assert not any(cell[0] == 8 for cell in cells_on_ray(0.25, 0.25, 0.0, 0.55 - 1e-9, RES))
    assert reach(0.25, 0.25, 0.0, 0.55 - 1e-9, owned) == REACH_SOME
    assert reach(0.25, 0.25, 0.0, 0.35, owned) == REACH_ALL
    owned[0 - TY0, 1 - TX0] = True  # and tile (1, 0)
    assert reach(0.25, 0.25, 0.0, 0.55 - 1e-9, owned) == REACH_ALL


def test_the_box_takes_the_cell_before_the_start_however_one_over_res_rounds():
    """The box's cells come from x * (1 / res), which floors a cell higher than the walk's x / res at 0.8999999999999999
    m: without the rounding allowance the box of a ray from there along +x (the walk's cells 8 and on) would start at
    cell 8 instead of 7, and a shard owning only tile 0 (cells 0..7) would skip a ray whose box is meant to reach it."""
    x0 = 0.8999999999999999
    assert math.floor(x0 / RES) == 8 and math.floor(x0 * (1.0 / RES)) == 9
    owned = np.zeros((16, 16), bool)
    owned[0 - TY0, 0 - TX0] = True
    assert reach(x0, 0.25, 0.0, 0.02, owned) == REACH_SOME


def scan_and_ray_reaches(lasers: np.ndarray, angles: np.ndarray, stops: np.ndarray, owned: np.ndarray):
    """scan_reach's answer per beam, and owned_reach's per (pose, beam), for laser poses (M, 3) and beams at ``angles``
    (rad, laser frame) ``stops`` m long, for the shard owning the tiles where ``owned`` is True."""
    tiles = Tiles(owned, bool(owned.all()), SHIFT, TX0, TY0)
    table = owned_table(owned)
    directions = (np.cos(angles), np.sin(angles))
    zeros = np.zeros(len(angles))
    beams = BeamTable(np.ones(len(angles), np.int8), zeros, stops, *(zeros,) * 6)  # (kind, z, r_stop, ...)
    per_beam = np.full(len(angles), -1, np.int64)
    scan_reach(lasers, directions, beams, 1.0 / RES, tiles, table, per_beam)
    per_ray = np.array(
        [
            [
                owned_reach(
                    laser, (math.cos(laser[2]), math.sin(laser[2])), directions, k, stops[k], 1.0 / RES, tiles, table
                )
                for k in range(len(angles))
            ]
            for laser in lasers
        ]
    )
    return per_beam, per_ray


@pytest.mark.parametrize("pattern", OWNERSHIP_PATTERNS)
def test_a_beam_bound_for_every_pose_at_once_agrees_with_each_ray(pattern):
    """Where scan_reach answers for a beam (REACH_NONE or REACH_ALL), owned_reach gives each pose's ray of the beam the
    same answer; and it answers for some beams, not only REACH_SOME. Clouds of poses within 0.3 m and 0.4 rad, some
    around the yaw of +-pi (the yaws' spread is taken about the first one, across the wrap), some at yaws near 1e15
    rad (finite, so the fusion takes them: their headings, not the yaws' sums, must bound the rays)."""
    owned = ownership_pattern(pattern)
    rng = np.random.default_rng(7)
    answered = 0
    for cloud in range(40):
        centre = rng.uniform(-2.0, 2.0, 2)
        yaw = math.pi if cloud % 4 == 0 else float(rng.uniform(-math.pi, math.pi))
        count = int(rng.integers(2, 12))
        lasers = np.column_stack([centre + rng.uniform(-0.15, 0.15, (count, 2)), yaw + rng.uniform(-0.2, 0.2, count)])
        if cloud % 4 == 1:
            lasers[:, 2] += 1e15  # (a yaw's last bit is 0.125 rad here)
        else:
            lasers[:, 2] = (lasers[:, 2] + math.pi) % (2 * math.pi) - math.pi
        angles = np.linspace(-2.3, 2.3, 47)
        stops = rng.uniform(0.01, 3.0, angles.shape[0])
        per_beam, per_ray = scan_and_ray_reaches(lasers, angles, stops, owned)
        for k, answer in enumerate(per_beam):
            if answer != REACH_SOME:
                answered += 1
                assert (per_ray[:, k] == answer).all(), (cloud, k, answer, per_ray[:, k])
    assert answered >= 20, answered  # (23 of 1 880 beams on the checkerboard, 714 on the blocks: not idle)


def test_a_beam_bound_takes_the_heading_between_the_yaws_ends():
    """Poses at yaws -0.3 and +0.3 rad and a beam straight ahead, 1.5 m from (0.05, 0.05) m: the ray at yaw 0 (which
    neither end's direction gives) reaches cell 15 across, its box cell 16, in tile 2 (cells 16..23); a bound from the
    ends' directions alone would stop at cell 15 (1.5 cos 0.3 = 1.43 m) and call the beam's rays all in tiles 0 and 1.
    With yaws spread wider than SCAN_YAW_SPREAD the bound leaves every beam to owned_reach."""
    owned = np.zeros((16, 16), bool)
    owned[:, 0 - TX0] = owned[:, 1 - TX0] = True  # tile columns 0 and 1 (x cells 0..15)
    owned[:, -1 - TX0] = True  # and -1, for the box's cell before the start
    lasers = np.array([[0.05, 0.05, -0.3], [0.05, 0.05, 0.3], [0.05, 0.05, 0.0]])
    per_beam, per_ray = scan_and_ray_reaches(lasers, np.array([0.0]), np.array([1.5]), owned)
    assert per_ray[2, 0] == REACH_SOME and per_beam[0] == REACH_SOME
    per_beam, per_ray = scan_and_ray_reaches(lasers[:2], np.array([0.0]), np.array([1.5]), owned)
    assert per_beam[0] == REACH_SOME  # (the poses at the ends only: the heading between them still counts)
    short = np.array([1.2])  # 1.25 m: cell 12, its box to 13, in tile 1
    per_beam, per_ray = scan_and_ray_reaches(lasers, np.array([0.0]), short, owned)
    assert per_beam[0] == REACH_ALL and (per_ray[:, 0] == REACH_ALL).all()
    spread = lasers.copy()
    spread[1, 2] = -0.3 + SCAN_YAW_SPREAD + 0.01
    per_beam, _ = scan_and_ray_reaches(spread, np.array([0.0]), short, owned)
    assert per_beam[0] == REACH_SOME


@pytest.mark.parametrize("big", [1e7, 1e15])
def test_a_beam_bound_depends_on_the_headings_not_on_how_large_the_yaws_are(big):
    """The same poses with yaws near ``big`` rad (1e7: the wire's bound; 1e15: a yaw's last bit 0.125 rad) and with
    yaws that give the same headings in (-pi, pi]: scan_reach answers alike for every beam (the walk goes along the
    headings, so a bound from yaw + a beam's angle would miss rays by up to half a last bit)."""
    owned = ownership_pattern("blocks")
    rng = np.random.default_rng(11)
    answered = 0
    angles = np.linspace(-2.3, 2.3, 181)
    for _ in range(20):
        centre = rng.uniform(-2.0, 2.0, 2)
        lasers = np.column_stack([centre + rng.uniform(-0.15, 0.15, (6, 2)), big + rng.uniform(-0.2, 0.2, 6)])
        headed = lasers.copy()
        headed[:, 2] = np.arctan2(np.sin(lasers[:, 2]), np.cos(lasers[:, 2]))
        stops = rng.uniform(0.5, 3.0, angles.shape[0])
        far, _ = scan_and_ray_reaches(lasers, angles, stops, owned)
        near, _ = scan_and_ray_reaches(headed, angles, stops, owned)
        assert np.array_equal(far, near)
        answered += int((near != REACH_SOME).sum())
    assert answered >= 100, answered
