"""Navigation measures, Habitat-style: one small registered class per metric, one registry.

A :class:`Measure` starts an episode with ``reset_metric(state, measures)`` and follows every step
with ``update_metric(state, measures)``; its current value is ``metric``. A measure that reads
others names their uuids in ``depends_on``; :class:`Measurements` resets and updates a scope's
measures in dependency order (as habitat-lab's ``habitat/tasks/nav/nav.py``). A new metric is one
class decorated with :func:`register_measure`; the env's ``info``, the navigation protocol's
episode records, its summaries and its report table pick it up from :data:`MEASURES`. Families of
measures that differ only in what they read are rows of a table: the map measures
(``map_precision``, ``map_recall``, ``map_iou``, ``path_phantoms``: :data:`_MAP_MEASURES`) and the
per-frame fractions of the estimate (``no_estimate``, ``tracked``, ``relocalized``:
:func:`_register_frame_fraction`).

Scopes (what a measure reads):

- ``"env"``: an :class:`EnvState`, the point-goal env's ground truth after a reset or a step. The
  env puts these metrics into ``info`` under their uuids.
- ``"estimate"``: an :class:`EstimateState`, the pose estimate an agent observes beside the true
  pose; the VGP-Nav wrapper puts these metrics into its ``info``.
- ``"map"``: a :class:`~vgpnav_env.map_measures.MapState`, the fused obstacle map against the true
  occupancy of the robot's layout over the cells it observed (:mod:`vgpnav_env.map_measures`); the
  perception wrappers put these metrics into their ``info``.

How a measure appears in evaluations (class attributes): ``record``, its field in an episode
record (None: not recorded); ``per_frame``, False: the record holds the final value, True: the
value over the frames the agent acted on (:meth:`Measure.episode_value`, None without frames)
and the record also keeps the per-frame values; ``summary``, the key of its mean over episodes in
a report (None: not summarised); ``frame_p95``, for per-frame measures, the key of the 95th
percentile over all frames of all episodes (None: not summarised); ``column``, its header in the
report's episode table (None: not shown).

Units: metres, radians; poses are (x, y, yaw) in W.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from graphlib import CycleError, TopologicalSorter
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from vgpnav_env.envs.episodes import Episode
from vgpnav_env.map_measures import MapState

SCOPES = ("env", "estimate", "map")


@dataclass(frozen=True)
class EnvState:
    """The env's ground truth after a reset (``previous_pose`` and ``action`` None) or a step.

    ``geodesic(xy)``: geodesic distance (m) from a point to the goal; ``action``: this step's
    action; ``stopped``: it was the stop action; ``blocked``: its motion hit something.
    """

    episode: Episode
    pose: NDArray[np.float64]
    previous_pose: NDArray[np.float64] | None
    geodesic: Callable[[NDArray[np.float64]], float]
    success_distance: float
    action: Any = None
    stopped: bool = False
    blocked: bool = False


@dataclass(frozen=True)
class EstimateState:
    """The observed pose estimate (x, y, yaw), whether the pose state took in a perceived pose this
    frame, and the true pose; ``fix``: what the pose state did with the perceived pose (a
    :data:`~vgpnav_env.perception.state.FIX_OUTCOMES` name), ``source``: where perception's
    references came from (``tracking`` or ``global``) and ``has_estimate``: whether the pose state
    has an estimate at all (False before the first fix of an episode: ``estimate`` is then a
    placeholder, and the pose-error measures are nan, "no estimate", not an error)."""

    estimate: NDArray[np.float64]
    localized: bool
    true_pose: NDArray[np.float64]
    fix: str = "accepted"
    source: str = "global"
    has_estimate: bool = True


class Measure:
    """One metric (see the module docstring); subclasses set ``uuid`` and implement the updates."""

    uuid: ClassVar[str]
    scope: ClassVar[str] = "env"
    depends_on: ClassVar[tuple[str, ...]] = ()
    record: ClassVar[str | None] = None
    per_frame: ClassVar[bool] = False
    summary: ClassVar[str | None] = None
    frame_p95: ClassVar[str | None] = None
    column: ClassVar[str | None] = None

    def __init__(self) -> None:
        self.metric: Any = None

    def reset_metric(self, state: Any, measures: Measurements) -> None:
        """Start an episode (default: the same as an update)."""
        self.update_metric(state, measures)

    def update_metric(self, state: Any, measures: Measurements) -> None:
        raise NotImplementedError

    @classmethod
    def episode_value(cls, values: Sequence[Any]) -> Any:
        """The episode record's value: ``per_frame``, the mean of the values at the frames the agent
        acted on; else the last of ``values`` (the final value). None without values."""
        if not len(values):
            return None
        return float(np.mean(values)) if cls.per_frame else values[-1]


#: uuid -> measure class, in registration order (the order of info keys, records and tables).
MEASURES: dict[str, type[Measure]] = {}


def register_measure(cls: type[Measure]) -> type[Measure]:
    """Class decorator: add a measure to :data:`MEASURES` (uuids are unique)."""
    if cls.uuid in MEASURES:
        raise ValueError(f"a measure with uuid {cls.uuid!r} is already registered")
    if cls.scope not in SCOPES:
        raise ValueError(f"measure {cls.uuid!r} has scope {cls.scope!r}; allowed: {SCOPES}")
    MEASURES[cls.uuid] = cls
    return cls


class Measurements:
    """The registered measures of one scope, reset and updated in dependency order."""

    def __init__(self, scope: str) -> None:
        classes = [cls for cls in MEASURES.values() if cls.scope == scope]
        if not classes:
            raise ValueError(f"no measures registered for scope {scope!r}; scopes: {SCOPES}")
        self.measures: dict[str, Measure] = {cls.uuid: cls() for cls in classes}
        self._order = _dependency_order(classes)

    def __getitem__(self, uuid: str) -> Measure:
        return self.measures[uuid]

    def reset(self, state: Any) -> None:
        for uuid in self._order:
            self.measures[uuid].reset_metric(state, self)

    def update(self, state: Any) -> None:
        for uuid in self._order:
            self.measures[uuid].update_metric(state, self)

    def metrics(self) -> dict[str, Any]:
        """uuid -> current value, in registration order."""
        return {uuid: m.metric for uuid, m in self.measures.items()}

    def defined_metrics(self) -> dict[str, Any]:
        """:meth:`metrics` without the undefined ones (a float nan, e.g. a pose error before the
        first estimate): an ``info`` of these compares equal between identical runs (nan != nan)."""
        return defined(self.metrics())


def defined(values: dict[str, Any]) -> dict[str, Any]:
    """``values`` without the undefined entries (float nan)."""
    return {k: v for k, v in values.items() if not (isinstance(v, float) and np.isnan(v))}


def frame_value(info: dict[str, Any], uuid: str) -> Any:
    """The per-frame value of measure ``uuid`` in a step's ``info``: its entry, or nan (undefined)
    when info left it out but holds other measures of its scope
    (:meth:`Measurements.defined_metrics`); None when info has no measure of that scope."""
    if uuid in info:
        return info[uuid]
    scope = MEASURES[uuid].scope
    return float("nan") if any(m.scope == scope and k in info for k, m in MEASURES.items()) else None


def _dependency_order(classes: list[type[Measure]]) -> list[str]:
    """uuids so that every measure comes after the ones it depends on (same scope only)."""
    known = {cls.uuid for cls in classes}
    for cls in classes:
        for dep in cls.depends_on:
            if dep not in known:
                raise ValueError(
                    f"measure {cls.uuid!r} depends on {dep!r}, which is not a {cls.scope!r} measure"
                )
    try:
        return list(TopologicalSorter({cls.uuid: cls.depends_on for cls in classes}).static_order())
    except CycleError as e:
        raise ValueError(f"measure dependencies form a cycle: {e.args[1]}") from e


class Accumulated(Measure):
    """A measure summing a per-step :meth:`increment` over the episode from ``initial`` at reset."""

    initial: ClassVar[Any] = 0

    def reset_metric(self, state: Any, measures: Measurements) -> None:
        self.metric = self.initial

    def update_metric(self, state: Any, measures: Measurements) -> None:
        self.metric += self.increment(state)

    def increment(self, state: Any) -> Any:
        raise NotImplementedError


class StateValue(Measure):
    """A measure whose value is a function ``value`` of the state alone, at reset and every step."""

    value: ClassVar[Callable[[Any], Any]]

    def update_metric(self, state: Any, measures: Measurements) -> None:
        self.metric = type(self).value(state)


def _register_value(name: str, doc: str, value: Callable[[Any], Any], **attributes: Any) -> None:
    """Register a :class:`StateValue` measure class ``name`` (docstring ``doc``) with the class
    attributes ``attributes`` (``uuid``, ``scope``, ``record``, ...)."""
    body = {"__doc__": doc, "__module__": __name__, "value": staticmethod(value), **attributes}
    register_measure(type(name, (StateValue,), body))


def _register_frame_fraction(
    name: str, uuid: str, column: str, doc: str, flag: Callable[[EstimateState], bool]
) -> None:
    """Register a per-frame flag of the estimate (:class:`EstimateState`) whose episodes report the
    fraction of the frames the agent acted on where it holds: record ``<uuid>_fraction``, summary
    ``mean_<uuid>_fraction``."""
    _register_value(
        name, doc, flag, uuid=uuid, scope="estimate", record=f"{uuid}_fraction", per_frame=True,
        summary=f"mean_{uuid}_fraction", column=column,
    )  # fmt: skip


def _efficiency(shortest: float, travelled: float) -> float:
    """Path efficiency of SPL: shortest / max(shortest, travelled)."""
    return shortest / max(shortest, travelled, 1e-9)


# -- env measures ---------------------------------------------------------------------------


@register_measure
class DistanceToGoal(Measure):
    """Geodesic distance (m) from the robot to the goal."""

    uuid = "distance_to_goal"
    record = "final_distance"

    def update_metric(self, state: EnvState, measures: Measurements) -> None:
        self.metric = state.geodesic(state.pose[:2])


@register_measure
class EuclideanDistanceToGoal(Measure):
    """Straight-line distance (m) from the robot to the goal."""

    uuid = "euclidean_distance_to_goal"
    record = "final_euclidean_distance"
    column = "final d (m)"

    def update_metric(self, state: EnvState, measures: Measurements) -> None:
        self.metric = float(np.linalg.norm(state.pose[:2] - np.asarray(state.episode.goal)))


@register_measure
class Success(Measure):
    """``stop`` within ``success_distance`` m (Euclidean) of the goal."""

    uuid = "success"
    depends_on = ("euclidean_distance_to_goal",)
    record = "success"
    summary = "success_rate"
    column = "success"

    def update_metric(self, state: EnvState, measures: Measurements) -> None:
        distance = measures["euclidean_distance_to_goal"].metric
        self.metric = state.stopped and distance <= state.success_distance


@register_measure
class SPL(Measure):
    """Success weighted by path length: success * shortest / max(shortest, travelled)."""

    uuid = "spl"
    depends_on = ("success", "travelled")
    record = "spl"
    summary = "spl"
    column = "SPL"

    def update_metric(self, state: EnvState, measures: Measurements) -> None:
        travelled = measures["travelled"].metric
        self.metric = float(measures["success"].metric) * _efficiency(state.episode.geodesic, travelled)


@register_measure
class SoftSPL(Measure):
    """SPL with progress instead of success: max(0, 1 - d / d_start) * shortest / max(shortest,
    travelled), d the geodesic distance to the goal."""

    uuid = "soft_spl"
    depends_on = ("distance_to_goal", "travelled")
    record = "soft_spl"
    summary = "soft_spl"
    column = "soft SPL"

    def reset_metric(self, state: EnvState, measures: Measurements) -> None:
        self.start_distance = measures["distance_to_goal"].metric
        self.update_metric(state, measures)

    def update_metric(self, state: EnvState, measures: Measurements) -> None:
        progress = max(0.0, 1.0 - measures["distance_to_goal"].metric / max(self.start_distance, 1e-9))
        self.metric = progress * _efficiency(state.episode.geodesic, measures["travelled"].metric)


@register_measure
class Collisions(Accumulated):
    """Steps whose motion hit something."""

    uuid = "collisions"
    record = "collisions"
    summary = "collisions_per_episode"
    column = "collisions"

    def increment(self, state: EnvState) -> int:
        return int(state.blocked)


@register_measure
class NumSteps(Accumulated):
    """Steps taken in the episode."""

    uuid = "steps"
    record = "steps"
    summary = "mean_steps"
    column = "steps"

    def increment(self, state: EnvState) -> int:
        return 1


@register_measure
class Travelled(Accumulated):
    """Distance (m) the robot moved (sum of its steps' straight displacements)."""

    uuid = "travelled"
    record = "travelled"
    initial = 0.0

    def increment(self, state: EnvState) -> float:
        return float(np.linalg.norm(state.pose[:2] - state.previous_pose[:2]))


# -- estimate measures ----------------------------------------------------------------------


def _mean_over_estimates(values: Sequence[Any]) -> float | None:
    """The mean of the finite ``values`` (the frames with a pose estimate); None when none is."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else None


@register_measure
class LocalizationError(Measure):
    """Horizontal distance (m) between the observed pose estimate and the true pose, nan while the
    pose state has no estimate (before the first fix: "no estimate", counted by
    :class:`NoEstimate`, not as an error); episodes report its mean over the frames the agent acted
    on that had an estimate."""

    uuid = "localization_error_m"
    scope = "estimate"
    record = "localization_error_m"
    per_frame = True
    summary = "mean_localization_error_m"
    frame_p95 = "p95_localization_error_m"
    column = "mean pose err (m)"

    def update_metric(self, state: EstimateState, measures: Measurements) -> None:
        error = float(np.linalg.norm(state.estimate[:2] - state.true_pose[:2]))
        self.metric = error if state.has_estimate else float("nan")

    @classmethod
    def episode_value(cls, values: Sequence[Any]) -> Any:
        return _mean_over_estimates(values)


_register_frame_fraction(
    "NoEstimate",
    "no_estimate",
    "no estimate",
    """Whether the pose state had no estimate at this frame (before the first fix of an episode).""",
    lambda state: not state.has_estimate,
)


@register_measure
class Localized(Measure):
    """Whether this frame's pose came from perception; episodes report the lost fraction of the
    frames the agent acted on."""

    uuid = "localized"
    scope = "estimate"
    record = "lost_fraction"
    per_frame = True
    summary = "mean_lost_fraction"
    column = "lost frames"

    def update_metric(self, state: EstimateState, measures: Measurements) -> None:
        self.metric = bool(state.localized)

    @classmethod
    def episode_value(cls, values: Sequence[Any]) -> Any:
        """The fraction of frames that were not localized (None without frames)."""
        return 1.0 - float(np.mean(values)) if len(values) else None


_register_frame_fraction(
    "Tracked",
    "tracked",
    "tracked",
    """Whether this frame's pose was taken in from tracking (references around the predicted pose).""",
    lambda state: bool(state.localized and state.source == "tracking"),
)
_register_frame_fraction(
    "Relocalized",
    "relocalized",
    "relocalized",
    """Whether this frame's pose was taken in from global retrieval (relocalization: the first fix,
    after tracking failed or a kidnapping).""",
    lambda state: bool(state.localized and state.source == "global"),
)


