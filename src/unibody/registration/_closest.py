"""Exact closest points on a triangle surface, accelerated by a one-level sphere hierarchy.

The triangles are grouped into compact clusters (k-means on their centroids), each with a
bounding sphere (centre, radius = farthest triangle vertex), so ``|p - centre| - radius``
bounds from below the distance from ``p`` to every triangle of the cluster. A query tests
exactly (:func:`unibody.geometry.tetra.closest_point_on_triangles`) all triangles of the
``k`` clusters with the smallest bounds and accepts the answer when the next cluster's
bound is not below it; rows that fail retry with 4x as many clusters, up to all of them, so
the result is always the exact closest triangle. Compared with
:func:`~unibody.geometry.tetra.closest_triangles` (bounds per triangle) the per-query cost
drops from O(F) to O(F / cluster size), which matters inside an ICP loop.

The clusters can follow a deforming mesh (:meth:`SurfaceIndex.refit`): membership stays,
centres and radii are recomputed, and the bounds stay valid.
"""

from __future__ import annotations

import torch

from ..geometry.tetra import closest_point_on_triangles

__all__ = ["SurfaceIndex", "cluster_triangles"]

_PAIRS = 1 << 17  # (point, triangle) pairs evaluated at once


def cluster_triangles(vertices: torch.Tensor, faces: torch.Tensor, *, cluster_size: int = 24, seed: int = 0):
    """(F,) cluster label of each triangle: a few k-means (Lloyd) steps on the centroids."""
    centroid = vertices[faces].mean(1)
    n_faces = faces.shape[0]
    k = max(1, n_faces // cluster_size)
    gen = torch.Generator().manual_seed(seed)
    c32 = centroid.float()
    centres = c32[torch.randperm(n_faces, generator=gen)[:k]].clone()
    for _ in range(5):
        label = torch.cdist(c32, centres).argmin(1)
        count = torch.bincount(label, minlength=centres.shape[0])
        sums = torch.zeros_like(centres).index_add_(0, label, c32)
        keep = count > 0
        centres = sums[keep] / count[keep, None]
    return torch.cdist(c32, centres).argmin(1)


class SurfaceIndex:
    """Closest-triangle queries against one triangle mesh (float64 recommended).

    Args:
        vertices: (V, 3) mesh vertices.
        faces: (F, 3) long triangles; zero-area triangles take part like any other.
        cluster_size: mean number of triangles per cluster.
        seed: seed of the k-means initialisation (results do not depend on it, speed does).
        labels: (F,) precomputed cluster labels (e.g. of the same mesh in another pose).
    """

    def __init__(
        self,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        *,
        cluster_size: int = 24,
        seed: int = 0,
        labels: torch.Tensor | None = None,
    ) -> None:
        self.faces = faces
        if labels is None:
            labels = cluster_triangles(vertices, faces, cluster_size=cluster_size, seed=seed)
        # Relabel to consecutive non-empty clusters, triangles sorted by cluster.
        used, label = torch.unique(labels, return_inverse=True)
        self.num_clusters = used.numel()
        self.order = torch.argsort(label, stable=True)  # triangles grouped by cluster
        self.count = torch.bincount(label, minlength=self.num_clusters)
        self.start = torch.cumsum(self.count, 0) - self.count
        self.label = label
        self.refit(vertices)

    def refit(self, vertices: torch.Tensor) -> None:
        """Recompute the cluster spheres for moved ``vertices`` (same topology)."""
        self.vertices = vertices
        tri = vertices[self.faces]  # (F, 3, 3)
        self.tri_sorted = tri[self.order]
        self.tri_centre = self.tri_sorted.mean(1)
        self.tri_radius = (self.tri_sorted - self.tri_centre[:, None]).norm(dim=-1).amax(1)
        sums = torch.zeros(self.num_clusters, 3, dtype=tri.dtype).index_add_(0, self.label, tri.mean(1))
        self.centre = sums / self.count[:, None]
        far = (tri - self.centre[self.label][:, None]).norm(dim=-1).amax(1)
        self.radius = torch.zeros(self.num_clusters, dtype=tri.dtype).scatter_reduce_(0, self.label, far, "amax")

    def _exact(self, p: torch.Tensor, clusters: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Best triangle among all triangles of ``clusters (n, k)`` for each point ``p (n, 3)``."""
        n, k = clusters.shape
        cnt = self.count[clusters]  # (n, k)
        per_point = cnt.sum(1)
        pid = torch.repeat_interleave(torch.arange(n), per_point)
        # position of each pair inside its cluster
        flat_c = clusters.reshape(-1)
        flat_cnt = cnt.reshape(-1)
        pair_cluster = torch.repeat_interleave(flat_c, flat_cnt)
        offs = torch.arange(pair_cluster.numel()) - torch.repeat_interleave(
            torch.cumsum(flat_cnt, 0) - flat_cnt, flat_cnt
        )
        tri_pos = self.start[pair_cluster] + offs
        # Per-triangle sphere test: the distance to a triangle's centroid bounds the answer
        # from above, |p - c_t| - r_t bounds each triangle from below; skip the hopeless ones.
        dc = (p[pid] - self.tri_centre[tri_pos]).norm(dim=-1)
        ub = torch.full((n,), torch.inf, dtype=p.dtype).scatter_reduce_(0, pid, dc, "amin")
        keep = dc - self.tri_radius[tri_pos] <= ub[pid]
        pid, tri_pos = pid[keep], tri_pos[keep]
        d2 = torch.empty(pid.numel(), dtype=p.dtype)
        q = torch.empty(pid.numel(), 3, dtype=p.dtype)
        for s in range(0, pid.numel(), _PAIRS):
            t = self.tri_sorted[tri_pos[s : s + _PAIRS]]
            qq, dd = closest_point_on_triangles(p[pid[s : s + _PAIRS]], t[:, 0], t[:, 1], t[:, 2])
            q[s : s + _PAIRS], d2[s : s + _PAIRS] = qq, dd
        best = torch.full((n,), torch.inf, dtype=p.dtype).scatter_reduce_(0, pid, d2, "amin")
        hit = d2 == best[pid]
        idx = torch.full((n,), -1, dtype=torch.long).scatter_reduce_(
            0, pid[hit], torch.arange(pid.numel())[hit], "amax"
        )
        return self.order[tri_pos[idx]], q[idx], best

    def query(
        self, points: torch.Tensor, *, clusters: int = 3, chunk: int = 2048
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Exact closest triangle for each of ``points (N, 3)``.

        Returns ``(face index (N,) long, closest point (N, 3), distance (N,))``.
        """
        n = points.shape[0]
        face = torch.empty(n, dtype=torch.long)
        q = torch.empty(n, 3, dtype=points.dtype)
        dist = torch.empty(n, dtype=points.dtype)
        scale = float(self.centre.abs().max()) + float(points.abs().max()) + float(self.radius.max())
        slack = 64.0 * torch.finfo(torch.float32).eps * scale
        for s in range(0, n, chunk):
            p = points[s : s + chunk]
            bound = torch.cdist(p.float(), self.centre.float()) - self.radius.float()
            todo = torch.arange(p.shape[0])
            k = min(clusters, self.num_clusters)
            while todo.numel():
                lb = bound[todo]
                if k >= self.num_clusters:
                    cand = torch.arange(self.num_clusters).expand(todo.numel(), -1)
                    next_lb = None
                else:
                    vals, idx = lb.topk(k + 1, dim=1, largest=False, sorted=True)
                    cand, next_lb = idx[:, :k], vals[:, k]
                f, qq, d2 = self._exact(p[todo], cand)
                d = d2.sqrt()
                ok = torch.ones_like(d, dtype=torch.bool) if next_lb is None else next_lb.to(d) >= d + slack
                rows = todo[ok] + s
                face[rows], q[rows], dist[rows] = f[ok], qq[ok], d[ok]
                todo = todo[~ok]
                k = min(4 * k, self.num_clusters)
        return face, q, dist
