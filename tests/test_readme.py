"""The README and docs say what the repository holds: their tables are what `results/render.py` renders
from the JSON of record, and every relative link resolves. (The README's JAX snippet runs in
test_generate.py, on a trained tiny model.)"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]


def _render_module():
  spec = importlib.util.spec_from_file_location("render", ROOT / "results" / "render.py")
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def test_the_tables_are_rendered_from_the_json_of_record():
  render = _render_module()
  assert "<!-- table:table1 -->" in (ROOT / "README.md").read_text()
  for doc in render.RENDERED:
    text = doc.read_text()
    assert "<!-- table:" in text
    assert render.render(text) == text, f"{doc.name}: run python results/render.py"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_relative_links_resolve(doc):
  text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)   # code blocks hold commands, not links
  for target in re.findall(r"\]\(([^)\s]+)\)", text):
    if re.match(r"[a-z]+:", target) or target.startswith("#"):
      continue
    path = (doc.parent / target.split("#")[0]).resolve()
    assert path.exists(), f"{doc.name}: {target} does not exist"


@pytest.mark.parametrize("doc", [d for d in DOCS if d.name != "CHANGELOG.md"], ids=lambda p: p.name)
def test_the_docs_say_what_is_true_now(doc):
  text = doc.read_text().lower()
  for phrase in ("this release", "previous release", "releases ago"):
    assert phrase not in text, f"{doc.name}: {phrase!r} (history belongs in CHANGELOG.md)"
