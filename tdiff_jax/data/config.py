"""The data config: caps of the scene contract and the agent-selection rules.

The caps decide every array shape (see `tdiff_jax.datatypes`), so they are part of the preprocessing
hash: a cache made with other caps is refused by `tdiff_jax.data.cache.load_split`.
"""

from __future__ import annotations

import hashlib
import json

import ml_collections

from tdiff_jax import datatypes


def default_data_config() -> ml_collections.ConfigDict:
  c = ml_collections.ConfigDict()
  # Caps. A = 64 and P = 256 cover the real AV2 samples (at most 33 kept agents, 150 polygons)
  # with room; K = 3 polylines x 10 points.
  c.max_agents = 64
  c.max_polygons = 256
  c.points_per_polyline = 10
  c.max_drivable_areas = 16
  c.max_drivable_area_vertices = 256
  # Agent selection (DESIGN.md): present at both tokens' steps, of a kept type, and for the
  # types in `near_lane_types` within `near_boundary_m` of a lane/crosswalk boundary point or
  # `near_centerline_m` of a centreline point at step 50 (the official code's in-lane test).
  c.agent_types = ",".join(datatypes.AGENT_TYPES)
  c.near_lane_types = "vehicle,bus,cyclist,motorcyclist"
  c.near_boundary_m = 2.0
  c.near_centerline_m = 4.0
  # Scene frame: positions / frame_scale are the model's normalised units.
  c.frame_scale_m = 125.0
  return c


def scene_config(c: ml_collections.ConfigDict | dict | None = None) -> ml_collections.ConfigDict:
  """The full data config: `default_data_config()` with the fields `c` sets (a training config's
  `data.scene` sets the caps `max_agents` and `max_polygons`; a cache's manifest or an older checkpoint,
  every field)."""
  full = default_data_config()
  if c is not None:
    extra = sorted(set(c.keys()) - set(full.keys()))
    if extra:
      raise ValueError(f"data config: unknown fields {extra}; the fields are {sorted(full.keys())}")
    full.update(dict(c.items()))
  return full


def parse_types(csv: str, field: str) -> tuple[str, ...]:
  names = tuple(t.strip() for t in csv.split(",") if t.strip())
  unknown = [t for t in names if t not in datatypes.AGENT_TYPES]
  if unknown:
    raise ValueError(f"data config {field}: unknown agent types {unknown}; choose from {datatypes.AGENT_TYPES}")
  return names


def validate_data_config(c: ml_collections.ConfigDict) -> None:
  """Raises ValueError with the offending field for impossible settings."""
  c = scene_config(c)
  for field in ("max_agents", "max_polygons", "points_per_polyline", "max_drivable_areas",
                "max_drivable_area_vertices"):
    if int(c[field]) < 1:
      raise ValueError(f"data config {field} must be >= 1, got {c[field]}")
  if int(c.points_per_polyline) < 2:
    raise ValueError("data config points_per_polyline must be >= 2 (a polyline needs a direction)")
  if not parse_types(c.agent_types, "agent_types"):
    raise ValueError("data config agent_types is empty")
  parse_types(c.near_lane_types, "near_lane_types")
  if float(c.frame_scale_m) <= 0:
    raise ValueError(f"data config frame_scale_m must be > 0, got {c.frame_scale_m}")


def config_hash(c: ml_collections.ConfigDict) -> str:
  """A stable short hash of everything that changes the preprocessed arrays."""
  blob = json.dumps(scene_config(c).to_dict(), sort_keys=True)
  return hashlib.sha256(blob.encode()).hexdigest()[:16]
