"""Topology generators: lattices (chains, grids, blocks), their springs and faces.

Particles of a lattice with shape (n0, n1, ...) are numbered in C order:
index = ravel_multi_index((i0, i1, ...), shape).
"""

from __future__ import annotations

import itertools

import numpy as np

# Neighbour sets, by the offsets they contain.
#   structural: +-1 along one lattice axis          (chain links, cloth warp/weft)
#   shear:      +-1 along two axes (face diagonals)  (cloth "diagonal" springs)
#   diagonal:   +-1 along three axes (body diagonals)
#   bend:       +-2 along one axis                   (resist folding: keep the shape)
NEIGHBOUR_SETS = ("structural", "shear", "diagonal", "bend")


def lattice_offsets(dimension: int, neighbour_set: str) -> list[tuple[int, ...]]:
    """Canonical offsets (first non-zero component positive) of one neighbour set.

    Example:
        >>> lattice_offsets(2, "shear")
        [(1, -1), (1, 1)]
    """
    if neighbour_set == "bend":
        return [tuple(2 if k == axis else 0 for k in range(dimension)) for axis in range(dimension)]
    order = {"structural": 1, "shear": 2, "diagonal": 3}[neighbour_set]
    offsets = []
    for offset in itertools.product((-1, 0, 1), repeat=dimension):
        nonzero = [c for c in offset if c]
        if len(nonzero) == order and nonzero[0] > 0:
            offsets.append(offset)
    return offsets


def lattice_springs(shape, neighbour_sets) -> np.ndarray:
    """Springs of a lattice joining each particle to its neighbours in the given sets.

    Args:
        shape: particles along each lattice axis, e.g. (31, 41).
        neighbour_sets: names from NEIGHBOUR_SETS.
    Returns:
        int64 array (S, 2) of particle index pairs, no duplicates.

    Example:
        >>> lattice_springs((31, 41), ["structural", "shear"]).shape
        (4870, 2)
    """
    shape = tuple(int(n) for n in shape)
    index = np.arange(int(np.prod(shape))).reshape(shape)
    pairs = []
    for name in neighbour_sets:
        for offset in lattice_offsets(len(shape), name):
            src = tuple(slice(max(0, -o), n - max(0, o)) for o, n in zip(offset, shape))
            dst = tuple(slice(max(0, o), n - max(0, -o)) for o, n in zip(offset, shape))
            a, b = index[src].reshape(-1), index[dst].reshape(-1)
            pairs.append(np.stack([a, b], axis=1))
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64)
    return np.concatenate(pairs, axis=0)


def lattice_positions(shape, spacing, origin, axes) -> np.ndarray:
    """Positions (N, 3) [m] of a lattice whose axis k runs along world axis axes[k]."""
    shape = tuple(int(n) for n in shape)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, len(shape))
    positions = np.tile(np.asarray(origin, dtype=float), (grid.shape[0], 1))
    for k, axis in enumerate(axes):
        positions[:, axis] += spacing * grid[:, k]
    return positions


def lattice_faces(shape) -> np.ndarray:
    """Surface triangles (F, 3): the grid of a 2-D lattice, the outer faces of a 3-D one."""
    shape = tuple(int(n) for n in shape)
    index = np.arange(int(np.prod(shape))).reshape(shape)
    if len(shape) == 2:
        sheets = [index]
    elif len(shape) == 3:
        sheets = []
        for axis in range(3):
            for side in (0, shape[axis] - 1):
                sheets.append(np.take(index, side, axis=axis))
    else:
        return np.zeros((0, 3), dtype=np.int64)
    triangles = []
    for sheet in sheets:
        a, b = sheet[:-1, :-1].reshape(-1), sheet[1:, :-1].reshape(-1)
        c, d = sheet[1:, 1:].reshape(-1), sheet[:-1, 1:].reshape(-1)
        triangles += [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
    return np.concatenate(triangles, axis=0)
