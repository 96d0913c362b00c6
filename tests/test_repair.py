"""`repair.faults` judges trajectories as the audit judges the written AV2 folders."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from tests.av2_samples import DATA, REAL_110
from tdiff_jax import audit, datatypes, geometry, repair
from tdiff_jax.data import av2_export, scene_builder


def test_faults_are_what_the_audit_reads_back_from_the_written_folder(tmp_path):
  """A real scenario's logged agents, one driven through another, one moved off the road and one stopped
  (held heading): the per-agent faults in the scene frame count what the audit counts in the files."""
  folder = DATA / REAL_110[0]
  scene, _ = scene_builder.load_scene(folder)
  n = int(scene.agent_valid.sum())
  xy = np.array(scene.agent_future[:n], np.float64)                    # [n, H, 2] scene frame
  xy[1] = xy[0] + np.array([0.5, 0.0])           # agent 1 drives through agent 0
  xy[2] += 60.0                                  # agent 2 off the road
  xy[3] = xy[3, :1]                              # agent 3 stopped all along
  types = np.array(scene.agent_type[:n])
  types[2] = datatypes.AGENT_TYPES.index("vehicle")
  heading0 = np.array(scene.agent_state[:n, 0, 3])
  batch = datatypes.stack_scenes([scene.replace(agent_type=np.pad(types, (0, scene.num_agents - n)))])
  pad = lambda x: np.pad(x, [(0, scene.num_agents - n)] + [(0, 0)] * (x.ndim - 1))   # noqa: E731
  overlap, offroad = repair.faults(jnp.asarray(pad(xy)[None], jnp.float32), batch.agent_valid, pad(heading0)[None],
                                   batch.agent_type, geometry.map_geometry(batch))
  overlap, offroad = np.asarray(overlap[0]), np.asarray(offroad[0])
  assert overlap[0] and overlap[1] and offroad[2] and not overlap[n:].any() and not offroad[n:].any()
  written = av2_export.write_generated_scenario(tmp_path, "gen", "city", next(folder.glob("log_map_archive_*.json")),
                                                datatypes.to_city(scene, xy), heading0, types, np.ones(n, bool))
  got = audit.audit_folders([written])
  assert (got["overlap"], got["offroad"]) == (int(overlap.sum()), int(offroad.sum()))
  # The headings the files get: the motion's, held while stopped.
  _, written_heading = av2_export.kinematics(xy, heading0)
  np.testing.assert_allclose(np.asarray(repair.motion_headings(jnp.asarray(xy[None]), heading0[None]))[0],
                             written_heading, atol=1e-4)
