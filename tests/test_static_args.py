"""A model's static settings read once per graphdef."""

from flax import nnx

from tdiff_jax import static_args


def _out_features(model) -> int:
  return model.out_features


def test_a_models_settings_are_read_once_per_graphdef(monkeypatch):
  graphdef, params = nnx.split(nnx.Linear(3, 2, rngs=nnx.Rngs(0)))
  merges = []
  original = nnx.merge
  monkeypatch.setattr(nnx, "merge", lambda *a, **k: merges.append(1) or original(*a, **k))
  assert [static_args.read_once(graphdef, params, _out_features) for _ in range(3)] == [2, 2, 2]
  assert len(merges) == 1
  other, other_params = nnx.split(nnx.Linear(3, 5, rngs=nnx.Rngs(0)))
  assert static_args.read_once(other, other_params, _out_features) == 5
