"""Symmetry handlers: map a pose to its canonical equivalent and list an object's symmetry transforms.

A symmetry transform ``S = (R_S, t_S)`` (4x4, model frame, mm) leaves the object unchanged, so the
poses ``(R, t)`` and ``(R R_S, t + R t_S)`` look identical. Seen from the object, the camera of the
second pose sits at ``S^-1(eye)`` where ``eye = -R^T t`` is the camera centre of the first.

* ``none``: no symmetry; ``canonicalize`` is the identity.
* ``rotational``: α-rotational symmetry (α = 2π / order) about an axis through ``offset``;
  ``canonicalize`` returns the equivalent pose whose camera azimuth about the axis lies in [0, α).
  Azimuth is measured from a reference direction normal to the axis: by default
  :func:`reference_direction` (the model's x axis projected onto the plane normal to the axis, or y
  when x is parallel to the axis); with ``boundary="least_motion"`` (:func:`handler_for_model`)
  :func:`least_motion_reference`, the direction from which the object's surface moves least in the
  image under its symmetry rotation. Views at the range's boundary are labelled by one equivalent
  pose on one side and the other on the other: there the least motion means the least difference
  between the two labels a network has to tell apart.
  ``in_canonical_range(R, t)`` tells whether a pose already lies there (for restricting pose sampling).
* ``discrete``: any finite group of symmetries (several axes); ``canonicalize`` picks the
  equivalent pose whose viewing direction is closest to a fixed reference direction.
* ``continuous``: body of revolution about an axis; ``canonicalize`` turns the pose about the axis so
  the camera lies in the half-plane of azimuth 0. Extra discrete symmetries (e.g. a flip of a
  cylinder) are folded first so the camera lies on the +axis side.

``transforms()`` lists the symmetry transforms as 4x4 matrices, the identity first (continuous ones
discretised in ``steps`` angles). :func:`handler_for_model` chooses the handler from a model's
``symmetries_discrete`` / ``symmetries_continuous``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from kpd6d.geometry import pose_matrix, rotation_about_axis
from kpd6d.registry import SYMMETRIES

__all__ = [
    "ContinuousSymmetry",
    "DiscreteSymmetry",
    "NoSymmetry",
    "RotationalSymmetry",
    "axis_angle_offset",
    "handler_for_model",
    "least_motion_reference",
    "reference_direction",
]

#: where :func:`handler_for_model` puts a rotational symmetry's canonical-range boundary
BOUNDARIES = ("model_x", "least_motion")


def check_boundary(boundary: str) -> str:
    """``boundary`` if it is one of :data:`BOUNDARIES`, else a ValueError listing them."""
    if boundary not in BOUNDARIES:
        raise ValueError(f"symmetry boundary {boundary!r} unknown; known: {', '.join(BOUNDARIES)}")
    return boundary


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"symmetry axis must be a finite non-zero 3-vector, got {v.tolist()}")
    return v / n


def _normal_part(v, axis: np.ndarray) -> np.ndarray:
    """The component of the 3-vector ``v`` normal to the unit vector ``axis``."""
    v = np.asarray(v, dtype=np.float64).reshape(3)
    return v - (v @ axis) * axis


def reference_direction(axis) -> np.ndarray:
    """Unit vector normal to ``axis`` from which azimuths are measured (model x, or y if x ∥ axis)."""
    a = _unit(axis)
    for ref in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        p = _normal_part(ref, a)
        if np.linalg.norm(p) > 0.3:
            return p / np.linalg.norm(p)
    raise AssertionError("unreachable")  # pragma: no cover


def least_motion_reference(points, axis, offset=(0.0, 0.0, 0.0), angle: float = math.pi,
                           samples: int = 720) -> np.ndarray:
    """Unit direction normal to ``axis`` from which ``points`` (N, 3; model frame) move least in the image
    when the object turns by ``angle`` about the axis through ``offset``.

    The motion seen from direction ``d`` is each point's displacement with its component along ``d``
    removed (an orthographic view); the returned ``d`` minimises its mean length over ``samples``
    azimuths. For a flat two-fold object (a bottle turned half-way about its height) it is the
    direction along its broad side: seen from there the turn only swaps its thin edges.
    """
    a = _unit(axis)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(P) == 0 or not np.isfinite(P).all():
        raise ValueError(f"least_motion_reference needs finite points, got {len(P)} points")
    o = np.asarray(offset, dtype=np.float64).reshape(3)
    D = (P - o) @ (rotation_about_axis(a, float(angle)).T - np.eye(3))  # displacement of each point
    e1 = reference_direction(a)
    e2 = np.cross(a, e1)
    theta = np.linspace(0.0, 2 * math.pi, int(samples), endpoint=False)
    d = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2  # (S, 3)
    along = D @ d.T  # (N, S)
    seen = np.sqrt(np.clip((D * D).sum(1)[:, None] - along ** 2, 0.0, None)).mean(0)
    return d[int(np.argmin(seen))]


def _nearest_rotation(M) -> np.ndarray:
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def axis_angle_offset(S) -> tuple[np.ndarray, float, np.ndarray]:
    """(unit axis, angle in [0, π] radians, offset) of a 4x4 (approximately) rigid symmetry transform.

    The rotation part is projected onto the nearest rotation first (BOP's approximate matrices);
    the offset is the point of the axis closest to the origin (least squares of (I - R) o = t).
    The axis sign is chosen so its largest component is positive.
    """
    S = np.asarray(S, dtype=np.float64).reshape(4, 4)
    R, t = _nearest_rotation(S[:3, :3]), S[:3, 3]
    angle = math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-9:
        raise ValueError(f"symmetry transform is (close to) the identity: {S.tolist()}")
    skew = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < math.pi - 1e-3:
        axis = skew / np.linalg.norm(skew)
    else:  # near 180°: skew part vanishes; R + I has rank 1 along the axis
        w, V = np.linalg.eigh((R + R.T) / 2.0)
        axis = V[:, np.argmax(w)]
        if skew @ axis < 0:
            axis = -axis
    if axis[np.argmax(np.abs(axis))] < 0:  # canonical sign; flip the angle so (axis, angle) stays R
        axis = -axis
        if angle < math.pi - 1e-3:
            angle = 2 * math.pi - angle
    offset = np.linalg.lstsq(np.eye(3) - R, t, rcond=None)[0]
    offset = _normal_part(offset, axis)
    return axis, angle, offset


def _rotation_transform(axis, angle: float, offset) -> np.ndarray:
    R = rotation_about_axis(axis, angle)
    o = np.asarray(offset, dtype=np.float64)
    return pose_matrix(R, o - R @ o)


def _as_batch(R, t):
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape[-2:] != (3, 3) or t.shape[-1:] != (3,) or R.shape[:-2] != t.shape[:-1]:
        raise ValueError(f"canonicalize: expected R (..., 3, 3) and t (..., 3), got {R.shape} and {t.shape}")
    return R, t


def _eye(R, t):
    """Camera centres in the model frame, -R^T t, (..., 3)."""
    return -np.einsum("...ji,...j->...i", R, t)


def _apply_symmetry(R, t, S):
    """Equivalent pose (R R_S, t + R t_S) for per-pose 4x4 transforms S (..., 4, 4)."""
    RS, tS = S[..., :3, :3], S[..., :3, 3]
    return R @ RS, t + np.einsum("...ij,...j->...i", R, tS)


class NoSymmetry:
    """An asymmetric object (also right for mirror symmetries: they are not rigid motions)."""

    name = "none"

    def canonicalize(self, R, t):
        R, t = _as_batch(R, t)
        return R.copy(), t.copy()

    def transforms(self, model=None) -> list[np.ndarray]:
        return [np.eye(4)]

    def in_canonical_range(self, R, t):
        R, t = _as_batch(R, t)
        return np.ones(R.shape[:-2], dtype=bool) if R.ndim > 2 else True

    def __repr__(self) -> str:
        return "NoSymmetry()"


class _AxisMixin:
    axis: np.ndarray
    offset: np.ndarray
    reference: np.ndarray | None = None  # azimuth 0 (normal to the axis); None: reference_direction(axis)

    def _frame(self):
        e1 = reference_direction(self.axis) if self.reference is None else self.reference
        return e1, np.cross(self.axis, e1)

    def azimuth(self, R, t):
        """Camera azimuth about the axis (radians, [0, 2π)) of pose(s) (R, t)."""
        R, t = _as_batch(R, t)
        e1, e2 = self._frame()
        d = _eye(R, t) - self.offset
        return np.mod(np.arctan2(d @ e2, d @ e1), 2 * math.pi)


class RotationalSymmetry(_AxisMixin):
    """α-rotational symmetry, α = 2π / ``order``, about ``axis`` through ``offset`` (model frame, mm).

    ``reference``: the direction of azimuth 0 (projected onto the plane normal to the axis); None:
    :func:`reference_direction`.
    """

    name = "rotational"

    def __init__(self, order: int = 2, axis: Sequence[float] = (0.0, 0.0, 1.0),
                 offset: Sequence[float] = (0.0, 0.0, 0.0), reference: Sequence[float] | None = None) -> None:
        if int(order) != order or order < 2:
            raise ValueError(f"rotational symmetry order must be an integer >= 2, got {order!r}")
        self.order = int(order)
        self.axis = _unit(axis)
        self.offset = _normal_part(offset, self.axis)
        self.alpha = 2 * math.pi / self.order
        if reference is not None:
            r = _normal_part(reference, self.axis)
            if not np.isfinite(r).all() or np.linalg.norm(r) < 1e-6:
                raise ValueError(f"rotational symmetry: reference {np.asarray(reference).tolist()} must not be parallel "
                                 f"to the axis {self.axis.round(4).tolist()}")
            self.reference = r / np.linalg.norm(r)

    def transforms(self, model=None) -> list[np.ndarray]:
        return [np.eye(4)] + [_rotation_transform(self.axis, j * self.alpha, self.offset) for j in range(1, self.order)]

    def canonicalize(self, R, t):
        R, t = _as_batch(R, t)
        phi = self.azimuth(R, t)
        j = np.floor(phi / self.alpha).astype(int) % self.order
        Ts = np.stack(self.transforms())
        return _apply_symmetry(R, t, Ts[j])

    def in_canonical_range(self, R, t, tol: float = 1e-9):
        phi = self.azimuth(R, t)
        return ((phi >= -tol) & (phi < self.alpha + tol)) | (phi > 2 * math.pi - tol)

    def canonical_azimuth_range(self) -> tuple[float, float]:
        """Azimuths [lo, hi) (radians, about the axis from the reference direction) of canonical poses."""
        return 0.0, self.alpha

    def __repr__(self) -> str:
        ref = "" if self.reference is None else f", reference={self.reference.round(4).tolist()}"
        return (f"RotationalSymmetry(order={self.order}, axis={self.axis.round(4).tolist()}, "
                f"offset={self.offset.round(3).tolist()}{ref})")


class DiscreteSymmetry:
    """A finite symmetry group given by its transforms (several axes); identity added if missing."""

    name = "discrete"

    def __init__(self, transforms: Sequence, reference: Sequence[float] = (0.3, 0.5, 0.8)) -> None:
        Ts = [np.asarray(T, dtype=np.float64).reshape(4, 4) for T in transforms]
        Ts = [T for T in Ts if not np.allclose(T, np.eye(4), atol=1e-6)]
        if not Ts:
            raise ValueError("discrete symmetry needs at least one non-identity 4x4 transform")
        for T in Ts:
            T[:3, :3] = _nearest_rotation(T[:3, :3])
        self._transforms = [np.eye(4), *Ts]
        self.reference = _unit(reference)

    def transforms(self, model=None) -> list[np.ndarray]:
        return [T.copy() for T in self._transforms]

    def canonicalize(self, R, t):
        R, t = _as_batch(R, t)
        Ts = np.stack(self._transforms)
        eyes = _eye(R, t)  # (..., 3)
        # camera centre of each equivalent pose: S^-1(eye) = R_S^T (eye - t_S)
        cand = np.einsum("kji,...kj->...ki", Ts[:, :3, :3], eyes[..., None, :] - Ts[:, :3, 3])
        cand = cand / np.linalg.norm(cand, axis=-1, keepdims=True).clip(1e-12)
        k = np.argmax(cand @ self.reference, axis=-1)
        return _apply_symmetry(R, t, Ts[k])

    def __repr__(self) -> str:
        return f"DiscreteSymmetry({len(self._transforms)} transforms)"


class ContinuousSymmetry(_AxisMixin):
    """Body of revolution about ``axis`` through ``offset``; ``flips`` are extra discrete symmetries."""

    name = "continuous"

    def __init__(self, axis: Sequence[float] = (0.0, 0.0, 1.0), offset: Sequence[float] = (0.0, 0.0, 0.0),
                 steps: int = 36, flips: Sequence = ()) -> None:
        self.axis = _unit(axis)
        self.offset = _normal_part(offset, self.axis)
        if int(steps) < 2:
            raise ValueError(f"continuous symmetry: steps must be >= 2, got {steps!r}")
        self.steps = int(steps)
        self.flips = [np.asarray(F, dtype=np.float64).reshape(4, 4) for F in flips]

    def transforms(self, model=None) -> list[np.ndarray]:
        """Identity, the rotations by multiples of 2π/steps, and their compositions with the flips."""
        rots = [np.eye(4)] + [_rotation_transform(self.axis, 2 * math.pi * j / self.steps, self.offset)
                              for j in range(1, self.steps)]
        return rots + [F @ T for F in self.flips for T in rots]

    def canonicalize(self, R, t):
        R, t = _as_batch(R, t)
        if self.flips:  # fold flips first: camera on the +axis side
            elev = (_eye(R, t) - self.offset) @ self.axis
            for F in self.flips:
                Rf, tf = _apply_symmetry(R, t, np.broadcast_to(F, (*R.shape[:-2], 4, 4)))
                better = ((_eye(Rf, tf) - self.offset) @ self.axis) > elev + 1e-9
                R = np.where(better[..., None, None], Rf, R)
                t = np.where(better[..., None], tf, t)
                elev = np.where(better, (_eye(R, t) - self.offset) @ self.axis, elev)
        phi = self.azimuth(R, t)
        S = np.stack([_rotation_transform(self.axis, float(p), self.offset) for p in np.ravel(phi)])
        S = S.reshape((*np.shape(phi), 4, 4))
        return _apply_symmetry(R, t, S)

    def in_canonical_range(self, R, t, tol: float = 1e-6):
        phi = self.azimuth(R, t)
        return (phi < tol) | (phi > 2 * math.pi - tol)

    def canonical_azimuth_range(self) -> tuple[float, float]:
        return 0.0, 0.0

    def __repr__(self) -> str:
        return f"ContinuousSymmetry(axis={self.axis.round(4).tolist()}, offset={self.offset.round(3).tolist()})"


@SYMMETRIES.register("none")
def _build_none() -> NoSymmetry:
    return NoSymmetry()


@SYMMETRIES.register("rotational")
def _build_rotational(order: int = 2, axis: Sequence[float] = (0.0, 0.0, 1.0),
                      offset: Sequence[float] = (0.0, 0.0, 0.0), reference: Sequence[float] | None = None
                      ) -> RotationalSymmetry:
    return RotationalSymmetry(order=order, axis=axis, offset=offset, reference=reference)


@SYMMETRIES.register("discrete")
def _build_discrete(transforms: Sequence, reference: Sequence[float] = (0.3, 0.5, 0.8)) -> DiscreteSymmetry:
    return DiscreteSymmetry(transforms, reference)


@SYMMETRIES.register("continuous")
def _build_continuous(axis: Sequence[float] = (0.0, 0.0, 1.0), offset: Sequence[float] = (0.0, 0.0, 0.0),
                      steps: int = 36) -> ContinuousSymmetry:
    return ContinuousSymmetry(axis=axis, offset=offset, steps=steps)


def handler_for_model(model, *, axis_tol_deg: float = 5.0, offset_tol: float | None = None, steps: int = 36,
                      boundary: str = "model_x"):
    """The symmetry handler for ``model`` from its ``symmetries_discrete`` / ``symmetries_continuous``.

    * none listed -> ``none``
    * continuous -> ``continuous`` (the first axis; discrete ones about other axes become flips)
    * discrete rotations all about one axis line (within ``axis_tol_deg`` and ``offset_tol`` mm,
      default 2% of the diameter) -> ``rotational`` of order round(2π / smallest angle), its canonical
      range starting at ``boundary``: ``model_x`` (:func:`reference_direction`) or ``least_motion``
      (:func:`least_motion_reference` of 2,000 points sampled on the model's surface, or its vertices)
    * discrete ones about several axes -> ``discrete`` over the listed transforms
    """
    check_boundary(boundary)
    disc = [np.asarray(S, dtype=np.float64).reshape(4, 4) for S in getattr(model, "symmetries_discrete", [])]
    cont = list(getattr(model, "symmetries_continuous", []))
    if offset_tol is None:
        offset_tol = 0.02 * float(getattr(model, "diameter", 100.0))
    if cont:
        c = cont[0]
        return ContinuousSymmetry(axis=c["axis"], offset=c.get("offset", (0, 0, 0)), steps=steps, flips=disc)
    if not disc:
        return NoSymmetry()
    aao = [axis_angle_offset(S) for S in disc]
    a0, _, o0 = aao[0]
    same_axis = all(
        abs(float(a @ a0)) > math.cos(math.radians(axis_tol_deg))
        and np.linalg.norm(_normal_part(o - o0, a0)) < offset_tol
        for a, _, o in aao
    )
    if same_axis:
        smallest = min(min(ang, 2 * math.pi - ang) for _, ang, _ in aao)
        order = round(2 * math.pi / smallest)
        offset = np.mean([o for _, _, o in aao], axis=0)
        order = max(order, 2)
        reference = None
        if boundary == "least_motion":
            pts = model.sample_points(2000, seed=0) if hasattr(model, "sample_points") else model.vertices
            reference = least_motion_reference(pts, a0, offset, 2 * math.pi / order)
        return RotationalSymmetry(order=order, axis=a0, offset=offset, reference=reference)
    return DiscreteSymmetry(disc)
