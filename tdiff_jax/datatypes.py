"""The scene contract: one traffic scene as fixed-shape padded arrays.

Every scene, real or synthetic, becomes a `Scene` whose array shapes depend only on the caps of the
data config, so XLA compiles once per configuration. Leading batch dimensions are allowed on every
field (a batch of scenes is a `Scene` whose arrays carry a leading `[B]`).

Shapes (per scene; A agents, P polygons, K points per polygon, D drivable-area polygons,
V vertices per drivable-area polygon):

| field             | shape          | dtype   | meaning                                                |
|-------------------|----------------|---------|--------------------------------------------------------|
| `agent_state`     | `[A, 2, 4]`    | float32 | token 0 = AV2 step 50, token 1 = step 109; features     |
|                   |                |         | `AGENT_FEATURES` = x, y (m, scene frame), speed (m/s),  |
|                   |                |         | heading (rad, city frame)                               |
| `agent_type`      | `[A]`          | int32   | `AGENT_TYPES` index                                     |
| `agent_valid`     | `[A]`          | bool    | padding mask (valid agents come first)                  |
| `agent_future`    | `[A, H, 2]`    | float32 | ground-truth positions (m, scene frame) at AV2 steps    |
|                   |                |         | 50..109 (H = 60; zeros where unknown or generated)      |
| `agent_future_valid` | `[A, H]`    | bool    | which of those steps were observed                      |
| `pl_xy`           | `[P, 2]`       | float32 | polygon position: first centreline point (m)            |
| `pl_heading`      | `[P]`          | float32 | direction of the first centreline segment (rad)         |
| `pl_type`         | `[P]`          | int32   | `POLYGON_TYPES` index                                   |
| `pl_intersection` | `[P]`          | int32   | 0 not in an intersection, 1 in one, 2 not applicable    |
| `pl_valid`        | `[P]`          | bool    | padding mask (valid polygons come first)                |
| `pt_xy`           | `[P, K, 2]`    | float32 | left, right, centre polylines, each resampled to K/3    |
| `pt_heading`      | `[P, K]`       | float32 | tangent direction at each point (rad)                   |
| `pt_type`         | `[P, K]`       | int32   | `POINT_TYPES` index (lane-mark type, crosswalk, centre) |
| `pt_side`         | `[P, K]`       | int32   | `POINT_SIDES` index                                     |
| `pt_valid`        | `[P, K]`       | bool    | padding mask                                            |
| `pl_edge`         | `[P, P]`       | int8    | `pl_edge[i, j]`: what polygon j is to polygon i         |
|                   |                |         | (`EDGE_TYPES`: none, predecessor, successor, left,      |
|                   |                |         | right neighbour)                                        |
| `da_xy`           | `[D, V, 2]`    | float32 | drivable-area polygon vertices (m), open rings          |
| `da_valid`        | `[D, V]`       | bool    | padding mask                                            |
| `frame_origin`    | `[2]`          | float64 | city-frame metres of the scene origin (map crop centre) |
| `frame_scale`     | `[]`           | float32 | metres per normalised unit (125 by default)             |

All positions are metres in the scene frame: city coordinates minus `frame_origin`, no rotation.
`to_city(scene, xy)` goes back. `frame_origin` is float64 in numpy caches; on a device with x64
disabled it becomes float32 (sub-millimetre error at AV2 city coordinates).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np
from flax import struct

# Agent feature layout of `Scene.agent_state[..., f]`.
AGENT_FEATURES = ("x", "y", "speed", "heading")
# The two tokens of an agent: AV2 step 50 (initial) and step 109 (goal).
INITIAL_STEP = 50
GOAL_STEP = 109
# H: the infilled horizon, AV2 steps 50..109 inclusive.
HORIZON = GOAL_STEP - INITIAL_STEP + 1
# A written trajectory's heading follows its motion; below this displacement per step (m) it is held.
STOPPED_STEP_M = 0.05

AGENT_TYPES = ("vehicle", "bus", "pedestrian", "cyclist", "motorcyclist")
# Length x width (m) per agent type (AV2 has no sizes; the values of av2's visualiser and ScenarioNet's
# AV2 converter): the boxes of the strict collision metric and of box-clearance guidance.
AGENT_BOX_SIZE_M = {"vehicle": (4.0, 2.0), "bus": (12.0, 2.5), "pedestrian": (0.5, 0.5), "cyclist": (2.0, 0.7),
                    "motorcyclist": (2.0, 0.8)}
POLYGON_TYPES = ("VEHICLE", "BIKE", "BUS", "PEDESTRIAN")
# Point types: av2's 15 lane-mark types in their enum order, then crosswalk edge and centreline.
POINT_TYPES = (
    "DASH_SOLID_YELLOW", "DASH_SOLID_WHITE", "DASHED_WHITE", "DASHED_YELLOW", "DOUBLE_SOLID_YELLOW",
    "DOUBLE_SOLID_WHITE", "DOUBLE_DASH_YELLOW", "DOUBLE_DASH_WHITE", "SOLID_YELLOW", "SOLID_WHITE",
    "SOLID_DASH_WHITE", "SOLID_DASH_YELLOW", "SOLID_BLUE", "NONE", "UNKNOWN", "CROSSWALK", "CENTERLINE",
)
POINT_SIDES = ("LEFT", "RIGHT", "CENTER")
EDGE_TYPES = ("NONE", "PRED", "SUCC", "LEFT", "RIGHT")
INTERSECTION_FLAGS = ("NO", "YES", "NOT_APPLICABLE")
# Indices the masks below test: pedestrians (not road users), crosswalk polygons (not lanes), centrelines.
PEDESTRIAN = AGENT_TYPES.index("pedestrian")
CROSSWALK = POLYGON_TYPES.index("PEDESTRIAN")
CENTER = POINT_SIDES.index("CENTER")

# Number of resampled polylines per polygon (left, right, centre).
POLYLINES_PER_POLYGON = 3  # left, right, centre: `pt_*[..., i * K / 3:(i + 1) * K / 3]` is `POINT_SIDES[i]`


@struct.dataclass
class Scene:
  """One scene (or a batch of scenes) as padded arrays; see the module docstring for shapes."""

  agent_state: Any
  agent_type: Any
  agent_valid: Any
  agent_future: Any
  agent_future_valid: Any
  pl_xy: Any
  pl_heading: Any
  pl_type: Any
  pl_intersection: Any
  pl_valid: Any
  pt_xy: Any
  pt_heading: Any
  pt_type: Any
  pt_side: Any
  pt_valid: Any
  pl_edge: Any
  da_xy: Any
  da_valid: Any
  frame_origin: Any
  frame_scale: Any

  # ---- derived sizes -----------------------------------------------------------------------
  @property
  def batch_shape(self) -> tuple[int, ...]:
    return tuple(self.agent_valid.shape[:-1])

  @property
  def num_agents(self) -> int:
    """A, the agent cap."""
    return self.agent_valid.shape[-1]

  @property
  def num_polygons(self) -> int:
    """P, the polygon cap."""
    return self.pl_valid.shape[-1]

  @property
  def num_points(self) -> int:
    """K, points per polygon."""
    return self.pt_valid.shape[-1]

  @property
  def agent_xy(self):
    """[..., A, 2, 2] positions in metres (scene frame)."""
    return self.agent_state[..., 0:2]

  @property
  def road_users(self):
    """[..., A] valid agents that are not pedestrians (the map metrics' and map costs' agents)."""
    return self.agent_valid & (self.agent_type != PEDESTRIAN)

  @property
  def lane_polygons(self):
    """[..., P] valid polygons that are lanes (not crosswalks)."""
    return self.pl_valid & (self.pl_type != CROSSWALK)

  @property
  def centerline_points_mask(self):
    """[..., P, K] valid points on a polygon's centre polyline (lanes and crosswalks)."""
    return self.pt_valid & (self.pt_side == CENTER)

  @property
  def centerline_slice(self) -> slice:
    """The slots of the centre polyline in the K points of a polygon (the last third, by the contract)."""
    n = self.num_points // POLYLINES_PER_POLYGON
    return slice((POLYLINES_PER_POLYGON - 1) * n, POLYLINES_PER_POLYGON * n)

  def crop(self, num_agents: int | None = None, num_polygons: int | None = None) -> "Scene":
    """The first `num_agents` agent rows and `num_polygons` polygon rows (valid rows come first, so
    cropping to at least the valid count drops only padding). Batched or not."""
    nb = len(self.batch_shape)
    changes = {}
    if num_agents is not None:
      changes.update({f: getattr(self, f)[(slice(None),) * nb + (slice(0, num_agents),)] for f in AGENT_FIELDS})
    if num_polygons is not None:
      changes.update({f: getattr(self, f)[(slice(None),) * nb + (slice(0, num_polygons),)] for f in POLYGON_FIELDS})
      changes["pl_edge"] = self.pl_edge[(slice(None),) * nb + (slice(0, num_polygons),) * 2]
    return dataclasses.replace(self, **changes)

  @classmethod
  def zeros(cls, num_agents: int, num_polygons: int, num_points: int, num_da: int = 1, num_vertices: int = 3,
            batch_shape: tuple[int, ...] = ()) -> "Scene":
    """An all-padding numpy scene of the given caps (`field_specs`), to fill with `replace`."""
    specs = field_specs(num_agents, num_polygons, num_points, num_da, num_vertices)
    return cls(**{n: np.zeros(tuple(batch_shape) + shape, dtype) for n, (shape, dtype) in specs.items()})

  def to_dict(self) -> dict[str, Any]:
    return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

  @classmethod
  def from_dict(cls, arrays: dict[str, Any]) -> "Scene":
    names = [f.name for f in dataclasses.fields(cls)]
    missing = [n for n in names if n not in arrays]
    if missing:
      raise KeyError(f"scene arrays are missing fields {missing}")
    return cls(**{n: arrays[n] for n in names})

  # ---- checks ------------------------------------------------------------------------------
  def validate(self) -> None:
    """Checks shapes and dtypes against each other and that padding is clean.

    Raises ValueError naming the first field that breaks the contract. Works on numpy and
    jax arrays (concrete values) with any leading batch shape.
    """
    b = self.batch_shape
    k = self.num_points
    specs = field_specs(self.num_agents, self.num_polygons, k, *self.da_valid.shape[-2:])
    for name, (shape, dtype) in specs.items():
      arr = getattr(self, name)
      if tuple(arr.shape) != b + shape:
        raise ValueError(f"Scene.{name}: shape {tuple(arr.shape)}, expected {b + shape}")
      # frame_origin is float64 in numpy caches and float32 on a device without x64.
      if name != "frame_origin" and np.dtype(arr.dtype) != dtype:
        raise ValueError(f"Scene.{name}: dtype {arr.dtype}, expected {dtype}")
    if k % POLYLINES_PER_POLYGON:
      raise ValueError(f"Scene: points per polygon K={k} is not a multiple of {POLYLINES_PER_POLYGON}")
    for name in ("agent_state", "agent_future", "pl_xy", "pl_heading", "pt_xy", "pt_heading", "da_xy", "frame_origin"):
      if not np.all(np.isfinite(np.asarray(getattr(self, name)))):
        raise ValueError(f"Scene.{name}: contains NaN or inf")
    agent_valid = np.asarray(self.agent_valid)
    pl_valid = np.asarray(self.pl_valid)
    if np.any(np.asarray(self.pt_valid) & ~pl_valid[..., None]):
      raise ValueError("Scene.pt_valid: a point of a padded polygon is marked valid")
    edge = np.asarray(self.pl_edge)
    if np.any((edge != 0) & ~(pl_valid[..., :, None] & pl_valid[..., None, :])):
      raise ValueError("Scene.pl_edge: an edge touches a padded polygon")
    if np.any((edge < 0) | (edge >= len(EDGE_TYPES))):
      raise ValueError("Scene.pl_edge: edge type out of range")
    for name, valid in (("agent_valid", agent_valid), ("pl_valid", pl_valid)):
      # Valid entries are packed first so batches can be cropped to size buckets.
      if np.any(valid[..., 1:] & ~valid[..., :-1]):
        raise ValueError(f"Scene.{name}: valid entries are not packed at the front")
    if np.any(np.asarray(self.agent_future_valid) & ~agent_valid[..., None]):
      raise ValueError("Scene.agent_future_valid: a step of a padded agent is marked valid")
    _check_range("agent_type", self.agent_type, len(AGENT_TYPES))
    _check_range("pl_type", self.pl_type, len(POLYGON_TYPES))
    _check_range("pl_intersection", self.pl_intersection, len(INTERSECTION_FLAGS))
    _check_range("pt_type", self.pt_type, len(POINT_TYPES))
    _check_range("pt_side", self.pt_side, len(POINT_SIDES))
    # Code that needs one polyline (the centrelines of guidance and of the grounded attention) slices it.
    layout = np.repeat(np.arange(POLYLINES_PER_POLYGON), k // POLYLINES_PER_POLYGON)
    if np.any(np.asarray(self.pt_valid) & (np.asarray(self.pt_side) != layout)):
      raise ValueError("Scene.pt_side: a valid point is not on the polyline of its slot (left, right, centre "
                       "thirds of K)")


def field_specs(a: int, p: int, k: int, d: int, v: int) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
  """Per-scene shape and dtype of every `Scene` field for caps A, P, K, D, V."""
  f32, i32 = np.dtype(np.float32), np.dtype(np.int32)
  return {
      "agent_state": ((a, 2, len(AGENT_FEATURES)), f32), "agent_type": ((a,), i32),
      "agent_valid": ((a,), np.dtype(bool)),
      "agent_future": ((a, HORIZON, 2), f32), "agent_future_valid": ((a, HORIZON), np.dtype(bool)),
      "pl_xy": ((p, 2), f32), "pl_heading": ((p,), f32), "pl_type": ((p,), i32),
      "pl_intersection": ((p,), i32), "pl_valid": ((p,), np.dtype(bool)),
      "pt_xy": ((p, k, 2), f32), "pt_heading": ((p, k), f32), "pt_type": ((p, k), i32),
      "pt_side": ((p, k), i32), "pt_valid": ((p, k), np.dtype(bool)),
      "pl_edge": ((p, p), np.dtype(np.int8)),
      "da_xy": ((d, v, 2), f32), "da_valid": ((d, v), np.dtype(bool)),
      "frame_origin": ((2,), np.dtype(np.float64)), "frame_scale": ((), f32),
  }


# Scene fields with an agent axis (after the batch axes) and with one polygon axis (`pl_edge` has two),
# read off `field_specs` with caps that tell the axes apart.
_AXES = field_specs(13, 17, 6, 7, 11)  # no fixed size (2 tokens, 4 features, H = 60) is 13 or 17
AGENT_FIELDS = tuple(n for n, (shape, _) in _AXES.items() if shape[:1] == (13,))
POLYGON_FIELDS = tuple(n for n, (shape, _) in _AXES.items() if shape[:1] == (17,) and shape[1:2] != (17,))


def _check_range(name: str, values, n: int) -> None:
  values = np.asarray(values)
  if np.any((values < 0) | (values >= n)):
    raise ValueError(f"Scene.{name}: values outside [0, {n})")


# Every array field of `Scene`, in declaration order.
SCENE_FIELDS = tuple(f.name for f in dataclasses.fields(Scene))


def bucket_size(count: int, buckets: Sequence[int]) -> int:
  """The smallest of `buckets` that holds `count` entries (the largest when none does): the padded size
  that batches are cropped to, so XLA compiles once per bucket."""
  for b in sorted(buckets):
    if count <= b:
      return b
  return max(buckets)


def stack_scenes(scenes: list[Scene]) -> Scene:
  """Unbatched numpy scenes (same caps) -> one batched `Scene` with a leading `[len(scenes)]`."""
  return Scene(**{n: np.stack([getattr(s, n) for s in scenes]) for n in SCENE_FIELDS})


def to_city(scene: Scene, xy):
  """Scene-frame metres `[..., 2]` -> city-frame metres. `xy` broadcasts against the scene's batch."""
  origin = scene.frame_origin
  extra = np.ndim(xy) - np.ndim(origin)
  return xy + origin.reshape(origin.shape[:-1] + (1,) * extra + (2,))