#: A pose estimate farther off than this (metres) is a gross error (the issue's 0.5 m target).
GROSS_POSE_ERROR_M = 0.5


@register_measure
class GrossPoseError(Measure):
    """Whether the observed pose estimate is more than :data:`GROSS_POSE_ERROR_M` off the true pose
    (1.0 / 0.0; nan without an estimate); episodes report the fraction of the frames with an
    estimate."""

    uuid = "gross_pose_error"
    scope = "estimate"
    depends_on = ("localization_error_m",)
    record = "gross_pose_fraction"
    per_frame = True
    summary = "mean_gross_pose_fraction"
    column = "err > 0.5 m"

    def update_metric(self, state: EstimateState, measures: Measurements) -> None:
        error = measures["localization_error_m"].metric
        self.metric = float(error > GROSS_POSE_ERROR_M) if np.isfinite(error) else float("nan")

    @classmethod
    def episode_value(cls, values: Sequence[Any]) -> Any:
        return _mean_over_estimates(values)


# -- map measures ---------------------------------------------------------------------------


#: The map measures, as (class name, uuid, record, report column, value of the :class:`MapState`,
#: docstring): episodes report the value at their end, summaries its mean as ``mean_<record>``.
_MAP_MEASURES: tuple[tuple[str, str, str, str | None, Callable[[MapState], Any], str], ...] = (
    ("MapPrecision", "map_precision", "map_precision", "map prec.", lambda state: state.score.precision,
     "Occupied precision of the fused map over the observed cells (:mod:`vgpnav_env.map_measures`; "
     "None while no occupied cell was observed)."),
    ("MapRecall", "map_recall", "map_recall", "map recall", lambda state: state.score.recall,
     "Occupied recall of the fused map over the observed cells (None while no true obstacle was "
     "observed)."),
    ("MapIoU", "map_iou", "map_iou", None, lambda state: state.score.iou,
     "Occupied IoU of the fused map over the observed cells (from precision and recall)."),
    ("PathPhantoms", "path_phantoms", "path_phantom_cells", "path phantoms",
     lambda state: state.path_phantoms,
     "Phantom cells of the fused map (occupied, no true obstacle near) within the robot radius of "
     "the true shortest path."),
)  # fmt: skip
for _name, _uuid, _record, _column, _value, _doc in _MAP_MEASURES:
    _register_value(
        _name, _doc, _value, uuid=_uuid, scope="map", record=_record, summary=f"mean_{_record}",
        column=_column,
    )  # fmt: skip
