"""Detect an object's rotational symmetries from its mesh: ``SYMMETRIES.build("auto")(model)``.

Returns a BOP models_info-style dict ``{"symmetries_discrete": [[16 floats], ...],
"symmetries_continuous": [{"axis": [x, y, z], "offset": [x, y, z]}, ...]}`` (translations in mm;
empty lists for an asymmetric object).

Method:

1. Sample the surface (``num_samples`` points, area-uniform; a denser set of ``num_reference`` points
   stands in for the surface in closest-point queries through a k-d tree). A rotational symmetry
   maps the surface onto itself, so its axis passes through the surface centroid.
2. Candidate axes through the centroid: the principal axes of the surface's second moments and the
   model's bounding-box axes (x, y, z), de-duplicated.
3. For each axis and order n = 2..``max_order``, the turn by 2π/n is scored by the closest-surface
   distance of the turned samples, relative to the diameter: the mean must be below ``mean_tol``
   and the ``quantile`` (default 95th percentile) below ``max_tol``. A candidate that nearly passes
   (within ``refine_factor`` × the tolerances) is refined by a few ICP steps restricted to rotations
   (the scanned LM-O eggbox and glue are only approximately symmetric about slightly tilted axes).
   With ``use_color=True`` the colours at corresponding points must also agree (mean absolute
   difference below ``color_tol`` on a 0..1 scale).
4. An axis that passes every order 2..``max_order`` and a turn by an irrational fraction of 2π is
   continuous (reported once, with its offset, instead of discrete turns). Otherwise the largest
   passing order n gives the n-1 non-identity turns about that axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kpd6d.geometry import pose_matrix, rotation_about_axis
from kpd6d.registry import SYMMETRIES
from kpd6d.symmetry.handlers import axis_angle_offset

__all__ = ["AutoSymmetry", "SymmetryScore"]

_DIST_CAP = 0.1  # closest-surface distances are capped at this fraction of the diameter


@dataclass
class SymmetryScore:
    """How well a rigid transform maps the surface onto itself (distances relative to the diameter)."""

    mean: float
    quantile: float
    color: float  # mean absolute colour difference (0..1); 0 when colour is not used

    def passes(self, mean_tol: float, max_tol: float, color_tol: float | None) -> bool:
        return self.mean <= mean_tol and self.quantile <= max_tol and (color_tol is None or self.color <= color_tol)


def _canonical_axis(a: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a)
    return -a if a[np.argmax(np.abs(a))] < 0 else a


def _sample_with_colours(mesh, n: int, seed: int):
    import trimesh

    pts, fidx = trimesh.sample.sample_surface(mesh, n, seed=seed)
    cols = None
    vc = getattr(getattr(mesh, "visual", None), "vertex_colors", None)
    if getattr(mesh.visual, "kind", None) == "vertex" and vc is not None and len(vc) == len(mesh.vertices):
        tri = mesh.vertices[mesh.faces[fidx]]
        bary = trimesh.triangles.points_to_barycentric(tri, pts)
        cols = np.einsum("nk,nkc->nc", np.clip(bary, 0, 1), np.asarray(vc, float)[mesh.faces[fidx], :3]) / 255.0
    else:
        try:  # textured meshes: trimesh can turn textures into vertex colours
            vcol = mesh.visual.to_color().vertex_colors
            if len(vcol) == len(mesh.vertices):
                cols = np.asarray(vcol, float)[mesh.faces[fidx], :3].mean(axis=1) / 255.0
        except Exception:
            cols = None
    return np.asarray(pts, dtype=np.float64), cols


class AutoSymmetry:
    """Callable ``(model) -> models_info-style dict``; see the module docstring for the parameters."""

    def __init__(self, max_order: int = 8, mean_tol: float = 0.012, max_tol: float = 0.028,
                 quantile: float = 0.95, use_color: bool = False, color_tol: float = 0.08,
                 num_samples: int = 3000, num_reference: int = 40000, refine_factor: float = 3.0,
                 refine_iters: int = 15, seed: int = 0) -> None:
        if int(max_order) < 2:
            raise ValueError(f"auto symmetry: max_order must be >= 2, got {max_order!r}")
        if not 0 < float(quantile) <= 1:
            raise ValueError(f"auto symmetry: quantile must be in (0, 1], got {quantile!r}")
        self.max_order = int(max_order)
        self.mean_tol, self.max_tol, self.quantile = float(mean_tol), float(max_tol), float(quantile)
        self.use_color, self.color_tol = bool(use_color), float(color_tol)
        self.num_samples, self.num_reference = int(num_samples), int(num_reference)
        self.refine_factor, self.refine_iters = float(refine_factor), int(refine_iters)
        self.seed = int(seed)
        self.last_scores: dict = {}

    # -- set-up -------------------------------------------------------------------------------
    def _prepare(self, model):
        from scipy.spatial import cKDTree

        mesh = model.mesh
        pts, cols = _sample_with_colours(mesh, self.num_samples, self.seed)
        ref, ref_cols = _sample_with_colours(mesh, self.num_reference, self.seed + 1)
        if self.use_color and (cols is None or ref_cols is None):
            raise ValueError(
                f"auto symmetry: use_color=True but object {getattr(model, 'obj_id', '?')} has no vertex "
                "colours or texture"
            )
        self._pts, self._cols = pts, cols if self.use_color else None
        self._ref_cols = ref_cols if self.use_color else None
        self._tree = cKDTree(ref)
        self._diameter = float(model.diameter)
        self._centroid = ref.mean(axis=0)

    def _candidate_axes(self, model) -> list[np.ndarray]:
        d = self._tree.data - self._centroid
        _, vecs = np.linalg.eigh(d.T @ d / len(d))
        axes: list[np.ndarray] = []
        for a in [*np.eye(3), *vecs.T]:  # box axes first: exact for objects modelled along them
            a = _canonical_axis(a)
            if all(abs(float(a @ b)) < math.cos(math.radians(3.0)) for b in axes):
                axes.append(a)
        return axes

    # -- scoring ------------------------------------------------------------------------------
    def score(self, R: np.ndarray, t: np.ndarray) -> SymmetryScore:
        """Score the transform x -> R x + t on the prepared model."""
        moved = self._pts @ R.T + t
        cap = _DIST_CAP * self._diameter  # far points cost a lot in the k-d tree; they fail anyway
        dist, idx = self._tree.query(moved, distance_upper_bound=cap)
        far = ~np.isfinite(dist)
        rel = np.where(far, cap, dist) / self._diameter
        col = 0.0
        if self._cols is not None:
            near = ~far
            col = float(np.abs(self._ref_cols[idx[near]] - self._cols[near]).mean()) if near.any() else 1.0
        return SymmetryScore(float(rel.mean()), float(np.quantile(rel, self.quantile)), col)

    def _turn(self, axis, angle, centre):
        R = rotation_about_axis(axis, angle)
        return R, centre - R @ centre

    def _refine(self, axis: np.ndarray, angle: float, centre: np.ndarray):
        """ICP over rotations by ``angle`` about axes through points near ``centre``: returns (axis, centre)."""
        ref = self._tree.data
        for _ in range(self.refine_iters):
            R, t = self._turn(axis, angle, centre)
            moved = self._pts @ R.T + t
            dist, idx = self._tree.query(moved, distance_upper_bound=_DIST_CAP * self._diameter)
            near = np.isfinite(dist)
            if near.sum() < 10:
                break
            src, target = self._pts[near], ref[idx[near]]
            # best rigid transform src -> target (Kabsch), then project onto a turn by `angle`
            mp, mt = src.mean(0), target.mean(0)
            H = (src - mp).T @ (target - mt)
            U, _, Vt = np.linalg.svd(H)
            Rk = Vt.T @ U.T
            if np.linalg.det(Rk) < 0:
                Vt[-1] *= -1
                Rk = Vt.T @ U.T
            tk = mt - Rk @ mp
            try:
                new_axis, _, off = axis_angle_offset(pose_matrix(Rk, tk))
            except ValueError:
                break
            if new_axis @ axis < 0:
                new_axis = -new_axis
            if np.degrees(math.acos(min(1.0, abs(float(new_axis @ axis))))) > 10:  # ran away: stop
                break
            new_centre = off + ((centre - off) @ new_axis) * new_axis
            done = np.linalg.norm(new_axis - axis) < 1e-6 and np.linalg.norm(new_centre - centre) < 1e-4
            axis, centre = _canonical_axis(new_axis), new_centre
            if done:
                break
        return axis, centre

    def _passes(self, s: SymmetryScore, factor: float = 1.0) -> bool:
        return s.passes(self.mean_tol * factor, self.max_tol * factor, self.color_tol * factor if self._cols is not None else None)

    def _test_turn(self, axis, angle, centre):
        """(passes, axis, centre, score) for the turn by ``angle``, refined when it nearly passes."""
        s = self.score(*self._turn(axis, angle, centre))
        if self._passes(s):
            return True, axis, centre, s
        if self.refine_iters > 0 and self._passes(s, self.refine_factor):
            a2, c2 = self._refine(axis, angle, centre)
            s2 = self.score(*self._turn(a2, angle, c2))
            if self._passes(s2):
                return True, a2, c2, s2
            return False, axis, centre, s2
        return False, axis, centre, s

    # -- the detector -------------------------------------------------------------------------
    def __call__(self, model) -> dict:
        self._prepare(model)
        discrete: list[np.ndarray] = []
        continuous: list[dict] = []
        self.last_scores = {}
        for axis in self._candidate_axes(model):
            centre = self._centroid
            passed: dict[int, tuple] = {}
            for n in range(2, self.max_order + 1):
                ok, a, c, s = self._test_turn(axis, 2 * math.pi / n, centre)
                self.last_scores[(tuple(np.round(axis, 4)), n)] = s
                # every multiple of the turn must pass too (a near-miss order such as 7 on a
                # hexagonal shape passes for the smallest turn only)
                if ok and all(self._passes(self.score(*self._turn(a, 2 * math.pi * k / n, c)))
                              for k in range(2, n // 2 + 1)):
                    passed[n] = (a, c)
            if len(passed) == self.max_order - 1:
                a, c = passed[self.max_order]
                irr = 2 * math.pi * (math.sqrt(5) - 1) / 2 * 0.37  # an irrational fraction of a turn
                ok, a, c, _ = self._test_turn(a, irr, c)
                if ok:
                    if not any(abs(float(a @ np.asarray(cc["axis"]))) > math.cos(math.radians(3.0)) for cc in continuous):
                        off = c - (c @ a) * a
                        continuous.append({"axis": a.tolist(), "offset": off.tolist()})
                    continue
            if not passed:
                continue
            n = max(passed)
            a, c = passed[n]
            for k in range(1, n):
                R, t = self._turn(a, 2 * math.pi * k / n, c)
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R, t
                if not any(np.allclose(T, D, atol=1e-2 * max(1.0, self._diameter / 100)) for D in discrete):
                    discrete.append(T)
        # discrete turns about a continuous axis are implied by it
        if continuous:
            keep = []
            for T in discrete:
                ax, _, _ = axis_angle_offset(T)
                if not any(abs(float(ax @ np.asarray(c["axis"]))) > math.cos(math.radians(3.0)) for c in continuous):
                    keep.append(T)
            discrete = keep
        return {
            "symmetries_discrete": [T.reshape(-1).tolist() for T in discrete],
            "symmetries_continuous": continuous,
        }


@SYMMETRIES.register("auto")
def _build_auto(max_order: int = 8, mean_tol: float = 0.012, max_tol: float = 0.028, quantile: float = 0.95,
                use_color: bool = False, color_tol: float = 0.08, num_samples: int = 3000,
                num_reference: int = 40000, refine_factor: float = 3.0, refine_iters: int = 15,
                seed: int = 0) -> AutoSymmetry:
    return AutoSymmetry(max_order, mean_tol, max_tol, quantile, use_color, color_tol, num_samples,
                        num_reference, refine_factor, refine_iters, seed)
