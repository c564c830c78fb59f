"""A grid's changed cells (mapping.grid, ``track_changes``): a cell's update as the applies make it, marked with the
layers whose values changed (:func:`update_cell`: a bit each, :data:`LOGODDS_CHANGED`, :data:`VARIANCE_CHANGED`,
:data:`OBSERVED_CHANGED`), and a tile's marked cells taken (:func:`take_changed_cells`): the smallest window that
holds them, which of its cells they are, which of those changed their log-odds and which their variance, and the
changed values, with the marks cleared. What a mapper
shard publishes of a tile (services.state.shard, schemas.messages.TileUpdate), in two compiled passes over the window
the fusions reported (one to bound the marks, one to gather them). They take about as long as numpy's bounding box,
masks and gathers did (2.5 against 2.9 ms a warehouse scan's 22 tiles): the time goes to reading the tiles' layers,
past a core's L2.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from mapping.jit import kernel

#: the bits of a grid's ``changed`` layer: which of a cell's layers changed since its changes were last taken
LOGODDS_CHANGED, VARIANCE_CHANGED, OBSERVED_CHANGED = 1, 2, 4
#: a cell every layer of which is to be given (a tile set whole)
ALL_CHANGED = LOGODDS_CHANGED | VARIANCE_CHANGED | OBSERVED_CHANGED


class ChangedCells(NamedTuple):
    """A tile's changed cells: ``window`` (row0, col0, rows, cols; tile-local cells) the smallest that holds them,
    ``given`` (bool (rows, cols)) which of its cells they are; of those n cells, in the window's row-major order,
    ``logodds_cells`` and ``variance_cells`` (bool (n,)) which changed their log-odds and which their variance, the
    new values of those (``logodds`` and ``variance``, one a marked cell), and every one's ``observed`` (bool (n,))."""

    window: tuple[int, int, int, int]
    given: np.ndarray
    logodds_cells: np.ndarray
    logodds: np.ndarray
    variance_cells: np.ndarray
    variance: np.ndarray
    observed: np.ndarray


@kernel(nogil=True, error_model="numpy", inline="always")
def update_cell(layers, at, mean, spread, l_min, l_max):  # pragma: no cover - compiled
    """Add ``mean`` to the log-odds of the cell at ``at`` (slot, row, column), clamped to [l_min, l_max], and
    ``spread`` to its variance; mark it observed and, in a grid that tracks them (``changed`` has slots), mark in
    ``changed`` the layers whose value changed. layers: the grid's (logodds, variance, observed, changed)."""
    logodds, variance, observed, changed = layers
    old, old_spread = logodds[at], variance[at]
    updated = old + mean
    if updated < l_min:
        updated = l_min
    elif updated > l_max:
        updated = l_max
    logodds[at] = updated
    variance[at] = old_spread + spread
    if changed.shape[0] > 0:
        changed[at] |= (
            (logodds[at] != old) * LOGODDS_CHANGED
            | (variance[at] != old_spread) * VARIANCE_CHANGED
            | (not observed[at]) * OBSERVED_CHANGED
        )
    observed[at] = True


def take_changed_cells(
    layers: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], window: tuple[int, int, int, int]
) -> ChangedCells | None:
    """The cells marked in ``changed`` inside ``window`` (row0, col0, rows, cols) of one tile's layers = (logodds,
    variance, observed, changed), each (T, T), with their marks there cleared; None when none is marked."""
    logodds, variance, observed, changed = layers
    row0, col0, rows, cols = window
    r0, c0, r1, c1, count = _marked_box(changed, row0, col0, rows, cols)
    if count == 0:
        return None
    box = (row0 + r0, col0 + c0, r1 - r0 + 1, c1 - c0 + 1)
    given = np.zeros(box[2:], np.bool_)
    cells = (np.empty(count, np.bool_), np.empty(count, np.bool_), np.empty(count, np.bool_))
    values = (np.empty(count, np.float32), np.empty(count, np.float32))
    n_logodds, n_variance = _gather_marked((logodds, variance, observed, changed), box[0], box[1], given, cells, values)
    window = (int(box[0]), int(box[1]), int(box[2]), int(box[3]))
    return ChangedCells(window, given, cells[0], values[0][:n_logodds], cells[1], values[1][:n_variance], cells[2])


@kernel(nogil=True, error_model="numpy")
def _marked_box(changed, row0, col0, rows, cols):  # pragma: no cover - compiled
    """(r0, c0, r1, c1, count): the first and last window row and column (inclusive, relative to (row0, col0)) that
    hold a mark of ``changed`` (T, T) in the window of rows x cols cells at (row0, col0), and the marks' count. A row's
    marks are counted without branches; its first and last mark are looked for only outside the columns already
    found to hold one."""
    r0, c0, r1, c1, count = rows, cols, -1, -1, 0
    for r in range(rows):
        here = 0
        for c in range(cols):
            here += changed[row0 + r, col0 + c] != 0
        if here == 0:
            continue
        r0 = min(r0, r)
        r1 = r
        count += here
        c = 0
        while c < c0 and not changed[row0 + r, col0 + c]:
            c += 1
        c0 = min(c0, c)
        c = cols - 1
        while c > c1 and not changed[row0 + r, col0 + c]:
            c -= 1
        c1 = max(c1, c)
    return r0, c0, r1, c1, count


@kernel(nogil=True, error_model="numpy")
def _gather_marked(layers, row0, col0, given, cells, values):  # pragma: no cover - compiled
    """Take the cells marked in the window at (row0, col0) the shape of ``given``, in the window's row-major order: set
    their bits of ``given``, their entries of ``cells`` = (log-odds changed, variance changed, observed), each (n,),
    and the changed values into ``values`` = (logodds, variance), one entry a cell whose layer changed; clear their
    marks. Returns how many log-odds and how many variances it gave. layers = (logodds, variance, observed,
    changed), each (T, T). Reads the values of the marked cells only: the layers of a warehouse scan's windows are
    5.4 MB, past a core's L2, and a variant without branches that read every cell's was slower."""
    logodds, variance, observed, changed = layers
    logodds_cells, variance_cells, out_observed = cells
    out_logodds, out_variance = values
    k = n_logodds = n_variance = 0
    for r in range(given.shape[0]):
        for c in range(given.shape[1]):
            mark = changed[row0 + r, col0 + c]
            if mark:
                changed[row0 + r, col0 + c] = 0
                given[r, c] = True
                logodds_cells[k] = mark & LOGODDS_CHANGED != 0
                variance_cells[k] = mark & VARIANCE_CHANGED != 0
                out_observed[k] = observed[row0 + r, col0 + c]
                out_logodds[n_logodds] = logodds[row0 + r, col0 + c]
                out_variance[n_variance] = variance[row0 + r, col0 + c]
                n_logodds += logodds_cells[k]
                n_variance += variance_cells[k]
                k += 1
    return n_logodds, n_variance
