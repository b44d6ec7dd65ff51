"""The feed-forward reconstruction backbone contract (DESIGN.md, Perception step 3).

A backbone turns a query image and ``k`` reference images (same pinhole camera) into

- ``T_qi`` (k, 4, 4): the pose of reference ``i`` in the QUERY camera frame (OpenCV axes),
  i.e. ``T_qi`` maps reference-camera coordinates into query-camera coordinates. Rotations
  are metric (exact up to estimation noise); translations share ONE unknown scale with the
  query depth -- the backbone's own normalised scale (each backbone documents its choice);
- ``confidence`` (k,) in [0, 1], 0 for a failed pair; ``n_matches`` (k,) int;
- ``query_depth`` (H, W) float32 z-depth at that same scale (0 where unknown) with
  ``query_depth_confidence`` (H, W) in [0, 1]; optional ``reference_depths`` (k, H, W);
- optional ``matches``: per reference the putative feature matches (m_i, 4) float32 pixels
  ``(u_q, v_q, u_i, v_i)`` the pair's geometry was estimated from, so that any pose can be checked
  against the images (:func:`vgpnav_env.perception.verify.epipolar_support`).

Backbones never see ground-truth depth or the query's true pose; only backbones whose class
attribute ``privileged`` is True read the :class:`Privileged` bundle. A caller that predicts the
query's pose (tracking) may pass ``expected_T_qi``: the ``T_qi`` it expects, from its predicted
query pose and the references' database poses (metric translations). It is a prior, not the
answer: a backbone may use it to guide its two-view geometry (the pose must still come from the
images) or ignore it, and must stay correct when it is wrong. A caller that needs the pairs only
passes ``depth=False``: a backbone may then skip the query depth (zeros) to save the work.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.geometry import PinholeCamera, invert_pose


@dataclass(frozen=True)
class Privileged:
    """Ground truth for privileged backbones only: world poses (camera -> world) and metric z-depth."""

    T_wq: NDArray[np.float64]
    T_wi: NDArray[np.float64]
    query_depth: NDArray[np.floating]
    reference_depths: NDArray[np.floating] | None = None


@dataclass(frozen=True)
class Views:
    """One backbone call's inputs, checked by :meth:`Backbone.__call__`: the ``query`` and the
    ``references`` (uint8 (H, W, 3) of ``camera``'s size), ``privileged`` ground truth
    (privileged backbones only), optional ``reference_keys`` (stable ids, e.g. database
    indices, for caching per-image work), optional ``expected_T_qi`` (k, 4, 4): the caller's
    expected relative poses (module docstring; None: no expectation) and ``depth``: False when the
    caller needs the pairs only (the query depth may be zeros)."""

    query: NDArray[np.uint8]
    references: Sequence[NDArray[np.uint8]]
    camera: PinholeCamera
    privileged: Privileged | None = None
    reference_keys: Sequence[Hashable] | None = None
    expected_T_qi: NDArray[np.float64] | None = None
    depth: bool = True


@dataclass
class BackboneOutput:
    """What a backbone returns for one query and ``k`` references (see the module docstring).

    ``scale_valid`` (k,) is False for a pair whose translation *direction* is estimated but
    whose translation *length* could not be tied to the common scale (its translation is then
    a unit-consistent guess; rotation and direction stay usable). ``scale`` names the
    backbone's normalisation of the unknown scale, e.g. ``"median_query_depth"``. ``matches``:
    see the module docstring (None when the backbone has no feature matches; an empty array for
    a pair that failed before matching).
    """

    T_qi: NDArray[np.float64]
    confidence: NDArray[np.float64]
    n_matches: NDArray[np.int64]
    query_depth: NDArray[np.float32]
    query_depth_confidence: NDArray[np.float32]
    name: str
    scale: str
    reference_depths: NDArray[np.float32] | None = None
    scale_valid: NDArray[np.bool_] | None = None
    timings: dict[str, float] = field(default_factory=dict)
    matches: list[NDArray[np.float32]] | None = None

    def __post_init__(self) -> None:
        k = len(self.T_qi)
        if self.T_qi.shape != (k, 4, 4):
            raise ValueError(f"T_qi must have shape (k, 4, 4), got {self.T_qi.shape}")
        if self.confidence.shape != (k,) or self.n_matches.shape != (k,):
            raise ValueError(
                f"confidence and n_matches must have shape ({k},), got "
                f"{self.confidence.shape} and {self.n_matches.shape}"
            )
        if self.query_depth.shape != self.query_depth_confidence.shape or self.query_depth.ndim != 2:
            raise ValueError(
                f"query_depth and its confidence must be the same (H, W) shape, got "
                f"{self.query_depth.shape} and {self.query_depth_confidence.shape}"
            )
        if self.scale_valid is None:
            self.scale_valid = self.confidence > 0
        if self.scale_valid.shape != (k,):
            raise ValueError(f"scale_valid must have shape ({k},), got {self.scale_valid.shape}")
        if self.matches is not None and (
            len(self.matches) != k or any(m.ndim != 2 or m.shape[1] != 4 for m in self.matches)
        ):
            raise ValueError(f"matches must be {k} arrays of shape (m, 4) (query and reference pixels)")
        if self.reference_depths is not None and self.reference_depths.shape != (k, *self.query_depth.shape):
            raise ValueError(
                f"reference_depths must have shape {(k, *self.query_depth.shape)}, "
                f"got {self.reference_depths.shape}"
            )

    @property
    def k(self) -> int:
        return len(self.T_qi)

    @property
    def T_iq(self) -> NDArray[np.float64]:
        """(k, 4, 4) pose of the query in each reference frame (maps query coords into reference i)."""
        return invert_pose(self.T_qi)

    @property
    def R_iq(self) -> NDArray[np.float64]:
        """(k, 3, 3) rotations mapping query-frame vectors into reference frames."""
        return np.swapaxes(self.T_qi[:, :3, :3], -1, -2)

    @property
    def R_qi(self) -> NDArray[np.float64]:
        """(k, 3, 3) rotations mapping reference-frame vectors into the query frame."""
        return self.T_qi[:, :3, :3]


class Backbone(ABC):
    """A feed-forward reconstruction backbone; subclasses set ``name`` and ``privileged``.

    Build one with :func:`vgpnav_env.perception.backbones.make_backbone` and call it; a subclass
    implements :meth:`reconstruct`. A backbone that draws random numbers overrides
    :meth:`reseed`, which callers run once per episode.
    """

    name: str = "backbone"
    privileged: bool = False

    def reseed(self, rng: np.random.Generator) -> None:  # noqa: B027 (deterministic: no-op)
        """Start a new episode's random stream, drawn from ``rng`` (e.g. the env's ``np_random``).

        Deterministic backbones (this default) draw nothing from ``rng``; a random one draws its
        seed from it, so episodes with the same ``rng`` state see the same noise.
        """

    def __call__(
        self,
        query: NDArray[np.uint8],
        references: Sequence[NDArray[np.uint8]],
        camera: PinholeCamera,
        privileged: Privileged | None = None,
        reference_keys: Sequence[Hashable] | None = None,
        expected_T_qi: NDArray[np.float64] | None = None,
        depth: bool = True,
    ) -> BackboneOutput:
        """Reconstruct the query and references (see the module docstring for frames and scale).

        Images must be uint8 (H, W, 3) of ``camera``'s size (else ValueError). ``reference_keys``
        are optional stable identifiers of the references (e.g. database indices) a backbone may
        use to cache per-image work; ``privileged`` is read by privileged backbones only;
        ``expected_T_qi`` (k, 4, 4): the caller's expected relative poses (module docstring);
        ``depth`` False: the pairs only, the query depth may be zeros.
        """
        check_inputs(query, references, camera, reference_keys)
        if expected_T_qi is not None:
            expected_T_qi = np.asarray(expected_T_qi, float)
            if expected_T_qi.shape != (len(references), 4, 4):
                raise ValueError(
                    f"expected_T_qi must have shape ({len(references)}, 4, 4), got {expected_T_qi.shape}"
                )
        return self.reconstruct(
            Views(query, references, camera, privileged, reference_keys, expected_T_qi, depth)
        )

    @abstractmethod
    def reconstruct(self, views: Views) -> BackboneOutput:
        """The backbone's work on checked :class:`Views` (what :meth:`__call__` runs)."""


def check_inputs(
    query: NDArray[np.uint8],
    references: Sequence[NDArray[np.uint8]],
    camera: PinholeCamera,
    reference_keys: Sequence[Hashable] | None = None,
) -> None:
    """Raise a clear ValueError unless the images are uint8 (H, W, 3) matching ``camera``."""
    expected = (camera.height, camera.width, 3)
    for what, image in [("query", query), *((f"reference {i}", r) for i, r in enumerate(references))]:
        image = np.asarray(image)
        if image.shape != expected or image.dtype != np.uint8:
            raise ValueError(
                f"{what} image must be uint8 with shape {expected} (camera size), "
                f"got {image.dtype} {image.shape}"
            )
    if reference_keys is not None and len(reference_keys) != len(references):
        raise ValueError(f"got {len(reference_keys)} reference_keys for {len(references)} references")
