"""Surface distances on a triangle mesh: the edge graph and (bounded) Dijkstra searches over it.

"Surface distance" follows Kshirsagar et al.: the length of the shortest path along mesh edges.
It respects holes (a mouth slit, an eye opening): two points facing each other across a slit are
as far apart as the path around the hole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra


def edge_graph(
    vertices: np.ndarray,
    triangles: np.ndarray,
    mask: np.ndarray | None = None,
    group: np.ndarray | None = None,
) -> sp.csr_matrix:
    """Symmetric ``(V, V)`` CSR matrix of edge lengths (float64, mesh units).

    Args:
        vertices: ``(V, 3)`` positions.
        triangles: ``(F, 3)`` vertex ids.
        mask: optional ``(V,) bool``; edges touching a vertex outside the mask are dropped (the
            vertex stays in the graph, isolated).
        group: optional ``(V,)`` labels (rigid groups); edges between different labels are
            dropped, so no path crosses from one part to another (the tongue to the upper gums).

    Zero-length edges (coincident vertices) get a tiny positive length so that they stay in the
    sparse structure (an explicit 0 would mean "no edge").
    """
    v = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = len(v)
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    e = e[e[:, 0] != e[:, 1]]
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        e = e[mask[e[:, 0]] & mask[e[:, 1]]]
    if group is not None:
        group = np.asarray(group)
        e = e[group[e[:, 0]] == group[e[:, 1]]]
    e = np.sort(e, axis=1)
    e = np.sort(e[:, 0] * n + e[:, 1])  # sort + diff: much faster than np.unique's hashing here
    e = e[np.r_[True, e[1:] != e[:-1]]] if len(e) else e
    a, b = e // n, e % n
    length = np.linalg.norm(v[a] - v[b], axis=1)
    length = np.maximum(length, 1e-12 * max(float(np.ptp(v)) if len(v) else 1.0, 1e-30))
    g = sp.coo_matrix((np.r_[length, length], (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()
    g.sort_indices()
    return g


def components(graph: sp.csr_matrix) -> np.ndarray:
    """``(V,) int`` connected-component label of every vertex."""
    return connected_components(graph, directed=False)[1]


@dataclass
class Voronoi:
    """Result of growing regions from several sources at once (a geodesic Voronoi diagram).

    Attributes:
        distance: ``(V,)`` surface distance to the nearest source (``inf`` where unreachable).
        source: ``(V,)`` index into ``sources`` of the nearest one (``-1`` where unreachable).
        pairs: ``(P, 2)`` indices into ``sources`` (i < j) whose regions share an edge.
        pair_distance: ``(P,)`` length of the shortest path through a shared boundary edge (an
            upper bound on the true source-to-source surface distance, exact in most cases).
    """

    distance: np.ndarray
    source: np.ndarray
    pairs: np.ndarray
    pair_distance: np.ndarray


def voronoi(graph: sp.csr_matrix, sources: np.ndarray) -> Voronoi:
    """Grow a region from every source vertex at once (multi-source Dijkstra) and find neighbours.

    Two sources are neighbours when their regions have a common boundary (an edge whose ends
    belong to different regions), as in the "feature point distribution" step of Kshirsagar et al.
    """
    sources = np.asarray(sources, dtype=np.int64)
    n = graph.shape[0]
    if len(sources) == 0:
        return Voronoi(np.full(n, np.inf), np.full(n, -1), np.zeros((0, 2), np.int64), np.zeros(0))
    dist, _, src_vertex = dijkstra(
        graph, directed=False, indices=sources, min_only=True, return_predecessors=True
    )
    lookup = np.full(n, -1, dtype=np.int64)
    lookup[sources] = np.arange(len(sources))
    source = np.where(src_vertex >= 0, lookup[np.maximum(src_vertex, 0)], -1)
    coo = graph.tocoo()
    a, b, w = coo.row, coo.col, coo.data
    keep = (a < b) & (source[a] >= 0) & (source[b] >= 0) & (source[a] != source[b])
    a, b, w = a[keep], b[keep], w[keep]
    si, sj = source[a], source[b]
    lo, hi = np.minimum(si, sj), np.maximum(si, sj)
    through = dist[a] + w + dist[b]
    key = lo * len(sources) + hi
    order = np.lexsort((through, key))
    key, through = key[order], through[order]
    first = np.r_[True, key[1:] != key[:-1]] if len(key) else np.zeros(0, bool)
    key, through = key[first], through[first]
    pairs = np.stack([key // len(sources), key % len(sources)], axis=1)
    return Voronoi(dist, source, pairs, through)


def bounded_distances(
    graph: sp.csr_matrix, sources: np.ndarray, limits: np.ndarray, *, budget: int = 10_000_000
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Surface distances from each source to every vertex closer than its own limit.

    Args:
        graph: ``(V, V)`` edge-length graph.
        sources: ``(S,)`` vertex ids.
        limits: ``(S,)`` search radius per source (mesh units).
        budget: largest dense block (sources x vertices) held at once; sources are searched in
            chunks of similar limit so a 500k-vertex mesh never needs a dense ``(S, V)`` array.

    Returns:
        per source, ``(vertex_ids (n,) int64 ascending, distances (n,) float64)`` with
        ``distance < limit`` (a positive limit always includes the source itself, at 0).
    """
    sources = np.asarray(sources, dtype=np.int64)
    limits = np.asarray(limits, dtype=np.float64)
    n = graph.shape[0]
    out: list[tuple[np.ndarray, np.ndarray]] = [None] * len(sources)  # type: ignore[list-item]
    chunk = max(1, budget // max(n, 1))
    order = np.argsort(limits)
    for start in range(0, len(order), chunk):
        idx = order[start : start + chunk]
        lim = float(limits[idx].max())
        dist = dijkstra(graph, directed=False, indices=sources[idx], limit=lim)
        dist = np.atleast_2d(dist)
        for row, s in zip(dist, idx):
            ids = np.flatnonzero(row < limits[s])
            out[s] = (ids, row[ids])
    return out
